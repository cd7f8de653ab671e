"""Figures (episeg_cv.drawing): sizes, dtypes, and colours where the geometry says they must be."""

import numpy as np
import pytest

from episeg_cv import TwoViewGeometry
from episeg_cv.drawing import (COLORS, draw_matches, draw_points, draw_segment_figure, draw_segments,
                               save_image)

K = [[50, 0, 49.5], [0, 50, 49.5], [0, 0, 1]]
SIZE = (100, 100)


def _geom(R=np.eye(3), t=(0, 0, -1)):
    return TwoViewGeometry(K, K, R, t, image_size1=SIZE, image_size2=SIZE)


def _dominant(img, y, x):
    """0 blue, 1 green, 2 red: the strongest channel of a pixel (lines are anti-aliased)."""
    return int(np.argmax(img[y, x]))


@pytest.mark.parametrize("image", [
    np.zeros((100, 100), np.uint8),
    np.zeros((100, 100, 1), np.uint8),
    np.zeros((100, 100, 3), np.uint8),
    np.zeros((100, 100, 4), np.uint8),
    np.zeros((100, 100), np.float32),
    np.zeros((100, 100), np.uint16),
])
def test_any_input_gives_bgr_uint8_of_the_same_size(image):
    seg = _geom().segments([[80.0, 49.5], [20.0, 20.0]])
    out = draw_segments(image, seg)
    assert out.shape == (100, 100, 3) and out.dtype == np.uint8
    assert draw_points(image, [[10.0, 10.0]]).shape == (100, 100, 3)
    assert image.sum() == 0  # the input is not drawn on


def test_segment_green_excluded_red_epipole_and_infinity_marked():
    # forward motion: epipole at the centre, the correct part runs from p_inf = x1 away from it
    seg = _geom().segments([[80.0, 49.5]])
    img = draw_segments(np.zeros((100, 100), np.uint8), seg, labels=False, legend=False)
    assert _dominant(img, 49, 95) == 1  # beyond p_inf: green
    assert _dominant(img, 49, 15) == 2  # the other side of the epipole: red
    assert _dominant(img, 49, 65) == 2  # between the epipole and p_inf: red
    # the epipole (49.5, 49.5) is magenta (blue and red), the infinity point orange
    e = img[46:53, 46:53].reshape(-1, 3)
    assert np.any((e[:, 0] > 150) & (e[:, 2] > 150) & (e[:, 1] < 100))
    d = img[44:56, 75:86].reshape(-1, 3)
    assert np.any(np.all(d == COLORS["infinity"], axis=1))


def test_empty_segment_draws_only_red():
    # camera 2 turned 180 degrees about y: every ray of camera 1 is behind it
    R = np.diag([-1.0, 1.0, -1.0])
    seg = _geom(R, (0.1, 0.0, 0.0)).segments([[49.5, 49.5]])
    assert not seg.valid[0]
    img = draw_segments(np.zeros((100, 100), np.uint8), seg, labels=False, legend=False)
    green = (img[..., 1] > img[..., 2]) & (img[..., 1] > 50)
    red = (img[..., 2] > img[..., 1]) & (img[..., 2] > 50)
    assert not green.any() and red.any()


def test_pure_rotation_draws_a_green_point():
    seg = _geom(t=(0, 0, 0)).segments([[30.0, 60.0]])
    assert seg.valid[0]
    img = draw_segments(np.zeros((100, 100), np.uint8), seg, labels=False, legend=False)
    assert _dominant(img, 60, 30) == 1
    assert img[:, :70].sum() > 0 and img[:, 40:].sum() == 0  # only the dot


def test_points_on_segments_coloured_by_correctness():
    seg = _geom().segments([[80.0, 49.5], [49.5, 20.0]])
    img = draw_segments(np.zeros((100, 100), np.uint8), seg, points=[[90.0, 49.5], [49.5, 8.0]],
                        correct=np.array([True, False]), labels=False, legend=False)
    assert _dominant(img, 49, 90) == 1 and _dominant(img, 8, 49) == 2
    with pytest.raises(ValueError, match=r"points must have shape \(2, 2\)"):
        draw_segments(np.zeros((100, 100), np.uint8), seg, points=[[1.0, 2.0]])
    with pytest.raises(ValueError, match=r"correct must be a \(2,\) bool array"):
        draw_segments(np.zeros((100, 100), np.uint8), seg, points=np.zeros((2, 2)), correct=[1, 0])


