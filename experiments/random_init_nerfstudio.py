"""The demo room in the nerfstudio layout without ``ply_file_path``: ``data.random_init=auto`` on it (issue 21).

Writes ``OUT/transforms.json`` (shared ``fl_x fl_y cx cy w h``, ``camera_model`` OPENCV with no distortion,
OpenGL camera-to-world matrices) and ``OUT/images/r_XXX.png`` for all 30 demo views, in the demo's order, so that
nerfstudio's every-8th hold-out picks the same 4 held-out views as the COLMAP demo and the Blender copy of
``random_init_blender.py``. Then, with defaults (random points along the rays, black background):

  python experiments/random_init_nerfstudio.py OUT
  cusgs-train data.path=OUT train.iterations=1500 features=none
"""

from __future__ import annotations

import json
import pathlib
import sys

import imageio.v3 as iio
import numpy as np

from cusgs_jax.config import DataConfig
from cusgs_jax.data.demo import demo_scene_path
from cusgs_jax.data.loader import load_scene


def main(out: str) -> None:
    scene = load_scene(demo_scene_path(), DataConfig(format="colmap"))
    out = pathlib.Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    K = scene.Ks[0].astype(np.float64)
    assert np.allclose(scene.Ks, scene.Ks[0])
    frames = []
    for i in range(scene.num_images):
        c2w = np.linalg.inv(scene.viewmats[i].astype(np.float64)) @ np.diag([1.0, -1.0, -1.0, 1.0])
        name = f"images/r_{i:03d}.png"
        iio.imwrite(out / name, scene.images[i])
        frames.append(dict(file_path=name, transform_matrix=c2w.tolist()))
    meta = dict(fl_x=K[0, 0], fl_y=K[1, 1], cx=K[0, 2], cy=K[1, 2], w=scene.width, h=scene.height,
                camera_model="OPENCV", frames=frames)
    (out / "transforms.json").write_text(json.dumps(meta))
    print(out)


if __name__ == "__main__":
    main(sys.argv[1])
