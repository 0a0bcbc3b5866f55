"""Augmentation keeps labels on the image; the dataset gives consistent targets; shards split by file."""

import cv2
import numpy as np
import pytest

from datagen.shards import FrameLabels, ShardError, write_shard
from deepcharuco import BoardSpec
from deepcharuco.networks.cells import decode_cells
from train.augment import AugmentConfig, augment, crop_labels, crop_origin, warp_labels
from train.dataset import FrameDataset, split_shards

GEOMETRY_ONLY = AugmentConfig(probabilities=())


def test_homography_moves_labels_with_the_image(default_views):
    """Labels pushed through the sampled homography sit on the warped image's corners (cornerSubPix)."""
    errors = []
    for k, (image, _, _, corners) in enumerate(default_views):
        rng = np.random.default_rng(k)
        warped, moved, visible = augment(image / 255.0, corners.astype(np.float32), np.ones(16, bool), True, rng, GEOMETRY_ONLY)
        gray = np.round(warped * 255).astype(np.uint8)
        inner = visible & np.all((moved > 6) & (moved < [314, 234]), axis=1)
        assert inner.sum() >= 6
        start = (moved[inner] + rng.uniform(-0.7, 0.7, (inner.sum(), 2))).reshape(-1, 1, 2).astype(np.float32)
        found = cv2.cornerSubPix(gray, start, (3, 3), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-3))
        errors += list(np.linalg.norm(found.reshape(-1, 2) - moved[inner], axis=1))
        assert not np.array_equal(moved, corners.astype(np.float32))
    assert np.median(errors) < 0.15, np.median(errors)


def test_crop_keeps_labels_on_the_image(default_views):
    """A crop's labels sit on the cropped image's corners; those cut off become invisible; crops mostly hold corners."""
    config = AugmentConfig(probabilities=(), homography_p=0.0, crop=(160, 120))
    held = 0
    for k, (image, _, _, corners) in enumerate(default_views * 4):
        rng = np.random.default_rng(k)
        cropped, moved, visible = augment(image / 255.0, corners.astype(np.float32), np.ones(16, bool), True, rng, config)
        assert cropped.shape == (120, 160)
        inside = np.all((moved >= -0.5) & (moved < [159.5, 119.5]), axis=1)
        assert np.array_equal(visible, inside)
        held += visible.any()
        inner = visible & np.all((moved > 6) & (moved < [154, 114]), axis=1)
        if inner.any():
            gray = np.round(cropped * 255).astype(np.uint8)
            start = (moved[inner] + 0.6).reshape(-1, 1, 2).astype(np.float32)
            found = cv2.cornerSubPix(gray, start, (3, 3), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-3))
            assert np.median(np.linalg.norm(found.reshape(-1, 2) - moved[inner], axis=1)) < 0.2
    assert held >= 0.7 * len(default_views) * 4


def test_crop_origin_holds_the_chosen_corner_and_stays_in_the_image():
    rng = np.random.default_rng(0)
    corners = np.array([[5.0, 5.0], [314.0, 234.0]], np.float32)
    for _ in range(200):
        x0, y0 = crop_origin(rng, (320, 240), (160, 120), corners, np.array([True, True]), on_corner_p=1.0)
        assert 0 <= x0 <= 160 and 0 <= y0 <= 120
        _, visible = crop_labels(corners, np.array([True, True]), (x0, y0), (160, 120))
        assert visible.sum() == 1


def test_corners_leaving_the_frame_become_invisible():
    corners = np.array([[10.0, 10.0], [300.0, 200.0]], np.float32)
    shift = np.array([[1, 0, 50.0], [0, 1, 0], [0, 0, 1]])
    moved, visible = warp_labels(corners, np.array([True, True]), shift, 320, 240)
    np.testing.assert_allclose(moved, [[60, 10], [350, 200]])
    assert visible.tolist() == [True, False]


def test_photometric_effects_keep_range_and_negatives_stay_put():
    rng = np.random.default_rng(0)
    image = np.full((48, 64), 0.5, np.float32)
    corners = np.full((16, 2), np.nan, np.float32)
    means = []
    for _ in range(40):
        out, moved, visible = augment(image, corners, np.zeros(16, bool), False, rng)
        assert out.dtype == np.float32 and out.min() >= 0 and out.max() <= 1
        assert np.all(np.isnan(moved)) and not visible.any()
        means.append(out.mean())
    assert min(means) < 0.1 and max(means) > 0.4  # brightness rescale reaches near-black


