"""Every input check of TwoViewGeometry, its constructors and EpipolarSegments.

Each bad argument must raise ValueError or TypeError with a message that names it.
"""

from __future__ import annotations

import numpy as np
import pytest

from episeg_cv import TwoViewGeometry

K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
R = np.eye(3)
T = np.array([1.0, 0.0, 0.2])
SIZE = (640, 480)
BAD = (ValueError, TypeError)


def make(**kw):
    args = dict(K1=K, K2=K, R=R, t=T, image_size1=SIZE, image_size2=SIZE)
    args.update(kw)
    return TwoViewGeometry(args.pop("K1"), args.pop("K2"), args.pop("R"), args.pop("t"), **args)


@pytest.fixture
def geom():
    return make()


def with_nan(a, idx=(0, 0), value=np.nan):
    a = np.array(a, dtype=float)
    a[idx] = value
    return a


def rot_x(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


# -- K1, K2 --------------------------------------------------------------------------------

BAD_K = {
    "shape (3, 4)": (np.zeros((3, 4)), ValueError),
    "shape (2, 2)": (np.eye(2), ValueError),
    "flat (9,)": (K.ravel(), ValueError),
    "NaN": (with_nan(K), ValueError),
    "inf": (with_nan(K, (0, 2), np.inf), ValueError),
    "lower entry": (with_nan(K, (1, 0), 1.0), ValueError),
    "last row [0, 0, 2]": (with_nan(K, (2, 2), 2.0), ValueError),
    "last row [0, 1, 1]": (with_nan(K, (2, 1), 1.0), ValueError),
    "last row [1, 0, 1]": (with_nan(K, (2, 0), 1.0), ValueError),
    "fx = 0 (singular)": (with_nan(K, (0, 0), 0.0), ValueError),
    "fx < 0": (with_nan(K, (0, 0), -500.0), ValueError),
    "fy < 0": (with_nan(K, (1, 1), -500.0), ValueError),
    "cx = 1e9 (ill-conditioned)": (with_nan(K, (0, 2), 1e9), ValueError),
    "fy = 0 (singular)": (with_nan(K, (1, 1), 0.0), ValueError),
    "string": ("K", TypeError),
    "None": (None, TypeError),
    "object dtype": (np.array([[1, 0, 0], [0, "a", 0], [0, 0, 1]], dtype=object), TypeError),
    "complex": (K.astype(complex), TypeError),
    "ragged": ([[1, 0, 0], [0, 1], [0, 0, 1]], ValueError),
}


@pytest.mark.parametrize("name", ["K1", "K2"])
@pytest.mark.parametrize("case", list(BAD_K))
def test_bad_K(name, case):
    value, exc = BAD_K[case]
    with pytest.raises(exc, match=name):
        make(**{name: value})


def test_K_errors_say_what_is_wrong():
    with pytest.raises(ValueError, match="positive focal lengths"):
        make(K1=with_nan(K, (1, 1), -500.0))
    with pytest.raises(ValueError, match=r"principal point \(1e\+09, 240\)"):
        make(K2=with_nan(K, (0, 2), 1e9))


# -- R -------------------------------------------------------------------------------------

BAD_R = {
    "shape (3,)": (np.ones(3), ValueError),
    "shape (4, 4)": (np.eye(4), ValueError),
    "NaN": (with_nan(R), ValueError),
    "inf": (with_nan(R, (1, 2), np.inf), ValueError),
    "reflection det -1": (np.diag([1.0, 1.0, -1.0]), ValueError),
    "reflection of a rotation": (-rot_x(30), ValueError),
    "scaled": (1.01 * R, ValueError),
    "non-orthonormal by 2e-3": (rot_x(20) + 2e-3 * np.array([[0, 1, 0], [0, 0, 0], [0, 0, 0]]), ValueError),
    "zero": (np.zeros((3, 3)), ValueError),
    "string": ("I", TypeError),
}


@pytest.mark.parametrize("case", list(BAD_R))
def test_bad_R(case):
    value, exc = BAD_R[case]
    with pytest.raises(exc, match="R"):
        make(R=value)


def test_R_within_tolerance_is_accepted():
    # an error of 1e-10 is used as given
    R = rot_x(20) + 1e-10 * np.array([[0, 1, 0], [0, 0, 0], [0, 0, 0]])
    np.testing.assert_array_equal(make(R=R).R, R)


@pytest.mark.parametrize("decimals", [3, 5, 8])
def test_rounded_rotations_are_repaired_and_logged(decimals, caplog):
    """Real calibration files are rounded: up to an error of 1e-3, R becomes the nearest rotation."""
    R = rot_x(20) @ np.array([[np.cos(0.7), 0, np.sin(0.7)], [0, 1, 0], [-np.sin(0.7), 0, np.cos(0.7)]])
    rounded = np.round(R, decimals)
    with caplog.at_level("INFO", logger="episeg_cv"):
        g = make(R=rounded)
    np.testing.assert_allclose(g.R.T @ g.R, np.eye(3), atol=1e-12)
    assert np.linalg.det(g.R) == pytest.approx(1.0, abs=1e-12)
    assert np.abs(g.R - R).max() < 10 ** -decimals  # the repair moves R by less than the rounding did
    assert "nearest rotation" in caplog.text


def test_real_calibrated_rotations_are_accepted():
    """dinoSparseRing (Middlebury): rotations orthonormal only to about 1e-6."""
    from pathlib import Path
    par = Path(__file__).resolve().parents[3] / "shared" / "data" / "dinoSparseRing" / "dinoSR_par.txt"
    if not par.is_file():
        pytest.skip("the shared real data is not next to this checkout")
    rows = [line.split() for line in par.read_text().splitlines()[1:] if line.strip()]
    for row in rows:
        R = np.array(row[10:19], dtype=float).reshape(3, 3)
        assert np.abs(R.T @ R - np.eye(3)).max() > 1e-9  # really rounded
        g = TwoViewGeometry.from_world_poses(K, R, [0, 0, 1], K, np.eye(3), [0, 0, 0], image_size1=SIZE,
                                             image_size2=SIZE)
        np.testing.assert_allclose(g.R.T @ g.R, np.eye(3), atol=1e-12)


# -- t -------------------------------------------------------------------------------------

@pytest.mark.parametrize("value, exc", [
    (np.ones(2), ValueError), (np.ones(4), ValueError), (np.ones((3, 3)), ValueError),
    (with_nan([1, 2, 3], 1), ValueError), (with_nan([1, 2, 3], 2, -np.inf), ValueError),
    ("abc", TypeError), (None, TypeError), ([1, [2, 3], 4], ValueError),
])
def test_bad_t(value, exc):
    with pytest.raises(exc, match="t"):
        make(t=value)


def test_t_column_vector_is_accepted():
    assert make(t=T.reshape(3, 1)).t.shape == (3,)


# -- image sizes ---------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["image_size1", "image_size2"])
@pytest.mark.parametrize("value, exc", [
    ((0, 480), ValueError), ((640, 0), ValueError), ((-640, 480), ValueError), ((640, -1), ValueError),
    ((640.5, 480), ValueError), ((640, 480.25), ValueError), ((np.inf, 480), ValueError),
    ((np.nan, 480), ValueError), ((640,), ValueError), ((640, 480, 3), ValueError), (640, ValueError),
    (None, ValueError), ("ab", ValueError), (("640", 480), TypeError), ((True, 480), TypeError),
])
def test_bad_image_size(name, value, exc):
    with pytest.raises(exc, match=name):
        make(**{name: value})


def test_integral_float_and_numpy_sizes_are_accepted():
    g = make(image_size1=(640.0, 480.0), image_size2=np.array([320, 240]))
    assert g.image_size1 == (640, 480) and g.image_size2 == (320, 240)
    assert all(type(v) is int for v in g.image_size1 + g.image_size2)


# -- alternative constructors --------------------------------------------------------------

@pytest.mark.parametrize("name, value", [
    ("K1", with_nan(K)), ("K2", np.eye(4)), ("R1", np.diag([1.0, -1.0, 1.0])), ("R2", 2 * np.eye(3)),
    ("t1", np.ones(4)), ("t2", with_nan(np.zeros(3), 0)), ("image_size1", (0, 1)), ("image_size2", (1.5, 2)),
])
def test_from_world_poses_bad(name, value):
    args = dict(K1=K, R1=R, t1=np.zeros(3), K2=K, R2=R, t2=T, image_size1=SIZE, image_size2=SIZE)
    args[name] = value
    with pytest.raises(BAD, match=name):
        TwoViewGeometry.from_world_poses(args.pop("K1"), args.pop("R1"), args.pop("t1"), args.pop("K2"),
                                         args.pop("R2"), args.pop("t2"), **args)


P_GOOD = K @ np.column_stack([R, T])


@pytest.mark.parametrize("value, exc", [
    (np.zeros((3, 3)), ValueError), (np.zeros((4, 4)), ValueError), (with_nan(P_GOOD), ValueError),
    (with_nan(P_GOOD, (2, 3), np.inf), ValueError), (np.zeros((3, 4)), ValueError),
    (np.column_stack([np.ones((3, 3)), np.ones(3)]), ValueError),  # singular left block: not a finite camera
    ("P", TypeError),
])
@pytest.mark.parametrize("name", ["P1", "P2"])
def test_from_projection_matrices_bad(name, value, exc):
    args = dict(P1=P_GOOD, P2=P_GOOD)
    args[name] = value
    with pytest.raises(exc, match=name):
        TwoViewGeometry.from_projection_matrices(args["P1"], args["P2"], image_size1=SIZE, image_size2=SIZE)


def test_from_projection_matrices_bad_size():
    with pytest.raises(ValueError, match="image_size2"):
        TwoViewGeometry.from_projection_matrices(P_GOOD, P_GOOD, image_size1=SIZE, image_size2=(0, 0))


# -- segments() ----------------------------------------------------------------------------

@pytest.mark.parametrize("value, exc", [
    (np.zeros(2), ValueError), (np.zeros((3, 3)), ValueError), (np.zeros((2, 2, 1)), ValueError),
    (with_nan(np.zeros((3, 2))), ValueError), (with_nan(np.zeros((3, 2)), (2, 1), np.inf), ValueError),
    ("points", TypeError), (None, TypeError), ([[1, 2], [3]], ValueError), (np.zeros((2, 2), dtype=complex), TypeError),
])
def test_segments_bad_points(geom, value, exc):
    with pytest.raises(exc, match="points1"):
        geom.segments(value)


PTS = np.array([[100.0, 100.0], [200.0, 300.0], [50.0, 400.0]])


@pytest.mark.parametrize("depth_range, exc, pattern", [
    ((-1.0, 5.0), ValueError, "depth_range zmin"),  # zmin < 0
    ((-1e-300, np.inf), ValueError, "depth_range zmin"),
    ((np.inf, np.inf), ValueError, "depth_range zmin"),
    ((2.0, 2.0), ValueError, "depth_range.*zmin < zmax"),  # zmin == zmax
    ((3.0, 2.0), ValueError, "depth_range.*zmin < zmax"),  # zmin > zmax
    ((0.0, -np.inf), ValueError, "depth_range.*zmin < zmax"),
    ((np.nan, 2.0), ValueError, "depth_range zmin"),
    ((0.0, np.nan), ValueError, "depth_range zmax"),
    ((np.array([0.0, np.nan, 1.0]), 5.0), ValueError, "depth_range zmin"),
    ((np.zeros(2), 5.0), ValueError, "depth_range zmin.*shape"),  # wrong length per-point bounds
    ((0.0, np.ones(4)), ValueError, "depth_range zmax.*shape"),
    ((np.zeros((3, 1)), 5.0), ValueError, "depth_range zmin.*shape"),
    ((np.array([0.0, 1.0, 2.0]), np.array([1.0, 1.0, 3.0])), ValueError, "depth_range.*zmin < zmax"),
    ((0.0,), ValueError, "depth_range"),
    ((0.0, 1.0, 2.0), ValueError, "depth_range"),
    (5.0, ValueError, "depth_range"),
    ("ab", ValueError, "depth_range"),
    (("0", 1.0), TypeError, "depth_range zmin"),
    ((0.0, None), TypeError, "depth_range zmax"),
])
def test_segments_bad_depth_range(geom, depth_range, exc, pattern):
    with pytest.raises(exc, match=pattern):
        geom.segments(PTS, depth_range=depth_range)


@pytest.mark.parametrize("depth_range", [(0, 5), (0.5, np.inf), (np.float32(0.25), np.int64(3)), (1, 2.5),
                                         (np.float64(2.0), np.float64(4.0))])
def test_scalar_depth_ranges_give_what_the_array_path_gives(depth_range):
    """Scalar bounds take a short path: the same 0-d float64 arrays as 0-d array bounds give."""
    from episeg_cv._validation import as_depth_range

    fast = as_depth_range(depth_range, 7)
    slow = as_depth_range(tuple(np.asarray(v) for v in depth_range), 7)
    for a, b in zip(fast, slow):
        assert a.shape == b.shape == () and a.dtype == b.dtype == np.float64 and a == b


@pytest.mark.parametrize("depth_range", [(True, 5.0), (0.0, False)])
def test_boolean_depth_bounds_are_refused(depth_range):
    from episeg_cv._validation import as_depth_range

    with pytest.raises(TypeError, match="depth_range z"):
        as_depth_range(depth_range, None)


@pytest.mark.parametrize("margin, exc", [
    (-1.0, ValueError), (-1e-9, ValueError), (np.nan, ValueError), (np.inf, ValueError),
    ("1", TypeError), (None, TypeError), (True, TypeError), (np.ones(2), TypeError),
])
def test_segments_bad_margin(geom, margin, exc):
    with pytest.raises(exc, match="margin"):
        geom.segments(PTS, margin=margin)


def test_segments_good_edge_values(geom):
    geom.segments(PTS, depth_range=(0, np.inf), margin=0)  # integers are fine
    geom.segments(PTS, depth_range=(np.zeros(3), np.full(3, np.inf)), margin=np.float32(2.5))
    geom.segments(PTS, depth_range=[0.5, 1e6])


# -- EpipolarSegments methods --------------------------------------------------------------

@pytest.mark.parametrize("method", ["distance", "line_distance", "classify"])
@pytest.mark.parametrize("value, exc", [
    (np.zeros((2, 2)), ValueError),  # not one point per segment
    (np.zeros((3, 3)), ValueError), (with_nan(np.zeros((3, 2))), ValueError), ("p", TypeError),
])
def test_paired_points_bad(geom, method, value, exc):
    seg = geom.segments(PTS)
    args = (value, 1.0) if method == "classify" else (value,)
    with pytest.raises(exc, match="points2"):
        getattr(seg, method)(*args)


@pytest.mark.parametrize("tol, exc", [(-1.0, ValueError), (np.nan, ValueError), ("1", TypeError), (None, TypeError)])
def test_classify_bad_tol(geom, tol, exc):
    with pytest.raises(exc, match="tol"):
        geom.segments(PTS).classify(PTS, tol)


@pytest.mark.parametrize("name, value", [
    ("points1", np.zeros(3)), ("depths", np.ones(2)), ("depths", np.nan), ("depths", np.ones((3, 1))),
])
def test_transfer_bad(geom, name, value):
    args = dict(points1=PTS, depths=1.0)
    args[name] = value
    with pytest.raises(ValueError, match=name):
        geom.transfer(args["points1"], args["depths"])
