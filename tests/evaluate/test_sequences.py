"""The rendered twins of the paper's evaluation videos (evaluate.paper.sequences).

Plans (no Blender) for every sequence; then three short sequences rendered with Blender in a
subprocess (~20 s): labels against OpenCV, light, shadow and shake, determinism and resume.
"""

import json
import os
import shutil
import subprocess
import sys

import h5py
import numpy as np
import pytest

from conftest import ROOT

from datagen.frames import blur_extent_px
from datagen.shards import ShardReader, list_shards
from deepcharuco import BoardSpec, OpenCVDetector
from evaluate.paper.sequences import (
    LIT_FRAMES, MAX_ATTEMPTS, SEQUENCE_NAMES, SEQUENCES, board_in_view, evaluation_config, main, plan_sequence,
)

FRAMES = 34  # 30 lit + 4 condition frames
CHOSEN = ["lux-1-a", "shadow-1", "motion-1"]
ARGS = ["--frames", FRAMES, "--samples", 2, "--quiet"]
EPOCH = {"SOURCE_DATE_EPOCH": "1700000000"}


def sequences_cli(*args, check=True):
    result = subprocess.run([sys.executable, "-m", "evaluate.paper.sequences", *map(str, args)], cwd=ROOT,
                            capture_output=True, text=True, env={**os.environ, **EPOCH})
    if check and result.returncode != 0:
        raise AssertionError(f"evaluate.paper.sequences failed ({result.returncode}):\n{result.stderr[-3000:]}")
    return result


def frames_of(path):
    reader = ShardReader(path)
    frames = [reader[i] for i in range(len(reader))]
    reader.close()
    return frames


def first_plan(sequence, seed=0, n_frames=60):
    board = BoardSpec()
    for attempt in range(MAX_ATTEMPTS):
        plan = plan_sequence(sequence, seed, n_frames, board, evaluation_config(), attempt)
        if plan is not None:
            return plan
    raise AssertionError(f"no plan for {sequence.name}")


def test_the_paper_set_of_26_sequences():
    assert len(SEQUENCES) == 26 and [s.number for s in SEQUENCES] == list(range(26))
    assert SEQUENCE_NAMES[:3] == ("lux-700-a", "lux-700-b", "lux-400-a") and SEQUENCE_NAMES[18:20] == ("lux-0.3-a", "lux-0.3-b")
    assert SEQUENCE_NAMES[20:] == ("shadow-1", "shadow-2", "shadow-3", "motion-1", "motion-2", "motion-3")
    assert sorted({s.level for s in SEQUENCES if s.kind == "lux"}) == [0.3, 1, 3, 5, 10, 30, 50, 100, 400, 700]


def test_plans_are_seeded_and_keep_the_board_in_view():
    board = BoardSpec()
    for sequence in SEQUENCES:
        plan = first_plan(sequence)
        again = first_plan(sequence)
        assert plan.attempt == again.attempt and plan.static.render_seed == again.static.render_seed
        np.testing.assert_array_equal(plan.static.K, again.static.K)
        assert len(plan.frames) == 60 and plan.static.denoise and plan.static.samples == 16
        assert not plan.static.distractors and plan.static.board_present
        assert all(board_in_view(board, spec) for spec in plan.frames)
        lux = [spec.lux for spec in plan.frames]
        assert min(lux[:LIT_FRAMES]) >= (400 if sequence.kind == "lux" else 60)  # well lit first
        if sequence.kind == "lux":
            assert lux[LIT_FRAMES:] == [sequence.level] * 30 and not any(plan.own_render)
        else:
            assert plan.own_render == [False] * LIT_FRAMES + [True] * 30
        blur = [blur_extent_px(board, spec) for spec in plan.frames]
        assert max(blur[:LIT_FRAMES]) == 0.0
        if sequence.kind == "motion":
            assert np.mean(blur[LIT_FRAMES:]) > 2.0, "a shake should blur"
            # The rest pose is the lit frames' camera: the shake is about it.
            np.testing.assert_array_equal(plan.frames[0].camera_matrix, plan.static.camera_matrix)
        if sequence.kind == "shadow":
            casters = [[s for s in spec.shapes if s.role == "shadow-caster"] for spec in plan.frames]
            assert not any(casters[:LIT_FRAMES]) and all(len(c) == 1 for c in casters[LIT_FRAMES:])
            places = np.array([c[0].matrix[:3, 3] for c in casters[LIT_FRAMES:]])
            assert np.linalg.norm(places[-1] - places[0]) > 0.05  # it travels across the board
    assert first_plan(SEQUENCES[0], seed=1).static.render_seed != first_plan(SEQUENCES[0]).static.render_seed


