"""evaluate: the paper's protocols on hand-computed cases and OpenCV, and the report end to end."""

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from conftest import VIEW_POSES, make_view
from datagen.shards import FrameLabels, write_shard
from deepcharuco import BoardSpec, Detection, OpenCVDetector, estimate_pose
from deepcharuco.networks import ChArUcoNet, ChArUcoNetConfig, RefineNet, RefineNetConfig, save_checkpoint
from evaluate import report
from evaluate.paper import unseen_boards
from evaluate.paper.data import TestSetError, frames_fingerprint, load_frames, select_well_lit
from evaluate.paper.protocols import (
    TestFrame, accuracy_vs_threshold, apply_effect, darken, motion_blur, score_corners, score_pose, summarize_poses,
    synthetic_curve, time_pipelines,
)
from evaluate.speed.machine import cpu_description

BOARD = BoardSpec()


class OracleDetector:
    """Returns the true corners, moved by ``shift`` px, with IDs remapped by ``ids`` and only ``keep`` of them."""

    def __init__(self, frames, shift=(0.0, 0.0), ids=None, keep=None):
        self.truth = {f.image.tobytes(): f for f in frames}
        self.shift, self.ids, self.keep = np.array(shift, np.float32), ids, keep

    def detect(self, image):
        frame = self.truth.get(image.tobytes())
        if frame is None:
            return Detection.empty()
        ids = np.flatnonzero(frame.visible)[: self.keep]
        corners = frame.corners[ids] + self.shift
        mapped = ids if self.ids is None else self.ids[ids]
        return Detection(mapped, corners, np.ones(len(ids)))

    def estimate_pose(self, detection, K, dist=None):
        return estimate_pose(detection, K, dist, board=BOARD)


@pytest.fixture(scope="module")
def frames(camera):
    out = []
    for i, pose in enumerate(VIEW_POSES):
        image, rvec, tvec, truth = make_view(BOARD, camera, **pose)
        out.append(TestFrame(image, truth.astype(np.float32), np.ones(16, bool), camera.K, rvec.ravel(), tvec.ravel(),
                             f"view{i}", {"lux": 500.0, "blur_px": 0.0, "has_board": True}))
    return out


def test_scores_follow_the_papers_rules(frames):
    perfect = [score_pose(OracleDetector(frames), f) for f in frames]
    assert all(s.accuracy == 1.0 and s.eps_re < 1e-3 and not s.confidently_wrong for s in perfect)
    assert all(s.rotation_deg < 0.01 and s.translation_fraction < 1e-4 for s in perfect)
    summary = summarize_poses(perfect)
    assert summary.pose_accuracy == 1.0 and summary.found == 1.0 and summary.confidently_wrong == 0
    # 2 px off: every corner still correct (< 3 px), with a 2 px sub-pixel error; 4 px off: none correct.
    near = score_corners(OracleDetector(frames, shift=(2.0, 0.0)).detect(frames[0].image), frames[0])
    assert near.accuracy == 1.0 and np.allclose(near.subpixel_errors, 2.0, atol=1e-4)
    far = score_corners(OracleDetector(frames, shift=(3.0, 4.0)).detect(frames[0].image), frames[0])
    assert far.accuracy == 0.0 and far.num_detected == 16
    half = score_corners(OracleDetector(frames, keep=8).detect(frames[0].image), frames[0])
    assert half.accuracy == 0.5
    # Nothing detected: accuracy 0, no pose, eps_re inf counts as a failure at every threshold.
    blind = score_pose(OracleDetector([]), frames[0])
    assert blind.accuracy == 0.0 and not blind.has_pose and not blind.confidently_wrong
    assert np.isnan(summarize_poses([blind]).mean_eps_re) and summarize_poses([blind]).pose_accuracy == 0.0


