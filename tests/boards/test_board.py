import json

import numpy as np
import pytest

from deepcharuco import BoardSpec, BoardSpecError, dictionary_names


def test_default_is_the_papers_board():
    board = BoardSpec()
    assert (board.squares_x, board.squares_y, board.dictionary) == (5, 5, "DICT_5X5_50")
    assert board.num_corners == 16 and board.num_markers == 12
    ids, corners = board.marker_corners()
    assert ids.tolist() == list(range(12)) and corners.shape == (12, 4, 3)


def test_corner_points_are_opencvs_ids():
    board = BoardSpec(7, 5, 0.03, 0.02, "DICT_6X6_250")
    points = board.corner_points()
    assert points.shape == (24, 3) and points.dtype == np.float64
    np.testing.assert_allclose(points, np.asarray(board.cv_board().getChessboardCorners()))
    # ID 0 is the top-left inner corner; IDs run along X first.
    np.testing.assert_allclose(points[0], [0.03, 0.03, 0.0])
    np.testing.assert_allclose(points[1], [0.06, 0.03, 0.0])
    np.testing.assert_allclose(points[6], [0.03, 0.06, 0.0])


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(dictionary="DICT_9X9_50"), "unknown ArUco dictionary"),
        (dict(squares_x=11, squares_y=11, dictionary="DICT_4X4_50"), "needs 60 markers but DICT_4X4_50 has only 50"),
        (dict(marker_length=0.05), "must be smaller than square_length"),
        (dict(marker_length=0.04), "must be smaller than square_length"),
        (dict(square_length=-1.0), "positive length"),
        (dict(square_length=float("nan")), "positive length"),
        (dict(squares_x=2), "must be >= 3"),
        (dict(squares_y=4.0), "must be an integer"),
        (dict(squares_x=True), "must be an integer"),
        (dict(legacy="yes"), "legacy must be true or false"),
        (dict(dictionary=5), "dictionary must be a name"),
    ],
)
def test_invalid_boards_are_refused_clearly(kwargs, message):
    with pytest.raises(BoardSpecError, match=message):
        BoardSpec(**kwargs)


def test_unknown_dictionary_error_lists_the_valid_names():
    with pytest.raises(BoardSpecError) as info:
        BoardSpec(dictionary="DICT_5x5_51")
    assert "DICT_5X5_50" in str(info.value) and "DICT_6X6_250" in str(info.value)
    assert "DICT_APRILTAG_36H11" in dictionary_names()


def test_dictionary_name_is_case_insensitive():
    assert BoardSpec(dictionary="dict_5x5_50") == BoardSpec()


@pytest.mark.parametrize("suffix", [".json", ".yaml", ".yml"])
def test_save_load_round_trip(tmp_path, suffix):
    board = BoardSpec(7, 5, 0.035, 0.026, "DICT_6X6_250", legacy=True)
    path = board.save(tmp_path / f"board{suffix}")
    assert BoardSpec.load(path) == board
    assert BoardSpec.from_json(board.to_json()) == board


def test_hand_written_yaml_without_directive(tmp_path):
    path = tmp_path / "board.yaml"
    path.write_text("squares_x: 7\nsquares_y: 5\nsquare_length: 0.04\nmarker_length: 0.03\n"
                    "dictionary: DICT_6X6_250\nlegacy: false\n")
    assert BoardSpec.load(path) == BoardSpec(7, 5, 0.04, 0.03, "DICT_6X6_250")


def test_bad_board_files(tmp_path):
    with pytest.raises(BoardSpecError, match="does not exist"):
        BoardSpec.load(tmp_path / "missing.json")
    (tmp_path / "b.json").write_text(json.dumps({"squares_x": 5, "colour": "red"}))
    with pytest.raises(BoardSpecError, match=r"unknown board field\(s\) \['colour'\]"):
        BoardSpec.load(tmp_path / "b.json")
    (tmp_path / "c.json").write_text("{not json")
    with pytest.raises(BoardSpecError, match="not valid JSON"):
        BoardSpec.load(tmp_path / "c.json")
    (tmp_path / "d.txt").write_text("{}")
    with pytest.raises(BoardSpecError, match="name it .json, .yaml or .yml"):
        BoardSpec.load(tmp_path / "d.txt")


