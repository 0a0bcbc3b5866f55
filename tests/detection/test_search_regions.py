"""Coarse-to-fine search by regions: a finer level looks only where the level before found the board or saw
board-like cells; a frame with nothing board-like stops at the whole levels. And the stage timer benchmarks use."""

import numpy as np
import pytest

from conftest import network_widths
from deepcharuco import BoardSpec, Detector
from deepcharuco.core.stage_times import StageTimes, stage, tally
from deepcharuco.detection.search_regions import (CONFIDENCE, DIM_CONFIDENCE, DIM_MIN_CELLS, DIM_WHITE, MIN_CELLS, area_share,
                                                  board_like_boxes, is_dim, to_full, white_level)
from deepcharuco.networks.cells import CELL, cell_confidence
from evaluate.speed.realistic import Placement, clutter, with_board, without_board


def test_a_dense_patch_of_corner_like_cells_is_board_like_scattered_ones_are_not():
    confidence = np.zeros((45, 80), np.float32)
    confidence[::9, ::9] = 0.9  # isolated corners, one a 9-cell stride: texture, not a board
    assert board_like_boxes(confidence) == []
    confidence[20:24, 30:34] = CONFIDENCE  # 16 corner-like cells in 4x4 cells: a board with ~8 px squares
    (x0, y0, x1, y1), = board_like_boxes(confidence)
    assert x0 <= 30 - 3 and y0 <= 20 - 3 and x1 >= 34 + 3 and y1 >= 24 + 3  # the margin for its markers
    assert x1 - x0 < 16 and y1 - y0 < 16
    few = np.zeros_like(confidence)
    few[5, 5:5 + MIN_CELLS - 1] = 1.0  # one short of the minimum
    assert board_like_boxes(few) == []


def test_a_dim_frame_counts_fainter_and_fewer_cells():
    faint = np.zeros((30, 40), np.float32)
    faint[10, 10:10 + DIM_MIN_CELLS] = DIM_CONFIDENCE  # the point head's answer in the dark: faint, few
    assert board_like_boxes(faint) == [] and len(board_like_boxes(faint, dim=True)) == 1
    lit = np.full((180, 320), 200, np.uint8)
    assert not is_dim(lit)
    assert is_dim((lit * (DIM_WHITE - 1) / 200).astype(np.uint8))
    lit[:, :2] = 255  # a lamp on 1 % of the frame does not make it lit
    assert not is_dim(lit) and is_dim(np.where(lit == 255, 255, 20).astype(np.uint8))


def test_the_white_level_is_the_99th_percentile_grey_by_rank():
    rng = np.random.default_rng(3)
    for shape in ((1, 1), (7, 13), (180, 320)):
        for high in (2, 30, 256):
            gray = rng.integers(0, high, shape).astype(np.uint8)
            rank = int(0.99 * (gray.size - 1))
            assert white_level(gray) == np.sort(gray.ravel())[rank]
            view = np.pad(gray, 3)[3:-3, 1:-5]  # a strided view (a region of a frame) reads the same
            assert white_level(view) == np.sort(view.ravel())[int(0.99 * (view.size - 1))]


def test_boxes_map_to_full_pixels_inside_the_image_at_least_the_minimum_side():
    (x0, y0, x1, y1), = to_full([(10, 4, 12, 6)], scale=0.25, image_size=(1280, 720))
    assert (x0, y0) <= (10 * CELL * 4, 4 * CELL * 4) and (x1, y1) >= (12 * CELL * 4, 6 * CELL * 4)
    assert x1 - x0 >= 8 * CELL * 4 and y1 - y0 >= 8 * CELL * 4  # widened to 8 cells of the level
    (x0, y0, x1, y1), = to_full([(0, 0, 50, 50)], scale=0.25, image_size=(1280, 720))
    assert (x0, y0, x1, y1) == (0, 0, 1280, 720)
    assert area_share([(0, 0, 640, 720)], (1280, 720)) == pytest.approx(0.5)


def test_a_small_board_in_a_large_frame_is_found_and_the_finest_level_sees_only_its_region():
    board = BoardSpec()
    rng = np.random.default_rng(7)
    frame = with_board(board, clutter(rng, (1920, 1080)), rng, Placement(0.12, 0.14, tilt_deg=15, roll_deg=10))
    found, widths = network_widths(Detector(board), frame.image)
    assert len(found.ids) >= 0.9 * board.num_corners
    error = np.linalg.norm(found.corners - frame.corners[found.ids], axis=1)
    assert np.median(error) < 0.3 and error.max() < 1.5
    assert widths[:2] == [320, 640]  # the levels searched whole
    assert all(width < 1280 for width in widths[2:])  # finer levels: regions only, never the whole frame


def test_a_frame_with_nothing_board_like_is_not_searched_past_the_levels_searched_whole():
    rng = np.random.default_rng(3)
    plain = np.clip(120 + rng.normal(0, 3, (1080, 1920)), 0, 255).astype(np.uint8)  # a wall, sensor noise
    found, widths = network_widths(Detector(), without_board(plain).image)
    assert len(found) == 0 and widths == [320, 640]
    inverted = BoardSpec(squares_x=4, squares_y=5, dictionary="DICT_4X4_1000", inverted=True)
    found, widths = network_widths(Detector(inverted), plain)
    assert len(found) == 0 and widths == [320, 640]  # and no second, local-white pass for an inverted print


def test_stage_times_are_kept_only_while_active():
    with stage("outside"):
        pass
    tally("outside")
    with StageTimes() as times:
        with stage("inside"):
            pass
        with stage("inside"):
            pass
        tally("cells", 5)
    assert times.counts == {"inside": 2, "cells": 5} and times.seconds["inside"] >= 0
    with StageTimes() as nested:
        found = Detector().detect(np.full((240, 320), 128, np.uint8))
    assert len(found) == 0 and any(name.startswith("network") for name in nested.seconds)
    assert "outside" not in times.counts and "outside" not in nested.counts


def test_cell_confidence_is_one_minus_the_dustbin_probability():
    rng = np.random.default_rng(0)
    logits = rng.normal(0, 2, (65, 3, 4)).astype(np.float32)
    softmax = np.exp(logits) / np.exp(logits).sum(axis=0)
    assert np.allclose(cell_confidence(logits), 1 - softmax[-1], atol=1e-6)
