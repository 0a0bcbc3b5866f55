"""The learned marker reader: its patches, its training data, its weights and its place in the marker decoding."""

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from deepcharuco import BoardSpec, Camera, Detector, project_corners
from deepcharuco.boards.synthetic import look_at_pose, render_board_view
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.detection.markers import marker_reader
from deepcharuco.detection.markers.marker_reader import (BIT_READER_WEIGHTS, board_markers, correlate, learned_bits,
                                                         rectify_squares)
from deepcharuco.networks.bit_reader import (
    MARGIN_BITS, SAMPLES_PER_BIT, BitReader, load_bit_reader, patch_side, save_bit_reader,
)
from train.bit_reader import FAMILIES, Degradation, candidate_signs, family_bits, match_scores, render_cell, train

# Close to ideal: big squares, no blur, no darkness, corners almost exact (JPEG and light gradients remain).
CLEAN = Degradation(bit_px=(4.0, 5.0), max_motion_px=1.0, max_defocus_sigma=0.31, max_darkness_k=0.0,
                    max_read_noise=0.5, corner_noise_px=(0.0, 0.05), corner_noise_fraction=0.0)
shipped = pytest.mark.skipif(not BIT_READER_WEIGHTS.is_file(), reason="no shipped bit reader weights")


def _warped_marker(dictionary: str, marker_id: int, turn: int, side_px: float, seed: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """A marker printed in a white square on grey, seen in perspective -> (image uint8, square unit frame -> image
    homography, inner bits (n, n) bool in the square's frame, marker/square ratio)."""
    rng = np.random.default_rng(seed)
    cv_dict = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    cells = cv_dict.markerSize + 2
    per_bit, ratio = 8, 0.75
    marker_px = cells * per_bit
    square_px = round(marker_px / ratio / 2) * 2
    marker = np.rot90(cv2.aruco.generateImageMarker(cv_dict, marker_id, marker_px, borderBits=1), turn)
    square = np.full((square_px, square_px), 255, np.uint8)
    start = (square_px - marker_px) // 2
    square[start:start + marker_px, start:start + marker_px] = marker
    corners = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64) * side_px + 40 + rng.uniform(-0.1, 0.1, (4, 2)) * side_px
    to_image = cv2.getPerspectiveTransform(np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32), corners.astype(np.float32))
    to_texture = np.array([[square_px, 0, -0.5], [0, square_px, -0.5], [0, 0, 1.0]])
    image = cv2.warpPerspective(square, to_image @ np.linalg.inv(to_texture), (int(side_px) + 80, int(side_px) + 80),
                                flags=cv2.INTER_AREA, borderValue=120)
    bits = np.rot90(cv_dict.getBitsFromByteList(cv_dict.bytesList[marker_id:marker_id + 1], cv_dict.markerSize)
                    .astype(bool), turn)
    return image, to_image.astype(np.float64), bits, ratio


@shipped
@pytest.mark.parametrize("dictionary", [name for names in FAMILIES.values() for name in names])
def test_clean_warped_markers_of_every_family_read_as_opencv_draws_them(dictionary):
    wrong = 0
    for index, marker_id in enumerate((0, 7, 33, 49)):
        image, homography, bits, ratio = _warped_marker(dictionary, marker_id, turn=index % 4, side_px=40.0, seed=index)
        logits = learned_bits(image, homography[None], bits.shape[0], ratio)[0]
        wrong += int(np.sum((logits > 0) != bits))
    assert wrong == 0


def test_training_labels_are_the_bits_seen_in_the_rectified_patch():
    rng = np.random.default_rng(4)
    right = total = 0
    for index in range(40):
        size = (4, 5, 6, 7)[index % 4]
        patch, bits = render_cell(rng, size, CLEAN)
        cells = size + 2 + 2 * MARGIN_BITS
        means = patch.reshape(cells, SAMPLES_PER_BIT, cells, SAMPLES_PER_BIT).mean(axis=(1, 3))
        inner = means[MARGIN_BITS + 1:MARGIN_BITS + 1 + size, MARGIN_BITS + 1:MARGIN_BITS + 1 + size]
        threshold = 0.5 * (np.percentile(means, 5) + np.percentile(means, 95))
        right += int(np.sum((inner > threshold) == bits))
        total += bits.size
    assert right / total > 0.97  # labels a quarter turn or a square off would read as chance (0.5)


def test_family_bits_are_opencv_markers_with_their_border():
    markers = family_bits("DICT_4X4_1000")
    assert markers.shape == (1000, 6, 6)
    assert not markers[:, 0].any() and not markers[:, :, -1].any()
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_1000)
    assert np.array_equal(markers[5, 1:-1, 1:-1], dictionary.getBitsFromByteList(dictionary.bytesList[5:6], 4).astype(bool))


def test_a_short_training_run_lowers_the_loss_and_resumes(tmp_path, torch_threads):
    torch_threads(1)
    first = train(tmp_path / "run", steps=10, batch=24, seed=3, validate_every=10, quiet=True)
    # Resuming the same run to more steps is refused (the schedule depends on the total), another --out trains on.
    with pytest.raises(SystemExit, match="resume with the same"):
        train(tmp_path / "run", steps=40, batch=24, seed=3, validate_every=10, quiet=True)
    longer = train(tmp_path / "longer", steps=40, batch=24, seed=3, validate_every=10, quiet=True)
    assert longer["val_loss"] < first["val_loss"] and longer["val_loss"] < 0.69  # below chance, ln 2
    log = (tmp_path / "longer" / "log.csv").read_text().splitlines()
    assert log[0].startswith("step,loss") and len(log) == 5
    again = train(tmp_path / "longer", steps=40, batch=24, seed=3, validate_every=10, quiet=True)  # already done
    assert again == pytest.approx(longer)


