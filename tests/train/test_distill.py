"""train.draw's frames and labels, train.distill's loss, resume and checkpoints (tiny frames, a few steps)."""

import json

import cv2
import numpy as np
import pytest
import torch

from deepcharuco.boards.board import BoardSpec
from deepcharuco.detection.deep_detector import Detector
from deepcharuco.networks.charuconet import ChArUcoNet, ChArUcoNetConfig, fold_batch_norm
from deepcharuco.networks.checkpoint import CheckpointError, load_charuconet, read_checkpoint, save_bundle
from deepcharuco.networks.shipped import DEFAULT_WEIGHTS
from train import distill
from train.draw import FrameDrawer, DrawConfig

PAPER_BOARD = BoardSpec.from_dict(read_checkpoint(DEFAULT_WEIGHTS, "charuconet")["board"])


def tiny_args(out, *extra):
    return distill.parse_args(["--out", str(out), "--steps", "6", "--warmup", "2", "--batch-size", "3",
                               "--size", "64x48", "--val-size", "64x48", "--val-batches", "1", "--val-every", "3",
                               "--threads", "1", "--device", "cpu", "--quiet", *extra])


@pytest.fixture(scope="module")
def drawer():
    return FrameDrawer([PAPER_BOARD], DrawConfig(size=(160, 120), lens_p=1.0, negative_p=0.0))


def test_labels_land_on_the_drawn_corners(drawer):
    """A label, taken back through the map the image was sampled by (lens, then the pose's homography), is its
    corner in the board's texture to 1e-3 px; and cornerSubPix on the clean frames finds the corners at the labels."""
    frames = drawer.draw(np.random.default_rng(3), 12, augment_frames=False)
    texture = drawer.textures[0][0]
    worst, refined = 0.0, []
    for k in range(12):
        visible = frames.visible[k]
        assert frames.params[k]["k"] != 0  # every frame through a lens
        labels = frames.corners[k][visible]
        if not len(labels):
            continue
        true_uv = texture.board_to_texture(PAPER_BOARD.object_points()[visible])
        uv = drawer.texture_points(labels, frames.params[k])
        texels_per_px = np.linalg.norm(drawer.texture_points(labels + [0.001, 0], frames.params[k]) - uv, axis=1) / 0.001
        worst = max(worst, float((np.linalg.norm(uv - true_uv, axis=1) / texels_per_px).max()))
        if frames.params[k]["square_px"] >= 12:
            image = frames.image[k, 0].numpy() * 255
            inner = np.all((labels > 6) & (labels < [153, 113]), axis=1)
            if inner.any():
                start = labels[inner].astype(np.float32).reshape(-1, 1, 2)
                found = cv2.cornerSubPix(image, start.copy(), (3, 3), (-1, -1),
                                         (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4))
                refined += list(np.linalg.norm((found - start)[:, 0], axis=1))
    assert worst < 1e-3
    assert len(refined) >= 10
    assert np.median(refined) < 0.15  # 0.06 px as drawn; sampling half a texel or a fine pixel off fails it


def test_drawing_is_a_function_of_the_seed(drawer):
    a = drawer.draw(np.random.default_rng([5, 2]), 3)
    b = drawer.draw(np.random.default_rng([5, 2]), 3)
    c = drawer.draw(np.random.default_rng([5, 3]), 3)
    assert torch.equal(a.image, b.image) and np.array_equal(a.corners, b.corners, equal_nan=True)
    assert not torch.equal(a.image, c.image)