def test_a_consistent_but_wrong_labelling_is_a_confidently_wrong_pose(frames):
    """IDs read as if the board were turned 180 degrees: the corners fit a pose perfectly (eps_re ~ 0),
    and that pose is the wrong one. The paper's eps_re test passes it; the truth does not."""
    turned = OracleDetector(frames, ids=np.arange(16)[::-1].copy())
    scores = [score_pose(turned, f) for f in frames]
    assert all(s.has_pose for s in scores)
    assert sum(s.eps_re < 0.5 for s in scores) >= 4  # a perfect fit (the fronto-parallel view finds a poorer one)
    assert all(s.confidently_wrong and s.rotation_deg > 90 for s in scores)
    assert all(s.accuracy < 0.5 for s in scores)
    assert summarize_poses(scores).confidently_wrong == len(frames)


def test_accuracy_vs_threshold_by_hand():
    np.testing.assert_allclose(accuracy_vs_threshold([0.5, 2.0, np.inf], [0.0, 1.0, 3.0, 10.0]), [0, 1 / 3, 2 / 3, 2 / 3])
    assert accuracy_vs_threshold([], [1.0, 2.0]).tolist() == [0.0, 0.0]


def test_synthetic_effects(frames):
    image = frames[0].image
    assert np.array_equal(darken(image, 0), image)
    assert darken(np.full((2, 2), 255, np.uint8), 9)[0, 0] == round(255 * 0.6 ** 9)  # 3: "perceptually black"
    assert np.array_equal(motion_blur(image, 1)[0], image) and motion_blur(image, 1)[1] == 0.0
    # An even kernel moves the content by half a pixel, and the truth moves with it: OpenCV + cornerSubPix
    # on the blurred views agrees with the moved truth as well as on odd kernels.
    opencv = OpenCVDetector(BOARD, refine="subpix")
    for k in (2, 3, 4):
        blurred, shift = motion_blur(image, k)
        assert shift == (0.5 if k % 2 == 0 else 0.0)
        moved = apply_effect(frames[0], "blur", k)
        score = score_corners(opencv.detect(blurred), moved)
        assert score.accuracy == 1.0 and np.median(score.subpixel_errors) < 0.15, k
    with pytest.raises(ValueError, match="effect"):
        apply_effect(frames[0], "fog", 1)


def test_opencv_curves_have_the_papers_shape(frames):
    """Full accuracy on clean views at k = 0, falling with blur, gone in the dark (the paper: by k = 4-5)."""
    opencv = OpenCVDetector(BOARD, refine="subpix")
    blur = synthetic_curve(opencv, frames, "blur")
    dark = synthetic_curve(opencv, frames, "darkness")
    assert blur.accuracy[0] == 1.0 and dark.accuracy[0] == 1.0
    assert blur.per_frame.shape == (11, len(frames)) and len(blur.detections[3]) == len(frames)
    assert blur.accuracy[10] < blur.accuracy[0] and np.isfinite(blur.subpixel_error[0]) and blur.subpixel_error[0] < 0.2
    assert dark.accuracy[10] == 0.0 and np.isnan(dark.subpixel_error[10])
    assert json.dumps(dark.to_dict())  # NaN -> null


def test_timing_ranks_pipelines_by_their_cost(frames, monkeypatch):
    """Frames per second from the clock time_pipelines reads, here one that only the detectors move (1 and 4 ms a
    frame): exact rates whatever the machine's load (wall-clock speed belongs in benchmarks/)."""
    from types import SimpleNamespace

    import evaluate.paper.protocols

    clock = [0.0]

    class Costing(OracleDetector):
        def __init__(self, frames, cost):
            super().__init__(frames)
            self.cost = cost

        def detect(self, image):
            clock[0] += self.cost  # the stand-in clock moves; nothing sleeps
            return super().detect(image)

    monkeypatch.setattr(evaluate.paper.protocols, "time", SimpleNamespace(perf_counter=lambda: clock[0]))
    fps = time_pipelines({"fast": Costing(frames, 0.001), "slow": Costing(frames, 0.004)}, frames[:2], rounds=3,
                         min_seconds=0.3)
    assert set(fps) == {"fast", "slow"}
    assert fps["fast"] == pytest.approx(1000, rel=1e-6) and fps["slow"] == pytest.approx(250, rel=1e-6)


