"""A collection's images in their stored grid (:mod:`episeg_cv.colmap.images`): EXIF orientation ignored,
sizes from the header."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from PIL import Image

from episeg_cv import colmap, scenes
from episeg_cv.colmap.images import image_size, read_grey

ORIENTATION = 0x0112  # the EXIF tag


def _texture(h, w, seed=0):
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 2).astype(np.uint8)


def _jpeg(path, pixels, orientation=None):
    exif = Image.Exif()
    if orientation is not None:
        exif[ORIENTATION] = orientation
    Image.fromarray(pixels).save(path, quality=95, exif=exif.tobytes())
    return path


def test_exif_orientation_is_ignored_where_opencv_applies_it(tmp_path):
    """cv2 reference: OpenCV's default read turns a picture tagged 'rotate 90' (6); the stored grid does not."""
    pixels = _texture(30, 40)
    tagged, plain = _jpeg(tmp_path / "t.jpg", pixels, 6), _jpeg(tmp_path / "p.jpg", pixels)
    assert cv2.imread(str(tagged), cv2.IMREAD_GRAYSCALE).shape == (40, 30)  # what we must not do
    assert image_size(tagged) == (40, 30) and read_grey(tagged).shape == (30, 40)
    np.testing.assert_array_equal(read_grey(tagged), cv2.imread(str(plain), cv2.IMREAD_GRAYSCALE))


def test_square_tagged_image_is_not_turned(tmp_path):
    """The silent case: a square image turned keeps its size, so only the pixels tell."""
    pixels = _texture(32, 32, seed=1)
    tagged, plain = _jpeg(tmp_path / "t.jpg", pixels, 8), _jpeg(tmp_path / "p.jpg", pixels)
    assert not np.array_equal(cv2.imread(str(tagged), cv2.IMREAD_GRAYSCALE), read_grey(tagged))
    np.testing.assert_array_equal(read_grey(tagged), read_grey(plain))


@settings(max_examples=15, deadline=None)
@given(w=st.integers(1, 90), h=st.integers(1, 90), ext=st.sampled_from([".png", ".jpg", ".tif", ".bmp", ".webp"]))
def test_header_size_is_the_decoded_size(tmp_path_factory, w, h, ext):
    """Property: the header's size is OpenCV's decoded shape, for every format a collection may use."""
    path = tmp_path_factory.mktemp("img") / f"a{ext}"
    assert cv2.imwrite(str(path), _texture(h, w))
    decoded = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image_size(path) == (decoded.shape[1], decoded.shape[0]) == (w, h)


def test_formats_pillow_cannot_open_fall_back_to_opencv(tmp_path, monkeypatch):
    path = tmp_path / "a.png"
    cv2.imwrite(str(path), np.zeros((7, 9), np.uint8))

    def refuse(*args, **kwargs):
        raise OSError("cannot identify image file")

    monkeypatch.setattr(Image, "open", refuse)
    assert image_size(path) == (9, 7)


@pytest.mark.parametrize("make", [lambda d: d / "missing.png", lambda d: d, lambda d: _text(d / "not.png")])
def test_unreadable_gives_none(tmp_path, make):
    path = make(tmp_path)
    assert image_size(path) is None and read_grey(path) is None


def _text(path):
    path.write_text("not an image")
    return path


def test_par_collection_of_tagged_jpegs_is_read_in_the_stored_grid(tmp_path):
    """End to end: a Middlebury camera file over portrait-tagged JPEGs; sizes and features use the stored
    grid (before, the features step refused the image: '120x160, but its camera says 160x120')."""
    K = np.array([[150.0, 0, 79.5], [0, 150.0, 59.5], [0, 0, 1]])
    R, t = scenes.look_at([1.0, 0, -3], [0, 0, 0])
    lines = []
    for k, (name, Rk, tk) in enumerate([("a.jpg", np.eye(3), [0, 0, 3]), ("b.jpg", R, t)]):
        _jpeg(tmp_path / name, _texture(120, 160, seed=k), 6)
        lines.append(" ".join([name] + [repr(float(v)) for v in np.concatenate([K.ravel(), np.ravel(Rk), tk])]))
    (tmp_path / "set_par.txt").write_text("\n".join(lines) + "\n")
    views = colmap.load_par(tmp_path / "set_par.txt", tmp_path)
    assert [v.image_size for v in views] == [(160, 120), (160, 120)]
    store = colmap.FeatureStore(tmp_path / "cache", tmp_path)
    n, _ = store.ensure(views[0])
    kp = store.keypoints(views[0])
    assert n > 10 and kp.shape == (n, 2) and kp[:, 0].max() > 120  # only the stored grid is this wide