def test_board_files_as_people_write_them(tmp_path):
    path = tmp_path / "board.yaml"
    path.write_text("# my calibration board\nsquares_x: 4   # columns\nsquares_y: 5\nsquare_length: 0.054\n"
                    "marker_length: 0.0405\ndictionary: \"DICT_4X4_1000\"\ninverted: true  # white on black\n"
                    "mirrored: false\n")
    assert BoardSpec.load(path) == BoardSpec(4, 5, 0.054, 0.0405, "DICT_4X4_1000", inverted=True)
    inverted = BoardSpec(4, 5, 0.054, 0.0405, "DICT_4X4_1000", inverted=True, mirrored=True)
    assert BoardSpec.load(inverted.save(tmp_path / "round.yaml")) == inverted


@pytest.mark.parametrize("text, message", [
    ("", "holds no board fields"),
    ("# nothing but a comment\n", "holds no board fields"),
    ("- 5\n- 5\n", "flat list of 'field: value' lines"),
    ("squares_x: [5, 7]\n", "'squares_x' must be a single value"),
    ("board:\n  squares_x: 5\n", "'board' must be a single value"),
    ("squares_x: 5\nsquares_x: 6\n", "'squares_x' is given twice"),
    ("squares_x: 7\nsquares_y: 5\nsquare_length: 0.04\nmarker_length: 0.03\n", r"lacks the field\(s\) \['dictionary'\]"),
    ("squares_x: 7\nsquares_y: 5\nsquare_length: 0.04\nmarker_length: 0.03\ndictionary: DICT_6X6_250\n"
     "inverted: maybe\n", "inverted must be true or false"),
])
def test_bad_yaml_board_files_name_the_problem(tmp_path, text, message):
    path = tmp_path / "board.yaml"
    path.write_text(text)
    with pytest.raises(BoardSpecError, match=message):
        BoardSpec.load(path)


def test_layout_ignores_size_polarity_and_mirroring():
    board = BoardSpec()
    assert board.same_layout(BoardSpec(square_length=0.02, marker_length=0.015, inverted=True, mirrored=True))
    assert not board.same_layout(BoardSpec(marker_length=0.025))  # another marker/square ratio
    assert not board.same_layout(BoardSpec(dictionary="DICT_5X5_100"))
    assert not board.same_layout(BoardSpec(squares_x=6))


def test_inverted_and_mirrored_textures_and_object_points():
    board = BoardSpec()
    plain = board.render_texture(1000.0, margin=0.01).image
    assert np.array_equal(BoardSpec(inverted=True).render_texture(1000.0, margin=0.01).image, 255 - plain)
    assert np.array_equal(BoardSpec(mirrored=True).render_texture(1000.0, margin=0.01).image, plain[:, ::-1])


def test_a_mirrored_texture_is_mirrored_about_the_grid_not_the_image_edge():
    """At a density that leaves the sheet a fractional number of pixels wide, the ink of a mirrored board still
    lies where `object_points` (X -> W - X) puts it: its ink centroid is the plain board's, mirrored."""
    board, px_per_m = BoardSpec(), 1003.3  # (0.2 + 0.02) m x 1003.3 = 220.7 px: not a whole number

    def ink_centroid_x(texture) -> float:
        ink = 255.0 - texture.image.astype(np.float64)
        columns = np.arange(ink.shape[1], dtype=np.float64)
        u = (ink.sum(axis=0) * columns).sum() / ink.sum()
        return float(texture.texture_to_board(np.array([u, 0.0]))[0])

    plain = ink_centroid_x(board.render_texture(px_per_m, margin=0.01))
    mirrored = ink_centroid_x(BoardSpec(mirrored=True).render_texture(px_per_m, margin=0.01))
    assert abs(mirrored - (board.size_m[0] - plain)) < 0.02 / px_per_m  # 1/50 px; an image flip was 0.3 px off
    mirrored = BoardSpec(mirrored=True).object_points()
    assert np.allclose(mirrored[:, 0], board.size_m[0] - board.corner_points()[:, 0])
    assert np.allclose(mirrored[:, 1:], board.corner_points()[:, 1:])


