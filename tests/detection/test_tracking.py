"""BoardTracker: a video's frames searched around the last board, whole frames when that fails."""

import numpy as np
import pytest

from conftest import Numbered, Racing, TrackedOnly, make_view, moving_video, video
from deepcharuco import BoardSpec, Detector, OpenCVDetector
from deepcharuco.core.detection import Detection
from deepcharuco.core.stage_times import StageTimes
from deepcharuco.detection.deep_detector import BACKUP_MIN_CELLS
from deepcharuco.detection.levels import Seen
from deepcharuco.detection.parallel import detect_all
from deepcharuco.detection.search_regions import is_dim
from deepcharuco.detection.tracking import BoardTracker, StreamFrames, predicted, search_region
from deepcharuco.geometry.camera import Camera


class Recording:
    """A detector that remembers the image sizes it was given."""

    def __init__(self, detector):
        self.detector, self.sizes = detector, []

    def detect(self, image):
        self.sizes.append(image.shape[:2])
        return self.detector.detect(image)


@pytest.fixture(scope="module")
def frames():
    """A 640x480 clip: the board drifts right over 6 frames, then leaves (2 empty frames), then returns."""
    camera = Camera.from_fov(640, 480, hfov_deg=60.0)
    board = BoardSpec()
    views = [make_view(board, camera, distance=0.45, tilt_x_deg=15, offset=(-0.06 + 0.02 * i, 0.0)) for i in range(6)]
    empty = np.full((480, 640), 120, np.uint8)
    back = make_view(board, camera, distance=0.45, offset=(0.05, 0.03))
    return [v[0] for v in views] + [empty, empty] + [back[0]], [v[3] for v in views] + [None, None] + [back[3]]


def test_crops_follow_the_board_and_find_what_the_full_frame_finds(frames):
    images, truths = frames
    recording = Recording(OpenCVDetector(BoardSpec(), refine="subpix"))
    tracker = BoardTracker(recording, refresh_every=100)
    searches = []
    for image, truth in zip(images, truths):
        found = tracker.detect(image)
        searches.append(tracker.last_search)
        if truth is None:
            assert len(found) == 0
        else:
            assert len(found) == 16
            np.testing.assert_allclose(found.corners, truth[found.ids], atol=0.3)
    assert searches[:6] == ["full"] + ["crop"] * 5
    assert searches[6:] == ["full", "full", "full"]  # the crop finds nothing -> whole frame; no board -> whole frame
    crop_pixels = [h * w for h, w in recording.sizes[1:6]]
    assert max(crop_pixels) < 0.5 * 640 * 480


def test_refresh_every_forces_whole_frames(frames):
    images, _ = frames
    tracker = BoardTracker(OpenCVDetector(BoardSpec()), refresh_every=3)
    searches = []
    for image in images[:6]:
        tracker.detect(image)
        searches.append(tracker.last_search)
    assert searches == ["full", "crop", "crop", "full", "crop", "crop"]  # a whole frame every 3rd
    with pytest.raises(ValueError, match="refresh_every must be >= 1"):
        BoardTracker(OpenCVDetector(BoardSpec()), refresh_every=0)


def test_search_region_stays_inside_the_image_and_has_a_minimum_size():
    corners = np.array([[5.0, 5.0], [10.0, 5.0], [5.0, 10.0], [10.0, 10.0]], np.float32)
    x0, y0, x1, y1 = search_region(corners, (640, 480))
    assert (x0, y0) == (0, 0) and x1 - x0 >= 64 and y1 - y0 >= 64
    corners = np.array([[600.0, 440.0], [630.0, 440.0], [600.0, 470.0], [630.0, 470.0]], np.float32)
    x0, y0, x1, y1 = search_region(corners, (640, 480))
    assert x1 == 640 and y1 == 480 and x0 < 600 - 30 and y0 < 440 - 30  # two corner spacings of margin


def test_a_crop_detection_with_too_few_corners_searches_the_whole_frame():
    class Scripted:
        def __init__(self):
            self.calls = []

        def detect(self, image):
            self.calls.append(image.shape)
            if image.shape == (480, 640):
                return Detection(np.arange(4), np.array([[300, 200], [330, 200], [300, 230], [330, 230]]), np.ones(4))
            return Detection(np.arange(2), np.zeros((2, 2)), np.ones(2))  # a crop that finds too little

    scripted = Scripted()
    tracker = BoardTracker(scripted)
    tracker.detect(np.zeros((480, 640), np.uint8))
    found = tracker.detect(np.zeros((480, 640), np.uint8))
    assert len(found) == 4 and tracker.last_search == "full"
    assert scripted.calls[0] == (480, 640) and scripted.calls[1] != (480, 640) and scripted.calls[2] == (480, 640)


def test_a_coarse_to_fine_detector_searches_the_crop_at_the_whole_frames_scale():
    """A crop of a 1280x720 frame is searched first at 320/1280 of its size, as the whole frame would be,
    not reduced to 320 px (a nearly square crop would then be seen in more pixels than the frame)."""
    class CoarseToFine:
        working_size = 320

        def __init__(self):
            self.calls = []

        def detect(self, image, working_size=None):
            self.calls.append((image.shape, working_size))
            corners = np.array([[500, 200], [540, 200], [500, 240], [540, 240], [580, 240]], np.float32)
            if image.shape != (720, 1280):
                corners -= np.array(search_region(corners, (1280, 720))[:2], np.float32)
            return Detection(np.arange(5), corners, np.ones(5))

    detector = CoarseToFine()
    tracker = BoardTracker(detector)
    tracker.detect(np.zeros((720, 1280), np.uint8))
    tracker.detect(np.zeros((720, 1280), np.uint8))
    (_, whole), (crop_shape, crop_size) = detector.calls
    assert whole is None and tracker.last_search == "crop"
    assert crop_size == round(max(crop_shape) * 320 / 1280)