def test_match_candidates_hold_the_true_marker_first_and_the_score_ranks_it_first():
    rng = np.random.default_rng(2)
    bits = family_bits("DICT_5X5_1000")[[3, 40], 1:-1, 1:-1].astype(np.float32)
    signs = candidate_signs(rng, 5, bits, negatives=7)
    assert signs.shape == (2, 32, 25)
    assert np.array_equal(signs[:, 0], bits.reshape(2, -1) * 2 - 1)
    assert np.array_equal(signs[:, 1].reshape(2, 5, 5), np.rot90(bits * 2 - 1, 1, axes=(1, 2)))  # turn 1 next
    confident = torch.from_numpy((bits * 2 - 1) * 8.0)  # logits of a sharp read
    scores = match_scores(confident, torch.from_numpy(signs))
    assert scores.argmax(dim=1).tolist() == [0, 0] and torch.all(scores < 1.0 + 1e-6)
    with pytest.raises(ValueError, match="objective must be one of"):
        train(Path("unused"), steps=1, objective="guess")


def test_weights_round_trip_and_clear_errors(tmp_path):
    model = BitReader()
    path = save_bit_reader(model, tmp_path / "reader.pt")
    loaded = load_bit_reader(path)
    patches = torch.randn(3, 1, patch_side(5), patch_side(5))
    assert torch.allclose(loaded(patches, 5), model(patches, 5), atol=2e-2)  # stored as float16
    with pytest.raises(DeepCharucoError, match="train them with python -m train.bit_reader"):
        load_bit_reader(tmp_path / "missing.pt")
    torch.save({"format": "something else"}, tmp_path / "other.pt")
    with pytest.raises(DeepCharucoError, match="not a bit reader"):
        load_bit_reader(tmp_path / "other.pt")
    with pytest.raises(ValueError, match="take 33x33 patches"):
        model(torch.zeros(1, 1, 30, 30), 5)


def test_rectified_patch_follows_the_homography():
    image = np.tile(np.arange(100, dtype=np.uint8), (100, 1))  # grey level = x
    homography = np.array([[40.0, 0, 30], [0, 40.0, 30], [0, 0, 1]])  # unit square -> [30, 70]^2
    patch = rectify_squares(image, homography[None], 4, 0.6)[0]
    assert patch.shape == (patch_side(4), patch_side(4))
    assert np.all(np.diff(patch, axis=1) > 0) and np.allclose(np.diff(patch, axis=0), 0)
    assert patch[0, 0] < 50 < patch[0, -1] and abs(patch.mean() - 49.5) < 1.0  # centred on the square


def test_learned_scores_are_the_log_likelihood_of_each_marker_in_each_turn():
    board = BoardSpec(squares_x=5, squares_y=4, dictionary="DICT_4X4_50")
    markers = board_markers(board)
    perfect = np.where(markers.bits[3, 2], 1.0, -1.0)[None]  # marker 3 read a half turn round, fully confident
    scores = correlate(perfect.astype(np.float32), markers, reader="learned")
    assert scores.shape == (1, len(markers.ids), 4)
    assert np.unravel_index(scores[0].argmax(), scores[0].shape) == (3, 2) and scores[0, 3, 2] == pytest.approx(1.0)
    assert np.all(scores[0][np.arange(len(markers.ids)) != 3] < 1.0)
    with pytest.raises(ValueError, match="reader must be one of"):
        correlate(perfect, markers, reader="magic")


@shipped
def test_the_learned_reader_decodes_an_unseen_board_blurred(monkeypatch):
    calls = []
    learned_correlate = marker_reader.correlate

    def counted(*args, **kwargs):
        calls.append(kwargs.get("reader", args[2] if len(args) > 2 else None))
        return learned_correlate(*args, **kwargs)

    monkeypatch.setattr(marker_reader, "correlate", counted)
    board = BoardSpec(squares_x=7, squares_y=5, square_length=0.04, marker_length=0.03, dictionary="DICT_6X6_250")
    camera = Camera.from_fov(320, 240, hfov_deg=60.0)
    rvec, tvec = look_at_pose(board, camera.K[0, 0] * max(board.size_m) / (0.8 * 240), tilt_x_deg=25, tilt_y_deg=-15,
                              roll_deg=10)
    image = render_board_view(board, camera.K, rvec, tvec, (320, 240))
    truth = project_corners(board, rvec, tvec, camera.K)
    detector = Detector(board=board, reader="learned")
    with pytest.raises(ValueError, match="reader must be one of"):
        Detector(board=board, reader="magic")
    for degraded in (image, cv2.filter2D(image, -1, np.ones((1, 10)) / 10)):
        found = detector.detect(degraded)
        assert len(found.ids) >= 0.8 * board.num_corners
        assert np.linalg.norm(found.corners - truth[found.ids], axis=1).max() < 3.0
    assert calls and set(calls) == {"learned"}  # the Detector's reader reached every read
