"""Damaged or mistaken data folders: every command names the file and the fix in one line, and
datagen.patches leaves its output folder as it was."""

from pathlib import Path

import numpy as np
import pytest

from datagen.inspect import main as inspect_main
from datagen.patches import main as patches_main
from datagen.patches import synthetic_patches
from datagen.shards import FrameLabels, write_patch_shard, write_shard
from deepcharuco import BoardSpec
from train.charuconet import main as charuconet_main
from train.refinenet import main as refinenet_main


@pytest.fixture
def frame_folder(tmp_path, default_views, camera) -> Path:
    """Two frame shards of the default views."""
    out = tmp_path / "renders"
    for shard in range(2):
        write_shard(out, shard, [FrameLabels(image, corners.astype(np.float32), np.ones(16, bool), camera.K, rvec, tvec,
                                             {"has_board": True, "frame": 10 * shard + k})
                                 for k, (image, rvec, tvec, corners) in enumerate(default_views)], BoardSpec(), {})
    return out


def one_line_error(capsys) -> str:
    """The error line a command printed last (after any progress bar), checked to be one line, no traceback."""
    err = capsys.readouterr().err
    last = err.strip().splitlines()[-1]
    assert last.startswith("error: ") and "Traceback" not in err, err
    return last


def truncate(path: Path) -> None:
    """A copy cut short (or a disk that filled up under another program)."""
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def damage_the_middle(path: Path) -> None:
    """Zero bytes inside the compressed images: the file opens, a frame does not read."""
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 64] = bytes(64)
    path.write_bytes(bytes(data))


def test_a_truncated_shard_is_named_with_the_fix_by_every_reader(frame_folder, tmp_path, capsys):
    shard = frame_folder / "shard-00001.h5"
    truncate(shard)
    runs = {
        "inspect": lambda: inspect_main([str(frame_folder), "--out", str(tmp_path / "inspect")]),
        "patches": lambda: patches_main(["--renders", str(frame_folder), "--out", str(tmp_path / "patches"),
                                         "--synthetic", "10"]),
        "charuconet": lambda: charuconet_main(["--data", str(frame_folder), "--out", str(tmp_path / "run"), "--steps", "1",
                                               "--width", "lite", "--workers", "0", "--quiet"]),
    }
    for name, run in runs.items():
        assert run() == 2, name
        err = one_line_error(capsys)
        assert f"{shard} is not a readable HDF5 shard, it is truncated or corrupt" in err and "--resume" in err, (name, err)
    assert not (tmp_path / "patches").exists() and not (tmp_path / "inspect").exists()


def test_patches_leave_no_half_written_output(frame_folder, tmp_path, capsys):
    """Shard 0 cuts fine, shard 1 fails halfway through: --out is not created (nor, with --overwrite, changed)."""
    damage_the_middle(frame_folder / "shard-00001.h5")
    out = tmp_path / "patches"
    argv = ["--renders", str(frame_folder), "--out", str(out), "--synthetic", "10"]
    assert patches_main(argv) == 2
    err = one_line_error(capsys)
    assert "shard-00001.h5 cannot be read" in err and "corrupt" in err
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == ["renders"], list(tmp_path.iterdir())
    out.mkdir()
    write_patch_shard(out, 7, *synthetic_patches(np.random.default_rng(0), 4), {"source": np.array(["x"] * 4)}, {})
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert patches_main(argv + ["--overwrite"]) == 2
    capsys.readouterr()
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    (frame_folder / "shard-00001.h5").unlink()
    assert patches_main(argv + ["--overwrite"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["shard-00000.h5", "shard-1000000.h5"]  # the old shard 7 replaced


def test_a_folder_of_the_other_kind_is_named(frame_folder, tmp_path, capsys):
    patches = tmp_path / "patch-shards"
    write_patch_shard(patches, 0, *synthetic_patches(np.random.default_rng(0), 8), {"source": np.array(["x"] * 8)}, {})
    assert charuconet_main(["--data", str(patches), "--out", str(tmp_path / "a"), "--steps", "1", "--quiet"]) == 2
    err = one_line_error(capsys)
    assert "is not a frame shard (no 'images') but a RefineNet patch shard" in err and "datagen.render" in err
    assert refinenet_main(["--data", str(frame_folder), "--out", str(tmp_path / "b"), "--steps", "1", "--quiet"]) == 2
    err = one_line_error(capsys)
    assert "is not a patch shard (no 'patches' dataset) but a frame shard" in err and "datagen.patches" in err


def test_data_commands_refuse_an_unwritable_or_file_out_in_one_line(frame_folder, tmp_path, capsys, unwritable_dir):
    from datagen.render import main as render_main

    (tmp_path / "a-file").write_text("")
    for out, message in ((tmp_path / "a-file", "is a file, not a folder"), (unwritable_dir / "x", "cannot write")):
        for run in (lambda: render_main(["--n", "1", "--out", str(out), "--quiet"]),
                    lambda: patches_main(["--renders", str(frame_folder), "--out", str(out), "--synthetic", "4"]),
                    lambda: inspect_main([str(frame_folder), "--out", str(out), "--frames", "2"])):
            assert run() == 2
            assert message in one_line_error(capsys)


@pytest.mark.parametrize("arguments, message", [
    (["--device", "foo"], "is not a device"),
    (["--out", "FILE"], "is a file, not a folder"),
])
def test_report_refuses_a_bad_device_or_out_before_making_anything(tmp_path, capsys, arguments, message):
    from evaluate.report import main as report_main

    (tmp_path / "FILE").write_text("not a folder")
    arguments = [str(tmp_path / a) if a == "FILE" else a for a in arguments]
    out = ["--out", str(tmp_path / "report")] if "--out" not in arguments else []
    assert report_main(arguments + out + ["--no-render", "--quiet"]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "report").exists()