@pytest.mark.parametrize("spacing, doublings", [(40.0, 0), (20.0, 1), (6.0, None)])
def test_a_tracked_crop_starts_at_the_level_before_its_squares_are_wide_enough(spacing, doublings):
    """Squares 40 px wide in a 1280x720 frame are 10 px at 320/1280 and 20 at the next level: the crop starts at the
    frame's scale. At 20 px wide they are 5 px there, too narrow for that level and the next (10 px < 16): it starts
    at half scale, where they are 10 px. At 6 px only full resolution comes near."""
    class CoarseToFine:
        working_size, min_square_px = 320, 16

        def __init__(self):
            self.calls = []

        def detect(self, image, working_size=None):
            self.calls.append((image.shape, working_size))
            corners = np.array([[600, 300], [600 + spacing, 300], [600, 300 + spacing], [600 + spacing, 300 + spacing]],
                               np.float32)
            if image.shape != (720, 1280):
                corners -= np.array(search_region(corners, (1280, 720))[:2], np.float32)
            return Detection(np.arange(4), corners, np.ones(4))

    detector = CoarseToFine()
    tracker = BoardTracker(detector)
    tracker.detect(np.zeros((720, 1280), np.uint8))
    tracker.detect(np.zeros((720, 1280), np.uint8))
    (crop_shape, crop_size) = detector.calls[1]
    longest = max(crop_shape)
    expected = longest if doublings is None else round(longest * 320 / 1280) * 2 ** doublings  # None: full size
    assert tracker.last_search == "crop" and crop_size == expected


def test_a_tracked_crop_that_skips_coarse_levels_finds_the_same_corners():
    """The real detector on a far board (squares ~28 px in 1280x720: 7 px at the 320-px level, which the crop now
    skips): the same corners as the crop searched from the frame's own scale."""
    camera = Camera.from_fov(1280, 720, hfov_deg=60.0)
    board = BoardSpec()
    detector = Detector(board=board)
    clip = [make_view(board, camera, distance=1.6, offset=(0.01 * i, 0.0))[0] for i in range(3)]
    skipping, every_level = BoardTracker(detector), BoardTracker(detector)
    found = [skipping.detect(frame) for frame in clip]
    detector.min_square_px = None  # this instance: every level of the crop, from the frame's scale
    reference = [every_level.detect(frame) for frame in clip]
    assert skipping.last_search == every_level.last_search == "crop"
    for a, b in zip(found, reference):
        assert len(a) == 16 and np.array_equal(a.ids, b.ids)
        np.testing.assert_allclose(a.corners, b.corners, atol=1e-3)


def test_a_detector_that_takes_expected_is_told_where_the_board_was_in_the_crop():
    class Expecting:
        def __init__(self):
            self.expected = []

        def detect(self, image, expected=None):
            self.expected.append(expected)
            corners = np.array([[500, 200], [540, 200], [500, 240], [540, 240], [580, 240]], np.float32)
            if image.shape != (720, 1280):
                corners -= np.array(search_region(corners, (1280, 720))[:2], np.float32)
            return Detection(np.arange(5), corners, np.ones(5))

    detector = Expecting()
    tracker = BoardTracker(detector)
    first = tracker.detect(np.zeros((720, 1280), np.uint8))
    region = search_region(first.corners, (1280, 720))
    tracker.detect(np.zeros((720, 1280), np.uint8))
    assert detector.expected[0] is None and tracker.last_search == "crop"
    np.testing.assert_array_equal(detector.expected[1].ids, first.ids)
    np.testing.assert_allclose(detector.expected[1].corners, first.corners - np.array(region[:2], np.float32))


class Levelled:
    """A coarse-to-fine detector stand-in: finds the board (4 corners) only where ``board_at`` says, at the coarse
    level only where ``coarse_sees`` says; records each call's levels."""

    working_size = 320

    def __init__(self, board_at, coarse_sees):
        self.board_at, self.coarse_sees, self.calls, self.frame = board_at, coarse_sees, [], 0

    def detect(self, image, working_size=None, levels=None):
        self.calls.append("crop" if image.shape != (720, 1280) else "coarse" if levels == 1 else "full")
        corners = np.array([[500, 200], [540, 200], [500, 240], [540, 240]], np.float32)
        if not self.board_at(self.frame) or (levels == 1 and not self.coarse_sees):
            return Detection(np.zeros(0, int), np.zeros((0, 2), np.float32), np.zeros(0))
        if image.shape != (720, 1280):  # a crop: its own pixels
            corners -= np.array(search_region(corners, (1280, 720))[:2], np.float32)
        return Detection(np.arange(4), corners, np.ones(4))


def run(tracker, detector, frames):
    detector.tracker = tracker
    searches = []
    for n in range(frames):
        detector.frame = n
        tracker.detect(np.zeros((720, 1280), np.uint8))
        searches.append(tracker.last_search)
    return searches


def test_search_every_searches_every_level_only_every_nth_frame_while_no_board_is_tracked():
    absent = Levelled(lambda n: False, coarse_sees=True)
    assert run(BoardTracker(absent, search_every=3), absent, 7) == ["full", "coarse", "coarse"] * 2 + ["full"]
    assert absent.calls == ["full", "coarse", "coarse"] * 2 + ["full"]
    # A board the coarse level reads is tracked from the frame it appears in; one it cannot read waits for the
    # next search of every level.
    large = Levelled(lambda n: n >= 1, coarse_sees=True)
    assert run(BoardTracker(large, search_every=3), large, 3) == ["full", "coarse", "crop"]
    small = Levelled(lambda n: n >= 1, coarse_sees=False)
    tracker = BoardTracker(small, search_every=3)
    assert run(tracker, small, 5) == ["full", "coarse", "coarse", "full", "crop"]
    # Every level, every frame: the default, and any detector without levels (OpenCV).
    everything = Levelled(lambda n: False, coarse_sees=True)
    assert run(BoardTracker(everything), everything, 3) == ["full"] * 3
    assert BoardTracker(OpenCVDetector(BoardSpec()), search_every=3).search_every == 1
    with pytest.raises(ValueError, match="search_every must be >= 1"):
        BoardTracker(everything, search_every=0)


