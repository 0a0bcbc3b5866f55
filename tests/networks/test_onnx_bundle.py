"""The shipped networks as ONNX bundles: current with the .pt weights, and the Detector without PyTorch gives what it
gives with it."""

import hashlib
import json
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT, VIEW_POSES, make_view
from deepcharuco import BoardSpec, Detector, DeepCharucoError
from deepcharuco.networks.checkpoint import load_charuconet, load_refinenet
from deepcharuco.networks.onnx_bundle import BundleError, bundle_path, read_bundle
from deepcharuco.networks.runtime import float_onnx, weights_fingerprint
from deepcharuco.networks.shipped import DEFAULT_WEIGHTS, FAMILY_WEIGHTS_DIR

SHIPPED = [DEFAULT_WEIGHTS, *sorted(FAMILY_WEIGHTS_DIR.glob("*.pt"))]


@pytest.mark.parametrize("weights", SHIPPED, ids=lambda p: p.stem)
def test_each_shipped_bundle_is_its_weights_exported_as_the_runtime_exports_them(weights):
    """A bundle out of date with its .pt fails here: deepcharuco export --bundle --weights W makes it anew."""
    bundle = read_bundle(bundle_path(weights))
    charuconet, board, checkpoint = load_charuconet(weights)
    assert bundle.meta["weights_sha256"] == weights_fingerprint(charuconet)
    # each file's sha256 too, so that a damaged shipped model or a changed .pt is named, not run
    assert bundle.meta["models_sha256"] == {name: hashlib.sha256(data).hexdigest() for name, data in bundle.models.items()}
    assert bundle.meta["weights_file_sha256"] == hashlib.sha256(weights.read_bytes()).hexdigest()
    assert bundle.meta["threshold"] == checkpoint.get("threshold") and bundle.board.to_dict() == board.to_dict()
    assert same_network(bundle.models["charuconet_points.onnx"], float_onnx(charuconet, points_only=True), (1, 1, 64, 96))
    assert bundle.id_head == ("charuconet.onnx" in bundle.models)
    if bundle.id_head:
        assert same_network(bundle.models["charuconet.onnx"], float_onnx(charuconet), (1, 1, 64, 96))
    assert same_network(bundle.models["refinenet.onnx"], float_onnx(load_refinenet(weights)[0]), (3, 1, 24, 24))


def same_network(shipped: bytes, exported: bytes, shape: tuple[int, ...]) -> bool:
    """The same bytes; or, exported by another PyTorch than the bundle's (whose exporter writes other bytes), the
    same outputs to 1e-5 on a random input."""
    if shipped == exported:
        return True
    import onnxruntime

    image = np.random.default_rng(0).random(shape, dtype=np.float32)
    outputs = []
    for model in (shipped, exported):
        session = onnxruntime.InferenceSession(model, providers=["CPUExecutionProvider"])
        outputs.append(session.run(None, {session.get_inputs()[0].name: image}))
    return len(outputs[0]) == len(outputs[1]) and all(np.allclose(a, b, atol=1e-5) for a, b in zip(*outputs))