@pytest.mark.parametrize(
    "board",
    [
        BoardSpec(5, 5, 0.04, 0.028),
        BoardSpec(7, 5, 0.04, 0.032, "DICT_6X6_250"),
        BoardSpec(6, 6, 0.04, 0.024, "DICT_4X4_50", legacy=True),
    ],
)
def test_texture_matches_opencv_where_edges_fall_on_pixels(board):
    # 100 px squares, marker cells of whole pixels: the area-exact texture must equal OpenCV's print.
    texture = board.render_texture(px_per_m=2500.0)
    height, width = texture.image.shape
    expected = board.cv_board().generateImage((width, height), marginSize=0, borderBits=1)
    assert np.array_equal(texture.image, expected)


def test_texture_is_area_exact_between_pixels():
    board = BoardSpec()
    # 101.25 px per square: a square edge at 101.25 px leaves a pixel 25% covered.
    texture = board.render_texture(px_per_m=101.25 / 0.04)
    row = texture.image[20].astype(int)  # first row of squares: black, white(marker), ...
    assert row[100] == 0 and row[102] == 255
    assert row[101] == round(255 * 0.75)


def test_texture_margin_and_map():
    board = BoardSpec()
    texture = board.render_texture(px_per_m=1000.0, margin=0.01)
    assert texture.image.shape == (220, 220)
    assert np.all(texture.image[:10] == 255) and np.all(texture.image[:, :10] == 255)
    np.testing.assert_allclose(texture.size_m, (0.22, 0.22))
    # The grid's top-left corner is pixel edge (10, 10), i.e. pixel-centre coordinate 9.5.
    np.testing.assert_allclose(texture.board_to_texture(np.array([0.0, 0.0])), [9.5, 9.5])
    uv = np.random.default_rng(0).uniform(0, 220, (50, 2))
    np.testing.assert_allclose(texture.board_to_texture(texture.texture_to_board(uv)), uv)
    homogeneous = texture.texture_to_board_matrix() @ np.c_[uv, np.ones(50)].T
    np.testing.assert_allclose(homogeneous[:2].T, texture.texture_to_board(uv))


def test_texture_partial_pixel_is_white_paper():
    texture = BoardSpec().render_texture(px_per_m=1002.5)  # 200.5 px of board
    assert texture.image.shape == (201, 201)
    assert np.all(texture.image[-1] >= 127) and np.all(texture.image[:, -1] >= 127)


def test_texture_size_guard():
    with pytest.raises(BoardSpecError, match="pixels per metre, not per millimetre"):
        BoardSpec().render_texture(px_per_m=1e6)
    with pytest.raises(BoardSpecError, match="px_per_m must be positive"):
        BoardSpec().render_texture(px_per_m=0)
    with pytest.raises(BoardSpecError, match="margin"):
        BoardSpec().render_texture(px_per_m=1000, margin=-0.1)


def test_board_file_nested_deeply_is_refused_in_one_line(tmp_path):
    path = tmp_path / "deep.json"
    path.write_text("[" * 30_000 + "]" * 30_000)  # under the size cap; deeper than Python's recursion limit
    with pytest.raises(BoardSpecError, match="nests too deeply"):
        BoardSpec.load(path)


def test_huge_board_file_is_refused_unread_and_briefly(tmp_path):
    path = tmp_path / "huge.yaml"
    with open(path, "w") as handle:
        for number in range(300_000):
            handle.write(f"key_{number}: {number}\n")
    with pytest.raises(BoardSpecError, match="too large for a board file") as error:
        BoardSpec.load(path)
    assert len(str(error.value)) < 300
    # Many unknown keys under the cap: five named, the rest counted.
    small = tmp_path / "many.json"
    small.write_text(json.dumps({f"key_{n}": n for n in range(2000)}))
    with pytest.raises(BoardSpecError, match="and 1,995 more") as error:
        BoardSpec.load(small)
    assert len(str(error.value)) < 400


@pytest.mark.parametrize("dictionary, squares, advice", [
    ("DICT_6X6_250", (1000, 3), "no DICT_6X6 dictionary holds 1500 (the largest, DICT_6X6_1000, has 1000): use fewer squares"),
    ("DICT_4X4_1000", (1000, 3), "no DICT_4X4 dictionary holds 1500"),
    ("DICT_6X6_250", (30, 30), "use the larger dictionary DICT_6X6_1000 or fewer squares"),
    ("DICT_5X5_50", (11, 11), "use the larger dictionary DICT_5X5_100 or fewer squares"),
])
def test_too_many_markers_suggests_a_dictionary_that_holds_them(dictionary, squares, advice):
    with pytest.raises(BoardSpecError) as error:
        BoardSpec(*squares, 0.04, 0.03, dictionary)
    assert advice in str(error.value)
    assert f"larger dictionary {dictionary}" not in str(error.value)