def test_a_board_lost_by_the_crop_is_searched_for_at_every_level_at_once():
    present = [True, True, False, False, False, False]
    detector = Levelled(lambda n: present[n], coarse_sees=True)
    tracker = BoardTracker(detector, search_every=3)
    searches = run(tracker, detector, 6)
    # frame 2: the crop finds nothing -> every level at once (the board may have shrunk); then coarse, coarse, full
    assert searches == ["full", "crop", "full", "coarse", "coarse", "full"]


def test_the_coarse_level_alone_finds_a_large_board_and_not_a_small_one():
    camera = Camera.from_fov(1280, 720, hfov_deg=60.0)
    board = BoardSpec()
    detector = Detector(board=board)
    near, _, _, truth = make_view(board, camera, distance=0.4)  # squares ~110 px: 28 px at the 320-px level
    coarse, every = detector.detect(near, levels=1), detector.detect(near)
    assert len(coarse) == 16 and np.array_equal(coarse.ids, every.ids)
    np.testing.assert_allclose(coarse.corners, every.corners, atol=1e-3)
    assert np.abs(coarse.corners - truth[coarse.ids]).max() < 0.1
    far = make_view(board, camera, distance=1.6)[0]  # squares ~28 px: 7 px at 320, read at 640
    assert len(detector.detect(far, levels=1)) == 0 and len(detector.detect(far)) == 16


def test_a_hybrid_quick_look_runs_the_networks_alone_and_a_full_search_runs_opencv_first():
    """While the board is away a hybrid detector's quick look (``levels``) is its coarse network level: OpenCV's
    whole-frame search costs more than that level where there is no board; the full search still asks OpenCV first."""
    camera = Camera.from_fov(1280, 720, hfov_deg=60.0)
    board = BoardSpec()
    detector = Detector(board=board, mode="hybrid")
    near, _, _, truth = make_view(board, camera, distance=0.4)
    with StageTimes() as quick:
        coarse = detector.detect(near, levels=1)
    assert "opencv" not in quick.counts and quick.counts["network 0"] == 1
    assert len(coarse) == 16 and np.abs(coarse.corners - truth[coarse.ids]).max() < 0.1
    with StageTimes() as full:
        every = detector.detect(near)
    assert full.counts["opencv"] == 1 and not any(name.startswith("network") for name in full.counts)
    assert np.array_equal(np.sort(every.ids), np.sort(coarse.ids))


def test_the_fast_networks_hand_a_tracked_board_they_lose_to_the_lite_ones(monkeypatch):
    """``network="fast"``: where the fast networks find fewer corners of an expected board (a tracked crop) than a
    tracker keeps, the lite networks search the same image (`Detector.backup`, deep alone); not a whole frame (nothing
    expected), and never behind the lite networks themselves."""
    camera = Camera.from_fov(1280, 720, hfov_deg=60.0)
    board = BoardSpec()
    image, _, _, truth = make_view(board, camera, distance=0.4)
    fast, lite = Detector(board=board, network="fast"), Detector(board=board)
    assert lite.backup is None and Detector(board=board, network="fast", mode="hybrid").backup.mode == "deep"
    tracker = BoardTracker(fast)
    assert fast._backup is not None  # built with the tracker: a live camera does not wait for it when the board is lost
    before = tracker.detect(image)
    assert len(before) == 16
    for detector in (fast, lite):  # their networks now see no board
        monkeypatch.setattr(detector, "_search", lambda *args, **kwargs: (None, Seen()))
    with StageTimes() as times:
        assert len(fast.detect(image)) == 0 and len(lite.detect(image, expected=before)) == 0
    assert "backup looks" not in times.counts
    with StageTimes() as times:
        tracked = tracker.detect(image)
    assert times.counts["backup looks"] == 1 and tracker.last_search == "crop"
    assert fast.backup.weights == lite.weights
    assert len(tracked) == 16 and np.abs(tracked.corners - truth[tracked.ids]).max() < 0.1


def test_the_lite_networks_search_a_dim_whole_frame_the_fast_ones_find_nothing_in(monkeypatch):
    """``network="fast"``: a whole frame (nothing expected) searched at every level in which the fast networks find
    nothing is searched by the lite networks (`Detector.backup`) where it is dim, not where it is lit, nor in a quick
    look at the coarse level (``levels``)."""
    camera = Camera.from_fov(1280, 720, hfov_deg=60.0)
    board = BoardSpec()
    lit, _, _, truth = make_view(board, camera, distance=0.4)
    dark = (lit.astype(np.float32) * 0.12).round().astype(np.uint8)  # white at ~31 of 255
    fast = Detector(board=board, network="fast")
    search = fast._search

    def blind(*args, **kwargs):  # the fast networks see nothing; the frame's dimness is still measured
        _, seen = search(*args, **kwargs)
        return None, seen

    monkeypatch.setattr(fast, "_search", blind)
    for image, options in ((lit, {}), (dark, {"levels": 1}), (dark, {"stream": True}), (dark, {"dim_backup": False})):
        with StageTimes() as times:
            assert len(fast.detect(image, **options)) == 0
        assert "backup searches" not in times.counts
    with StageTimes() as times:
        found = fast.detect(dark)
    assert times.counts["backup searches"] == 1 and "backup looks" not in times.counts
    assert len(found) == 16 and np.abs(found.corners - truth[found.ids]).max() < 0.2