def test_detections_without_torch_are_those_with_it(tmp_path, camera):
    """The paper's board (its own ID head), a 7x5 DICT_6X6 board (its family model, read by markers) and the
    11x8 DICT_5X5 board (the paper's model by markers): ids, corners and scores equal, bit for bit."""
    boards = [BoardSpec(), BoardSpec(7, 5, 0.03, 0.022, "DICT_6X6_250"), BoardSpec(11, 8, 0.02, 0.015, "DICT_5X5_1000")]
    images = np.stack([make_view(board, camera, **pose)[0] for board in boards for pose in VIEW_POSES[:3]])
    np.save(tmp_path / "images.npy", images)
    (tmp_path / "boards.json").write_text(json.dumps([b.to_dict() for b in boards]))
    with_torch = _detect(images, boards)
    code = f"""
import json, sys
import numpy as np
sys.modules["torch"] = None
from deepcharuco import BoardSpec, Detector
boards = [BoardSpec(**b) for b in json.loads(open(r"{tmp_path / 'boards.json'}").read())]
images = np.load(r"{tmp_path / 'images.npy'}")
out = []
for k, board in enumerate(boards):
    detector = Detector(board=board)
    assert detector.charuconet is None  # the bundle, not PyTorch
    out += [(f.ids, f.corners, f.scores) for f in map(detector.detect, images[3 * k:3 * k + 3])]
np.save(r"{tmp_path / 'without.npy'}", np.array(out, dtype=object), allow_pickle=True)
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    without = np.load(tmp_path / "without.npy", allow_pickle=True)
    assert sum(len(ids) for ids, _, _ in with_torch) >= 100  # the views are found: the comparison compares
    for (ids_a, corners_a, scores_a), (ids_b, corners_b, scores_b) in zip(with_torch, without, strict=True):
        assert np.array_equal(ids_a, ids_b) and np.array_equal(corners_a, corners_b)
        assert np.array_equal(scores_a, scores_b)


def _detect(images: np.ndarray, boards: list[BoardSpec]) -> list[tuple]:
    """Each image's detection, three images a board, by the board's default Detector (PyTorch loads the weights)."""
    out = []
    for k, board in enumerate(boards):
        detector = Detector(board=board)
        assert detector.charuconet is not None
        out += [(f.ids, f.corners, f.scores) for f in map(detector.detect, images[3 * k:3 * k + 3])]
    return out


def test_a_damaged_bundle_or_one_given_with_a_refinenet_is_refused(tmp_path):
    folder = tmp_path / "mine.onnx"
    folder.mkdir()
    (folder / "bundle.json").write_text('{"format": 1, "board": ')
    with pytest.raises(BundleError, match=r"bundle.json is damaged .*deepcharuco export --bundle"):
        Detector(weights=folder)
    (folder / "bundle.json").write_text(json.dumps({"format": 1, "board": BoardSpec().to_dict(), "heads": "all"}))
    with pytest.raises(BundleError, match="lacks its ChArUcoNet model"):
        Detector(weights=folder)
    with pytest.raises(DeepCharucoError, match="holds its own RefineNet"):
        Detector(weights=bundle_path(DEFAULT_WEIGHTS), refine_weights=DEFAULT_WEIGHTS)
    detector = Detector(weights=bundle_path(DEFAULT_WEIGHTS))
    assert detector.runner.name == "onnx" and detector.charuconet is None and detector.threshold == 0.25


def test_the_package_ships_only_its_own_weights():
    """Every weights file beside the shipped ones is in the wheel: a test's bundle (3.4 MB) once was."""
    from deepcharuco.networks.shipped import WEIGHTS_DIR

    shipped = {"MODEL_CARD.md", "bit_reader.pt", "detector.pt", "detector.onnx", "families", "fast"}
    assert {path.name for path in WEIGHTS_DIR.iterdir()} - {"__pycache__"} == shipped
    families = {path.name for path in (WEIGHTS_DIR / "families").iterdir()}
    assert families == {f"{family}{suffix}" for family in ("DICT_4X4", "DICT_6X6") for suffix in (".md", ".onnx", ".pt")}
    # the fast networks (network="fast"): ONNX bundles alone, the same layout
    assert {path.name for path in (WEIGHTS_DIR / "fast").iterdir()} == {"MODEL_CARD.md", "detector.onnx", "families"}
    assert {path.name for path in (WEIGHTS_DIR / "fast" / "families").iterdir()} == {"DICT_4X4.onnx", "DICT_6X6.onnx"}


MARKERS_BOARD = BoardSpec(5, 7, 0.04, 0.02, "DICT_6X6_250")  # not the weights' board: read by its markers alone


