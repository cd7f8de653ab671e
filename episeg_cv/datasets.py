"""Ready-made image pairs with calibration and ground truth.

- :func:`load_default_pair`: the synthetic pair shipped in ``data/default``
  (rendered by ``data/make_default_pair.py``; no rendering at load time).
- :func:`load_motorcycle`: the real Middlebury 2014 "Motorcycle" pair shipped
  by scikit-image (``skimage.data.stereo_motorcycle``; no network), with the
  calibration in ``data/motorcycle/calib.json``.

Both return an :class:`~episeg_cv.evaluation.ImagePair`, whose
:meth:`~episeg_cv.evaluation.ImagePair.ground_truth` gives the true match of
every keypoint.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from .evaluation import ImagePair
from .io import load_calibration

__all__ = ["data_dir", "load_default_pair", "load_motorcycle"]


def data_dir() -> Path:
    """The directory of the shipped data files.

    ``episeg_cv/_data`` inside an installed wheel (the build copies the
    repository's ``data/`` there), otherwise the repository's ``data/``
    (source checkout or editable install).

    Raises
    ------
    FileNotFoundError
        Neither exists.

    Examples
    --------
    >>> (data_dir() / "default" / "calib.json").is_file()
    True
    """
    here = Path(__file__).resolve().parent
    for d in (here / "_data", here.parent / "data"):
        if (d / "default" / "calib.json").is_file():
            return d
    raise FileNotFoundError(f"episeg_cv data files not found in {here / '_data'} or {here.parent / 'data'}")


def _read_grey(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise FileNotFoundError(f"cannot read image {path}")
    return img


def load_default_pair() -> ImagePair:
    """The default synthetic pair: the ``forward`` case of the pose suite at 640 x 480.

    Returns
    -------
    ImagePair
        ``image1, image2`` (480, 640) uint8; ``depth1, depth2`` (480, 640)
        float64 ``z`` in metres (``inf`` where nothing is seen); ``geometry``
        and ``geometry_true`` (the same, exact) with ``X2 = R X1 + t``;
        ``ground_truth(points1, points2)`` with a 3 px radius.

    Examples
    --------
    >>> pair = load_default_pair()
    >>> pair.image1.shape, pair.image1.dtype.name, pair.geometry.image_size2
    ((480, 640), 'uint8', (640, 480))
    """
    d = data_dir() / "default"
    geom = load_calibration(d / "calib.json").geometry
    case = json.loads((d / "calib.json").read_text()).get("case", "synthetic")  # (the name of the render)
    with np.load(d / "depth.npz") as z:
        depth1 = z["depth1"].astype(np.float64)
        depth2 = z["depth2"].astype(np.float64)
    return ImagePair(f"default ({case})", _read_grey(d / "image1.png"), _read_grey(d / "image2.png"),
                     geom, geom, depth1, depth2, None, 3.0)


def load_motorcycle() -> ImagePair:
    """Middlebury 2014 "Motorcycle", 741 x 500, rectified, with ground-truth disparity.

    Images from ``skimage.data.stereo_motorcycle()`` (bundled with
    scikit-image), converted to grey. Calibration (``data/motorcycle/calib.json``):
    ``f = 994.978``, ``cx = 311.193`` (right: ``+ 31.086``), ``cy = 254.877``,
    ``R = I``, ``t = (-193.001, 0, 0)`` mm.

    The disparity is indexed by the **left** pixel: ``x_R = x_L - disp[y_L, x_L]``
    (on SIFT matches the median error is about 0.16 px this way and about
    1.07 px the other way; see ``tests/test_datasets.py``).

    Returns
    -------
    ImagePair
        ``image1`` (left), ``image2`` (right): (500, 741) uint8;
        ``disparity`` (500, 741) float32, ``inf`` where unknown; ``depth1``
        ``= f B / (disp + 31.086)`` in mm (``inf`` where unknown);
        ``depth2`` None; ``ground_truth(points1, points2)`` with a 2 px radius.

    Examples
    --------
    >>> pair = load_motorcycle()
    >>> pair.image1.shape, pair.t.tolist()
    ((500, 741), [-193.001, 0.0, 0.0])
    """
    import skimage.data

    left, right, disp = skimage.data.stereo_motorcycle()
    geom = load_calibration(data_dir() / "motorcycle" / "calib.json").geometry
    disp = np.asarray(disp, dtype=np.float32).copy()
    disp[~np.isfinite(disp)] = np.inf
    f = geom.K1[0, 0]
    baseline = float(np.linalg.norm(geom.t))
    doffs = geom.K2[0, 2] - geom.K1[0, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        depth1 = np.where(np.isfinite(disp), f * baseline / (disp.astype(np.float64) + doffs), np.inf)
    return ImagePair("motorcycle", cv2.cvtColor(left, cv2.COLOR_RGB2GRAY), cv2.cvtColor(right, cv2.COLOR_RGB2GRAY),
                     geom, geom, depth1, None, disp, 2.0)