def test_auto_lets_the_lite_networks_search_a_photo_and_a_streams_dim_frames_the_fast_ones_find_too_little_in(
        monkeypatch):
    """``network="auto"``: a whole frame the fast networks find nothing in is searched by the lite networks too where
    it is a photo, lit (they saw its board's corner-like cells: the test after) or dim, and where it is a stream's
    (``stream``) only when dim and searched whole at every level (640x480: a 1280x720 one goes to the fast networks'
    finest level, the test after the next); a dim photo whose board they found in part is searched by lite too and the
    detection with more corners kept. ``network="fast"``: a dim photo alone. Neither in a quick look (``levels``).
    (`deep_detector.WHOLE_BACKUP`)"""
    camera = Camera.from_fov(640, 480, hfov_deg=60.0)
    board = BoardSpec()
    lit, _, _, truth = make_view(board, camera, distance=0.3)
    dark = (lit.astype(np.float32) * 0.12).round().astype(np.uint8)  # white at ~31 of 255
    auto, fast = Detector(board=board, network="auto"), Detector(board=board, network="fast")
    assert auto.backup_weights is not None and auto._backup is None  # named before it is built
    assert auto.backup.weights == auto.backup_weights == Detector(board=board).weights and auto.network == "auto"
    for detector in (auto, fast):
        search = detector._search

        def blind(*args, search=search, **kwargs):  # the fast networks see nothing; the frame's dimness is measured
            _, seen = search(*args, **kwargs)
            return None, seen

        monkeypatch.setattr(detector, "_search", blind)
    cases = [(auto, lit, {}, 1), (auto, dark, {}, 1), (auto, lit, {"stream": True}, 0),
             (auto, dark, {"stream": True}, 1), (auto, dark, {"levels": 1}, 0), (fast, lit, {}, 0), (fast, dark, {}, 1),
             (fast, dark, {"stream": True}, 0)]
    for detector, image, options, searches in cases:
        with StageTimes() as times:
            found = detector.detect(image, **options)
        assert times.counts.get("backup searches", 0) == searches, (detector.network, options)
        assert len(found) == (16 if searches else 0)
        if searches:
            assert np.abs(found.corners - truth[found.ids]).max() < 0.2
    whole = Detector(board=board).detect(dark)
    half = Detection(whole.ids[:8], whole.corners[:8], whole.scores[:8])
    for detector in (auto, fast):  # the fast networks find half the board
        monkeypatch.setattr(detector, "_detect", lambda image, *args, **kwargs: (half, Seen(dim=is_dim(image))))
    for detector, image, options, corners in ((auto, dark, {}, 16), (auto, dark, {"stream": True}, 8),
                                              (auto, lit, {}, 8), (fast, dark, {}, 8)):
        with StageTimes() as times:
            assert len(detector.detect(image, **options)) == corners, (detector.network, options)
        assert times.counts.get("backup searches", 0) == (corners == 16)


def test_auto_leaves_a_lit_photo_to_the_fast_networks_where_they_saw_too_few_corner_like_cells(monkeypatch):
    """``network="auto"``: a lit photo the fast networks find nothing in is searched by the lite networks only where
    one pass of theirs saw `BACKUP_MIN_CELLS` cells of point confidence >= 0.3 (`levels.Seen`); a dim photo always.
    The cue is counted: none on a blank page, the board's corners on a view of it."""
    camera = Camera.from_fov(640, 480, hfov_deg=60.0)
    board = BoardSpec()
    lit, _, _, _ = make_view(board, camera, distance=0.3)
    blank = np.full((480, 640), 200, np.uint8)
    auto = Detector(board=board, network="auto")
    assert auto._detect(blank, None)[1].corner_cells == 0
    assert auto._detect(lit, None)[1].corner_cells >= board.num_corners
    with StageTimes() as times:
        assert len(auto.detect(blank)) == 0
    assert "backup searches" not in times.counts
    # (cells, dim, lite searches of the photo and of the same frame as a stream's: lit, never; dim, always)
    for cells, dim, searches in ((BACKUP_MIN_CELLS - 1, False, 0), (BACKUP_MIN_CELLS, False, 1), (0, True, 2)):
        monkeypatch.setattr(auto, "_detect", lambda *args, seen=Seen(False, dim, cells), **kwargs:
                            (Detection.empty(), seen))
        monkeypatch.setattr(auto.backup, "_detect", lambda *args, **kwargs: (Detection.empty(), Seen()))
        with StageTimes() as times:
            assert len(auto.detect(lit)) == 0
            assert len(auto.detect(lit, stream=True)) == 0
        assert times.counts.get("backup searches", 0) == searches, (cells, dim)


@pytest.mark.parametrize("mode", ["deep", "hybrid"])
def test_auto_searches_a_streams_dim_720p_frame_again_at_full_resolution_with_the_fast_networks(monkeypatch, mode):
    """``network="auto"``, a stream's dim 1280x720 frame the fast networks find nothing in: their search of the
    full-resolution level went only around board-like cells (a level longer than `WHOLE_SEARCH_SIZE`), so they search
    that level whole (`WHOLE_BACKUP`'s "finest"), not the lite networks, and OpenCV (hybrid) is not asked again. Not in
    a lit frame, a quick look, a tracked crop, nor with ``network="fast"``; a photo is still lite's."""
    camera = Camera.from_fov(1280, 720, hfov_deg=60.0)
    board = BoardSpec()
    lit, _, _, truth = make_view(board, camera, distance=0.5)
    dark = (lit.astype(np.float32) * 0.04).round().astype(np.uint8)  # white at ~10 of 255: OpenCV finds nothing
    auto, fast = Detector(board=board, network="auto", mode=mode), Detector(board=board, network="fast", mode=mode)
    searched = []
    for detector in (auto, fast):
        search = detector._search

        def coarse_blind(full, working_size, *args, search=search, **kwargs):
            """The fast networks' search level by level sees no board; their full-resolution level alone does."""
            searched.append(working_size)
            found, seen = search(full, working_size, *args, **kwargs)
            return (found if working_size == max(full.shape) else None), seen

        monkeypatch.setattr(detector, "_search", coarse_blind)
    with StageTimes() as times:
        found = auto.detect(dark, stream=True)
    assert searched == [320, 1280]
    assert times.counts["finest searches"] == 1 and "backup searches" not in times.counts
    assert times.counts.get("opencv", 0) == (mode == "hybrid")
    assert len(found) == 16 and np.abs(found.corners - truth[found.ids]).max() < 0.2
    for detector, image, options in ((auto, lit, {"stream": True}), (auto, dark, {"stream": True, "levels": 1}),
                                     (fast, dark, {"stream": True})):
        with StageTimes() as times:  # in hybrid mode OpenCV finds the lit board
            assert len(detector.detect(image, **options)) == (16 if mode == "hybrid" and image is lit else 0)
        assert "finest searches" not in times.counts and "backup searches" not in times.counts
    with StageTimes() as times:
        assert len(auto.detect(dark)) == 16  # a photo: the lite networks
    assert times.counts["backup searches"] == 1 and "finest searches" not in times.counts
    with StageTimes() as times:
        assert len(auto.detect(dark, stream=True, expected=found)) == 16  # a tracked crop lost: the lite networks look
    assert times.counts["backup looks"] == 1 and "finest searches" not in times.counts


