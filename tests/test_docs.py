"""The project's documents are self-contained: no reference to a file outside the repository (users have
only the repository), and every relative link in them resolves."""

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


def test_the_readme_picture_shows_what_its_caption_says():
    """docs/dark_frame.jpg (python -m evaluate.paper.readme_figure): OpenCV finds nothing, the deep detector every corner."""
    from evaluate.paper.readme_figure import BOARD, figure

    picture, found = figure()
    assert found == {"OpenCV + cornerSubPix": 0, "Deep ChArUco": BOARD.num_corners}
    assert picture.shape == (480, 1280, 3) and (ROOT / "docs" / "dark_frame.jpg").is_file()