@pytest.mark.parametrize("damage, board, message", [
    (lambda d: (d / "charuconet.onnx").write_bytes((d / "charuconet.onnx").read_bytes()[:5000]), None,
     "charuconet.onnx cannot be loaded by ONNX Runtime (InvalidProtobuf"),
    (lambda d: (d / "refinenet.onnx").write_bytes((d / "refinenet.onnx").read_bytes()[:100]), None,
     "refinenet.onnx cannot be loaded by ONNX Runtime"),
    (lambda d: (d / "charuconet_points.onnx").write_bytes(b""), MARKERS_BOARD, "charuconet_points.onnx is empty"),
    (lambda d: (d / "charuconet_points.onnx").write_bytes((d / "refinenet.onnx").read_bytes()), MARKERS_BOARD,
     "charuconet_points.onnx is not a charuconet_points model (its outputs are logits"),
    (lambda d: (d / "bundle.json").unlink(), None,
     "is a folder without bundle.json or detector.pt, so neither an ONNX bundle nor a weights folder"),
], ids=["truncated", "truncated-refinenet", "empty", "swapped", "no-bundle-json"])
def test_a_damaged_model_file_is_named_not_a_traceback(tmp_path, damage, board, message):
    """A bundle whose model file was cut short, emptied or replaced by another model's, or a folder without
    bundle.json: `BundleError` naming the file and the fix (one line from the commands), not ONNX Runtime's
    traceback (``InvalidProtobuf``) or "weights file does not exist"."""
    folder = tmp_path / "mine.onnx"
    shutil.copytree(bundle_path(DEFAULT_WEIGHTS), folder)
    damage(folder)
    if (folder / "bundle.json").is_file() and "empty" not in message:
        # the shipped bundle records its files' sha256: the changed file is named before ONNX Runtime sees it
        with pytest.raises(BundleError, match="is not the model exported into this bundle"):
            Detector(weights=folder, board=board)
        # one exported before the sha256s were recorded: ONNX Runtime's load and the outputs tell
        meta = json.loads((folder / "bundle.json").read_text())
        del meta["models_sha256"]
        (folder / "bundle.json").write_text(json.dumps(meta))
    with pytest.raises(BundleError, match=re.escape(message)):
        Detector(weights=folder, board=board)