def test_the_loss_falls_on_a_fixed_batch(tmp_path):
    args = tiny_args(tmp_path / "run")
    distiller = distill.Distiller(args, torch.device("cpu"))
    batch = distiller.batch(0)
    optimizer = torch.optim.Adam(distiller.student.parameters(), lr=3e-3)
    history = []
    for _ in range(40):
        loss, terms = distiller.loss(*batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        history.append(terms)
    assert set(terms) == {"kl_points", "ce_points", "kl_ids", "ce_ids"}  # the paper's board: both heads distilled
    for name in terms:  # each term, not only their sum: to the teacher and to the labels
        assert history[-1][name] < 0.5 * history[0][name], name


def test_a_resumed_run_equals_an_uninterrupted_one(tmp_path):
    whole = distill.run(tiny_args(tmp_path / "whole"))
    assert whole["step"] == 6 and whole["signal"] is None
    stopped = distill.run(tiny_args(tmp_path / "parts"), stop_at=4)
    assert stopped["step"] == 4
    resumed = distill.run(tiny_args(tmp_path / "parts", "--resume"))
    assert resumed["step"] == 6
    a = torch.load(tmp_path / "whole" / "last.pt", weights_only=True)
    b = torch.load(tmp_path / "parts" / "last.pt", weights_only=True)
    assert all(torch.equal(a["state_dict"][name], b["state_dict"][name]) for name in a["state_dict"])
    assert (tmp_path / "whole" / "log.csv").read_text().splitlines()[1:] and [
        row.split(",")[:2] for row in (tmp_path / "whole" / "log.csv").read_text().splitlines()] == [
        row.split(",")[:2] for row in (tmp_path / "parts" / "log.csv").read_text().splitlines()]


def test_the_checkpoint_loads_through_the_runtime_loader(tmp_path):
    distill.run(tiny_args(tmp_path / "run"))
    model, board, data = load_charuconet(tmp_path / "run" / "last.pt")
    assert model.config == ChArUcoNetConfig.fast(16) and board == PAPER_BOARD
    assert data["input_size"] == [64, 48] and data.get("heads", "all") == "all"
    trained = ChArUcoNet(ChArUcoNetConfig.fast(16))
    trained.load_state_dict(data["state_dict"])
    image = torch.rand(1, 1, 96, 136)
    with torch.no_grad():
        for ours, theirs in zip(model(image), fold_batch_norm(trained.eval())(image)):
            torch.testing.assert_close(ours, theirs, atol=1e-4, rtol=1e-4)
    # The ONNX export the runtime makes of it gives PyTorch's logits, at a size that is no multiple of 32.
    from deepcharuco.networks.onnx_runner import OnnxRunner
    from deepcharuco.networks.runtime import float_onnx

    runner = OnnxRunner(float_onnx(model), None, threads=1)
    points, ids = runner.charuconet(image.numpy())
    with torch.no_grad():
        expected = model(image)
    np.testing.assert_allclose(points, expected[0][0].numpy(), atol=1e-3)
    np.testing.assert_allclose(ids, expected[1][0].numpy(), atol=1e-3)
    # Bundled with the shipped RefineNet, a Detector builds the fast network from the checkpoint's own config.
    # Its input_white (dim inputs brightened) travels from the bundle into its ONNX bundle and the Detector.
    bundle = save_bundle(tmp_path / "fast.pt", tmp_path / "run" / "last.pt", DEFAULT_WEIGHTS, threshold=0.25,
                         input_white=0.3)
    detector = Detector(weights=bundle, backend="onnx")
    assert detector.charuconet.config.arch == "fast" and detector.input_white == 0.3
    assert detector.detect(np.full((120, 160), 128, np.uint8)) is not None
    from deepcharuco.cli.export import write_onnx_bundle

    exported = write_onnx_bundle(bundle)
    assert json.loads((exported / "bundle.json").read_text())["input_white"] == 0.3
    with pytest.raises(CheckpointError, match="input_white 1.5"):
        save_bundle(tmp_path / "bad.pt", tmp_path / "run" / "last.pt", DEFAULT_WEIGHTS, input_white=1.5)


def test_a_missing_teacher_is_one_line_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "run"
    code = distill.main(["--teacher", str(tmp_path / "nope.pt"), "--out", str(out), "--quiet"])
    error = capsys.readouterr().err.strip()
    assert code == 2 and len(error.splitlines()) == 1 and "--teacher" in error and "nope.pt" in error
    assert not out.exists()


def test_inverted_prints_are_drawn_as_the_detector_sees_them():
    # A board file's inverted print (white on black paper), drawn, then the frame inverted whole (the detector's
    # canonical view): OpenCV reads the board there as a normal print, and not in the frame as the camera saw it.
    config = DrawConfig(size=(320, 240), lens_p=0.0, negative_p=0.0, square_px=(12.0, 16.0), max_tilt_deg=20.0,
                        inverted_p=1.0)
    frames = FrameDrawer([PAPER_BOARD], config).draw(np.random.default_rng(7), 8, augment_frames=False)
    assert frames.inverted.all()
    detector = cv2.aruco.CharucoDetector(PAPER_BOARD.cv_board())
    whole = np.flatnonzero(frames.visible.sum(axis=1) == PAPER_BOARD.num_corners)  # the board wholly in the frame
    assert len(whole) >= 2
    for k in range(8):
        canonical = np.rint(frames.image[k, 0].numpy() * 255).astype(np.uint8)
        corners, ids, _, _ = detector.detectBoard(canonical)
        if k in whole:
            assert ids is not None and len(ids) >= 8
            # OpenCV 4.11's CharucoDetector is shifted ~0.5 px (its issue 25539)
            assert np.abs(corners.reshape(-1, 2) - frames.corners[k][ids.ravel()]).max() < 1.5
        assert detector.detectBoard(255 - canonical)[1] is None  # as captured: an inverted print
    plain = FrameDrawer([PAPER_BOARD], DrawConfig(size=(64, 48))).draw(np.random.default_rng(7), 2)
    assert not plain.inverted.any()


def test_a_run_begun_before_the_newer_frames_resumes_with_its_own(tmp_path, capsys):
    # A run whose checkpoint predates --inverted-p, --bits and --min-brightness drew plain, unrounded frames down to
    # 0.02 of the light: --resume keeps drawing those; asking for others is refused; a new run gets the newer frames.
    distill.run(tiny_args(tmp_path / "run"))
    saved = torch.load(tmp_path / "run" / "last.pt", weights_only=True)
    for name in ("inverted_p", "bits", "min_brightness", "max_tilt"):
        del saved["training"]["settings"][name]
    torch.save(saved, tmp_path / "run" / "last.pt")
    common = ["--out", str(tmp_path / "run"), "--resume", "--quiet", "--size", "64x48", "--val-size", "64x48",
              "--batch-size", "3", "--warmup", "2", "--val-batches", "1", "--val-every", "3", "--threads", "1",
              "--device", "cpu"]
    resumed = distill.parse_args([*common, "--steps", "7"])
    assert distill.run(resumed)["step"] == 7
    assert (resumed.inverted_p, resumed.bits, resumed.min_brightness) == (0.0, 0, 0.02)
    assert distill.draw_config(resumed, (64, 48)).augmentation.min_brightness == 0.02
    assert resumed.max_tilt == 55.0 and distill.draw_config(resumed, (64, 48)).max_tilt_deg == 55.0
    for option in (["--inverted-p", "0.2"], ["--bits", "8"], ["--min-brightness", "0.005"], ["--max-tilt", "70"]):
        assert distill.main([*common, "--steps", "8", *option]) == 2 and option[0] in capsys.readouterr().err
    new = distill.parse_args(["--out", str(tmp_path / "new")])
    config = distill.draw_config(new, (64, 48))
    assert (config.inverted_p, config.bits, config.augmentation.min_brightness) == (0.2, 8, 0.005)
    steep = distill.parse_args(["--out", str(tmp_path / "steep"), "--max-tilt", "70"])
    assert distill.draw_config(steep, (64, 48)).max_tilt_deg == 70.0
    with pytest.raises(SystemExit) as exit_:
        distill.parse_args(["--out", str(tmp_path / "bad"), "--max-tilt", "95"])
    assert exit_.value.code == 2 and "--max-tilt must be within 0 and 90" in capsys.readouterr().err


def test_frames_are_rounded_to_a_cameras_grey_levels():
    frames = FrameDrawer([PAPER_BOARD], DrawConfig(size=(64, 48), bits=8, inverted_p=0.5)).draw(
        np.random.default_rng(3), 6)
    levels = frames.image.numpy() * 255
    assert np.abs(levels - np.round(levels)).max() < 1e-4 and frames.inverted.any()
    plain = FrameDrawer([PAPER_BOARD], DrawConfig(size=(64, 48))).draw(np.random.default_rng(3), 6).image.numpy() * 255
    assert np.abs(plain - np.round(plain)).max() > 0.1  # unrounded without bits


def test_init_starts_a_run_from_a_students_weights(tmp_path, capsys):
    distill.run(tiny_args(tmp_path / "first"))
    saved = read_checkpoint(tmp_path / "first" / "last.pt", "charuconet")["state_dict"]
    student = ChArUcoNet(distill.named_config("fast", PAPER_BOARD.num_corners))
    distill.warm_start(student, str(tmp_path / "first" / "last.pt"), "fast")
    assert all(torch.equal(student.state_dict()[name], value) for name, value in saved.items())
    result = distill.run(tiny_args(tmp_path / "second", "--init", str(tmp_path / "first" / "last.pt")))
    assert result["step"] == 6  # its own schedule, from step 0
    code = distill.main(["--out", str(tmp_path / "third"), "--arch", "lite", "--init", str(tmp_path / "first" / "last.pt"),
                         "--steps", "2", "--quiet", "--size", "64x48", "--val-size", "64x48", "--batch-size", "2"])
    error = capsys.readouterr().err
    assert code == 2 and "--init" in error and "--arch lite" in error and not (tmp_path / "third" / "last.pt").exists()


def test_resume_refuses_other_settings(tmp_path, capsys):
    distill.run(tiny_args(tmp_path / "run"))
    code = distill.main(["--out", str(tmp_path / "run"), "--resume", "--quiet", "--steps", "8", "--size", "64x48",
                         "--val-size", "64x48", "--batch-size", "3", "--lr", "1e-2"])
    error = capsys.readouterr().err
    assert code == 2 and "--lr" in error and "resume with its settings" in error


def test_the_fast_architecture():
    """Same outputs as lite's at any size that is a multiple of 8 (not of 32), context for the ID head alone,
    recorded in its config, batch norm folded exactly, and under a fifth of lite's multiply-adds for the point
    network (9.3x fewer as built)."""
    from benchmarks.network import count_macs
    from deepcharuco.networks.charuconet import PointHeadOnly

    config = ChArUcoNetConfig.fast(16)
    assert ChArUcoNetConfig.from_dict(config.to_dict()) == config and config.to_dict()["arch"] == "fast"
    assert "arch" not in ChArUcoNetConfig.lite().to_dict()  # the VGG networks' files are as before
    torch.manual_seed(0)
    model = ChArUcoNet(config)
    for module in model.modules():
        if isinstance(module, torch.nn.BatchNorm2d):
            module.running_mean.uniform_(-0.5, 0.5)
            module.running_var.uniform_(0.5, 2.0)
    model.eval()
    image = torch.rand(2, 1, 248, 328)
    with torch.no_grad():
        points, ids = model(image)
        assert points.shape == (2, 65, 31, 41) and ids.shape == (2, 17, 31, 41)
        torch.testing.assert_close(model.points(image), points)
        # The ID head sees a marker's context (the 1/16 and 1/32 branches), the point head only its neighbourhood:
        # the pixels beyond (64, 64) change cell (3, 3)'s ID logits (its pixels are 24-31), never its point logits
        # (the point head's receptive field ends at pixel 51).
        changed = image.clone()
        changed[:, :, 64:, 64:] = 1.0
        other_points, other_ids = model(changed)
        assert torch.equal(other_points[..., 3, 3], points[..., 3, 3])
        assert not torch.equal(other_ids[..., 3, 3], ids[..., 3, 3])
        folded = fold_batch_norm(model)
        assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in folded.modules())
        for ours, theirs in zip(folded(image), (points, ids)):
            torch.testing.assert_close(ours, theirs, atol=1e-4, rtol=1e-4)
    frame = torch.zeros(1, 1, 240, 320)
    lite = count_macs(PointHeadOnly(ChArUcoNet(ChArUcoNetConfig.lite(16))), frame)
    fast = count_macs(PointHeadOnly(ChArUcoNet(config)), frame)
    assert 5 * fast <= lite