def test_cli_refuses_bad_arguments(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--frames", "30", "--out", str(tmp_path)])
    assert exit_info.value.code == 2 and "--frames must be >= 31" in capsys.readouterr().err
    assert main(["--only", "lux-2-a", "--out", str(tmp_path)]) == 2
    error = capsys.readouterr().err
    assert "unknown sequence(s) lux-2-a" in error and "lux-0.3-b" in error
    assert not list(tmp_path.iterdir())


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    pytest.importorskip("bpy", reason="the renderer needs the [render] extra (bpy)")
    out = tmp_path_factory.mktemp("sequences")
    sequences_cli("--only", *CHOSEN, "--out", out, *ARGS)
    return out


def test_schema_meta_and_index(rendered):
    numbers = [SEQUENCE_NAMES.index(name) for name in CHOSEN]
    assert [p.name for p in list_shards(rendered)] == [f"shard-{n:05d}.h5" for n in numbers]
    index = json.loads((rendered / "index.json").read_text())
    assert index["frames"] == 3 * FRAMES
    with h5py.File(rendered / f"shard-{numbers[0]:05d}.h5") as f:
        assert f["images"].shape == (FRAMES, 240, 320) and f["corners"].shape == (FRAMES, 16, 2)
        assert json.loads(f.attrs["generator"])["args"]["frames"] == FRAMES
        assert json.loads(f.attrs["generator"])["sequence"] == "lux-1-a"
        for key in ("sequence", "sequence_frame", "lux", "blur_px", "has_board", "condition", "lit", "seed", "frame",
                    "exposure_s", "gain", "shadow_fraction", "render_seed", "samples", "visible_count"):
            assert f["meta"][key].shape == (FRAMES,), key
    for name in CHOSEN:
        frames = frames_of(rendered / f"shard-{SEQUENCE_NAMES.index(name):05d}.h5")
        assert [f.meta["sequence"] for f in frames] == [name] * FRAMES
        assert [f.meta["sequence_frame"] for f in frames] == list(range(FRAMES))
        assert [f.meta["lit"] for f in frames] == [True] * LIT_FRAMES + [False] * (FRAMES - LIT_FRAMES)
        assert all(f.meta["has_board"] and f.visible.all() for f in frames)  # the whole board, unoccluded
        assert all(np.array_equal(f.K, frames[0].K) for f in frames)  # a still camera


def test_lit_frames_labels_agree_with_opencv(rendered):
    detector = OpenCVDetector(BoardSpec(), refine="subpix")
    for name in CHOSEN:
        frames = frames_of(rendered / f"shard-{SEQUENCE_NAMES.index(name):05d}.h5")
        errors = []
        for frame in frames[:LIT_FRAMES:10]:
            detection = detector.detect(frame.image)
            assert len(detection) >= 12, f"{name}: OpenCV finds {len(detection)} corners in a well-lit frame"
            errors += [np.linalg.norm(c - frame.corners[i]) for i, c in zip(detection.ids, detection.corners)]
        assert np.median(errors) < 0.25 and np.max(errors) < 1.0, (name, np.median(errors), np.max(errors))


def test_lux_sequence_gets_darker_with_the_same_labels(rendered):
    frames = frames_of(rendered / f"shard-{SEQUENCE_NAMES.index('lux-1-a'):05d}.h5")
    lit, dark = frames[:LIT_FRAMES], frames[LIT_FRAMES:]
    assert {f.meta["lux"] for f in lit} == {400.0} and {f.meta["lux"] for f in dark} == {1.0}
    assert max(f.image.mean() for f in dark) < 0.6 * min(f.image.mean() for f in lit)
    assert min(f.meta["gain"] for f in dark) > max(f.meta["gain"] for f in lit)  # the webcam adapts
    for frame in frames:
        np.testing.assert_array_equal(frame.corners, frames[0].corners)
        np.testing.assert_array_equal(frame.rvec, frames[0].rvec)
        assert frame.meta["blur_px"] == 0.0
    assert not np.array_equal(lit[0].image, lit[1].image)  # fresh sensor noise every frame


def test_shadow_crosses_and_shake_blurs(rendered):
    shadow = frames_of(rendered / f"shard-{SEQUENCE_NAMES.index('shadow-1'):05d}.h5")
    assert max(f.meta["shadow_fraction"] for f in shadow[LIT_FRAMES:]) > 0.05
    assert all(f.meta["shadow_fraction"] == 0.0 for f in shadow[:LIT_FRAMES])
    for frame in shadow:  # the geometry stays
        np.testing.assert_array_equal(frame.corners, shadow[0].corners)
    motion = frames_of(rendered / f"shard-{SEQUENCE_NAMES.index('motion-1'):05d}.h5")
    assert all(f.meta["blur_px"] == 0.0 for f in motion[:LIT_FRAMES])
    assert all(f.meta["blur_px"] > 0.0 and f.meta["shake"] for f in motion[LIT_FRAMES:])
    moved = [np.linalg.norm(f.corners - motion[0].corners, axis=1).max() for f in motion[LIT_FRAMES:]]
    assert max(moved) > 0.5  # labels follow the shaken camera (pose at the shutter centre)
    assert {f.meta["lux"] for f in motion} == {motion[0].meta["lux"]} and {f.meta["exposure_s"] for f in motion} == {
        motion[0].meta["exposure_s"]}


def test_resume_renders_only_what_is_missing_with_the_same_bytes(rendered, tmp_path):
    out = tmp_path / "copy"
    shutil.copytree(rendered, out)
    missing = [out / f"shard-{SEQUENCE_NAMES.index(name):05d}.h5" for name in ("lux-1-a", "shadow-1")]
    for path in missing:
        path.unlink()
    kept = {p.name: p.stat().st_mtime_ns for p in list_shards(out)}
    refused = sequences_cli("--only", *CHOSEN, "--out", out, *ARGS, check=False)
    assert refused.returncode == 2 and "--resume" in refused.stderr and not any(p.exists() for p in missing)
    sequences_cli("--only", *CHOSEN, "--out", out, *ARGS, "--resume")
    assert {p.name: p.stat().st_mtime_ns for p in list_shards(out) if p not in missing} == kept  # untouched
    for path in missing:  # same seed, same bytes (SOURCE_DATE_EPOCH fixes the one time stamp)
        assert path.read_bytes() == (rendered / path.name).read_bytes(), path.name
    other = sequences_cli("--only", "lux-1-a", "--out", out, "--frames", FRAMES, "--seed", 1, "--resume", "--quiet",
                          check=False)
    assert other.returncode == 2 and "seed" in other.stderr