def test_shadow_edge_crosses_a_visible_corner_and_is_off_by_default(default_views):
    """--shadow-edges darkens one side of a line near a visible corner, moves no label, and at 0 draws nothing."""
    image, _, _, corners = default_views[0]
    image, corners, visible = image / 255.0, corners.astype(np.float32), np.ones(16, bool)
    plain = AugmentConfig(probabilities=(), homography_p=0.0)
    shadowed = AugmentConfig(probabilities=(), homography_p=0.0, shadow_edge_p=1.0)
    out, moved, _ = augment(image, corners, visible, True, np.random.default_rng(3), plain)
    assert np.array_equal(out, np.clip(image.astype(np.float32), 0, 1))  # p = 0: no draw, no change
    darker_near_a_corner = 0
    for seed in range(20):
        out, moved, shown = augment(image, corners, visible, True, np.random.default_rng(seed), shadowed)
        assert np.array_equal(moved, corners) and np.array_equal(shown, visible)
        ratio = (out + 1e-3) / (image.astype(np.float32) + 1e-3)
        assert ratio.max() <= 1.0 + 1e-5 and ratio.min() < 0.65  # only darkened, and some of it well darkened
        dark = ratio < 0.95
        assert 0.0 < dark.mean() < 1.0  # one side of a line, not the whole image
        near = [dark[max(0, int(y) - 3):int(y) + 4, max(0, int(x) - 3):int(x) + 4] for x, y in corners]
        darker_near_a_corner += any(0.0 < patch.mean() < 1.0 for patch in near)  # the edge passes by a corner
    assert darker_near_a_corner == 20
    same = [augment(image, corners, visible, True, np.random.default_rng(7), shadowed)[0] for _ in range(2)]
    assert np.array_equal(*same)
    nothing = np.zeros(16, bool)  # no visible corner: nothing to lay the edge through
    out, _, _ = augment(image, corners, nothing, True, np.random.default_rng(0), shadowed)
    assert np.array_equal(out, np.clip(image.astype(np.float32), 0, 1))


def _shard(tmp_path, index, board, n=3, has_board=True):
    rng = np.random.default_rng(index)
    frames = []
    for i in range(n):
        corners = rng.uniform(10, [300, 220], (16, 2)).astype(np.float32) if has_board else np.full((16, 2), np.nan, np.float32)
        frames.append(FrameLabels(image=rng.integers(0, 255, (240, 320), dtype=np.uint8), corners=corners,
                                  visible=np.full(16, has_board), K=np.eye(3), rvec=np.zeros(3), tvec=np.zeros(3),
                                  meta={"has_board": has_board, "frame": index * n + i}))
    write_shard(tmp_path, index, frames, board, {"test": True})


def test_dataset_targets_and_split(tmp_path):
    board = BoardSpec()
    for index in range(5):
        _shard(tmp_path, index, board, has_board=index != 2)
    train, validation = split_shards(tmp_path, val_fraction=0.2)
    assert [p.name for p in validation] == ["shard-00004.h5"] and len(train) == 4
    dataset = FrameDataset(train, board, augmentation=None)
    assert len(dataset) == 12
    sample = dataset[0]
    assert sample["image"].shape == (1, 240, 320) and sample["points"].shape == (30, 40)
    point_logits = np.full((65, 30, 40), -20.0, np.float32)
    id_logits = np.full((17, 30, 40), -20.0, np.float32)
    r, c = np.indices((30, 40))
    point_logits[sample["points"].numpy(), r, c] = 20
    id_logits[sample["ids"].numpy(), r, c] = 20
    import torch

    ids, pixels, _ = decode_cells(torch.from_numpy(point_logits), torch.from_numpy(id_logits), 0.5)
    assert len(ids) >= 14
    assert np.all(np.abs(pixels - sample["corners"].numpy()[ids]) <= 0.5 + 1e-5)
    negative = dataset[7]  # shard 2 is all negatives
    assert not negative["has_board"] and (negative["points"] == 64).all() and (negative["ids"] == 16).all()
    augmented = FrameDataset(train, board, seed=3)
    a, b = augmented[5], augmented[5]
    assert torch.equal(a["image"], b["image"])
    augmented.set_epoch(1)
    assert not torch.equal(augmented[5]["image"], a["image"])
    with pytest.raises(ShardError, match="rendered for"):
        FrameDataset(train, BoardSpec(squares_x=6, squares_y=6, dictionary="DICT_5X5_50"))