def write_test_shards(folder, frames, camera, sequences):
    """Shards shaped like evaluate.paper.sequences' output: frames with sequence names and lux."""
    rng = np.random.default_rng(0)
    for index, (name, lux_levels) in enumerate(sequences.items()):
        labels = []
        for j, lux in enumerate(lux_levels):
            source = frames[(index + j) % len(frames)]
            image = darken(source.image, 0 if lux >= 100 else 8)
            image = np.clip(image + rng.normal(0, 2, image.shape), 0, 255).astype(np.uint8)
            labels.append(FrameLabels(image, source.corners, source.visible, camera.K, source.rvec, source.tvec,
                                      {"has_board": True, "lux": float(lux), "blur_px": 0.0, "sequence": name,
                                       "sequence_frame": j}))
        write_shard(folder, index, labels, BOARD, {"version": "test"})


def test_well_lit_selection(frames, camera, tmp_path):
    write_test_shards(tmp_path, frames, camera, {"lux-700-a": [700, 700, 700], "lux-1-a": [400, 1, 1],
                                                 "dark-only": [1, 1]})
    loaded = load_frames(tmp_path)
    assert len(loaded) == 8 and loaded[0].name == "shard-00000.h5#0" and loaded[0].rvec is not None
    chosen = select_well_lit(loaded, 2, seed=0)
    assert [f.meta["sequence"] for f in chosen] == ["lux-700-a", "lux-1-a"]  # one per sequence, lit frames only
    assert chosen[1].meta["lux"] == 400
    with pytest.raises(TestSetError, match="only 2 well-lit frames"):
        select_well_lit(loaded, 3)
    with pytest.raises(TestSetError, match="not of"):
        load_frames(tmp_path, BoardSpec(squares_x=6))
    with pytest.raises(TestSetError, match="no shard"):
        load_frames(tmp_path / "empty")


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    folder = tmp_path_factory.mktemp("weights")
    torch.manual_seed(0)
    save_checkpoint(folder / "charuconet.pt", ChArUcoNet(ChArUcoNetConfig.lite(16)), board=BOARD, input_size=(320, 240))
    save_checkpoint(folder / "refinenet.pt", RefineNet(RefineNetConfig.lite()))
    return folder


def test_report_end_to_end(frames, camera, tmp_path, checkpoint):
    write_test_shards(tmp_path / "seq", frames, camera,
                      {f"lux-{lux}-a": [400] * 3 + [lux] * 3 for lux in (700, 100, 1)} | {"shadow-1": [500] * 4})
    write_test_shards(tmp_path / "data", frames, camera, {"renders": [300, 3, 30, 0.5, 900]})
    out = tmp_path / "report"
    argv = ["--sequences", str(tmp_path / "seq"), "--data", str(tmp_path / "data"), "--out", str(out), "--quiet",
            "--weights", str(checkpoint / "charuconet.pt"), "--refine-weights", str(checkpoint / "refinenet.pt"),
            "--synthetic-images", "4", "--timing-seconds", "0.2", "--gallery", "2", "--no-autolabel-check", "--no-render",
            "--no-calibration",  # a data/calibration in the checkout must not slow this down (test_calibrate covers it)
            "--no-captures",  # nor the shipped real-capture sample (test_captures covers it)
            "--no-unseen-boards",  # nor a data/unseen (evaluate.paper.unseen_boards; test_any_board covers the detector)
            "--no-false-positives",  # test_false_positives covers it with the shipped weights
            "--no-corner-precision"]  # test_corner_fit covers it
    assert report.main(argv) == 0
    results = json.loads((out / "results.json").read_text())
    assert set(results["detectors"]) == {"deep", "deep_subpix", "deep_norefine", "deep_paper", "deep_markers", "opencv",
                                         "opencv_norefine"}
    assert set(results["timing"]["fps"]) == set(results["detectors"]) and results["timing"]["image_size"] == [320, 240]
    table = {row["sequence"]: row for row in results["sequences"]["table"]}
    assert list(table) == ["lux-700-a", "lux-100-a", "lux-1-a", "shadow-1"]
    # OpenCV's numbers in the report are what the protocol gives on the same frames.
    seq = [f for f in load_frames(tmp_path / "seq") if f.meta["sequence"] == "lux-1-a"]
    expected = summarize_poses([score_pose(OpenCVDetector(BOARD), f) for f in seq])
    assert table["lux-1-a"]["opencv"]["pose_accuracy"] == pytest.approx(expected.pose_accuracy)
    assert table["lux-1-a"]["opencv"]["pose_accuracy"] == pytest.approx(0.5)  # lit half found, dark half not
    assert table["lux-700-a"]["opencv"]["pose_accuracy"] == 1.0
    assert results["synthetic"]["blur"]["opencv"]["accuracy"][0] == 1.0
    assert len(results["synthetic"]["images"]) == 4 and len(results["gallery"]) == 2
    assert {t["target"].split(",")[0] for t in results["targets"]} >= {"synthetic blur k=10", "speed"}
    html = (out / "report.html").read_text()
    assert html.count("data:image/png;base64,") == 2 + 1 + 2 and "Rendered capture sequences" in html
    markdown = (out / "report.md").read_text()
    assert "| lux-1-a | 6 |" in markdown and (out / "figures" / "synthetic_blur.png").stat().st_size > 1000
    assert "Held-out renders" in markdown and "Timing" in markdown