def test_empty_input_and_legend_on_large_image():
    seg = _geom().segments(np.zeros((0, 2)))
    img = draw_segments(np.zeros((100, 100), np.uint8), seg, legend=False)
    drawn = img.reshape(-1, 3)[img.reshape(-1, 3).any(axis=1)]
    assert len(drawn) and np.all(drawn[:, 1] < drawn[:, 0])  # only the (magenta) epipole, a property of the pose
    big = draw_segments(np.zeros((960, 1280), np.uint8), _geom().segments([[80.0, 49.5]]))
    assert big.shape == (960, 1280, 3) and big.any()


def test_two_panel_figure_and_points():
    seg = _geom().segments([[80.0, 49.5]])
    fig = draw_segment_figure(np.zeros((100, 100)), np.zeros((90, 100, 3), np.uint8), [[80.0, 49.5]], seg, gap=6)
    assert fig.dtype == np.uint8 and fig.shape[1:] == (206, 3) and fig.shape[0] > 100
    pts = draw_points(np.zeros((60, 80), np.uint8), [[40.0, 30.0]], numbers=False)
    assert np.array_equal(pts[30, 40], COLORS["point"])
    with pytest.raises(ValueError, match="points1 has 2 points but segments has 1"):
        draw_segment_figure(np.zeros((100, 100)), np.zeros((100, 100)), [[1.0, 1.0], [2.0, 2.0]], seg)


def test_matches_side_by_side_colours():
    p1 = np.array([[150.0, 150.0], [150.0, 180.0]])
    p2 = np.array([[100.0, 150.0], [100.0, 180.0]])
    img = draw_matches(np.zeros((200, 200)), np.zeros((220, 210, 3), np.uint8), p1, p2, [[0, 0], [1, 1]],
                       np.array([True, False]), gap=10)
    assert img.shape == (220, 420, 3) and img.dtype == np.uint8
    assert _dominant(img, 150, 150) == 1 and _dominant(img, 180, 150) == 2
    assert _dominant(img, 150, 310) == 1 and _dominant(img, 180, 310) == 2
    unknown = draw_matches(np.zeros((200, 200)), np.zeros((200, 200)), p1, p2, [[0, 1]])
    assert _dominant(unknown, 150, 150) == 0  # blue
    empty = draw_matches(np.zeros((200, 200)), np.zeros((200, 200)), p1, p2, np.zeros((0, 2), int))
    assert empty.shape == (200, 408, 3)
    with pytest.raises(ValueError, match="pairs index out of range"):
        draw_matches(np.zeros((200, 200)), np.zeros((200, 200)), p1, p2, [[0, 5]])


def test_bad_images_and_saving(tmp_path):
    with pytest.raises(ValueError, match="image2 must be an"):
        draw_segments(np.zeros((10, 10, 2), np.uint8), _geom().segments([[1.0, 1.0]]))
    with pytest.raises(TypeError, match="image1 must be uint8, uint16 or float"):
        draw_points(np.zeros((10, 10), np.int64), [[1.0, 1.0]])
    with pytest.raises(TypeError, match="segments must be an EpipolarSegments"):
        draw_segments(np.zeros((10, 10), np.uint8), [[1.0, 1.0]])
    p = save_image(tmp_path / "sub" / "fig.png", np.zeros((5, 5, 3), np.uint8))
    assert p.is_file()
    with pytest.raises(ValueError, match="cannot write the extension '.unknown_ext'"):
        save_image(tmp_path / "fig.unknown_ext", np.zeros((5, 5, 3), np.uint8))
    # file-system errors say what they are (not "unknown extension")
    with pytest.raises(IsADirectoryError, match="is a folder"):
        save_image(tmp_path / "sub.png" if (tmp_path / "sub.png").mkdir() is None else None, np.zeros((5, 5), np.uint8))
    (tmp_path / "afile").write_text("x")
    with pytest.raises(NotADirectoryError, match="'.*afile' is a file"):
        save_image(tmp_path / "afile" / "fig.png", np.zeros((5, 5), np.uint8))
