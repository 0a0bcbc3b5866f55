import json
import pickle

import h5py
import numpy as np
import pytest

from conftest import make_view
from datagen.shards import FrameLabels, ShardError, ShardReader, list_shards, update_index, write_shard
from deepcharuco import BoardSpec, project_corners

BOARD = BoardSpec()


def positive(camera, seed):
    image, rvec, tvec, truth = make_view(BOARD, camera, distance=0.35 + 0.01 * seed, roll_deg=10 * seed)
    meta = {"seed": seed, "lux": 700.0, "exposure_s": 0.01, "gain": 1.0, "blur_px": 0.0, "has_board": True,
            "tags": "clean"}
    return FrameLabels(image, truth.astype(np.float32), np.ones(16, bool), camera.K, rvec, tvec, meta)


def negative(seed):
    meta = {"seed": seed, "lux": 50.0, "exposure_s": 0.03, "gain": 4.0, "blur_px": 1.5, "has_board": False,
            "tags": "negative chessboard"}
    return FrameLabels(np.full((240, 320), 7, np.uint8), np.full((16, 2), np.nan, np.float32), np.zeros(16, bool),
                       np.eye(3), np.zeros(3), np.zeros(3), meta)


def test_round_trip_follows_the_schema(tmp_path, camera):
    frames = [positive(camera, 0), negative(1), positive(camera, 2)]
    path = write_shard(tmp_path, 0, frames, BOARD, {"version": "test", "args": {"n": 3}})
    assert path.name == "shard-00000.h5"
    with h5py.File(path) as f:
        assert f["images"].shape == (3, 240, 320) and f["images"].dtype == np.uint8
        assert f["images"].chunks == (1, 240, 320) and f["images"].compression == "gzip"
        assert f["corners"].dtype == np.float32 and f["visible"].dtype == bool
        assert f["K"].shape == (3, 3, 3) and f["rvec"].shape == (3, 3) and f["tvec"].shape == (3, 3)
        assert list(f.attrs["image_size"]) == [320, 240]
        assert {"seed", "lux", "exposure_s", "gain", "blur_px", "has_board", "tags"} <= set(f["meta"])
    reader = ShardReader(path)
    assert len(reader) == 3 and reader.board == BOARD and reader.image_size == (320, 240)
    back = reader[2]
    np.testing.assert_array_equal(back.image, frames[2].image)
    np.testing.assert_allclose(back.corners, project_corners(BOARD, back.rvec, back.tvec, back.K), atol=1e-3)
    assert reader[1].meta["has_board"] is False and reader[1].meta["tags"] == "negative chessboard"
    assert np.all(np.isnan(reader[1].corners))
    with pytest.raises(IndexError):
        reader[3]


def test_negatives_must_not_carry_corners(tmp_path, camera):
    bad = negative(0)
    bad.corners[3] = (10.0, 20.0)
    with pytest.raises(ShardError, match="negative .* carries corners"):
        write_shard(tmp_path, 0, [bad], BOARD, {})
    assert list_shards(tmp_path) == []


def test_frames_must_match_the_board(tmp_path, camera):
    with pytest.raises(ShardError, match=r"\(24, 2\)"):
        write_shard(tmp_path, 0, [positive(camera, 0)], BoardSpec(7, 5, 0.04, 0.03, "DICT_6X6_250"), {})


def test_only_complete_shards_count_and_index_is_rebuilt(tmp_path, camera):
    write_shard(tmp_path, 1, [negative(0)], BOARD, {})
    write_shard(tmp_path, 0, [negative(1), negative(2)], BOARD, {})
    (tmp_path / ".shard-00002.h5.tmp-999").write_bytes(b"half a shard from a killed worker")
    assert [p.name for p in list_shards(tmp_path)] == ["shard-00000.h5", "shard-00001.h5"]
    index = json.loads((tmp_path / "index.json").read_text())
    assert index["frames"] == 3 and [s["file"] for s in index["shards"]] == ["shard-00000.h5", "shard-00001.h5"]
    (tmp_path / "index.json").unlink()
    assert update_index(tmp_path)["frames"] == 3


def test_same_inputs_same_bytes(tmp_path, camera):
    frames = [positive(camera, 0), negative(1)]
    a = write_shard(tmp_path / "a", 0, frames, BOARD, {"seed": 1}, created="2026-01-01T00:00:00+00:00")
    b = write_shard(tmp_path / "b", 0, frames, BOARD, {"seed": 1}, created="2026-01-01T00:00:00+00:00")
    assert a.read_bytes() == b.read_bytes()


def test_reader_pickles_unopened_and_refuses_other_schemas(tmp_path):
    path = write_shard(tmp_path, 0, [negative(0)], BOARD, {})
    reader = ShardReader(path)
    reader[0]
    clone = pickle.loads(pickle.dumps(reader))
    assert clone._file is None and clone[0].meta["seed"] == 0
    reader.close()
    clone.close()
    with h5py.File(path, "a") as f:
        f.attrs["schema_version"] = 99
    with pytest.raises(ShardError, match="schema_version 99"):
        ShardReader(path)
    with pytest.raises(ShardError, match="does not exist"):
        ShardReader(tmp_path / "nope.h5")
    with pytest.raises(ShardError, match="not a folder of shards"):
        list_shards(tmp_path / "nope")


def test_an_index_temporary_is_removed_when_its_writer_is_gone(tmp_path):
    """A worker killed while it rewrote index.json leaves its temporary: the run removes it once that process has
    ended on this host, or once it is old; a fresh one of a live process, or of another host's task, stays."""
    import os
    import socket
    import subprocess
    import sys
    import time

    from datagen.render import STALE_INDEX_S, remove_stale_temporaries
    from datagen.shards import index_temporary_name, index_temporary_writer

    ended = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid, host = int(ended.stdout), socket.gethostname()
    names = {"dead": index_temporary_name(host, dead_pid), "alive": index_temporary_name(host, os.getpid()),
             "elsewhere": index_temporary_name("another-host-1", dead_pid), "old": index_temporary_name("h", 7)}
    for name in names.values():
        (tmp_path / name).write_text("{}")
    stale = time.time() - STALE_INDEX_S - 60
    os.utime(tmp_path / names["old"], (stale, stale))
    assert index_temporary_writer(names["elsewhere"]) == ("another-host-1", dead_pid)
    remove_stale_temporaries(tmp_path, [])
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([names["alive"], names["elsewhere"]])
