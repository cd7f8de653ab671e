"""A collection's images as COLMAP sees them: the stored pixel grid, EXIF orientation ignored.

COLMAP reads every image as it is stored and never applies the EXIF orientation tag, so that one
camera's intrinsics fit all its images whichever way up they were taken (colmap/colmap#1406,
#2104). The poses and cameras of a COLMAP model, a poses JSON written from one, or a calibration
file refer to that grid. OpenCV's ``cv2.imread`` applies the tag by default: a phone picture taken
upright would be turned by 90 degrees, its keypoints would lie in another grid than its pose, and a
square image would be matched wrongly with no error. Every image of a collection is read here.

Sizes are read from the file's header (Pillow, which opens a file lazily), not by decoding it: on
dinoSparseRing, decoding the 16 PNGs only for their sizes took 80 ms, longer than matching the
collection. Formats that Pillow cannot open fall back to OpenCV's decoder.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np

__all__ = ["read_grey", "image_size", "GREY"]

#: ``cv2.imread`` flags of a collection's images: 8-bit grey, EXIF orientation ignored.
GREY = cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION


def read_grey(path) -> np.ndarray | None:
    """The image at ``path`` as ``(H, W)`` uint8 grey in its stored grid, or None when OpenCV cannot read it.

    Examples
    --------
    >>> import tempfile, pathlib, cv2, numpy as np
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "a.png"
    >>> _ = cv2.imwrite(str(p), np.zeros((3, 5), np.uint8))
    >>> read_grey(p).shape, read_grey(p.with_name("missing.png")) is None
    ((3, 5), True)
    """
    return cv2.imread(str(path), GREY)


def image_size(path) -> tuple[int, int] | None:
    """``(width, height)`` of the image at ``path`` in its stored grid, or None when it cannot be read.

    From the file's header where Pillow knows the format (no pixel is decoded), else by decoding it
    with OpenCV. Either way the EXIF orientation is ignored, as in :func:`read_grey`.

    Examples
    --------
    >>> import tempfile, pathlib, cv2, numpy as np
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "a.png"
    >>> _ = cv2.imwrite(str(p), np.zeros((3, 5), np.uint8))
    >>> image_size(p), image_size(p.with_name("missing.png"))
    ((5, 3), None)
    """
    path = Path(path)
    if not path.is_file():
        return None
    from PIL import Image  # (a dependency of scikit-image, declared in pyproject.toml)

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # (DecompressionBombWarning: nothing is decoded here)
            with Image.open(path) as im:
                w, h = im.size
        if w > 0 and h > 0:
            return int(w), int(h)
    except Exception:  # noqa: BLE001 - any file Pillow cannot open (or refuses as too large): OpenCV decides
        pass
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)  # (IMREAD_UNCHANGED never applies the orientation)
    return None if image is None else (int(image.shape[1]), int(image.shape[0]))