def test_a_stream_never_lets_the_fast_networks_lite_backup_search_a_dim_whole_frame(monkeypatch):
    """With ``network="fast"``, `BoardTracker`'s whole searches, and `StreamFrames` (a stream's frames each searched
    whole), say each frame is a stream's (``stream``): the lite backup searches no dim whole frame there, since in a
    dark video the board is away in most frames the fast networks find nothing in, and each cost lite's whole search
    (docs/detector.md). The same frame given to the detector itself is searched by lite."""
    rng = np.random.default_rng(0)
    dark = rng.integers(0, 30, (360, 640)).astype(np.uint8)  # no board, white below is_dim's 64
    fast = Detector(board=BoardSpec(), network="fast")
    monkeypatch.setattr(fast.backup, "_search", lambda *args, **kwargs: (None, Seen(dim=True)))
    tracker, stream = BoardTracker(fast, search_every=2), StreamFrames(fast)
    with StageTimes() as times:
        for _ in range(5):
            assert tracker.push(dark) == [] and len(stream.detect(dark)) == 0
        assert len(fast.detect(dark)) == 0
    assert times.counts["backup searches"] == 1  # the last, the detector's own
    assert len(StreamFrames(OpenCVDetector(BoardSpec())).detect(dark)) == 0  # a detector without the option


def test_the_detector_finds_a_board_by_markers_where_it_is_expected_without_searching_its_cells(monkeypatch):
    """A 4x5 inverted board (found by its markers) in a 1280x720 frame, expected where a frame before put it 3 px
    away: the same corners as the search through the cells, which does not run."""
    import deepcharuco.detection.markers.placement as placement

    board = BoardSpec(squares_x=4, squares_y=5, square_length=0.05, marker_length=0.0375,
                      dictionary="DICT_4X4_1000", inverted=True)
    camera = Camera.from_fov(1280, 720, hfov_deg=60.0)
    image = make_view(board, camera, distance=0.9, tilt_x_deg=20)[0]
    detector = Detector(board=board)
    searched = detector.detect(image)
    assert len(searched) == board.num_corners
    before = Detection(searched.ids, searched.corners + np.array([3.0, -2.0], np.float32), searched.scores)

    def no_search(*args, **kwargs):
        raise AssertionError("the cells were searched")
    monkeypatch.setattr(placement, "find_cells", no_search)
    found = detector.detect(image, expected=before)
    assert np.array_equal(found.ids, searched.ids)
    np.testing.assert_allclose(found.corners, searched.corners, atol=1e-3)


def _small_squares_view():
    """(board, image, true corners): a 4x5 inverted board (found by its markers) with squares ~35 px in a 1280x720
    frame: ~9 px at the 320-px level, too narrow to stop the search there; ~17 px at 640."""
    board = BoardSpec(squares_x=4, squares_y=5, square_length=0.05, marker_length=0.0375,
                      dictionary="DICT_4X4_1000", inverted=True)
    camera = Camera.from_fov(1280, 720, hfov_deg=60.0)
    image, _, _, truth = make_view(board, camera, distance=1.6, tilt_x_deg=15)
    return board, image, truth


def _small_squares_frame():
    board, image, _ = _small_squares_view()
    return board, image


def test_an_expected_board_is_searched_first_at_the_level_where_its_squares_are_wide_enough():
    """Expected (a frame before) with squares too narrow for the coarse level: the search starts at the finer one, the
    coarse level's network never runs, and it finds the corners the search from the coarse level finds."""
    board, image = _small_squares_frame()
    detector = Detector(board=board)
    with StageTimes() as coarse_first:
        searched = detector.detect(image)
    assert len(searched) == board.num_corners
    assert coarse_first.counts["network 0"] == 1 and coarse_first.counts["network 1"] == 1
    before = Detection(searched.ids, searched.corners + np.array([3.0, -2.0], np.float32), searched.scores)
    with StageTimes() as expected_first:
        found = detector.detect(image, expected=before)
    assert expected_first.counts["network 0"] == 0 and expected_first.counts["network 1"] == 1
    assert np.array_equal(found.ids, searched.ids)
    np.testing.assert_allclose(found.corners, searched.corners, atol=0.05)


def test_a_board_a_coarse_level_found_with_narrow_squares_is_looked_for_in_that_view_at_the_next(monkeypatch):
    """Searched whole, the coarse level finds the board with squares too narrow to stop at, and the next level looks
    for it first in the view the coarse level's markers verified (as a tracked board's): the cells are searched at the
    coarse level alone, and the corners are the board's."""
    import deepcharuco.detection.markers.placement as placement

    board, image, truth = _small_squares_view()
    searches = []
    find_cells = placement.find_cells
    monkeypatch.setattr(placement, "find_cells", lambda *args, **kwargs: searches.append(1) or find_cells(*args, **kwargs))
    with StageTimes() as times:
        found = Detector(board=board).detect(image)
    assert times.counts["network 0"] == 1 and times.counts["network 1"] == 1 and len(searches) == 1
    assert len(found) == board.num_corners and np.abs(found.corners - truth[found.ids]).max() < 0.1


