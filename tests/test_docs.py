"""The project's documents are self-contained: no reference to a file outside the repository (users have
only the repository), every relative link in them resolves, and every source path and ``python -m`` command they
name exists."""

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def tracked(*patterns: str) -> list[Path]:
    try:
        listed = subprocess.run(["git", "ls-files", *patterns], cwd=ROOT, capture_output=True, text=True, check=True)
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    return [ROOT / line for line in listed.stdout.splitlines()]


# Spelled in two parts so that this file does not name them itself.
OUTSIDE_REFERENCES = ("DESIGN" + ".md", ".." + "/shared")


def test_no_reference_to_a_design_document_users_do_not_have():
    offenders = [f"{path.relative_to(ROOT)}:{n}" for path in tracked("*.py", "*.md", "Makefile", "*.toml")
                 if path.is_file()
                 for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1)
                 if any(reference in line for reference in OUTSIDE_REFERENCES)]
    assert not offenders, f"point these to docs/conventions.md: {offenders}"


def test_conventions_hold_what_users_need():
    text = (ROOT / "docs" / "conventions.md").read_text()
    for heading in ("## Coordinates and frames", "## Images given to detectors", "## Runtime API", "## Command lines",
                    "## HDF5 shard schema", "## Evaluation protocols"):
        assert heading in text, heading
    for needle in ("centre of the top-left pixel is (0.0, 0.0)", "getChessboardCorners()[i]", "camera_matrix",
                   "distortion_coefficients", "board → camera", "`corners` | float32 | (N, C, 2)", "`offset` float32"):
        assert needle in text, needle


@pytest.mark.parametrize("document", ["README.md", "CHANGELOG.md", "deepcharuco/weights/MODEL_CARD.md",
                                      *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "docs").glob("*.md"))])
def test_relative_links_resolve(document):
    path = ROOT / document
    if not path.exists():
        pytest.skip(f"{document} not here")
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", path.read_text()):
        if "://" in target:
            continue
        assert (path.parent / target).exists(), f"{document} links to {target}, which does not exist"


# A path into the project's source folders as documents write it (`deepcharuco/detection/markers/placement.py`).
SOURCE_PATH = re.compile(r"(?<![\w./-])((?:deepcharuco|evaluate|train|datagen|benchmarks|blender_scenes|tests|docs)/"
                         r"[\w/-]*\w\.(?:py|md))\b")
COMMAND = re.compile(r"python -m ((?:deepcharuco|evaluate|train|datagen|benchmarks)(?:\.\w+)*)")
DOCUMENTS = ["README.md", "deepcharuco/weights/MODEL_CARD.md", *sorted(f"docs/{p.name}" for p in (ROOT / "docs").glob("*.md"))]


def named_in(document: str, pattern: re.Pattern) -> set[str]:
    return set(pattern.findall((ROOT / document).read_text()))


@pytest.mark.parametrize("document", DOCUMENTS)
def test_source_paths_and_commands_resolve(document):
    """The files and modules a document sends users to exist (CHANGELOG.md is history: it keeps old names)."""
    import importlib.util

    missing = sorted(path for path in named_in(document, SOURCE_PATH) if not (ROOT / path).exists())
    assert not missing, f"{document} names files that do not exist: {missing}"
    unknown = sorted(module for module in named_in(document, COMMAND) if importlib.util.find_spec(module) is None)
    assert not unknown, f"{document} names commands whose module does not exist: {unknown}"


def test_the_path_check_sees_a_moved_module():
    old = "deepcharuco/" + "placement.py"  # before the runtime's subpackages (spelled so that no rewrite moves it)
    assert SOURCE_PATH.findall(f"see `{old}` and deepcharuco/detection/markers/placement.py.") == [
        old, "deepcharuco/detection/markers/placement.py"]
    assert not (ROOT / old).exists()
    assert COMMAND.findall("python -m deepcharuco.detect IMAGE; python -m evaluate.report") == [
        "deepcharuco.detect", "evaluate.report"]


def test_the_readme_picture_shows_what_its_caption_says():
    """docs/dark_frame.jpg (python -m evaluate.paper.readme_figure): OpenCV finds nothing, the deep detector every corner."""
    from evaluate.paper.readme_figure import BOARD, figure

    picture, found = figure()
    assert found == {"OpenCV + cornerSubPix": 0, "Deep ChArUco": BOARD.num_corners}
    assert picture.shape == (480, 1280, 3) and (ROOT / "docs" / "dark_frame.jpg").is_file()