def test_a_family_teacher_distils_the_point_head_on_random_boards_of_its_family(tmp_path):
    args = tiny_args(tmp_path / "run", "--teacher", "deepcharuco/weights/families/DICT_4X4.pt", "--family", "DICT_4X4",
                     "--boards", "3")
    distiller = distill.Distiller(args, torch.device("cpu"))
    assert not distiller.with_ids and len(distiller.drawer.boards) == 3
    assert {b.dictionary.rsplit("_", 1)[0] for b in distiller.drawer.boards} == {"DICT_4X4"}
    assert len({(b.squares_x, b.squares_y) for b in distiller.drawer.boards}) > 1
    _, terms = distiller.loss(*distiller.batch(0))
    assert set(terms) == {"kl_points", "ce_points"}  # its ID head was never trained: nothing to learn from it
    distill.run(args)
    _, board, data = load_charuconet(tmp_path / "run" / "last.pt")
    assert data["heads"] == "points" and type(board).__name__ == "PointsOnlyBoard"
    without = tiny_args(tmp_path / "other", "--teacher", "deepcharuco/weights/families/DICT_4X4.pt")
    with pytest.raises(distill.DeepCharucoError, match="--family"):  # its checkpoint does not say which family
        distill.Distiller(without, torch.device("cpu"))


