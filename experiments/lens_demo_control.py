"""Control for the lens-demo comparison (issue 21, ``lens_demo.sh``): is a distorted run's PSNR moved by
the undistortion's resampling or by the smaller, cropped view?

For each distorted lens, writes ``OUT/sharp_<lens>/``: a PINHOLE COLMAP scene with exactly the camera, size,
poses and points the loader gives for ``data.demo.lens=<lens>`` (COLMAP's undistorted camera), whose
images are ray cast straight through that pinhole camera (2×2 supersampled, like every demo image)
instead of being resampled from the lens images. Training on it (``data.path=OUT/sharp_<lens>``) differs
from the lens run only in the resampling blur. Also writes ``OUT/target_blur.json``: per lens, the PSNR
of the loader's undistorted images against these sharp renders (how far the undistortion moves the
targets) and a sharpness ratio (mean |horizontal gradient|, undistorted / sharp).

    PYTHONPATH=src python experiments/lens_demo_control.py [OUT]
"""

from __future__ import annotations

import json
import pathlib
import shutil
import sys
import warnings

import imageio.v3 as iio
import numpy as np
import pycolmap

from cusgs_jax.config import DataConfig
from cusgs_jax.data.demo.lens import lens_demo_path, render_lens_view
from cusgs_jax.data.demo.render import build_scene
from cusgs_jax.data.loader import load_scene
from cusgs_jax.data.undistort import undistorted_cameras


def sharp_scene(lens: str, out: pathlib.Path) -> dict:
    """Write ``out`` (module docstring) and return the target-blur numbers for ``lens``."""
    src = lens_demo_path(lens=lens)
    rec = pycolmap.Reconstruction(str(src / "sparse" / "0"))
    (cid, lens_cam), = rec.cameras.items()
    pin = undistorted_cameras({cid: lens_cam})[cid]
    loaded = load_scene(src, DataConfig(format="colmap", holdout_every=0))  # the undistorted images, in name order
    room = build_scene()
    if out.exists():
        shutil.rmtree(out)
    (out / "images").mkdir(parents=True)
    psnr, grad = [], []
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        pose = image.cam_from_world()
        sharp, *_ = render_lens_view(room, pose.rotation.matrix(), pose.translation, pin)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            iio.imwrite(out / "images" / image.name, sharp)
        undist = loaded.images[loaded.names.index(image.name)].astype(np.float64)
        mse = np.mean((undist - sharp) ** 2)
        psnr.append(float(10 * np.log10(255.0**2 / mse)))
        grad.append(np.abs(np.diff(undist, axis=1)).mean() / np.abs(np.diff(sharp.astype(float), axis=1)).mean())
    rec.cameras[cid] = pycolmap.Camera(camera_id=cid, model="PINHOLE", width=pin.width, height=pin.height,
                                       params=list(pin.params))
    (out / "sparse" / "0").mkdir(parents=True)
    rec.write(str(out / "sparse" / "0"))
    return dict(lens=lens, camera=[int(pin.width), int(pin.height), [float(p) for p in pin.params]],
                psnr_undistorted_vs_sharp_db=round(float(np.mean(psnr)), 3),
                psnr_min_db=round(min(psnr), 3), gradient_ratio=round(float(np.mean(grad)), 4))


def main(argv: list[str]) -> None:
    out = pathlib.Path(argv[0] if argv else "experiments/results/lens_demo/control")
    results = [sharp_scene(lens, out / f"sharp_{lens}") for lens in ("opencv", "simple_radial")]
    (out / "target_blur.json").write_text(json.dumps(results, indent=1) + "\n")
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main(sys.argv[1:])
