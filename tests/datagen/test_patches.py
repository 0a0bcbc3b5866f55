"""RefineNet patches: offsets, the one-corner rule, the sub-pixel convention, the shard format."""

import cv2
import numpy as np
import pytest

from datagen.patches import (CENTRE_HIGH, CENTRE_LOW, SHADOW_LEVELS, cast_shadow_edges, cut_patches, in_centre,
                             synthetic_patch, synthetic_patches)
from datagen.shards import ShardError, read_patch_shard, write_patch_shard


def test_cut_patches_put_the_corner_in_the_centre(default_views):
    image, _, _, corners = default_views[1]
    visible = np.ones(len(corners), bool)
    rng = np.random.default_rng(0)
    patches, offsets, ids = cut_patches(image, corners.astype(np.float32), visible, rng, per_corner=4)
    assert len(patches) > 10 and patches.shape[1:] == (24, 24)
    assert np.all(in_centre(offsets))
    for patch, offset, corner_id in zip(patches, offsets, ids):
        x0, y0 = np.round(corners[corner_id] - offset).astype(int)
        np.testing.assert_allclose(np.array([x0, y0]) + offset, corners[corner_id], atol=1e-4)
        np.testing.assert_array_equal(patch, image[y0:y0 + 24, x0:x0 + 24])
    # Every central pixel gets used: the corner's pixel within the 8x8 is uniform.
    assert len(np.unique(np.floor(offsets[:, 0] + 0.5))) == 8


def test_cut_patches_skip_occluded_and_crowded_corners():
    image = np.full((60, 60), 128, np.uint8)
    corners = np.array([[30.2, 30.4], [33.0, 31.0], [np.nan, np.nan]], np.float32)  # 0 and 1 are 3 px apart
    visible = np.array([True, False, False])  # corner 1 is occluded: no patch of its own, but it is real
    patches, offsets, ids = cut_patches(image, corners, visible, np.random.default_rng(0), per_corner=60)
    assert set(ids) == {0} and 0 < len(patches) < 60  # some placements had both corners in the centre
    for offset in offsets:
        assert not in_centre(corners[1] - corners[0] + offset)


def test_synthetic_patch_corner_is_where_the_label_says():
    """cornerSubPix on an exact (undegraded) junction lands on the labelled offset."""
    rng = np.random.default_rng(1)
    errors = []
    for _ in range(30):
        patch, offset = synthetic_patch(rng, degrade=False)
        assert CENTRE_LOW <= offset.min() and offset.max() < CENTRE_HIGH
        start = (offset + rng.uniform(-1.0, 1.0, 2)).reshape(1, 1, 2).astype(np.float32)
        found = cv2.cornerSubPix(patch, start, (4, 4), (-1, -1),
                                 (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4))
        errors.append(np.linalg.norm(found.ravel() - offset))
    assert np.median(errors) < 0.05, np.median(errors)
    # A label off by half a pixel would be caught:
    assert np.median(errors) < 0.5 / 4


def test_synthetic_patches_are_deterministic_and_varied():
    a, oa = synthetic_patches(np.random.default_rng(5), 200)
    b, ob = synthetic_patches(np.random.default_rng(5), 200)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(oa, ob)
    means = a.reshape(200, -1).mean(axis=1)
    assert means.min() < 20 and means.max() > 120  # near-black to bright


def test_shadow_edges_darken_one_side_of_a_line_beside_the_corner():
    rng = np.random.default_rng(3)
    offsets = rng.uniform(CENTRE_LOW, CENTRE_HIGH, (200, 2))
    grey = np.full((200, 24, 24), 200, np.uint8)
    out, shadowed = cast_shadow_edges(grey, offsets, np.random.default_rng(4), 0.5)
    again, _ = cast_shadow_edges(grey, offsets, np.random.default_rng(4), 0.5)
    np.testing.assert_array_equal(out, again)
    assert 70 < shadowed.sum() < 130
    np.testing.assert_array_equal(out[~shadowed], grey[~shadowed])
    np.testing.assert_array_equal(grey, 200)  # the input is left as it was
    yy, xx = np.mgrid[0:24, 0:24]
    for patch, offset in zip(out[shadowed] / 200.0, offsets[shadowed]):
        assert patch.max() <= 1.0 and patch.min() <= SHADOW_LEVELS[1] + 0.2  # a shadow, darker on one side
        # The edge passes beside the corner: the pixels near it lie on both sides of the half-way brightness.
        near = np.hypot(xx - offset[0], yy - offset[1]) <= 4.0
        middle = (patch.min() + patch.max()) / 2
        assert (patch[near] < middle).any() and (patch[near] > middle).any()
    none, _ = cast_shadow_edges(grey, offsets, np.random.default_rng(4), 0.0)
    np.testing.assert_array_equal(none, grey)


def test_patch_shard_round_trip_and_errors(tmp_path):
    patches, offsets = synthetic_patches(np.random.default_rng(0), 10)
    write_patch_shard(tmp_path, 3, patches, offsets, {"source": np.array(["synthetic"] * 10)}, {"test": True})
    read, read_offsets, meta = read_patch_shard(tmp_path / "shard-00003.h5")
    np.testing.assert_array_equal(read, patches)
    np.testing.assert_array_equal(read_offsets, offsets)
    assert [s.decode() for s in meta["source"]] == ["synthetic"] * 10
    with pytest.raises(ShardError, match="source"):
        write_patch_shard(tmp_path, 4, patches, offsets, {}, {})
    with pytest.raises(ShardError, match="uint8"):
        write_patch_shard(tmp_path, 4, patches.astype(np.float32), offsets, {"source": np.array(["x"] * 10)}, {})
    with pytest.raises(ShardError, match="does not exist"):
        read_patch_shard(tmp_path / "nope.h5")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["shard-00003.h5"]  # failed writes leave nothing