def test_points_only_distils_the_point_head_of_a_teacher_with_ids(tmp_path):
    """--points-only: the paper's teacher's point head alone; the student is a points-only model (read by its markers,
    as a family model is), drawn on the teacher's board."""
    args = tiny_args(tmp_path / "run", "--points-only")
    distiller = distill.Distiller(args, torch.device("cpu"))
    assert not distiller.with_ids and distiller.drawer.boards == [PAPER_BOARD]
    _, terms = distiller.loss(*distiller.batch(0))
    assert set(terms) == {"kl_points", "ce_points"}
    distill.run(args)
    _, board, data = load_charuconet(tmp_path / "run" / "last.pt")
    assert data["heads"] == "points" and type(board).__name__ == "PointsOnlyBoard"
    assert Detector(board=PAPER_BOARD, weights=tmp_path / "run" / "last.pt", refine="none").geometry == "markers"
    # a run made before the option resumes: its settings lack it, and the default stands for it
    assert distill.parser().get_default("points_only") is False


def test_init_from_a_shipped_fast_bundle_starts_where_that_network_is(tmp_path, capsys):
    """The shipped fast students survive only as ONNX bundles (batch normalisation folded in): `--init` takes one into a
    student without batch normalisation whose outputs are the bundle's, and a run from it trains, saves, resumes and
    loads through the runtime loader; a points-only (family) bundle fills the point path and nothing else."""
    import onnxruntime as ort

    from deepcharuco.networks.shipped import FAST_WEIGHTS_DIR

    bundle = str(FAST_WEIGHTS_DIR / "detector.onnx")
    args = tiny_args(tmp_path / "run", "--init", bundle)
    student = ChArUcoNet(distill.student_config(args, PAPER_BOARD.num_corners)).eval()
    assert not student.config.batch_norm
    distill.warm_start(student, bundle, "fast")
    image = np.random.default_rng(2).random((1, 1, 240, 320)).astype(np.float32)
    session = ort.InferenceSession(str(FAST_WEIGHTS_DIR / "detector.onnx" / "charuconet.onnx"),
                                   providers=["CPUExecutionProvider"])
    expected = session.run(None, {session.get_inputs()[0].name: image})
    with torch.no_grad():
        found = student(torch.from_numpy(image))
    for a, b in zip(expected, found):
        assert np.abs(a - b.numpy()).max() < 1e-4
    stopped = distill.run(args, stop_at=4)
    assert stopped["step"] == 4
    assert distill.run(tiny_args(tmp_path / "run", "--init", bundle, "--resume"))["step"] == 6
    model, _, data = load_charuconet(tmp_path / "run" / "last.pt")
    assert not data["config"]["batch_norm"] and not model.config.batch_norm
    family = ChArUcoNet(distill.named_config("fast", PAPER_BOARD.num_corners))
    family_fast = ChArUcoNet(distill.student_config(args, PAPER_BOARD.num_corners))
    before = {k: v.clone() for k, v in family_fast.state_dict().items()}
    distill.warm_start(family_fast, str(FAST_WEIGHTS_DIR / "families" / "DICT_4X4.onnx"), "fast")
    changed = {k for k, v in family_fast.state_dict().items() if not torch.equal(v, before[k])}
    assert changed and all(k.startswith(distill.POINT_PATH) for k in changed)
    points = ort.InferenceSession(str(FAST_WEIGHTS_DIR / "families" / "DICT_4X4.onnx" / "charuconet_points.onnx"),
                                  providers=["CPUExecutionProvider"])
    with torch.no_grad():
        own = family_fast.eval().points(torch.from_numpy(image)).numpy()
    assert np.abs(points.run(None, {points.get_inputs()[0].name: image})[0] - own).max() < 1e-4
    code = distill.main(["--out", str(tmp_path / "lite"), "--arch", "lite", "--init", bundle, "--steps", "2", "--quiet",
                         "--size", "64x48", "--val-size", "64x48", "--batch-size", "2"])
    assert code == 2 and "is not a --arch lite ChArUcoNet" in capsys.readouterr().err
    assert family.config.batch_norm  # a run without a bundle keeps its batch normalisation
