"""train.drawn_patches: RefineNet's patch shards cut from drawn frames (labels, determinism, resume, refusals)."""

import subprocess
import sys
from dataclasses import replace

import cv2
import numpy as np
import pytest

from conftest import ROOT

from datagen.shards import read_patch_shard, shard_name
from train import drawn_patches
from train.augment import AugmentConfig
from train.draw import FrameDrawer


def test_a_clean_patch_holds_its_corner_where_the_label_says():
    """Drawn without the photometric augmentations, the corner cornerSubPix finds in a patch is its label: the
    labels follow the patch's pixels (OpenCV's convention), not half a pixel beside them."""
    config = replace(drawn_patches.draw_config(), negative_p=0.0, inverted_p=0.0,
                     square_px=(12.0, 40.0), augmentation=AugmentConfig(probabilities=(), homography_p=0.0))
    drawer = FrameDrawer(drawn_patches.boards(0)[:2], config)
    patches, offsets, sources = drawn_patches.shard_patches(drawer, np.random.default_rng(1), 6, 0.0, 0.0)
    assert len(patches) > 30 and set(sources) == {"drawn"}
    assert np.all((offsets >= 7.5) & (offsets < 15.5))
    errors = []
    for patch, offset in zip(patches, offsets):
        start = np.round(offset).astype(np.float32).reshape(1, 1, 2)
        found = cv2.cornerSubPix(patch.astype(np.float32), start, (4, 4), (-1, -1),
                                 (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 0.001)).reshape(2)
        errors.append(np.hypot(*(found - offset)))
    # a junction 12-80 px wide, drawn area-exact: cornerSubPix agrees to a tenth of a pixel on most
    assert np.median(errors) < 0.1, np.median(errors)


def test_shards_are_drawn_from_their_seed_alone_and_a_rerun_keeps_them(tmp_path):
    out = tmp_path / "patches"
    args = ["--out", str(out), "--shards", "2", "--frames", "4", "--synthetic", "0.5", "--shadow-edges", "0.5"]
    assert drawn_patches.main(args) == 0
    first = [read_patch_shard(out / shard_name(k)) for k in range(2)]
    patches, offsets, meta = first[0]
    sources = meta["source"].astype(str)
    assert patches.dtype == np.uint8 and patches.shape[1:] == (24, 24) and len(patches) == len(offsets)
    assert set(sources) == {"drawn", "synthetic"}
    assert np.sum(sources == "synthetic") == round(0.5 * np.sum(sources == "drawn"))
    assert not np.array_equal(first[0][1][:5], first[1][1][:5])  # shards differ from each other
    (out / shard_name(1)).unlink()
    before = (out / shard_name(0)).stat().st_mtime_ns
    assert drawn_patches.main(args) == 0  # shard 0 kept, shard 1 drawn again: the same patches
    assert (out / shard_name(0)).stat().st_mtime_ns == before
    again = read_patch_shard(out / shard_name(1))
    np.testing.assert_array_equal(again[0], first[1][0])
    np.testing.assert_array_equal(again[1], first[1][1])


def test_bad_options_are_one_line_and_help_works(tmp_path):
    done = subprocess.run([sys.executable, "-m", "train.drawn_patches", "--out", str(tmp_path / "p"), "--shards", "0"],
                          cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1 and "--shards" in done.stderr
    assert not (tmp_path / "p").exists()
    shown = subprocess.run([sys.executable, "-m", "train.drawn_patches", "--help"], cwd=ROOT, capture_output=True,
                           text=True)
    assert shown.returncode == 0 and "--synthetic" in shown.stdout


@pytest.mark.parametrize("option", ["--synthetic=-1", "--shadow-edges=1.5"])
def test_bad_shares_are_refused(tmp_path, capsys, option):
    assert drawn_patches.main(["--out", str(tmp_path / "p"), option]) == 2
    assert "--synthetic" in capsys.readouterr().err