def test_report_of_a_points_only_model_leaves_out_the_papers_decoding(frames, camera, tmp_path, checkpoint):
    # A family model (`train.pipeline --family`, heads "points") has no ID head: the report reads the board by its
    # markers in every deep row and says why the paper's decoding is missing, instead of refusing.
    torch.manual_seed(0)
    save_checkpoint(tmp_path / "family.pt", ChArUcoNet(ChArUcoNetConfig.lite(16)), board=BOARD, input_size=(320, 240),
                    heads="points")
    write_test_shards(tmp_path / "seq", frames, camera, {f"lux-{lux}-a": [400] * 3 + [lux] * 3 for lux in (700, 1)})
    write_test_shards(tmp_path / "data", frames, camera, {"renders": [300, 3, 30, 0.5, 900]})
    out = tmp_path / "report"
    argv = ["--sequences", str(tmp_path / "seq"), "--data", str(tmp_path / "data"), "--out", str(out), "--quiet",
            "--weights", str(tmp_path / "family.pt"), "--refine-weights", str(checkpoint / "refinenet.pt"),
            "--synthetic-images", "2", "--timing-seconds", "0.1", "--gallery", "1", "--no-autolabel-check",
            "--no-render", "--no-calibration", "--no-captures", "--no-unseen-boards", "--no-false-positives",
            "--no-corner-precision"]
    assert report.main(argv) == 0
    results = json.loads((out / "results.json").read_text())
    assert set(results["detectors"]) == {"deep", "deep_subpix", "deep_norefine", "opencv", "opencv_norefine"}
    assert any("by its markers" in note and "not evaluated" in note for note in results["notes"])


def test_report_refuses_missing_data_and_weights(tmp_path, capsys, frames, camera):
    argv = ["--sequences", str(tmp_path / "none"), "--data", str(tmp_path / "none2"), "--out", str(tmp_path / "r"),
            "--quiet"]
    assert report.main(argv) == 2
    assert f"{tmp_path / 'none'} does not exist" in capsys.readouterr().err  # given explicitly: never skipped
    write_test_shards(tmp_path / "seq", frames, camera, {f"s{i}": [500] for i in range(4)})
    argv = ["--sequences", str(tmp_path / "seq"), "--no-render", "--out", str(tmp_path / "r"),
            "--weights", str(tmp_path / "missing.pt"), "--quiet", "--no-autolabel-check"]
    assert report.main(argv) == 2
    assert "missing.pt does not exist" in capsys.readouterr().err