def test_an_expected_board_its_level_does_not_find_is_looked_for_at_the_coarser_levels(monkeypatch):
    """Where the level an expected board's squares call for finds nothing (a blurred board the coarse level still
    reads), the coarser levels are searched after it, and only they: the finer ones were searched."""
    board, image = _small_squares_frame()
    detector = Detector(board=board)
    searched = detector.detect(image)
    searches = []
    original = Detector._search_levels

    def finer_levels_find_nothing(self, full, scales, first, stop, prior, white=None):
        searches.append((first, stop, len(scales)))
        return (None, Seen()) if first > 0 else original(self, full, scales, first, stop, prior, white)

    monkeypatch.setattr(Detector, "_search_levels", finer_levels_find_nothing)
    with StageTimes() as times:
        found = detector.detect(image, expected=searched)
    assert searches == [(1, 3, 3), (0, 1, 3)]  # 320, 640 and 1280 px: from 640 first, then 320 alone
    assert times.counts["network 0"] == 1 and times.counts["network 1"] == 0
    assert len(found) == 0 or set(found.ids) <= set(searched.ids)
    assert Detector._expected_start([0.25, 0.5, 1.0], 1280, None) == 0  # nothing expected: from the coarsest
    assert Detector._expected_start([0.25, 0.5, 1.0], 1280, 80.0) == 0  # squares of 20 px at 320 px already
    assert Detector._expected_start([0.25, 0.5, 1.0], 1280, 20.0) == 0  # 1280 px only: searched whole it costs more


def test_a_quick_look_leaves_the_inverted_prints_second_search_to_the_full_search(monkeypatch):
    """A frame with board-like cells and no board of ours (another dictionary's board): the full search searches it
    again negated about its local white, a quick look at the coarse level does not."""
    import deepcharuco.detection.deep_detector as deep_detector

    ours = BoardSpec(squares_x=4, squares_y=5, square_length=0.05, marker_length=0.0375,
                     dictionary="DICT_4X4_1000", inverted=True)
    other = BoardSpec(squares_x=4, squares_y=5, square_length=0.05, marker_length=0.0375,
                      dictionary="DICT_6X6_250", inverted=True)
    camera = Camera.from_fov(1280, 720, hfov_deg=60.0)
    image = make_view(other, camera, distance=1.6)[0]  # squares ~35 px, ~9 at 320 px: a dense patch of corner-like cells
    calls = []
    local_white = deep_detector.canonical_view_local_white
    monkeypatch.setattr(deep_detector, "canonical_view_local_white",
                        lambda gray, board: calls.append(1) or local_white(gray, board))
    detector = Detector(board=ours)
    assert len(detector.detect(image)) == 0 and len(calls) == 1
    assert len(detector.detect(image, levels=1)) == 0 and len(calls) == 1
    # A tracker's whole frames: only in a dim one (the image darkened to a tenth of its light).
    assert len(detector.detect(image, local_white="dim")) == 0 and len(calls) == 1 and detector.local_white_skipped
    dim = (image.astype(np.float32) * 0.1).round().astype(np.uint8)
    assert len(detector.detect(dim, local_white="dim")) == 0 and len(calls) == 2 and not detector.local_white_skipped
    assert len(detector.detect(dim)) == 0 and len(calls) == 3 and not detector.local_white_skipped
    with pytest.raises(ValueError, match="local_white"):
        detector.detect(image, local_white="never")


class Shadowed(Numbered):
    """`Numbered` for an inverted print (``inverted``) in lit frames: in frame ``shadowed`` only a whole-frame search
    that also looks about the local white (``local_white`` "always") finds the board; records each call's
    ``local_white``."""

    def __init__(self, present, shadowed, inverted=True):
        super().__init__(present)
        self.shadowed, self.board, self.local_white = shadowed, BoardSpec(inverted=inverted), []
        self.local_white_skipped = False

    def detect(self, image, working_size=None, levels=None, local_white="always"):
        whole = image.shape == (720, 1280)
        self.local_white.append((int(image.flat[0]), "crop" if not whole else "coarse" if levels == 1 else "full",
                                 local_white))
        self.local_white_skipped = whole and levels is None and local_white == "dim"
        if int(image.flat[0]) == self.shadowed and not (whole and levels is None and local_white == "always"):
            self.calls.append((self.shadowed, "crop" if not whole else "full"))
            return Detection.empty()
        return super().detect(image, working_size, levels)


def test_a_tracker_leaves_an_inverted_prints_second_search_to_its_crops_and_its_look_back():
    """The board is in frames 3-7 (lit); in frame 3 only the search about the local white finds it. The tracker's
    whole frames leave that search out of lit frames (frame 3 is then found a frame late); looking back, frame 3's crop
    misses it and frame 3, whose search left that out, is searched whole with it."""
    present = {3, 4, 5, 6, 7}
    found = lambda detections: [n for n, d in enumerate(detections) if len(d) >= 4]  # noqa: E731
    camera = Shadowed(present, 3)
    assert found(detect_all(BoardTracker(camera, look_back=False), video(9))) == [4, 5, 6, 7]
    assert (3, "full", "dim") in camera.local_white and (3, "full", "always") not in camera.local_white
    detector = Shadowed(present, 3)
    assert found(detect_all(BoardTracker(detector), video(9))) == [3, 4, 5, 6, 7]
    after = detector.local_white[detector.local_white.index((4, "full", "dim")) + 1:]
    assert after[:2] == [(3, "crop", "always"), (3, "full", "always")]
    assert {call for call in detector.local_white if call[1] == "crop"} <= {(n, "crop", "always") for n in range(9)}
    # a print that is not inverted has no second search to leave out: every search is whole
    plain = Shadowed(present, 3, inverted=False)
    assert found(detect_all(BoardTracker(plain, look_back=False), video(9))) == [3, 4, 5, 6, 7]
    assert all(local_white == "always" for _, _, local_white in plain.local_white)


