"""ChArUco board geometry: the board description (`BoardSpec`), its corner points and its printable texture (its
dictionaries in `dictionaries`, its files read by `board_files`).

Board frame (OpenCV's, >= 4.6): origin at the top-left outer corner of the square grid,
X to the right along a row, Y down along a column, Z into the board; units are metres.
Inner corner ``i`` is ``cv2.aruco.CharucoBoard.getChessboardCorners()[i]``.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, fields
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np

from deepcharuco.boards.board_files import REQUIRED_FIELDS, read_board_text, read_flat_yaml, read_toml_board
from deepcharuco.boards.dictionaries import dictionary_id, dictionary_size, marker_family, more_markers_advice
from deepcharuco.core.errors import BoardSpecError
from deepcharuco.core.files import write_atomic


# Textures larger than this per side are almost certainly a units mistake (px/mm vs px/m).
MAX_TEXTURE_SIDE = 16384


# The comment in every YAML board file this project writes: `deepcharuco board` replaces only such files.
BOARD_FILE_MARK = "deepcharuco board file: --board for detect and calibrate"


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board: the default is the paper's 5x5 board with DICT_5X5_50 markers 0..11.

    Attributes:
        squares_x: squares along X (columns).
        squares_y: squares along Y (rows).
        square_length: side of a chessboard square in metres.
        marker_length: side of an ArUco marker in metres (< square_length).
        dictionary: OpenCV ArUco dictionary name, e.g. ``"DICT_5X5_50"``.
        legacy: OpenCV's pre-4.6 layout (``CharucoBoard.setLegacyPattern``): for an even
            number of rows the top-left square is white instead of black.
        inverted: the print is white squares and markers on black paper (the negative of
            OpenCV's image); detectors look for it in ``255 - gray``.
        mirrored: the board is seen from a mirror-printed back face (its image is the
            left-right mirror of the board's); detectors look for it in the flipped image and
            poses use `object_points`, the mirrored corner positions.
        first_marker_id: the board's markers are the dictionary's IDs first_marker_id ..
            first_marker_id + num_markers - 1 (OpenCV's ``CharucoBoard`` ``ids`` argument);
            0, OpenCV's default, is left out of `to_dict`, so files of such boards are unchanged.

    Two specs that differ only in size (square_length and marker_length scaled together),
    polarity or mirroring have the same `layout`: the same corners, IDs and markers.
    """

    squares_x: int = 5
    squares_y: int = 5
    square_length: float = 0.04
    marker_length: float = 0.03
    dictionary: str = "DICT_5X5_50"
    legacy: bool = False
    inverted: bool = False
    mirrored: bool = False
    first_marker_id: int = 0

    def __post_init__(self) -> None:
        for name in ("squares_x", "squares_y"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise BoardSpecError(f"{name} must be an integer, got {value!r}")
            if value < 3:
                raise BoardSpecError(
                    f"{name} must be >= 3 (a board needs a 2D grid of inner corners for a pose), got {value}"
                )
            object.__setattr__(self, name, int(value))
        for name in ("square_length", "marker_length"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
                raise BoardSpecError(f"{name} must be a number in metres, got {value!r}")
            if not math.isfinite(value) or value <= 0:
                raise BoardSpecError(f"{name} must be a positive length in metres, got {value}")
            object.__setattr__(self, name, float(value))
        if self.marker_length >= self.square_length:
            raise BoardSpecError(
                f"marker_length ({self.marker_length} m) must be smaller than square_length "
                f"({self.square_length} m): a marker sits inside a white square with a white border"
            )
        if not isinstance(self.dictionary, str):
            raise BoardSpecError(f"dictionary must be a name such as 'DICT_5X5_50', got {self.dictionary!r}")
        object.__setattr__(self, "dictionary", self.dictionary.upper())
        holds = dictionary_size(self.dictionary)
        first = self.first_marker_id
        if isinstance(first, bool) or not isinstance(first, (int, np.integer)) or first < 0:
            raise BoardSpecError(f"first_marker_id must be an integer >= 0, got {first!r}")
        object.__setattr__(self, "first_marker_id", int(first))
        if self.num_markers > holds:
            raise BoardSpecError(
                f"a {self.squares_x}x{self.squares_y} board needs {self.num_markers} markers but "
                f"{self.dictionary} has only {holds}; {more_markers_advice(self.dictionary, self.num_markers)}"
            )
        if first and first + self.num_markers > holds:
            raise BoardSpecError(
                f"a {self.squares_x}x{self.squares_y} board with markers from ID {first} needs IDs up to "
                f"{first + self.num_markers - 1} but {self.dictionary} has only {holds} markers; "
                f"{more_markers_advice(self.dictionary, first + self.num_markers, 'a smaller first_marker_id')}"
            )
        for name in ("legacy", "inverted", "mirrored"):
            value = getattr(self, name)
            if not isinstance(value, (bool, np.bool_)):
                raise BoardSpecError(f"{name} must be true or false, got {value!r}")
            object.__setattr__(self, name, bool(value))

    # ----------------------------------------------------------------- geometry
    @property
    def num_markers(self) -> int:
        """Markers on the board: one in every white square (half the squares, either layout)."""
        return self.squares_x * self.squares_y // 2

    @property
    def num_corners(self) -> int:
        """Inner chessboard corners, i.e. the corner IDs 0 .. num_corners-1."""
        return (self.squares_x - 1) * (self.squares_y - 1)

    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) of the square grid in metres, without any margin."""
        return self.squares_x * self.square_length, self.squares_y * self.square_length

    @property
    def layout(self) -> tuple:
        """What decides which corner is which: grid, dictionary, legacy flag, the marker/square
        ratio (rounded to 1e-6) and the first marker ID. Size, polarity and mirroring only change how the board is seen."""
        return (self.squares_x, self.squares_y, self.dictionary, self.legacy,
                round(self.marker_length / self.square_length, 6), self.first_marker_id)

    def same_layout(self, other: "BoardSpec") -> bool:
        """True when ``other`` is this board printed at another size, inverted or mirrored."""
        return self.layout == other.layout

    def shared_markers(self, other: "BoardSpec") -> tuple[int, int] | None:
        """(first, last) marker IDs that both this board and ``other`` print, or None. Dictionaries of one family share
        their first markers (DICT_4X4_50's are DICT_4X4_1000's first 50), so boards of DICT_4X4_50 and DICT_4X4_1000
        from ID 0 share theirs: where those markers show, a view of one reads as the other."""
        family, other_family = marker_family(self.dictionary), marker_family(other.dictionary)
        if not (family is not None and family == other_family or self.dictionary.upper() == other.dictionary.upper()):
            return None
        first = max(self.first_marker_id, other.first_marker_id)
        last = min(self.first_marker_id + self.num_markers, other.first_marker_id + other.num_markers) - 1
        return (first, last) if first <= last else None

    def cv_dictionary(self) -> cv2.aruco.Dictionary:
        return cv2.aruco.getPredefinedDictionary(dictionary_id(self.dictionary))

    def __getstate__(self) -> dict:
        # Cached OpenCV objects do not pickle (worker processes are sent board specs): rebuilt there on first use.
        return {name: value for name, value in self.__dict__.items() if not name.startswith("_")}

    @cached_property
    def _cv_board(self) -> cv2.aruco.CharucoBoard:
        ids = np.arange(self.first_marker_id, self.first_marker_id + self.num_markers, dtype=np.int32)
        board = cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_length, self.marker_length, self.cv_dictionary(), ids
        )
        board.setLegacyPattern(self.legacy)
        return board

    def cv_board(self) -> cv2.aruco.CharucoBoard:
        """The matching ``cv2.aruco.CharucoBoard`` (built once per spec, shared)."""
        return self._cv_board

    def corner_points(self) -> np.ndarray:
        """(C, 3) float64 board-frame positions (m) of the inner corners, row i = corner ID i."""
        return np.asarray(self.cv_board().getChessboardCorners(), dtype=np.float64).reshape(-1, 3)

    def object_points(self) -> np.ndarray:
        """(C, 3) float64 where the inner corners physically lie as the camera sees the printed face:
        `corner_points`, mirrored left-right (X -> width - X) for a ``mirrored`` board, so that poses
        solved from them are proper rotations."""
        points = self.corner_points()
        if self.mirrored:
            points = points.copy()
            points[:, 0] = self.size_m[0] - points[:, 0]
        return points

    def marker_corners(self) -> tuple[np.ndarray, np.ndarray]:
        """Marker IDs (M,) and their corners (M, 4, 3) in the board frame, clockwise from top-left."""
        board = self.cv_board()
        ids = np.asarray(board.getIds(), dtype=np.int64).ravel()
        return ids, np.asarray(board.getObjPoints(), dtype=np.float64).reshape(-1, 4, 3)

    # ----------------------------------------------------------------- texture
    def render_texture(self, px_per_m: float, margin: float = 0.0) -> "BoardTexture":
        """Render the printed board, area-exact, at ``px_per_m`` pixels per metre.

        Every pixel holds the exact fraction of its square that is white paper (box-filter
        anti-aliasing), so the texture carries sub-pixel geometry at any resolution.
        ``margin`` is a white border in metres around the square grid. See `BoardTexture`
        for the map between texture pixels and board metres.
        """
        return BoardTexture.render(self, px_per_m, margin)

    # ----------------------------------------------------------------- (de)serialisation
    def to_dict(self) -> dict:
        data = asdict(self)
        if not data["first_marker_id"]:
            del data["first_marker_id"]  # OpenCV's default: board files and shards stay as they were
        return data

    @classmethod
    def from_dict(cls, data: dict, source: str = "a board description") -> "BoardSpec":
        """A spec from a mapping of its fields. The grid, lengths and dictionary are required (a
        missing one is an error, never the paper's board's value); legacy, inverted and mirrored
        default to false. ``source`` names the file in errors."""
        if not isinstance(data, dict):
            raise BoardSpecError(f"{source} must be a mapping of board fields, got {type(data).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(map(str, set(data) - known))
        if unknown:
            listed = [name[:40] for name in unknown[:5]]  # a file of a million keys gets a message of one line
            more = f" and {len(unknown) - 5:,} more" if len(unknown) > 5 else ""
            raise BoardSpecError(f"{source}: unknown board field(s) {listed}{more}; known fields: {sorted(known)}")
        missing = [name for name in REQUIRED_FIELDS if name not in data]
        if missing:
            raise BoardSpecError(
                f"{source} lacks the field(s) {missing}; a board needs {list(REQUIRED_FIELDS)} "
                "(legacy, inverted and mirrored default to false)")
        return cls(**data)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "BoardSpec":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise BoardSpecError(f"board JSON is not valid JSON: {exc}") from exc
        return cls.from_dict(data)

    def save(self, path: str | Path) -> Path:
        """Write the spec as JSON (``.json``) or OpenCV-readable YAML (``.yaml``/``.yml``)."""
        path = Path(path)
        return write_atomic(path, self.file_text(path.suffix, str(path)))

    def file_text(self, suffix: str = ".yaml", name: str = "the board file") -> str:
        """The text `save` writes for a file with ``suffix``: JSON (``.json``) or OpenCV-readable YAML."""
        suffix = suffix.lower()
        if suffix == ".json":
            return json.dumps(self.to_dict(), indent=2, sort_keys=True) + "\n"
        if suffix in (".yaml", ".yml"):
            lines = ["%YAML:1.0", "---", f"# {BOARD_FILE_MARK}"]
            for key, value in self.to_dict().items():
                text = ("true" if value else "false") if isinstance(value, bool) else value
                lines.append(f"{key}: {text}")
            return "\n".join(lines) + "\n"
        raise BoardSpecError(f"cannot tell the format of {name}: name it .json, .yaml or .yml")

    @classmethod
    def load(cls, path: str | Path) -> "BoardSpec":
        """Read a spec written by `save` (or by hand) from a .json/.yaml/.yml file."""
        path = Path(path)
        if not path.is_file():
            raise BoardSpecError(f"board file {path} does not exist")
        suffix = path.suffix.lower()
        if suffix not in (".json", ".yaml", ".yml", ".toml"):
            raise BoardSpecError(f"cannot tell the format of {path}: name it .json, .yaml or .yml (or caliscope's "
                                 f".toml)")
        text = read_board_text(path)
        if suffix == ".toml":
            return cls.from_dict(read_toml_board(text, path), source=str(path))
        if suffix == ".json":
            try:
                data = json.loads(text)
            except json.JSONDecodeError as exc:
                raise BoardSpecError(f"{path} is not valid JSON: {exc}") from exc
            except RecursionError:  # nesting deeper than Python's stack: no board is written so
                raise BoardSpecError(f"{path} nests too deeply to be a board file: a board is one flat mapping of "
                                     f"fields ({', '.join(REQUIRED_FIELDS)}, ...)") from None
            return cls.from_dict(data, source=str(path))
        return cls.from_dict(read_flat_yaml(text, path), source=str(path))


def _coverage_1d(n_px: int, lo: float, hi: float) -> tuple[int, np.ndarray]:
    """Fraction of each pixel [k, k+1) (edge coordinates) covered by [lo, hi).

    Returns the first pixel index and the coverage of the pixels from there on.
    """
    first = max(int(math.floor(lo)), 0)
    last = min(int(math.ceil(hi)), n_px)
    k = np.arange(first, last, dtype=np.float64)
    return first, np.clip(np.minimum(k + 1.0, hi) - np.maximum(k, lo), 0.0, 1.0)


@dataclass(frozen=True)
class BoardTexture:
    """A rendered board texture and its exact map to board metres.

    The map (pixel centres in OpenCV's convention, board frame of `BoardSpec`):

        X = (u + 0.5) / px_per_m - margin        u = (X + margin) * px_per_m - 0.5
        Y = (v + 0.5) / px_per_m - margin        v = (Y + margin) * px_per_m - 0.5

    i.e. the top-left edge of the texture is board point (-margin, -margin) and the
    texture spans ``size_m`` metres. When the grid plus margins is not a whole number of
    pixels, the texture is one partial pixel larger and that strip is white paper.
    """

    board: BoardSpec
    image: np.ndarray  # (H, W) uint8, 255 = white paper (black for an inverted print), as the camera sees the face
    px_per_m: float
    margin: float

    @classmethod
    def render(cls, board: BoardSpec, px_per_m: float, margin: float = 0.0) -> "BoardTexture":
        if not math.isfinite(px_per_m) or px_per_m <= 0:
            raise BoardSpecError(f"px_per_m must be positive, got {px_per_m}")
        if not math.isfinite(margin) or margin < 0:
            raise BoardSpecError(f"margin must be >= 0 metres, got {margin}")
        width_m, height_m = board.size_m
        width = math.ceil((width_m + 2 * margin) * px_per_m - 1e-9)
        height = math.ceil((height_m + 2 * margin) * px_per_m - 1e-9)
        if max(width, height) > MAX_TEXTURE_SIDE:
            raise BoardSpecError(
                f"texture of {width}x{height} px is too large (max {MAX_TEXTURE_SIDE} per side): "
                f"px_per_m={px_per_m} is pixels per metre, not per millimetre"
            )
        ink = np.zeros((height, width), dtype=np.float64)

        grid_width = board.size_m[0]

        def add(x0: float, y0: float, x1: float, y1: float, sign: float) -> None:
            """Add ``sign`` x the coverage of the board rectangle [x0, x1) x [y0, y1) (metres)."""
            if board.mirrored:  # the face seen from behind: drawn mirrored about the grid's middle, X -> W - X
                x0, x1 = grid_width - x1, grid_width - x0
            cx0, cov_x = _coverage_1d(width, (x0 + margin) * px_per_m, (x1 + margin) * px_per_m)
            cy0, cov_y = _coverage_1d(height, (y0 + margin) * px_per_m, (y1 + margin) * px_per_m)
            ink[cy0 : cy0 + cov_y.size, cx0 : cx0 + cov_x.size] += sign * np.outer(cov_y, cov_x)

        square = board.square_length
        ids, marker_corners = board.marker_corners()
        white_squares = {
            (int(c[:, 0].mean() // square), int(c[:, 1].mean() // square)) for c in marker_corners
        }
        for row in range(board.squares_y):
            for col in range(board.squares_x):
                if (col, row) not in white_squares:
                    add(col * square, row * square, (col + 1) * square, (row + 1) * square, 1.0)

        dictionary = board.cv_dictionary()
        cells = dictionary.markerSize + 2  # one black border cell each side, as OpenCV prints
        for marker_id, corners in zip(ids, marker_corners):
            x0, y0 = corners[:, 0].min(), corners[:, 1].min()
            x1, y1 = corners[:, 0].max(), corners[:, 1].max()
            if not np.allclose(corners[0, :2], (x0, y0)):
                raise AssertionError("OpenCV marker corners are expected clockwise from the top-left")
            add(x0, y0, x1, y1, 1.0)
            bits = cv2.aruco.generateImageMarker(dictionary, int(marker_id), cells, borderBits=1)
            cell = (x1 - x0) / cells
            for r, c in zip(*np.nonzero(bits)):
                add(x0 + c * cell, y0 + r * cell, x0 + (c + 1) * cell, y0 + (r + 1) * cell, -1.0)

        image = np.round(255.0 * (1.0 - np.clip(ink, 0.0, 1.0))).astype(np.uint8)
        # The printed face as the camera sees it. A mirrored face is drawn mirrored (above) rather than
        # flipped as an image: a flip is about the image's middle, which is the grid's only when the sheet
        # is a whole number of pixels wide (renders were 0.3 px off their labels). The map to board metres
        # is `BoardSpec.object_points`' frame for a mirrored board.
        if board.inverted:
            image = 255 - image
        return cls(board=board, image=image, px_per_m=float(px_per_m), margin=float(margin))

    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) in metres that the texture image covers."""
        height, width = self.image.shape
        return width / self.px_per_m, height / self.px_per_m

    def texture_to_board_matrix(self) -> np.ndarray:
        """3x3 affine map from homogeneous texture pixels (u, v, 1) to board (X, Y, 1)."""
        s = 1.0 / self.px_per_m
        offset = 0.5 * s - self.margin
        return np.array([[s, 0.0, offset], [0.0, s, offset], [0.0, 0.0, 1.0]])

    def texture_to_board(self, uv: np.ndarray) -> np.ndarray:
        """(..., 2) texture pixels -> (..., 2) board metres."""
        return (np.asarray(uv, dtype=np.float64) + 0.5) / self.px_per_m - self.margin

    def board_to_texture(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) board metres (X, Y) -> (..., 2) texture pixels."""
        return (np.asarray(xy, dtype=np.float64)[..., :2] + self.margin) * self.px_per_m - 0.5


def check_boards_apart(boards: list[BoardSpec], names: list[str]) -> None:
    """Raises `BoardSpecError` naming the first two of ``boards`` (called ``names``) that print the same markers
    (`BoardSpec.shared_markers`): searched together, each would be found wherever the other is, with its corners and
    pose (a phantom board), and a rig would count each view twice."""
    for i, board in enumerate(boards):
        for j in range(i):
            shared = boards[j].shared_markers(board)
            if shared is not None:
                family = marker_family(board.dictionary) or board.dictionary
                raise BoardSpecError(
                    f"{names[j]} and {names[i]} both print markers {shared[0]}-{shared[1]} of {family}: a view of one "
                    f"reads as the other (each would be found where the other is); give boards of other dictionaries, "
                    f"or first_marker_id values that keep their markers apart")