def test_report_refuses_a_data_folder_that_is_missing_empty_or_damaged(tmp_path, capsys, frames, camera):
    """An explicitly given test folder is never skipped in silence; a truncated shard is named, with the fix."""
    write_test_shards(tmp_path / "seq", frames, camera, {f"s{i}": [500] for i in range(4)})
    (tmp_path / "empty").mkdir()
    write_test_shards(tmp_path / "damaged", frames, camera, {"renders": [300, 3]})
    shard = next((tmp_path / "damaged").glob("shard-*.h5"))
    shard.write_bytes(shard.read_bytes()[: shard.stat().st_size // 2])  # a copy cut short
    for folder, message in (("nowhere", "nowhere does not exist"), ("empty", "empty holds no shard-*.h5 files"),
                            ("damaged", f"{shard} is not a readable HDF5 shard, it is truncated or corrupt")):
        argv = ["--sequences", str(tmp_path / "seq"), "--data", str(tmp_path / folder), "--out", str(tmp_path / "r"),
                "--quiet", "--no-autolabel-check", "--no-render"]
        assert report.main(argv) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, err


def test_quick_takes_an_explicit_synthetic_images(tmp_path, capsys, frames, camera):
    """--quick's fewer synthetic images yield to --synthetic-images, so the error's advice to lower it is right."""
    write_test_shards(tmp_path / "seq", frames, camera, {f"s{i}": [500] for i in range(4)})
    argv = ["--sequences", str(tmp_path / "seq"), "--out", str(tmp_path / "r"), "--quiet", "--no-autolabel-check",
            "--no-render", "--quick"]
    assert report.main(argv + ["--synthetic-images", "5"]) == 2
    err = capsys.readouterr().err
    assert "only 4 well-lit frames" in err and "where 5 are needed" in err and "lower --synthetic-images" in err


def test_unseen_boards_only_refuses_a_board_it_does_not_know(capsys, tmp_path):
    code = unseen_boards.main(["--no-render", "--root", str(tmp_path), "--only", "5x5 DICT_9X9"])
    err = capsys.readouterr().err
    assert code == 2 and "--only names no unseen board: 5x5 dict_9x9" in err and '"4x5 DICT_4X4_1000 inverted"' in err


def test_timings_name_the_cpu_and_its_widest_vector_extension():
    intel = ("processor\t: 0\nmodel name\t: Intel(R) Xeon(R) Platinum 8375C CPU @ 2.90GHz\n"
             "flags\t\t: fpu sse4_2 avx avx2 avx512f avx512_vnni\n\nprocessor\t: 1\nmodel name\t: other\n")
    amd = "processor\t: 0\nmodel name\t: AMD EPYC\nflags\t\t: fpu sse4_2 avx avx2 fma\n"
    assert cpu_description(intel).startswith("Intel(R) Xeon(R) Platinum 8375C CPU @ 2.90GHz (")
    assert cpu_description(intel).endswith("AVX-512 VNNI)")  # the first processor's, the widest only
    assert cpu_description(amd).startswith("AMD EPYC (") and cpu_description(amd).endswith("AVX2)")
    assert "AVX" not in cpu_description("")  # no /proc/cpuinfo: the architecture alone, no guessed extension


def test_a_test_sets_fingerprint_names_its_pixels_and_labels(frames):
    same = frames_fingerprint(frames)
    assert same == frames_fingerprint(list(frames)) and len(same) == 16
    assert frames_fingerprint(frames[::-1]) != same  # order is part of the set
    changed = frames[0].image.copy()
    changed[0, 0] ^= 1  # one pixel, one bit
    assert frames_fingerprint([replace(frames[0], image=changed)] + frames[1:]) != same
    moved = frames[0].corners + np.float32(1e-3)
    assert frames_fingerprint([replace(frames[0], corners=moved)] + frames[1:]) != same
    board = {"board": BOARD.to_dict(), "frames": 1, "data_fingerprint": same, "summary": {
        "deep": {"k0": 1.0, "blur10": 1.0, "dark9": 1.0, "pose_accuracy": 1.0, "confidently_wrong": 0,
                 "mean_eps_re_good_light": 0.1}}}
    text = unseen_boards.sections({"boards": {"5x5 test": board}}, {})[0][1]
    assert f"5x5 test {same}" in text