def test_a_whole_video_looks_back_for_the_board_the_quick_search_reached_late():
    frames = video(10)
    present = {4, 5, 6, 7}
    found = lambda detections: [n for n, d in enumerate(detections) if len(d) >= 4]  # noqa: E731
    every = BoardTracker(Numbered(present))  # every level of every frame: the reference
    assert found([every.detect(f) for f in frames]) == [4, 5, 6, 7]
    quick = BoardTracker(Numbered(present), search_every=3)  # a camera's: frames 4 and 5 only at the coarse level
    assert found([quick.detect(f) for f in frames]) == [6, 7]
    detector = Numbered(present)
    tracker = BoardTracker(detector, search_every=3)
    answers = [len(tracker.push(f)) for f in frames]
    # frames 0-5 found nothing and are held back; frame 6's found board settles them; frames 8 (crop and full search)
    # and 9 (coarse) found nothing and wait for the end of the video
    assert answers == [0, 0, 0, 0, 0, 0, 7, 1, 0, 0]
    assert len(tracker.flush()) == 2 and tracker.flush() == []
    # looking back: frame 6 found the board, so frame 5 is searched around it, then 4, then 3, which does not show it
    # and was searched whole before (no second whole search)
    assert detector.calls[detector.calls.index((6, "full")):][:4] == [(6, "full"), (5, "crop"), (4, "crop"),
                                                                     (3, "crop")]
    assert (3, "full") not in detector.calls[detector.calls.index((6, "full")):]
    assert tracker.looked_back == 2
    tracker = BoardTracker(Numbered(present), search_every=3)
    detections = detect_all(tracker, frames)
    assert len(detections) == 10 and found(detections) == [4, 5, 6, 7]
    np.testing.assert_array_equal(detections[4].corners, Numbered.CORNERS)  # in frame pixels, as forwards


def test_looking_back_stops_at_the_first_frame_without_the_board():
    detector = Numbered({5, 6})  # frame 4 (held, like 5) has no board: the look back stops there
    tracker = BoardTracker(detector, search_every=3)
    detections = detect_all(tracker, video(8))
    assert [n for n, d in enumerate(detections) if len(d) >= 4] == [5, 6]
    assert (4, "crop") in detector.calls and (3, "crop") not in detector.calls  # 3 was searched whole: not held


def test_a_live_camera_is_answered_frame_by_frame_without_looking_back():
    tracker = BoardTracker(Numbered({4, 5, 6, 7}), search_every=3, look_back=False)
    answers = [tracker.push(f) for f in video(10)]
    assert [len(a) for a in answers] == [1] * 10
    assert [n for n, a in enumerate(answers) if len(a[0]) >= 4] == [6, 7]
    assert tracker.flush() == []


def test_reset_drops_the_frames_held_back():
    tracker = BoardTracker(Numbered(set()), search_every=3)
    assert [len(tracker.push(f)) for f in video(3)] == [0, 0, 0]
    tracker.reset()
    assert tracker.flush() == []


class MissedOnce(Numbered):
    """`Numbered`, but the whole search of frame ``missed`` does not find the board (a blurred frame) where a crop
    around the board of the frame after it does."""

    def __init__(self, present, missed):
        super().__init__(present)
        self.missed = missed

    def detect(self, image, working_size=None, levels=None):
        if int(image.flat[0]) == self.missed and image.shape == (720, 1280):
            self.calls.append((self.missed, "coarse" if levels == 1 else "full"))
            return Detection.empty()
        return super().detect(image, working_size, levels)


def test_a_frame_a_whole_search_missed_is_found_from_the_frame_after_it():
    """The board is in frames 3-7; frame 3's whole search misses it (a blurred first frame), so every level of every
    frame finds it from frame 4. Looking back, frame 3 is found around frame 4's board."""
    present = {3, 4, 5, 6, 7}
    found = lambda detections: [n for n, d in enumerate(detections) if len(d) >= 4]  # noqa: E731
    assert found(detect_all(BoardTracker(MissedOnce(present, 3), look_back=False), video(9))) == [4, 5, 6, 7]
    assert found(detect_all(BoardTracker(MissedOnce(present, 3)), video(9))) == [3, 4, 5, 6, 7]
    # search_every 3: frames 0 (full), 1-2 (coarse), 3 (full, missed) and 4-5 (coarse) find nothing, 6 (full) finds
    # the board; the look back reaches frame 3 through 5 and 4, and frame 2, which had only the coarse look, is
    # searched whole before it stops
    detector = MissedOnce(present, 3)
    assert found(detect_all(BoardTracker(detector, search_every=3), video(9))) == [3, 4, 5, 6, 7]
    after = detector.calls[detector.calls.index((6, "full")) + 1:]
    assert after[:5] == [(5, "crop"), (4, "crop"), (3, "crop"), (2, "crop"), (2, "full")]
    assert (1, "crop") not in after


def test_frames_beyond_the_hold_budget_are_settled_oldest_first(monkeypatch):
    import deepcharuco.detection.tracking as tracking

    monkeypatch.setattr(tracking, "HOLD_BYTES", 3 * 1280 * 720)  # three frames
    tracker = BoardTracker(Numbered(set()), search_every=3)
    assert [len(tracker.push(f)) for f in video(6)] == [0, 0, 0, 1, 1, 1]
    assert len(tracker.flush()) == 3


def test_the_real_detector_finds_a_small_board_in_a_whole_video_where_every_frame_searched_finds_it():
    """A board too small for the coarse level (squares 7 px there) appears in a frame searched at the coarse level
    alone: looking back finds it there, with at least the corners a search of every level gives, on the truth."""
    camera = Camera.from_fov(1280, 720, hfov_deg=60.0)
    board = BoardSpec()
    empty = np.full((720, 1280), 120, np.uint8)
    views = [make_view(board, camera, distance=1.6, offset=(0.01 * i, 0.0)) for i in range(3)]
    frames, truths = [empty, empty] + [v[0] for v in views], [None, None] + [v[3] for v in views]
    detector = Detector(board=board)
    every = [detector.detect(f) for f in frames]
    tracker = BoardTracker(detector, search_every=3)
    detections = detect_all(tracker, frames)
    assert tracker.looked_back == 1  # frame 2: searched at the coarse level alone, found from frame 3 backwards
    for found, reference, truth in zip(detections, every, truths):
        if truth is None:
            assert len(found) == 0
            continue
        assert len(found) >= 15 and set(reference.ids) <= set(found.ids)
        assert np.abs(found.corners - truth[found.ids]).max() < 0.3


