"""Reading board files: YAML or JSON with `BoardSpec`'s keys (`#` comments), OpenCV FileStorage YAML, and
caliscope's TOML boards, each into a dict of `BoardSpec`'s fields; refusals name the file, the key and the fix.
"""

from __future__ import annotations

from pathlib import Path


from deepcharuco.core.errors import BoardSpecError


# The fields a board file must spell out; the flags default to false.
REQUIRED_FIELDS = ("squares_x", "squares_y", "square_length", "marker_length", "dictionary")


# A board file is a few lines; anything larger is the wrong file, and is not read further than this.
MAX_BOARD_FILE_BYTES = 64 * 1024


# caliscope's charuco.toml (or the [charuco] table of its config.toml): its keys, and how they make a board.
CALISCOPE_KEYS = {"columns", "rows", "board_height", "board_width", "dictionary", "units", "aruco_scale",
                  "square_size_overide_cm", "square_size_override_cm", "inverted", "legacy_pattern"}
CM_PER_INCH = 2.54
CALISCOPE_UNITS = {"inch": CM_PER_INCH / 100.0, "cm": 0.01}  # metres per unit of board_width and board_height


def read_toml_board(text: str, path: Path) -> dict:
    """A TOML board file as `BoardSpec.from_dict` takes it: caliscope's (``columns``, ``rows``, ``aruco_scale``,
    the square from ``square_size_overide_cm`` or, as caliscope computes it, the largest square that fits
    ``board_width`` x ``board_height`` in ``units``), or this project's own fields in TOML."""
    try:
        import tomllib
    except ImportError:  # Python < 3.11
        try:
            import tomli as tomllib
        except ImportError:
            raise BoardSpecError(f"reading {path} needs Python 3.11 or the tomli package (pip install tomli)") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise BoardSpecError(f"{path} is not valid TOML: {error}") from None
    if isinstance(data.get("charuco"), dict):  # caliscope's config.toml keeps the board in a [charuco] table
        data = data["charuco"]
    if "columns" not in data and "rows" not in data:
        return data  # this project's fields, written as TOML
    unknown = sorted(set(data) - CALISCOPE_KEYS)
    missing = [key for key in ("columns", "rows", "dictionary") if key not in data]
    if unknown or missing:
        raise BoardSpecError(f"{path}: {'unknown field(s) ' + str(unknown[:5]) if unknown else ''}"
                             f"{'; ' if unknown and missing else ''}{'missing ' + str(missing) if missing else ''}: "
                             f"a caliscope board has {sorted(CALISCOPE_KEYS)}")
    override = data.get("square_size_overide_cm", data.get("square_size_override_cm"))
    if override:
        square = float(override) / 100.0
    else:
        if "board_height" not in data or "board_width" not in data:
            raise BoardSpecError(f"{path}: give square_size_overide_cm or board_width and board_height")
        units = str(data.get("units", "inch")).strip().lower()
        if units not in CALISCOPE_UNITS:
            raise BoardSpecError(f"{path}: units {data['units']!r} unknown: caliscope's board_width and board_height "
                                 f"are in {' or '.join(repr(u) for u in CALISCOPE_UNITS)}")
        to_metres = CALISCOPE_UNITS[units]
        square = min(float(data["board_height"]) * to_metres / data["rows"],
                     float(data["board_width"]) * to_metres / data["columns"])
    # Lengths to the nanometre: 5.4 cm / 100 is 0.054, not float's 0.054000000000000006.
    flags = {}
    for key, field in (("inverted", "inverted"), ("legacy_pattern", "legacy")):
        value = data.get(key, False)
        if not isinstance(value, bool):  # bool("false") is True: a quoted "false" read as true
            raise BoardSpecError(f"{path}: {key} must be true or false (unquoted), got {value!r}")
        flags[field] = value
    return {"squares_x": data["columns"], "squares_y": data["rows"], "square_length": round(square, 9),
            "marker_length": round(square * float(data.get("aruco_scale", 0.75)), 9), "dictionary": data["dictionary"],
            **flags}


def read_board_text(path: Path) -> str:
    """The text of a board file, refused when larger than `MAX_BOARD_FILE_BYTES` (read no further) or not text."""
    with open(path, "rb") as handle:
        data = handle.read(MAX_BOARD_FILE_BYTES + 1)
    if len(data) > MAX_BOARD_FILE_BYTES:
        raise BoardSpecError(f"{path} is over {MAX_BOARD_FILE_BYTES // 1024} KiB, too large for a board file (a few "
                             f"lines of 'field: value'): is it the right file?")
    try:
        return data.decode("utf-8-sig")  # a byte-order mark (Windows Notepad's UTF-8) is not part of the text
    except UnicodeDecodeError as exc:
        raise BoardSpecError(f"{path} is not a text file ({exc}): a board file is YAML or JSON text") from None


def read_flat_yaml(text: str, path: Path) -> dict:
    """Read a board file: a flat YAML mapping of scalars, ``#`` comments allowed anywhere.

    OpenCV's FileStorage YAML (``%YAML:1.0`` / ``---`` header, quoted strings) reads too. Its own
    parser is not used because it keeps trailing comments in values and fails on an empty file
    with an assertion instead of a reason.
    """
    lines = text.splitlines()
    data: dict = {}
    for number, raw in enumerate(lines, start=1):
        line = strip_comment(raw).rstrip()
        if not line.strip() or line.startswith(("%YAML", "---", "...")):
            continue
        where = f"{path}, line {number}"
        if line[0].isspace() or line.lstrip().startswith("-"):
            raise BoardSpecError(f"{where}: a board file is a flat list of 'field: value' lines; got {shown(raw)}")
        key, colon, value = line.partition(":")
        key, value = key.strip(), value.strip()
        if not colon or not key.isidentifier():
            raise BoardSpecError(f"{where}: expected 'field: value', got {shown(raw)}")
        if not value or value[0] in "[{|>":
            raise BoardSpecError(f"{where}: field {key!r} must be a single value (a number, name or true/false)")
        if key in data:
            raise BoardSpecError(f"{where}: field {key!r} is given twice")
        data[key] = scalar(value)
    if not data:
        raise BoardSpecError(f"{path} holds no board fields; write e.g. 'squares_x: 5' lines "
                             f"for {', '.join(REQUIRED_FIELDS)}")
    return data


def shown(line: str, limit: int = 60) -> str:
    """A line of the file as an error message quotes it: at most ``limit`` characters."""
    line = line.strip()
    return repr(line if len(line) <= limit else line[:limit] + "...")


def strip_comment(line: str) -> str:
    """``line`` without a ``#`` comment (a ``#`` inside quotes is text)."""
    quote = ""
    for index, char in enumerate(line):
        if quote:
            quote = "" if char == quote else quote
        elif char in "'\"":
            quote = char
        elif char == "#" and (index == 0 or line[index - 1].isspace()):
            return line[:index]
    return line


def scalar(text: str) -> bool | int | float | str:
    """A YAML scalar: quoted string, true/false, integer, real, or a bare string."""
    if len(text) >= 2 and text[0] == text[-1] and text[0] in "'\"":
        return text[1:-1]
    lowered = text.lower()
    if lowered in ("true", "false"):
        return lowered == "true"
    for parse in (int, float):
        try:
            return parse(text)
        except ValueError:
            pass
    return text