def test_a_model_file_other_than_the_one_exported_is_refused_by_its_sha256(tmp_path):
    """A bundle records each model's sha256 (`models_sha256`, written by `export.write_onnx_bundle`): a file changed
    since, even one ONNX Runtime loads, is refused before any session is made; detect says so in one line."""
    folder = tmp_path / "mine.onnx"
    shutil.copytree(bundle_path(DEFAULT_WEIGHTS), folder)
    meta = json.loads((folder / "bundle.json").read_text())
    meta["models_sha256"] = {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.glob("*.onnx")}
    (folder / "bundle.json").write_text(json.dumps(meta))
    assert read_bundle(folder).models  # as exported: read
    (folder / "refinenet.onnx").write_bytes((folder / "charuconet_points.onnx").read_bytes())
    with pytest.raises(BundleError, match="refinenet.onnx is not the model exported into this bundle"):
        read_bundle(folder)
    done = subprocess.run([sys.executable, "-m", "deepcharuco.detect", str(ROOT / "deepcharuco"
                           / "examples" / "board_320x240.png"), "--weights", str(folder), "--out", str(tmp_path / "o")],
                          capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 2 and "refinenet.onnx is not the model exported into this bundle" in \
        done.stderr.strip().splitlines()[-1]
    assert "Traceback" not in done.stderr and not (tmp_path / "o").exists()


def test_an_exported_bundle_records_its_files_and_is_refused_once_its_weights_change(tmp_path):
    """`write_onnx_bundle` records each model's sha256 and the weights file's; without PyTorch the bundle beside
    NAME.pt stands in for it only while NAME.pt is the file it was exported from (a retrained detector.pt beside a
    stale detector.onnx/ ran the old networks without a word)."""
    from deepcharuco.cli.export import write_onnx_bundle

    weights = tmp_path / "mine.pt"
    shutil.copyfile(DEFAULT_WEIGHTS, weights)
    folder = write_onnx_bundle(weights)
    meta = json.loads((folder / "bundle.json").read_text())
    assert meta["models_sha256"] == {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.glob("*.onnx")}
    assert meta["weights_file_sha256"] == hashlib.sha256(weights.read_bytes()).hexdigest()
    code = f"""
import sys
sys.modules["torch"] = None  # as without PyTorch: the bundle beside the weights is read
from deepcharuco import Detector
from deepcharuco.networks.onnx_bundle import BundleError
assert Detector(weights=r"{weights}").runner.name == "onnx"
open(r"{weights}", "ab").write(b"retrained")
try:
    Detector(weights=r"{weights}")
except BundleError as error:
    print(error)
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "mine.onnx was exported from another mine.pt than the one beside it" in done.stdout


def test_a_bundle_given_as_weights_is_refused_when_the_network_beside_it_is_another(tmp_path):
    """With PyTorch installed, a bundle folder given as the weights is checked against the network of the weights
    file it names beside it (``weights_sha256``, the loaded network's fingerprint): a retrained or replaced .pt is
    named; the same network saved again (other bytes) is not."""
    import torch
    from deepcharuco.cli.export import write_onnx_bundle

    weights = tmp_path / "mine.pt"
    shutil.copyfile(DEFAULT_WEIGHTS, weights)
    folder = write_onnx_bundle(weights)
    torch.save(torch.load(weights, weights_only=False), weights)  # re-saved: other bytes, the same network
    assert Detector(weights=folder).runner.name.startswith("onnx")
    shutil.copyfile(FAMILY_WEIGHTS_DIR / "DICT_4X4.pt", weights)  # another network under the name
    with pytest.raises(BundleError, match=r"mine.onnx was exported from another network than .*mine.pt holds now"):
        Detector(weights=folder)


def test_the_fast_bundles_carry_one_fast_refinenet_that_places_a_junction_to_a_tenth_of_a_pixel():
    """The three fast bundles hold the same fast RefineNet (`train.swap_refinenet`), recorded in bundle.json; on clean
    synthetic X-junctions it errs 0.09 px in median (the lite one 0.07): a wrong or untrained network errs pixels."""
    from datagen.patches import synthetic_patch
    from deepcharuco.networks.offsets import soft_argmax_offsets
    from deepcharuco.networks.onnx_runner import _session
    from deepcharuco.networks.shipped import FAST_WEIGHTS_DIR

    bundles = [read_bundle(FAST_WEIGHTS_DIR / "detector.onnx"),
               *(read_bundle(path) for path in sorted((FAST_WEIGHTS_DIR / "families").glob("*.onnx")))]
    assert len(bundles) == 3 and len({b.models["refinenet.onnx"] for b in bundles}) == 1
    assert all(b.meta["refinenet"]["config"]["arch"] == "fast" for b in bundles)
    lite = read_bundle(bundle_path(DEFAULT_WEIGHTS)).models["refinenet.onnx"]
    assert bundles[0].models["refinenet.onnx"] != lite
    rng = np.random.default_rng(0)
    pairs = [synthetic_patch(rng, degrade=False) for _ in range(200)]
    patches = np.stack([p for p, _ in pairs])[:, None].astype(np.float32) / 255.0
    truth = np.stack([offset for _, offset in pairs])
    session = _session(bundles[0].models["refinenet.onnx"], 1)
    (logits,) = session.run(None, {session.get_inputs()[0].name: patches})
    errors = np.hypot(*(soft_argmax_offsets(logits, 2) - truth).T)
    assert np.median(errors) < 0.15 and np.percentile(errors, 90) < 0.3, (np.median(errors), errors.max())