def test_a_refresh_that_finds_nothing_keeps_the_board_the_crop_still_finds():
    tracker = BoardTracker(TrackedOnly(), refresh_every=5)  # whole frames find the board in frame 1 alone
    found, searches = [], []
    for frame in video(25):
        found.append(len(tracker.detect(frame)) >= 4)
        searches.append(tracker.last_search)
    assert [n for n, f in enumerate(found) if f] == list(range(1, 21))
    assert searches[1:7] == ["full", "crop", "crop", "crop", "crop", "crop"]  # frame 6: the refresh, then the crop


def test_predicted_moves_each_corner_on_by_its_own_motion_and_a_new_one_by_their_median():
    before = Detection(np.array([0, 1, 2, 3]), np.array([[0, 0], [10, 0], [0, 10], [10, 10]], np.float32), np.ones(4))
    motion = np.array([[2, 1], [3, 1], [2, 2], [4, 0]], np.float32)
    last = Detection(np.array([0, 1, 2, 3, 5]), np.array([[2, 1], [13, 1], [2, 12], [14, 10], [30, 30]], np.float32),
                     np.ones(5))
    expected = predicted(last, before)
    np.testing.assert_array_equal(expected.ids, last.ids)
    np.testing.assert_allclose(expected.corners, last.corners + np.vstack([motion, np.median(motion, axis=0)]))
    few = Detection(last.ids[2:], last.corners[2:], np.ones(3))  # shares corners 2 and 3 alone with before
    assert predicted(few, before) is few and predicted(last, Detection.empty()) is last
    jitter = np.array([[0.4, -0.3], [-0.5, 0.2], [0.3, 0.5], [-0.2, -0.4]], np.float32)  # a still board's
    still = Detection(before.ids, before.corners + jitter, np.ones(4))
    assert predicted(still, before) is still
    moving = Detection(before.ids, before.corners + jitter + np.array([2, 0], np.float32), np.ones(4))
    np.testing.assert_allclose(predicted(moving, before).corners, moving.corners + jitter + [2, 0])


class Moving:
    """A detector that takes ``expected``, for a video whose frame n holds a board moving ``STEP`` px a frame: each
    pixel of a frame is (n, x, y), so a crop knows its frame and origin. The board is found in crops always, in whole
    frames from ``whole_from`` on; every call's ``expected`` is kept in frame pixels, and its image's (x0, y0, x1, y1)
    in the frame, by frame."""

    CORNERS = np.array([[300, 200], [340, 200], [300, 240], [340, 240], [380, 240]], np.float32)
    STEP = np.array([14, -6], np.float32)

    def __init__(self, whole_from=0):
        self.whole_from, self.expected, self.regions = whole_from, {}, {}

    def board(self, n):
        return self.CORNERS + n * self.STEP

    def detect(self, image, expected=None):
        n, x0, y0 = (int(v) for v in image[0, 0])
        origin = np.array([x0, y0], np.float32)
        self.regions[n] = (x0, y0, x0 + image.shape[1], y0 + image.shape[0])
        if expected is not None:
            self.expected[n] = expected.corners + origin
        if image.shape[:2] == (720, 1280) and n < self.whole_from:
            return Detection.empty()
        return Detection(np.arange(5), self.board(n) - origin, np.ones(5))


@pytest.mark.parametrize("predict_motion", [True, False])
def test_a_tracked_board_is_expected_where_it_moves_on_to(predict_motion):
    detector = Moving()
    tracker = BoardTracker(detector, predict_motion=predict_motion)
    for frame in moving_video(5):
        tracker.detect(frame)
    assert tracker.last_search == "crop" and sorted(detector.expected) == [1, 2, 3, 4]
    np.testing.assert_allclose(detector.expected[1], detector.board(0))  # no motion seen yet
    for n in (2, 3, 4):
        np.testing.assert_allclose(detector.expected[n], detector.board(n if predict_motion else n - 1), atol=1e-3)
        assert detector.regions[n] == search_region(detector.board(n if predict_motion else n - 1), (1280, 720))


def test_looking_back_expects_the_board_to_move_on_backwards():
    detector = Moving(whole_from=4)  # frames 0-3 are held back and found by looking back from frame 4
    detections = detect_all(BoardTracker(detector), moving_video(6))
    assert all(len(d) == 5 for d in detections)
    np.testing.assert_allclose(detector.expected[3], detector.board(4))  # no motion after frame 4 seen yet
    for n in (2, 1, 0):
        np.testing.assert_allclose(detector.expected[n], detector.board(n), atol=1e-3)
    np.testing.assert_allclose(detector.expected[5], detector.board(5), atol=1e-3)  # on from frames 3 and 4


def test_a_board_followed_from_two_frames_is_expected_where_it_moves_on_to():
    # A worker's chunk that continues another's (`parallel._continue_chunk`): the two frames before the chunk.
    detector = Racing()
    frames = moving_video(7)
    board = [Detection(np.arange(5), detector.board(n), np.ones(5)) for n in range(7)]
    tracker = BoardTracker(detector)
    tracker.follow_from(board[3], board[2])
    assert [len(d) for d in detect_all(tracker, frames[4:])] == [5, 5, 5]
    tracker.reset()
    tracker.follow_from(board[3])  # no motion known: the crop is where the board was, and misses it
    assert [len(d) for d in detect_all(tracker, frames[4:])] == [0, 0, 0]
