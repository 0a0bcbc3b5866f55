"""`Detector`: ChArUcoNet (+ RefineNet / cornerSubPix) behind the same interface as `OpenCVDetector`.

    image -> canonical view (an inverted print negated, a mirrored face flipped: `print_face`)
          -> ChArUcoNet, coarse to fine (320 px, 640 px whole; finer levels in regions: `search_regions`)
          -> per-cell point and ID softmax, then one of two decodings:
             the weights' own board (its layout: the same board at any size, inverted or mirrored):
                best cell per ID (score >= threshold) -> board-geometry check (`board_check`): the
                confident cells' likeliest IDs must fit one homography of the board's plane; every
                corner it predicts takes the cell found there;
             any other board (geometry "markers"): the point head's corners only -> chessboard cells ->
                the markers in them read and matched to the board's own (`placement`) -> the view they
                agree on; every corner it predicts takes the cell found there
          -> integer corner pixels -> refine: RefineNet on 24x24 patches (batched), cornerSubPix, or none
          -> corners mapped back from the canonical view -> Detection
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec, check_boards_apart
from deepcharuco.boards.dictionaries import marker_family
from deepcharuco.boards.print_face import (canonical_view, canonical_view_local_white, corners_from_canonical,
                                           covariances_from_canonical)
from deepcharuco.core.blas import single_threaded_blas
from deepcharuco.core.checks import check_choice
from deepcharuco.core.detection import Detection, corner_spacing, detect_board_result, no_corners
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.core.errors import OptionError
from deepcharuco.core.image import to_gray_u8
from deepcharuco.core.stage_times import stage, tally
from deepcharuco.detection.board_check import (
    GEOMETRY_MODES, MIN_CONSENSUS, TOLERANCE_PX, apply_homography, assign_ids, fit_board_homography, id_hypotheses,
)
from deepcharuco.detection.corner_fit import FALLBACK_SIGMA_PX, fit_corners, view_homography
from deepcharuco.detection.junction import locate_by_pattern, printed_pattern
from deepcharuco.detection.levels import (EarlyRefinement, Found, Seen, candidates_in_image, moves_limited,
                                          network_input, nudged, from_level, on_cell_grid, patches_around, reduced,
                                          to_level)
from deepcharuco.detection.markers.marker_reader import READERS
from deepcharuco.detection.markers.placement import PATTERN_SCORE, corners_from_markers, weak_confidence
from deepcharuco.detection.markers.settling import drop_isolated, neighbour_distances, settle_corners
from deepcharuco.detection.markers.verification import layout_ends_short, marker_view_verified
from deepcharuco.detection.opencv_detector import OpenCVDetector
from deepcharuco.detection.search_regions import Box, area_share, board_like_boxes, corner_cells, is_dim, to_full
from deepcharuco.detection.tracking import MIN_CORNERS as MIN_TRACKED_CORNERS, search_region
from deepcharuco.geometry.pose import Pose, estimate_pose
from deepcharuco.networks.backends import BACKENDS
from deepcharuco.networks.cells import CELL, best_per_id, cell_candidates, cell_confidence
from deepcharuco.networks.offsets import soft_argmax_offsets
from deepcharuco.networks.onnx_bundle import (
    BundleError, OnnxBundle, bundle_path, check_exported_from, checked_runner, input_white, is_bundle, read_bundle,
)
from deepcharuco.networks.onnx_runner import OnnxRunner, onnxruntime_available
from deepcharuco.networks.shipped import DEFAULT_WEIGHTS, FAMILY_WEIGHTS_DIR, WEIGHTS_DIR  # noqa: F401 (WEIGHTS_DIR: API)
from deepcharuco.networks.shipped import FAST_WEIGHTS_DIR
from deepcharuco.networks.shipped import network_weights


REFINE_MODES = ("refinenet", "subpix", "none")
DEFAULT_THRESHOLD = 0.3


# Longest side the network searches at first: it finds squares of ~12-64 px best (trained at 320x240);
# a 1280x720 frame is searched at 320x180, then 640x360, then 1280x720, until the board's squares are at
# least MIN_SQUARE_PX wide, and its corners are refined at full resolution.
WORKING_SIZE = 320
MIN_SQUARE_PX = 16


# An image no larger than the working size is previewed at half size first (a quarter of the network's
# cost): the preview's corners stand when they are the whole board in view with squares of at least
# MIN_PREVIEW_SQUARE_PX there; anything less and the full image is searched as without a preview.
# Chosen on validation renders (datagen.render --n 160 --seed 2000): no protocol level lost more than 0.001.
MIN_PREVIEW_SQUARE_PX = 12


# A board found by its markers: RefineNet starts on the confident candidates on a second thread while the markers
# are read (`EarlyRefinement`), unless they number more than this per board corner.
MAX_EARLY_PER_CORNER = 2


# The finest level searched: an 8000x6000 photo at full resolution took 145 s and 9.5 GB in the network;
# at 2048 px its squares need to be >= ~50 px (12 px at this level) to be found, and every corner is still
# refined at full resolution.
MAX_SEARCH_SIZE = 2048


# A search level within this factor of the full image is the full image: a tracked crop's working size, its frame's
# scale rounded, put a doubled level a pixel or two short of the crop (a 157-px crop: 78, 156, then 157 px), and
# where the board's squares were too narrow at 156 px the network and the markers ran again at 157.
LEVEL_SNAP = 1.05


# Search levels no longer than this are searched whole; finer ones only around what the level before found or saw
# (`Detector._search`, `deepcharuco.detection.search_regions`): a frame without a board is not searched above 640 px, and a
# small board in a large frame costs the pixels around it. 320 was faster still (a 1280x720 frame without a board
# 12 ms) but lost boards whose squares are large enough yet unreadable at 320 px (calibtargets' defocused 22x22
# board: 22 of 89 corners, one frame none), which only a whole finer level finds (docs/detector.md).
WHOLE_SEARCH_SIZE = 640


# Regions covering more of a level than this: the level is searched whole (one network pass beats many crops).
MAX_REGION_SHARE = 0.5


# RefineNet may move a corner this far from the point head's own pixel, no farther: in near darkness it drew
# some good corners 3-6 px off, onto noise; beyond the protocols' own 3 px the point head's pixel is kept.
# Chosen on validation renders (seed 2000): no protocol level lower (darkness k=9 0.378 -> 0.401), wrong
# corners 332 -> 234, good-light eps_re unchanged.
MAX_REFINE_MOVE_PX = TOLERANCE_PX


# Where the printed-pattern fit follows (`corner_fit`), a level at most this many times smaller than the full image has
# its corners refined by RefineNet once, at full resolution, from their cell pixels scaled up (a cell pixel within
# ~1.5 px of its corner at the level lands within ~3 px, inside the central 8x8 of RefineNet's patch), instead of at
# the level and again at full resolution: half the patches. Validation (`python -m
# evaluate.calibration.corner_precision --seed 0 --frames 3 --conditions good oblique dark5 dark7 blur9`: 640x480
# frames, found at 320 px): the same corners, the detector's median and p90 errors within 1e-3 px of two passes in
# each condition. A 4x smaller level's cell pixels land up to ~6 px off, beyond the patch's reach: two passes there.
ONE_PASS_MAX_RATIO = 2.0


# A cell's second likeliest ID goes to RANSAC only where the ID head gives it at least this much: in good
# light the second IDs are all near 0 and only slow RANSAC down (validation renders, seed 2000: detection
# 13 % faster, no protocol level lower by more than 0.001; 0.003 and above lost blur k=7 0.016).
SECOND_ID_MIN_PROB = 0.001


# "hybrid": OpenCV first, kept when the board's geometry verifies it; the networks only where it fails.
MODES = ("deep", "hybrid")

# Where an inverted print the first search does not find is searched again negated about its local white
# (`Detector.detect`'s ``local_white``): in every frame, or only in a dim one (a `BoardTracker`'s whole frames).
LOCAL_WHITE = ("always", "dim")


# What searches a whole frame again where the fast networks find fewer than 4 corners in it, by (network, whether the
# frame is a stream's): the lite networks "dim" (where the frame is dim, `search_regions.is_dim`), "seen" (where it is
# dim, or where the fast networks saw `BACKUP_MIN_CELLS` corner-like cells in one pass, `levels.Seen`) or "never";
# "finest": where it is dim, the fast networks search its finest level whole, where their search of it went
# only where a coarser level saw board-like cells (a level longer than `WHOLE_SEARCH_SIZE`); else as "dim". "fast" is
# for speed: a dark video's frames without a board would each cost lite's whole search (docs/detector.md, "A dim
# whole frame searched by the lite networks"). "auto" is for lite's frames: on the real videos as `detect` reads
# them, and on the real photos, it found what lite finds, at the fast networks' speed in lit videos (docs/detector.md,
# "Auto: the fast networks first, the lite ones where they find too little"). A lit photo in which they saw fewer than
# `BACKUP_MIN_CELLS` corner-like cells had no board lite found, on drawn validation frames of steep, defocused, small
# and cut-off boards (`benchmarks/photo_backup.py`); it had cost lite's search (docs/detector.md, "A lit photo's lite
# search only where the fast networks saw corners"). In a dim stream the boards lite found and they did not were small (squares of 7-11 px at
# 720p), which their own finest level found as often, at a third of lite's cost: the real dark videos the same frames
# at 2-3x the speed (docs/detector.md, "A dark video's frames searched at full resolution").
WHOLE_BACKUP = {("fast", False): "dim", ("fast", True): "never", ("auto", False): "seen", ("auto", True): "finest"}
BACKUP_MIN_CELLS = 3

# "markers" reads the board from its markers, so it needs the point head alone and fits any board.
DECODINGS = (*GEOMETRY_MODES, "markers")


def shipped_weights(board: BoardSpec | None, folder: str | Path | None = None) -> Path:
    """The shipped weights `Detector` loads for ``board`` when none are given: the paper's board-specific model
    (`DEFAULT_WEIGHTS`, ID head and all) for no board or a board of its layout; else the family model of the
    board's marker family (`FAMILY_WEIGHTS_DIR`/<family>.pt) when this version ships one; else the paper's
    model, whose point head finds the corners of other boards too (their IDs then come from the markers).

    ``folder``: a weights folder laid out as the shipped one (`is_weights_folder`: ``detector.pt`` and
    ``families/<FAMILY>.pt``, or their ONNX bundles alone): its models instead, chosen the same way."""
    if folder is None:
        default, families = DEFAULT_WEIGHTS, FAMILY_WEIGHTS_DIR
    else:
        default, families = _model_file(Path(folder) / "detector"), Path(folder) / "families"
    if board is None or board.same_layout(BoardSpec()):
        return default
    family = marker_family(board.dictionary)
    if family is not None:
        model = _model_file(families / family)
        if model.exists():
            return model
    return default


def _model_file(stem: Path) -> Path:
    """``stem``.pt, or its ONNX bundle ``stem``.onnx where only that is there."""
    checkpoint = stem.with_suffix(".pt")
    bundle = stem.with_suffix(".onnx")
    return bundle if not checkpoint.is_file() and is_bundle(bundle) else checkpoint


def is_weights_folder(path: str | Path) -> bool:
    """Whether ``path`` is a folder of weights laid out as the shipped ones (``detector.pt`` or its bundle
    ``detector.onnx/``, and optionally ``families/<FAMILY>.pt`` or ``.onnx/``): `shipped_weights` picks from it."""
    path = Path(path)
    return path.is_dir() and not is_bundle(path) and _model_file(path / "detector").exists()


def _torch_installed() -> bool:
    try:
        import torch  # noqa: F401
    except ImportError:
        return False
    return True


def _onnx_bundle(weights: Path, refine_weights: str | Path | None) -> OnnxBundle | None:
    """The ONNX bundle the detector runs (`deepcharuco.networks.onnx_bundle`): ``weights`` itself when it is one, else
    the one beside the weights where PyTorch is not installed; None where PyTorch reads the weights."""
    if Path(weights).is_dir() and not is_bundle(weights):
        raise BundleError(f"{weights} is a folder without bundle.json or detector.pt, so neither an ONNX bundle nor a "
                          f"weights folder: give the weights file (.pt), a bundle folder (deepcharuco export --bundle "
                          f"--weights NAME.pt), or a folder laid out as deepcharuco/weights")
    if is_bundle(weights):
        if refine_weights is not None:
            raise DeepCharucoError(f"{weights} is an ONNX bundle and holds its own RefineNet: leave refine_weights out")
        bundle = read_bundle(weights)
        if _torch_installed():  # the network's own fingerprint; without PyTorch, the file's sha256 stands in
            from deepcharuco.networks.runtime import check_fingerprint
            check_fingerprint(bundle)
        elif bundle.meta.get("weights"):  # a bundle that names no weights file has none to be checked against
            check_exported_from(bundle, bundle.path.parent / str(bundle.meta["weights"]))
        return bundle
    if _torch_installed():
        return None
    if is_bundle(bundle_path(weights)) and refine_weights is None:
        bundle = read_bundle(bundle_path(weights))
        check_exported_from(bundle, weights)
        return bundle
    raise DeepCharucoError(
        f"{weights} is a PyTorch checkpoint and PyTorch is not installed: pip install torch (the CPU build is enough), "
        f"or where PyTorch is, write its ONNX bundle (deepcharuco export --bundle --weights {weights}) and "
        f"pass weights={bundle_path(weights)}")


def _bundle_runner(bundle: OnnxBundle, backend: str, refinenet: bool, points_only: bool) -> OnnxRunner:
    """ONNX Runtime over a bundle's models; ``backend`` as `deepcharuco.networks.runtime.resolve_backend` reads it on the CPU
    ("auto": the int8 ChArUcoNet where the bundle has one, run whole)."""
    check_choice("backend", backend, BACKENDS)
    if backend == "torch":
        raise DeepCharucoError("backend='torch' needs PyTorch: pip install torch, or use backend='auto' or 'onnx'")
    if not onnxruntime_available():
        raise DeepCharucoError("the networks need ONNX Runtime (or PyTorch): pip install onnxruntime")
    int8 = bundle.models.get("charuconet_int8.onnx")
    if backend == "onnx-int8" and int8 is None:
        raise DeepCharucoError(f"{bundle.path} carries no int8 model: use backend='onnx'")
    refine_model = bundle.models.get("refinenet.onnx") if refinenet else None
    if refinenet and refine_model is None:
        raise DeepCharucoError(f"{bundle.path} holds no RefineNet: use refine='subpix' or 'none'")
    refine_names = ["refinenet.onnx"] if refine_model is not None else []
    if backend in ("auto", "onnx-int8") and int8 is not None:
        return checked_runner(bundle, ["charuconet_int8.onnx", *refine_names],
                              lambda: OnnxRunner(int8, refine_model, name="onnx-int8"))
    name = "charuconet_points.onnx" if points_only else "charuconet.onnx"
    return checked_runner(bundle, [name, *refine_names], lambda: OnnxRunner(bundle.models[name], refine_model))


class Detector:
    """The deep ChArUco detector.

    Args:
        board: the board (default: the weights' board). A board of another layout than the weights'
            (grid, dictionary, legacy flag, marker/square ratio) is found by its markers
            (``geometry="markers"``) with no training; the same board at another size, inverted or
            mirrored keeps the weights' ID head.
        weights: a ChArUcoNet checkpoint or a bundle with both networks (default: the shipped weights for the
            board, `shipped_weights`: the paper's board-specific model for its board, the family model of the
            board's marker family where one is shipped, else the paper's), or a folder of them laid out as the
            shipped ones (`is_weights_folder`), chosen from the same way. ``self.weights`` says which. An ONNX
            bundle (``NAME.onnx/``, `deepcharuco.networks.onnx_bundle`) runs without PyTorch; where PyTorch is not
            installed, the bundle beside ``NAME.pt`` is run (the shipped weights all have one).
        refine: "refinenet" (the paper's best), "subpix" (OpenCV cornerSubPix) or "none" (cell pixels).
        device: "cpu", "cuda", "mps" ...
        refine_weights: RefineNet checkpoint when ``weights`` holds only ChArUcoNet.
        threshold: the smallest score (point confidence x ID probability; "markers": point confidence)
            a corner is reported at (default: the operating point stored with the weights, chosen on
            validation frames; else 0.3).
        soft_radius: RefineNet soft-argmax window (cells of 1/8 px) around the argmax; 0 = argmax only.
        working_size: longest image side the network searches at first (default 320); larger images are
            reduced to it, then to twice it ... up to full resolution (at most 2048 px, `MAX_SEARCH_SIZE`)
            until the board is found with squares of at least 16 px, and their corners refined again at
            full resolution; levels above 640 px only in the regions a coarser level found the board or saw
            board-like cells in (`deepcharuco.detection.search_regions`). None: native resolution only, whatever its size.
        preview: an image no longer than ``working_size`` is searched at half size first (a quarter of the
            network's cost) and those corners kept when they are the whole board in view (every corner their
            view puts in the image, squares >= 12 px there), refined at full resolution; else the full image
            is searched as with ``preview=False``. Only with ``geometry`` "repair" or "filter".
        mode: "deep" (default) or "hybrid": OpenCV's detector (+ cornerSubPix) runs first and its corners
            are returned when at least 6 of them, and nine in ten, fit one view of the board (to 3 px or a
            quarter of the corner spacing); the networks
            run only when they do not (near OpenCV's speed in good light, the networks' recall in bad light).
        geometry: how corners get their IDs (default: "repair" for the weights' board, "markers" otherwise):
            "repair": the confident cells' two likeliest IDs are fitted to one view of the board
            (RANSAC homography, 6 or more agreeing); the corners that view predicts take the confident cells
            found there (wrong IDs dropped, IDs the ID head was unsure of recovered);
            "filter": keep only the corners that fit the view; "none": the paper's decoding as it is.
            With "repair" or "filter" the view must also show the board's own markers where it puts them
            (`verification.view_is_verified`: a look-alike board gives nothing), and corners that fit no view
            (fewer than 6, or IDs that disagree) are decoded by their markers as with "markers", or dropped:
            no answer rather than a wrong pose. `decode` without the image keeps the older rule: 6 or more
            corners that fit no view are dropped, fewer are returned unchecked.
            "markers": the ID head is not used; the markers in the chessboard cells between the point
            head's corners are read and matched to the board's own, and the view that 2 or more distinct
            markers agree on names every corner (`deepcharuco.detection.markers.placement`). A board with other markers
            (another dictionary, other IDs, mirrored) yields nothing.
        backend: how the networks run (`deepcharuco.networks.runtime`): "auto" (default: on CPU, ONNX Runtime with the
            weights' accepted int8 ChArUcoNet if they carry one, else float32 ONNX Runtime when installed, else
            PyTorch), "torch", "onnx" or "onnx-int8".
        reader: how markers are read (`deepcharuco.detection.markers.marker_reader.READERS`): "sampled" (the default, 4 samples
            per bit correlated with the board's markers) or "learned" (a 9.5k-parameter CNN's bit logits).
        boards: several boards to find in each image instead of ``board`` (boards of different dictionaries, or of
            one dictionary with other ``first_marker_id``s: rigs cover a room with several). `detect_boards`
            returns one `Detection` per board, in this order, each with that board's corner IDs; `detectors`
            are the per-board detectors (for `BoardTracker` and poses); ``detect`` refuses (its one result could
            not say which board a corner is of). Each board is searched on its own: N boards cost N searches.
        corner_fit: each corner's last position is where the board's printed pattern, blurred, fits the pixels
            around it (`deepcharuco.detection.corner_fit`), from where ``refine`` put it, and the detection carries each
            corner's covariance; a corner the fit cannot place keeps ``refine``'s position, with a sigma of
            `FALLBACK_SIGMA_PX` or its distance from where its neighbours put it, whichever is larger.
            False: ``refine``'s positions, no covariances.
        network: "lite" (default: the shipped networks, or ``weights``), "fast" or "auto". "fast": the shipped
            distilled fast ChArUcoNets (`FAST_WEIGHTS_DIR`, ONNX bundles, CPU only; 2-4x less network time, less
            recall on small and dark boards: docs/detector.md, "The fast networks"), with the lite networks looking
            where they lose a tracked board and searching a dim photo they find nothing in (`backup`). "auto" (the
            command line's default): the fast networks first and the lite ones wherever those find too little: a
            tracked board lost, a photo that is dim or shows corner-like cells (`BACKUP_MIN_CELLS`), and a stream's
            dim whole frames (`detect`'s ``stream``; where its finest level is longer than `WHOLE_SEARCH_SIZE`, the
            fast networks search that level whole instead); lite's frames at the fast networks' speed where those
            find the board. Neither with ``weights``. Weights whose bundle says ``input_white`` (the fast networks':
            `input_white` attribute) see a dim whole frame brightened (`levels.network_input`), not a tracked crop
            (``detect``'s ``expected``).

    Every argument after ``weights`` is keyword-only.

    Raises:
        OptionError: an option outside its choices (``refine``, ``mode``, ``backend``, ``reader``, ``geometry``),
            ``working_size`` below 16 px, or ``board`` and ``boards`` both given.
        DeepCharucoError: weights that cannot be read or run here (missing, damaged, a backend not installed),
            each with the fix.
    """

    min_square_px = MIN_SQUARE_PX  # a board found with narrower squares is searched again at the next finer level

    def __init__(self, board: BoardSpec | None = None, weights: str | Path | None = None, *, refine: str = "refinenet",
                 device: str = "cpu", refine_weights: str | Path | None = None, threshold: float | None = None,
                 soft_radius: int = 2, geometry: str | None = None, working_size: int | None = WORKING_SIZE,
                 mode: str = "deep", backend: str = "auto", reader: str | None = None, preview: bool = True,
                 boards: list[BoardSpec] | None = None, corner_fit: bool = True, network: str = "lite"):
        self._each: list[Detector] = []
        self._backup_options: dict | None = None  # `backup`'s arguments (the fast networks')
        self._backup: Detector | None = None
        self.local_white_skipped = False  # whether the last `detect` left an inverted print's second search out
        given_weights, given_geometry, weights = weights, geometry, network_weights(network, weights, device)
        if network == "lite" and weights is not None and Path(weights).resolve() == FAST_WEIGHTS_DIR.resolve():
            network = "fast"  # the shipped fast networks named by their folder
        self.network = network
        self.corner_fit = bool(corner_fit)
        if boards is not None:
            boards = list(boards)
            if board is not None:
                raise OptionError("give board or boards, not both")
            if not boards:
                raise OptionError("boards is empty: give one board or more")
            check_boards_apart(boards, [f"boards[{i}]" for i in range(len(boards))])
            if len(boards) > 1:
                self.boards = boards
                self._each = [Detector(board=b, weights=given_weights, refine=refine, device=device,
                                       refine_weights=refine_weights, threshold=threshold, soft_radius=soft_radius,
                                       geometry=geometry, working_size=working_size, mode=mode, backend=backend,
                                       reader=reader, preview=preview, corner_fit=corner_fit, network=network)
                              for b in boards]
                self.board = None
                return
            board = boards[0]
        check_choice("refine", refine, REFINE_MODES)
        check_choice("mode", mode, MODES)
        if reader is not None:
            check_choice("reader", reader, READERS)
        if geometry is not None:
            check_choice("geometry", geometry, DECODINGS)
        if weights is not None and is_weights_folder(weights):
            weights = shipped_weights(board, weights)
        if weights is None:
            weights = shipped_weights(board)
            if not weights.is_file():
                raise DeepCharucoError(
                    f"no shipped weights in this version ({weights} is missing): train them with python -m "
                    f"train.charuconet and python -m train.refinenet, then pass weights=..., refine_weights=...")
        self.weights = Path(weights)
        bundle = _onnx_bundle(self.weights, refine_weights)  # None: PyTorch reads the weights
        if bundle is None:
            import torch

            from deepcharuco.networks.checkpoint import load_charuconet

            self.device = torch.device(device)
            self.charuconet, trained_for, self.checkpoint = load_charuconet(weights)
        else:
            if device != "cpu":
                raise DeepCharucoError(f"device={device!r} needs PyTorch: without it the networks run on the CPU "
                                       f"(ONNX Runtime); pip install torch, or use device='cpu'")
            self.device, self.charuconet, trained_for, self.checkpoint = "cpu", None, bundle.board, bundle.meta
        self.board = board or trained_for
        own_board = self.board.same_layout(trained_for)
        if geometry is None:
            stored = self.checkpoint.get("geometry")  # its own board's, where the bundle says (--default-geometry)
            geometry = (stored if stored in DECODINGS else "repair") if own_board else "markers"
        elif geometry != "markers" and not own_board:
            raise DeepCharucoError(
                f"geometry={geometry!r} decodes with the ID head of {weights}, trained for {trained_for}, whose "
                f"layout differs from {self.board}: use geometry='markers' (or leave it out) for this board")
        self.refine = refine
        self.threshold = float(threshold if threshold is not None else self.checkpoint.get("threshold", DEFAULT_THRESHOLD))
        self.input_white = input_white(self.checkpoint, self.weights)
        self.soft_radius = int(soft_radius)
        self.geometry = geometry
        if working_size is not None and working_size < 2 * CELL:
            raise OptionError(f"working_size must be None (native resolution) or >= {2 * CELL} px, got {working_size}")
        self.working_size = working_size
        self.mode = mode
        # Only with the board-geometry check of the weights' own board. Not by markers: on the 4x5 inverted
        # DICT_4X4 board's sequences the preview put 12 corners, 3 of them wrong, on two frames the full image
        # found nothing in (a confidently wrong pose); its validation views had shown none. Not "none": the
        # paper's decoding stays the paper's.
        self.preview = bool(preview) and geometry in ("repair", "filter")
        self.reader = reader
        self._opencv = OpenCVDetector(self.board, refine="subpix") if mode == "hybrid" else None
        self._board_xy = self.board.corner_points()[:, :2]
        if geometry == "markers":  # drawn now, not in the first frame that fills a corner in (~50 ms for 11x8 squares)
            printed_pattern(self.board)
        # The fast networks lose some boards the lite ones read (steep, cut by the frame's edge, dark): where a tracked
        # board (``expected``) is lost to them, the lite networks look in the same crop (`backup`), built when first
        # needed (a `BoardTracker` asks at once), and search the whole frames `WHOLE_BACKUP` names.
        # Deep alone: in hybrid mode OpenCV has just looked there.
        self._backup_options = None if network == "lite" else dict(
            board=self.board, refine=refine, device=device, refine_weights=refine_weights, threshold=threshold,
            soft_radius=soft_radius, geometry=given_geometry,
            working_size=working_size, backend=backend, reader=reader, preview=preview, corner_fit=corner_fit)
        self.refinenet = None
        # Boards found by their markers never read the ID head: ChArUcoNet runs without it (~1 ms at 320x240).
        if bundle is None:
            from deepcharuco.networks.checkpoint import load_refinenet
            from deepcharuco.networks.runtime import make_runner

            if refine == "refinenet":
                self.refinenet, _ = load_refinenet(refine_weights or weights)
            self.runner = make_runner(backend, self.charuconet, self.refinenet, self.device, self.checkpoint,
                                      points_only=geometry == "markers")
        else:
            self.runner = _bundle_runner(bundle, backend, refine == "refinenet", points_only=geometry == "markers")

    @property
    def detectors(self) -> list["Detector"]:
        """One single-board detector per board (`boards`), or ``[self]``."""
        return list(self._each) or [self]

    def detect_boards(self, image: np.ndarray) -> list[Detection]:
        """One `Detection` per board (``boards``, or this detector's one board), in order; empty where a board is
        not found."""
        return [detector.detect(image) for detector in self.detectors]

    def __repr__(self) -> str:
        if self._each:
            return f"Detector(boards={self.boards!r})"
        return (f"Detector(board={self.board!r}, refine={self.refine!r}, geometry={self.geometry!r}, "
                f"mode={self.mode!r}, device={str(self.device)!r}, backend={self.runner.name!r}, "
                f"network={self.network!r})")

    def detectBoard(self, image: np.ndarray):  # noqa: N802 - OpenCV's name, so that scripts switch in one line
        """`detect` in the shapes ``cv2.aruco.CharucoDetector.detectBoard`` returns: (charuco corners (N, 1, 2)
        float32, charuco ids (N, 1) int32; None for both when none are found; marker corners ``()``, marker ids
        None: the corners do not come from OpenCV's marker detection, and in the dark there are none to give)."""
        return detect_board_result(self.detect(image))

    def detect(self, image: np.ndarray, *, working_size: int | None = None, levels: int | None = None,
               expected: Detection | None = None, local_white: str = "always", stream: bool = False,
               dim_backup: bool | None = None) -> Detection:
        """Find the board's corners in a uint8 grayscale (or BGR) image of any size.

        Images longer than ``working_size`` are searched at that size (area-averaged) first, then at twice
        that, up to full resolution, until a verified board is found whose squares are at least
        `MIN_SQUARE_PX` wide there (else the finest level that found one); each corner is refined again in
        the full-resolution image. Large boards are found where the network sees them best, and a large
        image costs little when the board is found at a coarse level; levels longer than
        `WHOLE_SEARCH_SIZE` are searched only around what a coarser level found or saw (`_search`). An image no longer than ``working_size``
        is previewed at half size first (``preview``). ``working_size`` overrides the first level's size for
        this call (`BoardTracker` searches a crop at the scale its whole frame was searched at); ``levels``
        searches only the first (coarsest) that many levels (`BoardTracker`'s quick search while it has lost
        the board: a board whose squares are too small there is not found, nor an inverted print that only its
        local white shows, `print_face.canonical_view_local_white`); in hybrid mode a quick look is the networks'
        alone: OpenCV on a whole frame without a board costs more than the fast networks' coarse level.
        ``expected``: where the board's corners are expected in ``image`` (`BoardTracker`: the frame before's); a
        board found by its markers is first looked for in that view, moved onto the point head's corners and verified
        by its markers as any view is (`placement.view_near`), and searched for through its cells only where that
        fails. With ``network`` "fast" or "auto", where the fast networks lose an ``expected`` board (fewer corners
        than a tracker keeps, 4), the lite networks look in the image as well (`backup`): on the real videos that
        found the lite networks' frames on every lit video, for 0-9 % of the fast networks' speed (docs/detector.md,
        "The lite networks behind the fast ones"). Where they find fewer than 4 in a whole frame (nothing
        ``expected``, every level: no ``levels``), the lite networks search it whole as well (`WHOLE_BACKUP`): with
        "fast" a photo that is dim (`search_regions.is_dim`: the fast networks miss dark, steep boards that lite
        reads), with "auto" a photo that is dim or in which they saw `BACKUP_MIN_CELLS` corner-like cells in one pass
        (`levels.Seen`: a lit photo with fewer had no board lite found, on drawn validation frames) and a stream's dim
        frames (below); with "auto" a dim photo whose board they found in part (fewer corners than their view of it
        puts inside the image) is searched by lite too, and the detection with more corners kept. ``stream``: the
        frame is one of a video's or a camera's, searched whole (`BoardTracker`'s whole searches, `StreamFrames`):
        with "fast" the lite networks never search it (in a dark video that cost lite's whole search in every frame
        without the board: docs/detector.md, "A dim whole frame searched by the lite networks"), with "auto" only where
        it is dim, and where the fast networks searched its finest level only around board-like cells (a level longer
        than `WHOLE_SEARCH_SIZE`) they search that level whole instead, as one level (the real dark videos' frames at
        2-3x the speed: docs/detector.md, "A dark video's frames searched at full resolution").
        ``dim_backup=False``: the same as ``stream=True`` (its earlier name).
        ``local_white``: where an inverted print that the first search does not find (but saw board-like cells) is
        searched again negated about its local white (`print_face.canonical_view_local_white`): "always", or "dim":
        only in a dim frame (`search_regions.is_dim` of its coarse level). A `BoardTracker`'s whole-frame searches ask
        for "dim": in a lit frame without a board the second search doubled the cost, and a tracker's crops and look
        back keep it. ``local_white_skipped`` then says whether this call left it out.

        numpy's BLAS runs single-threaded for the call (`core.blas.single_threaded_blas`) and is restored after."""
        if self._each:
            raise DeepCharucoError(f"this Detector finds {len(self._each)} boards: detect_boards(image) returns one "
                                   f"Detection per board")
        check_choice("local_white", local_white, LOCAL_WHITE)
        with single_threaded_blas():
            found, looked = self._detect(image, working_size, levels, expected, local_white)
        if self._backup_options is None:
            return found
        whole, stream = expected is None and levels is None, stream or dim_backup is False
        if len(found) < MIN_TRACKED_CORNERS:
            if expected is not None:
                tally("backup looks")
                return self.backup.detect(image, working_size=working_size, levels=levels, expected=expected)
            finest = whole and looked.dim and WHOLE_BACKUP[self.network, stream] == "finest" \
                and self._finest_searched_in_part(image.shape[:2], working_size)
            if finest:
                # That level as a search of one level (``levels``): OpenCV (hybrid) does not look again, nor does an
                # inverted print's second search about its local white, which the coarser levels made; on the drawn
                # validation videos it found no frame more for 12 % more time (docs/detector.md).
                tally("finest searches")
                with single_threaded_blas():
                    more, _ = self._detect(image, finest, levels=1)
                return more if len(more) > len(found) else found
            if not (whole and self._backs_whole(looked, stream)):
                return found
        elif not (whole and looked.dim and not stream and self.network == "auto"
                  and not self._whole_view_found(found.ids, found.corners, image.shape[:2])):
            return found
        # Too few corners, or (auto) a dim photo's board found in part: the fast networks' confidences fade first in
        # the dark (the report's darkness k = 9: lite 0.988 of the corners, fast 0.897, most boards found in part).
        tally("backup searches")
        more = self.backup.detect(image, working_size=working_size, local_white=local_white)
        return more if len(more) > len(found) else found

    def _backs_whole(self, looked: Seen, stream: bool) -> bool:
        """Whether the lite networks search a whole frame the fast networks found fewer than 4 corners in: ``looked``,
        what their search saw there; ``stream``, whether it is a stream's (`detect`)."""
        rule = WHOLE_BACKUP[self.network, stream]
        if rule == "never":
            return False
        return looked.dim or (rule == "seen" and looked.corner_cells >= BACKUP_MIN_CELLS)

    def _finest_searched_in_part(self, shape: tuple[int, int], working_size: int | None) -> int | None:
        """The finest level's longest side (px) where a whole search of an image of ``shape`` (H, W) searches that
        level only where a coarser one saw board-like cells (`_search`: a level longer than `WHOLE_SEARCH_SIZE`), else
        None (every level it searches, it searches whole)."""
        longest = max(shape)
        scales = self._level_scales(longest, working_size or self.working_size)
        size = round(scales[-1] * longest)
        return size if len(scales) > 1 and size > WHOLE_SEARCH_SIZE else None

    @property
    def backup(self) -> Detector | None:
        """With ``network`` "fast" or "auto": the lite networks' deep detector of the same board and options, which
        looks where the fast networks lose an expected board (`detect`'s ``expected``: the board a `BoardTracker`
        follows) and searches the whole frames they find too little in (`WHOLE_BACKUP`), built at the first use
        (`BoardTracker` asks when it is made). None with the lite networks."""
        if self._backup is None and self._backup_options is not None:
            self._backup = Detector(**self._backup_options)
        return self._backup

    @property
    def backup_weights(self) -> Path | None:
        """The weights `backup` reads (the shipped lite networks for this board), named without building it; None with
        the lite networks."""
        return None if self._backup_options is None else shipped_weights(self.board)

    def _detect(self, image: np.ndarray, working_size: int | None, levels: int | None = None,
                expected: Detection | None = None, local_white: str = "always") -> tuple[Detection, Seen]:
        """`detect` by these networks alone -> (the detection, what their first search saw: `backup`'s cues; its
        ``dim`` False where OpenCV's corners stand, where the preview found the board, and where the markers beyond the
        view refused it)."""
        self.local_white_skipped = False
        # Not in a quick look (`levels`): while the board is away OpenCV's whole-frame search was 2/3 of a hybrid
        # quick look's time (the fast networks' coarse level ~8 ms, OpenCV ~17 ms on caliscope's 720p webcams). The
        # next full search runs OpenCV; a whole video looks back from it (`BoardTracker.push`).
        if self._opencv is not None and levels is None:
            with stage("opencv"):
                found = self._opencv.detect(image)
            if self._verified(found):
                return (self._opencv_fitted(image, found) if self.corner_fit else found), Seen(board_like=True)
        with stage("canonical view"):
            gray_u8 = to_gray_u8(image)
            full = canonical_view(gray_u8, self.board)  # the networks learnt black ink on white paper
        working_size = working_size or self.working_size
        prior = self._expected_view(expected, full.shape[1])
        # The fast networks' dim input brightened (their bundle's ``input_white``) where nothing is expected: in a tracked
        # crop the expected view holds the board, and brightened crops put corners 3-10 px off on caliscope's darkened
        # videos, where the lit frames' detections and OpenCV's agree (docs/detector.md).
        white = self.input_white if expected is None else None
        found, looked = self._search(full, working_size, levels, prior,
                                   None if prior is None else corner_spacing(expected.corners), white)
        second = found is None and looked.board_like and self.geometry == "markers" and self.board.inverted \
            and levels is None
        self.local_white_skipped = second and local_white == "dim" and not looked.dim
        if second and not self.local_white_skipped:
            # An inverted print negated about the frame's white is pale grey on white under a shadow, or when dim
            # in a frame whose white is a lamp: negated about its local white it is a dim board (`print_face`).
            # Only where the first search saw board-like cells: a frame without a board was searched twice. Not in a
            # quick look at the first levels, nor in a lit frame where the caller asks (``local_white`` "dim": a
            # `BoardTracker`'s whole frames, which its crops and its look back cover).
            with stage("canonical view"):
                full = canonical_view_local_white(gray_u8, self.board)
            found, _ = self._search(full, working_size, levels, prior, white=white)
        if found is None:
            return Detection.empty(), looked
        region = found.region
        gray, ids, pixels, scores = found.gray, found.ids, found.pixels, found.scores
        by_pattern = scores == PATTERN_SCORE if self.geometry == "markers" else np.zeros(len(ids), bool)
        # Refined where found, then again at full resolution: a single full-resolution pass from the reduced
        # level's cell pixel (up to ~1.5 px off) fitted a pose less well in good light (validation sequences,
        # seed 2001: corner error 0.082 vs 0.075 px). A preview's squares are >= 12 px wide: there
        # cornerSubPix centres the corners as well as RefineNet does, for a tenth of its cost.
        ratio = found.ratio()
        corners = (pixels.astype(np.float32) + 0.5) * ratio - 0.5  # pixel centres: OpenCV's convention at both sizes
        seen = ~by_pattern
        with stage("refine"):
            corners = self._refined(region, gray, pixels, corners, seen, ratio, found.preview, found.early)
        if by_pattern.any():  # corners the point head missed (a shadow's edge): where the printed pattern fits
            with stage("pattern fit"):
                corners[by_pattern] = self._placed_by_pattern(region, ids, corners, by_pattern)
        if self.geometry == "markers":  # corners refined away from where their neighbours put them go
            with stage("settle"):
                ids, corners, scores = settle_corners(self._board_xy, ids, corners, scores, self.threshold)
                ids, corners, scores = drop_isolated(self._board_xy, ids, corners, scores)
        covariances = None
        if self.corner_fit:
            with stage("corner fit"):
                # a corner the point head missed sits on a shadow's edge, which the fit's model does not hold: the
                # junction's pattern, which allows the edge, keeps it (tests/detection/test_junction.py)
                corners, covariances = self._fitted(region, ids, corners, keep=scores == PATTERN_SCORE)
        corners = corners + np.array(found.box[:2], np.float32)
        if self._layout_ends_short(full, found, ids, corners):
            return Detection.empty(), looked._replace(dim=False)
        return Detection(ids=ids, corners=corners_from_canonical(corners, self.board, full.shape[1]), scores=scores,
                         covariances=covariances_from_canonical(covariances, self.board)), looked

    def _layout_ends_short(self, full: np.ndarray, found: Found, ids: np.ndarray, corners: np.ndarray) -> bool:
        """Whether the board's own markers are printed beyond the edge of the view the markers verified, read in
        the whole canonical frame ``full`` (`verification.layout_ends_short`): the board file's layout is not the
        print's (its IDs shifted), though every marker inside the view agrees with it. The view is fitted to the
        refined corners (``ids``, ``corners`` in ``full``'s pixels) where they span the board in both directions (a
        level's whole cell pixels put squares two beyond the board a marker's width off), else it is the markers'
        view (``found.view``) mapped to ``full``."""
        if found.view is None:
            return False
        with stage("markers"):
            xy = self._board_xy[ids]
            if len(ids) >= 4 and np.linalg.matrix_rank(xy - xy.mean(axis=0), tol=1e-9) == 2:
                view, _ = cv2.findHomography(xy.astype(np.float64), corners.astype(np.float64), 0)
            else:
                view = from_level(found.view, found.box, found.gray.shape, found.region.shape)
            if layout_ends_short(full, self.board, view, self.reader):
                tally("views beyond the print")
                return True
        return False

    def _expected_view(self, expected: Detection | None, width: int) -> np.ndarray | None:
        """(3, 3) board metres -> the canonical image's pixels fitted to ``expected``'s corners (an image ``width`` px
        wide), or None: no expectation, fewer than `MIN_CONSENSUS` corners, or a board not found by its markers."""
        if expected is None or len(expected) < MIN_CONSENSUS or self.geometry != "markers":
            return None
        corners = corners_from_canonical(expected.corners, self.board, width).astype(np.float64)
        homography, _ = cv2.findHomography(self._board_xy[expected.ids].astype(np.float64), corners, 0)
        return homography

    def _opencv_fitted(self, image: np.ndarray, found: Detection) -> Detection:
        """OpenCV's verified corners placed by the printed-pattern fit, with their covariances (hybrid mode)."""
        with stage("corner fit"):
            full = canonical_view(to_gray_u8(image), self.board)
            width = full.shape[1]
            # a mirror's flip is its own inverse: the same call maps the corners into the canonical view and back
            canonical = corners_from_canonical(found.corners, self.board, width)
            corners, covariances = self._fitted(full, found.ids, canonical)
            return Detection(found.ids, corners_from_canonical(corners, self.board, width), found.scores,
                             covariances_from_canonical(covariances, self.board))

    def _fitted(self, full: np.ndarray, ids: np.ndarray, corners: np.ndarray, keep: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray | None]:
        """(N, 2) corners of ``ids`` in ``full`` -> (the printed pattern's fit of each where it converges, else the
        corner as it was; (N, 2, 2) covariances: the fit's, else the larger of `FALLBACK_SIGMA_PX` and the corner's
        distance from where its neighbours put it (`settling.neighbour_distances`), squared). ``keep`` (N,) bool:
        corners left where they are, with the fallback's covariance."""
        homography = view_homography(self.board, ids, corners)
        if homography is None:
            return corners, None
        fit_rows = np.ones(len(ids), bool) if keep is None else ~keep
        fit = fit_corners(full, self.board, homography, ids[fit_rows], corners[fit_rows])
        fitted = corners.copy()
        fitted[fit_rows] = fit.corners
        converged = np.zeros(len(ids), bool)
        converged[fit_rows] = fit.ok
        covariances = np.empty((len(ids), 2, 2))
        covariances[converged] = fit.covariances[fit.ok]
        if not converged.all():
            # Where the fit fails the corner is often off (seed-1515 validation renders: median 1.6-2.3 px, 1-3 % of
            # corners); its distance from where its neighbours put it tracks that error (error / it: median 1.01).
            distance = np.nan_to_num(neighbour_distances(self._board_xy, ids, fitted)[~converged], nan=0.0)
            covariances[~converged] = np.maximum(FALLBACK_SIGMA_PX, distance)[:, None, None] ** 2 * np.eye(2)
        return fitted.astype(np.float32), covariances

    def _refined(self, full: np.ndarray, gray: np.ndarray, pixels: np.ndarray, corners: np.ndarray, seen: np.ndarray,
                 ratio: np.ndarray, preview: bool, early: EarlyRefinement | None) -> np.ndarray:
        """``corners`` (N, 2) with the rows ``seen`` refined from their integer ``pixels`` in the level ``gray``,
        then again in ``full`` where the level was reduced by ``ratio``; in ``full`` alone where `_one_pass`."""
        if seen.any() and not preview and self._one_pass(gray, full):
            # ``corners`` hold the cell pixels scaled up to ``full`` as they come in: RefineNet starts from them
            corners[seen] = self._refinenet(full, corners[seen], MAX_REFINE_MOVE_PX * float(ratio.max()))
        elif seen.any():
            refined = nudged(gray, pixels[seen]) if preview and self.refine == "refinenet" else \
                self._refine(gray, pixels[seen], early=early)
            if gray is not full:
                refined = self._refine(full, (refined + 0.5) * ratio - 0.5, window_scale=float(ratio.max()))
            corners[seen] = refined
        return corners

    def _one_pass(self, gray: np.ndarray, full: np.ndarray) -> bool:
        """Whether RefineNet refines the corners found in the level ``gray`` once, in ``full`` from their cell pixels
        scaled up (`ONE_PASS_MAX_RATIO`), rather than in ``gray`` first: then none is refined early in ``gray``."""
        ratio = max(full.shape[0] / gray.shape[0], full.shape[1] / gray.shape[1])
        return self.refine == "refinenet" and self.corner_fit and gray is not full and ratio <= ONE_PASS_MAX_RATIO

    def _placed_by_pattern(self, full: np.ndarray, ids: np.ndarray, corners: np.ndarray, placing: np.ndarray
                           ) -> np.ndarray:
        """The corners ``placing`` (bool (N,)) of (ids (N,), corners (N, 2)) located where the board's printed
        pattern fits ``full`` best (`junction.locate_by_pattern`) in the view the others fit (least squares)."""
        homography = view_homography(self.board, ids[~placing], corners[~placing])
        if homography is None:
            return corners[placing]
        return locate_by_pattern(full, self.board, homography, ids[placing], corners[placing]).astype(np.float32)

    def _search(self, full: np.ndarray, working_size: int | None, levels: int | None = None,
                prior: np.ndarray | None = None, expected_spacing: float | None = None, white: float | None = None
                ) -> tuple[Found | None, Seen]:
        """The board searched level by level, coarse first, in the canonical image ``full`` -> (what the level
        that decided found, or None; what the search saw, `levels.Seen`: its ``dim`` False where the preview found the
        board).

        The preview (``self.preview``, images no longer than ``working_size``) stands when it holds the whole
        board in view. Levels no longer than `WHOLE_SEARCH_SIZE` are searched whole; a finer one only where the
        level before found the board with squares under `MIN_SQUARE_PX` (around it, first in the view its markers
        verified there, as a tracked board is), or saw board-like cells
        (`search_regions.board_like_boxes`), and not at all where it saw neither: a frame without a board
        stops at the coarse levels. Regions that would cover more than `MAX_REGION_SHARE` of a level make it
        searched whole. ``levels``: at most that many levels, coarse first (None: all). ``prior``: (3, 3) board
        metres -> ``full``'s pixels, where the board is expected (`_expected_view`); ``expected_spacing``: its
        corner spacing in ``full``'s pixels. An expected board is searched first from the first level where its
        squares are `MIN_SQUARE_PX` wide (the level a search from the coarsest would stop at), and the coarser
        levels only where that finds nothing (`_expected_start`). ``white``: the networks' dim inputs are brightened
        to it (`levels.network_input`; None: as they are)."""
        height, width = full.shape
        whole: Box = (0, 0, width, height)
        if self.preview and working_size is not None and 4 * CELL <= max(height, width) <= working_size:
            gray = reduced(full, 0.5)
            ids, pixels, scores, early, confidence, view = self._find(gray, full, "preview", white=white)
            if corner_spacing(pixels) >= MIN_PREVIEW_SQUARE_PX and self._whole_view_found(ids, pixels, gray.shape):
                # dim is asked only where nothing is found: not worked out for a board the preview found
                return (Found(whole, full, gray, ids, pixels, scores, preview=True, early=early, view=view),
                        Seen(True, False, corner_cells(confidence)))
            # part of the board, or squares too small to trust: the full image decides alone
        scales = self._level_scales(max(height, width), working_size)[:levels]
        start = self._expected_start(scales, max(height, width), expected_spacing)
        if start:
            found, looked = self._search_levels(full, scales, start, len(scales), prior, white)
            if found is not None:
                return found, looked
            found, coarse = self._search_levels(full, scales, 0, start, prior, white)
            return found, looked.merged(coarse)
        return self._search_levels(full, scales, 0, len(scales), prior, white)

    @staticmethod
    def _expected_start(scales: list[float], longest: int, spacing: float | None) -> int:
        """The level (an index of ``scales``) an expected board of corner ``spacing`` px (full image, whose longest
        side is ``longest``) is searched from first: the first where its squares are `MIN_SQUARE_PX` wide (else the
        finest), or 0 where there is no expectation or that level is longer than `WHOLE_SEARCH_SIZE` (searched whole,
        it would cost more than the coarse levels save)."""
        if not spacing or len(scales) < 2:
            return 0
        start = next((level for level, scale in enumerate(scales) if spacing * scale >= MIN_SQUARE_PX),
                     len(scales) - 1)
        return start if scales[start] * longest <= WHOLE_SEARCH_SIZE else 0

    def _search_levels(self, full: np.ndarray, scales: list[float], first: int, stop: int,
                       prior: np.ndarray | None, white: float | None = None) -> tuple[Found | None, Seen]:
        """`_search` through the levels ``scales[first:stop]``, the first of them whole -> (what the level that
        decided found, or None; what they saw, `levels.Seen`: ``dim`` of the first)."""
        height, width = full.shape
        whole: Box = (0, 0, width, height)
        found, board_like, boxes, dim, cells = None, False, [whole], False, 0
        for level in range(first, stop):
            scale = scales[level]
            if level > first:
                if found is not None:  # squares too small where found: look again, closer, around it alone
                    corners = (found.pixels + 0.5) * found.ratio() - 0.5 + np.array(found.box[:2], np.float32)
                    boxes = [search_region(corners, (width, height))]
                elif scale * max(height, width) <= WHOLE_SEARCH_SIZE:
                    boxes = [whole]
                if not boxes:
                    break  # the level before saw nothing board-like: no finer level will find a board
                if area_share(boxes, (width, height)) > MAX_REGION_SHARE:
                    boxes = [whole]
            tally("levels")
            level_found, next_boxes = None, []
            # A board the level before verified by its markers, with squares too narrow there, is looked for in that
            # view first, as a tracked board is: the same frames on the real videos, 0-6 % less time.
            level_prior = prior if found is None or found.view is None else \
                from_level(found.view, found.box, found.gray.shape, found.region.shape)
            for box in boxes:
                box = on_cell_grid(box, scale, (width, height))
                x0, y0, x1, y1 = box
                region = full[y0:y1, x0:x1]
                gray = region if scale == 1.0 else reduced(region, scale)
                if level == first:
                    dim = is_dim(gray)  # the whole frame at the first level searched
                ids, pixels, scores, early, confidence, view = self._find(
                    gray, region, level, to_level(level_prior, box, gray.shape, region.shape), white)
                cells = max(cells, corner_cells(confidence))
                reached = gray.shape[1] / region.shape[1]
                next_boxes += [(a + x0, b + y0, c + x0, d + y0) for a, b, c, d in
                               to_full(board_like_boxes(confidence, dim, self.board.num_corners), reached,
                                       (x1 - x0, y1 - y0))]
                if len(ids) and (level_found is None or len(ids) > len(level_found.ids)):
                    level_found = Found(box, region, gray, ids, pixels, scores, preview=False, early=early, view=view)
            board_like = board_like or bool(next_boxes) or level_found is not None
            boxes = next_boxes
            if level_found is not None:
                found = level_found
                if corner_spacing(found.pixels) >= MIN_SQUARE_PX:
                    break  # squares large enough here: a finer level would cost more and find no more
        return found, Seen(board_like, dim, cells)

    def _whole_view_found(self, ids: np.ndarray, pixels: np.ndarray, shape: tuple[int, int]) -> bool:
        """Whether (ids, pixels) are every board corner that their view (a homography fitted to them) puts
        inside an image of ``shape`` (H, W), at least half a cell from its border; False for fewer than
        `MIN_CONSENSUS` corners."""
        if len(ids) < MIN_CONSENSUS:
            return False
        homography, _ = cv2.findHomography(self._board_xy[ids].astype(np.float64), pixels.astype(np.float64), 0)
        if homography is None:
            return False
        predicted, w = apply_homography(homography, self._board_xy)
        height, width = shape
        margin = CELL / 2
        inside = (w * w[ids[0]] > 0) & (predicted >= margin).all(axis=1) \
            & (predicted[:, 0] <= width - 1 - margin) & (predicted[:, 1] <= height - 1 - margin)
        return bool(np.isin(np.flatnonzero(inside), ids).all())

    def _verified(self, detection: Detection) -> bool:
        """Hybrid mode: OpenCV's corners stand when at least `MIN_CONSENSUS` of them, and all but a tenth,
        fit one view of the board (`board_check.fit_board_homography`) to within 3 px or a quarter of the
        corner spacing, whichever is larger: a wide lens bends a large board's rows away from any one
        homography by more than 3 px, and a wrong ID lands a whole square away. A board of fewer corners
        than that (a 3x3 board has 4) stands on OpenCV's marker reads when every corner is found: no
        geometry can check so few (the networks' own view of it is proved by its markers' codes,
        `verification.code_errors`)."""
        if self.board.num_corners < MIN_CONSENSUS:
            return len(detection.ids) == self.board.num_corners
        if len(detection.ids) < MIN_CONSENSUS:
            return False
        tolerance = max(TOLERANCE_PX, 0.25 * corner_spacing(detection.corners))
        view = fit_board_homography(self.board.object_points()[detection.ids, :2], detection.corners, tolerance)
        return view is not None and view.inliers.sum() >= 0.9 * len(detection.ids)

    @staticmethod
    def _level_scales(longest: int, working_size: int | None) -> list[float]:
        """The scales (of the full image, whose longest side is ``longest``) the board is searched at, coarse first:
        ``working_size``, then twice that, ... up to the full image itself (a board whose squares are too small for
        the coarse level is found at a finer one), the finest never longer than `MAX_SEARCH_SIZE`; a level within
        `LEVEL_SNAP` of the full image is the full image."""
        if working_size is None:
            return [1.0]
        scales, size = [], max(working_size, 2 * CELL)
        while size * LEVEL_SNAP < longest and size < MAX_SEARCH_SIZE:
            scales.append(size / longest)
            size *= 2
        # the network never sees more than MAX_SEARCH_SIZE: memory and time stay bounded
        scales.append(1.0 if longest <= MAX_SEARCH_SIZE else MAX_SEARCH_SIZE / longest)
        return scales

    def _find(self, gray: np.ndarray, full: np.ndarray, level: int | str = 0, prior: np.ndarray | None = None,
              white: float | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, EarlyRefinement | None, np.ndarray, np.ndarray | None]:
        """ChArUcoNet and the decoding on a canonical image -> (ids, integer pixels, scores) in ``gray``, the
        `EarlyRefinement` started for them (or None), the (Hc, Wc) cell confidences, and the view the markers
        verified (3x3, board metres -> ``gray``'s pixels; None: none, or not found by markers); markers are read in
        ``full``, the same image at full resolution; ``level`` names the search level in stage times
        (`deepcharuco.core.stage_times`); ``prior``: where the board is expected, board metres -> ``gray``'s pixels
        (boards found by their markers); ``white``: ChArUcoNet's input brightened to it where dim (`network_input`)."""
        height, width = gray.shape
        with stage(f"network {level}"):
            point_logits, id_logits = self.runner.charuconet(network_input(gray, white))
        with stage("candidates"):
            confidence = cell_confidence(point_logits)
        if self.geometry == "markers":
            # Weaker cells too: they may only fill in corners of the view the confident ones found (`placement`).
            with stage("candidates"):
                candidates = candidates_in_image(cell_candidates(point_logits, None, weak_confidence(self.threshold),
                                                     confidence), (width, height))
            tally("candidate cells", int((candidates.confidence >= self.threshold).sum()))
            early = self._refine_early(gray, full, candidates.pixels[candidates.confidence >= self.threshold])
            with stage("markers"):
                found, view = corners_from_markers(gray, self.board, candidates, read_gray=full, reader=self.reader,
                                                   threshold=self.threshold, expected=prior)
            return (*found, early, confidence, None if view is None else view.view.homography)
        return (*self.decode(point_logits, id_logits, (width, height), gray, full, confidence), None, confidence, None)

    def _refine_early(self, gray: np.ndarray, full: np.ndarray, pixels: np.ndarray) -> EarlyRefinement | None:
        """RefineNet started on ``pixels`` of ``gray`` on the runner's background thread, or None where the
        runner cannot, RefineNet does not refine, refines the level's corners at full resolution alone (`_one_pass`), or
        the pixels are more than `MAX_EARLY_PER_CORNER` per board corner (a noisy frame's: refining them would take the
        core the next work needs)."""
        if self.refine != "refinenet" or not 0 < len(pixels) <= MAX_EARLY_PER_CORNER * len(self._board_xy) \
                or self._one_pass(gray, full):
            return None
        origins, patches = patches_around(gray, pixels)
        future = self.runner.refinenet_in_background(patches)
        return None if future is None else EarlyRefinement(gray=gray, pixels=pixels, origins=origins, logits=future)

    def _refine(self, gray: np.ndarray, pixels: np.ndarray, window_scale: float = 1.0,
                early: EarlyRefinement | None = None) -> np.ndarray:
        """(N, 2) corner pixels -> (N, 2) float32 refined in ``gray`` by ``self.refine``; ``window_scale``
        widens cornerSubPix's window when the pixels come from a reduced image; ``early``: RefineNet's output
        for some of these pixels, started while the markers were read."""
        if self.refine == "refinenet":
            # The limit holds for the point head's own pixels; corners scaled up from a reduced level may be
            # a few pixels off at full resolution, which is what RefineNet is there to correct.
            return self._refinenet(gray, pixels, MAX_REFINE_MOVE_PX if window_scale == 1.0 else np.inf, early)
        if self.refine == "subpix":
            window = max(3, round(3 * window_scale))
            criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 0.01)
            return cv2.cornerSubPix(gray, pixels.reshape(-1, 1, 2).astype(np.float32), (window, window), (-1, -1),
                                    criteria).reshape(-1, 2)
        return pixels.astype(np.float32)

    def decode(self, point_logits: np.ndarray, id_logits: np.ndarray | None, image_size: tuple[int, int],
               gray: np.ndarray | None = None, read_gray: np.ndarray | None = None,
               confidence: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One image's ChArUcoNet logits (65, Hc, Wc), (N+1, Hc, Wc) -> integer corner pixels before refinement:
        (ids (M,), pixels (M, 2) float32, scores (M,)), decoded at ``self.threshold`` with ``self.geometry``.
        ``image_size``: (width, height) of the image before padding. With ``gray`` (the image in the board's
        canonical appearance) a "repair"/"filter" view must also pass the marker check
        (`verification.view_is_verified`): a look-alike board (other markers) gives no corners; ``read_gray``
        is the same image at full resolution, to read the markers in; ``confidence``: the logits'
        `models.cells.cell_confidence` where the caller has it."""
        if self.geometry == "markers":
            raise DeepCharucoError("geometry='markers' reads the markers from the image: use detect(image)")
        width, height = image_size
        # A score is at most its cell's confidence: cells less confident than the threshold never count.
        with stage("candidates"):
            candidates = candidates_in_image(cell_candidates(point_logits, id_logits, self.threshold, confidence), image_size)
            ids, pixels, scores = best_per_id(candidates, self.threshold)
        tally("candidate cells", len(candidates))
        view = None
        with stage("board check"):
            if self.geometry == "filter":
                view = fit_board_homography(self._board_xy[ids], pixels)
                if view is not None:
                    ids, pixels, scores = ids[view.inliers], pixels[view.inliers], scores[view.inliers]
            elif self.geometry == "repair":
                proposed_ids, proposed_pixels = id_hypotheses(candidates, min_prob=SECOND_ID_MIN_PROB)
                view = fit_board_homography(self._board_xy[proposed_ids], proposed_pixels)
                if view is not None:
                    ids, pixels, scores = assign_ids(view, self._board_xy, candidates, (width, height))
        if self.geometry == "none":
            return ids, pixels, scores
        if gray is not None:
            with stage("markers"):
                if view is None:  # too few corners to check, or IDs that fit no view: the markers may still tell
                    return corners_from_markers(gray, self.board, candidates, read_gray=read_gray,
                                                reader=self.reader)[0]
                if not marker_view_verified(gray, self.board, view.homography, read_gray, reader=self.reader):
                    return no_corners()  # the corners fit the board's grid, its markers are not there
        elif view is None and len(ids) >= MIN_CONSENSUS:
            return no_corners()  # enough corners to check, and they fit no view
        return ids, pixels, scores

    def _refinenet(self, gray: np.ndarray, pixels: np.ndarray, max_move: float = np.inf,
                   early: EarlyRefinement | None = None) -> np.ndarray:
        """Batched RefineNet over 24x24 patches whose pixel 12 is each candidate pixel; a corner it moves
        more than ``max_move`` px keeps its candidate pixel. Pixels that ``early`` refined in this ``gray``
        take its result; only the others run now."""
        refined = np.zeros((len(pixels), 2), np.float32)
        todo = np.ones(len(pixels), bool)
        if early is not None and early.gray is gray:
            done, rows = early.lookup(pixels)
            if done.any():
                refined[done] = self._corners(early.origins, early.logits.result())[rows]
                todo = ~done
        if todo.any():
            origins, patches = patches_around(gray, pixels[todo])
            refined[todo] = self._corners(origins, self.runner.refinenet(patches))
        return moves_limited(refined, pixels, max_move)

    def _corners(self, origins: np.ndarray, logits: np.ndarray) -> np.ndarray:
        """Patch top-left pixels (N, 2), RefineNet's logits (N, 4096) -> (N, 2) float32 refined corners."""
        return (origins + soft_argmax_offsets(logits, self.soft_radius)).astype(np.float32)

    def estimate_pose(self, detection: Detection, K: np.ndarray, dist: np.ndarray | None = None, **kwargs) -> Pose | None:
        """`deepcharuco.estimate_pose` for this detector's board.

        With the board-geometry check on (``geometry`` "repair" or "filter") a pose needs a RANSAC
        consensus of at least 6 corners (``min_inliers``): 4 fit some view of the board whatever their
        IDs, so a pose from a few corners may be confidently wrong; the corners are still reported. A board of
        fewer corners (a 3x3 board has 4), found by its markers' codes, needs all of them."""
        if self._each:
            raise DeepCharucoError("this Detector finds several boards: take each board's pose from its own "
                                   "detector, detectors[i].estimate_pose(detections[i], K, dist)")
        if self.geometry != "none":
            kwargs.setdefault("min_inliers", min(MIN_CONSENSUS, self.board.num_corners))
        return estimate_pose(detection, K, dist, board=self.board, **kwargs)