def test_first_marker_id_past_the_dictionary_suggests_a_larger_one():
    with pytest.raises(BoardSpecError, match="use the larger dictionary DICT_4X4_100 or a smaller first_marker_id"):
        BoardSpec(5, 5, 0.04, 0.03, "DICT_4X4_50", first_marker_id=40)


def test_caliscope_charuco_toml_reads_as_its_board(tmp_path):
    """caliscope's charuco.toml (fields as caliscope writes them; its square from the override, else the largest
    that fits the sheet, as caliscope computes it) is a board file, alone or as config.toml's [charuco] table."""
    fields = ('columns = 4\nrows = 5\nboard_height = 11.0\nboard_width = 8.5\ndictionary = "DICT_4X4_1000"\n'
              'units = "inch"\naruco_scale = 0.75\n')
    (tmp_path / "charuco.toml").write_text(fields + "square_size_overide_cm = 5.4\ninverted = true\n")
    assert BoardSpec.load(tmp_path / "charuco.toml") == BoardSpec(4, 5, 0.054, 0.0405, "DICT_4X4_1000", inverted=True)
    (tmp_path / "config.toml").write_text("[charuco]\n" + fields)
    board = BoardSpec.load(tmp_path / "config.toml")
    assert board.square_length == pytest.approx(8.5 * 0.0254 / 4) and not board.inverted  # 2.125 in fits 8.5 in / 4
    assert board.marker_length == pytest.approx(0.75 * board.square_length)
    (tmp_path / "ours.toml").write_text('squares_x = 7\nsquares_y = 5\nsquare_length = 0.03\nmarker_length = 0.022\n'
                                        'dictionary = "DICT_6X6_250"\n')
    assert BoardSpec.load(tmp_path / "ours.toml") == BoardSpec(7, 5, 0.03, 0.022, "DICT_6X6_250")
    (tmp_path / "bad.toml").write_text("columns = 4\nrows = 5\ndictionary = 'DICT_4X4_50'\n")
    with pytest.raises(BoardSpecError, match="give square_size_overide_cm or board_width and board_height"):
        BoardSpec.load(tmp_path / "bad.toml")
    (tmp_path / "broken.toml").write_text("columns = \n")
    with pytest.raises(BoardSpecError, match="is not valid TOML"):
        BoardSpec.load(tmp_path / "broken.toml")
    # Units: caliscope's two, in any case; any other is refused, not read as centimetres (units "mm" gave 10x squares).
    for units, square in (("cm", 8.5 * 0.01 / 4), ("Inch", 8.5 * 0.0254 / 4)):
        (tmp_path / "u.toml").write_text(fields.replace('units = "inch"', f'units = "{units}"'))
        assert BoardSpec.load(tmp_path / "u.toml").square_length == pytest.approx(square)
    (tmp_path / "mm.toml").write_text(fields.replace('units = "inch"', 'units = "mm"'))
    with pytest.raises(BoardSpecError, match="units 'mm' unknown: .* 'inch' or 'cm'"):
        BoardSpec.load(tmp_path / "mm.toml")
    # A quoted "false" was bool("false"), true: an inverted board read where the file said not inverted.
    (tmp_path / "quoted.toml").write_text(fields + 'inverted = "false"\n')
    with pytest.raises(BoardSpecError, match="inverted must be true or false \\(unquoted\\), got 'false'"):
        BoardSpec.load(tmp_path / "quoted.toml")


def test_a_board_file_with_a_byte_order_mark_reads(tmp_path):
    """Windows Notepad's UTF-8 starts with a byte-order mark: the YAML's first field and JSON were refused."""
    board = BoardSpec(7, 5, 0.03, 0.022, "DICT_6X6_250")
    board.save(tmp_path / "b.yaml")
    (tmp_path / "bom.yaml").write_bytes(b"\xef\xbb\xbf" + (tmp_path / "b.yaml").read_bytes())
    (tmp_path / "bom.json").write_bytes(b"\xef\xbb\xbf" + board.to_json().encode())
    assert BoardSpec.load(tmp_path / "bom.yaml") == board and BoardSpec.load(tmp_path / "bom.json") == board
