"""Render the default synthetic pair shipped in ``data/default/``.

Run from anywhere (rerunning overwrites the files with identical content):

    python data/make_default_pair.py

Writes, beside this script:

- ``default/image1.png``, ``default/image2.png``: grey 640 x 480 renders of the
  ``forward`` case of :func:`episeg_cv.scenes.pose_suite` (the epipole is in
  image 2, the case where the correct segment helps most);
- ``default/depth.npz``: ``depth1`` and ``depth2``, float32 ``z`` in each camera
  in metres (``inf`` where nothing is seen), compressed;
- ``default/calib.json``: ``K1``, ``K2``, ``R``, ``t`` (``X2 = R X1 + t``, metres),
  ``image_size1``, ``image_size2`` (``[width, height]``) and the case's name and seed.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from episeg_cv.scenes import make_pair, pose_suite

CASE = "forward"
IMAGE_SIZE = (640, 480)


def main(out_dir: Path = Path(__file__).resolve().parent / "default") -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    pair = make_pair(CASE, IMAGE_SIZE)
    g = pair.geometry_true
    cv2.imwrite(str(out_dir / "image1.png"), pair.image1)
    cv2.imwrite(str(out_dir / "image2.png"), pair.image2)
    np.savez_compressed(out_dir / "depth.npz", depth1=pair.depth1.astype(np.float32), depth2=pair.depth2.astype(np.float32))
    calib = {
        "name": f"synthetic room, pose case '{CASE}'",
        "case": CASE,
        "seed": pose_suite()[CASE].seed,
        "convention": "X2 = R X1 + t; pixel centres at integer coordinates; depth = z in the camera, metres",
        "K1": g.K1.tolist(),
        "K2": g.K2.tolist(),
        "R": g.R.tolist(),
        "t": g.t.tolist(),
        "image_size1": list(g.image_size1),
        "image_size2": list(g.image_size2),
        "depth_unit": "m",
    }
    (out_dir / "calib.json").write_text(json.dumps(calib, indent=2) + "\n")
    print(f"wrote {out_dir}: {sorted(p.name for p in out_dir.iterdir())}")


if __name__ == "__main__":
    main()
