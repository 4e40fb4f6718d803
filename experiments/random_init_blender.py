"""Does the growing schedule reach a good model from random initial points? (issue 21)

Writes the built-in demo room in the Blender / NeRF-synthetic layout (transforms_train.json with its
26 training views, transforms_test.json with the 4 held-out ones, camera_angle_x, OpenGL
camera-to-world matrices, RGB PNGs; no points), so that a run starts from `data.random_points`
uniform points instead of the SfM points, with everything else equal. Then compare the held-out
PSNR with the COLMAP run of the same scene (`experiments/issue20_psnr.sh`'s sparse runs).

  python experiments/random_init_blender.py OUT_SCENE
  cusgs-train data.path=OUT_SCENE splat.background=[0,0,0] train.iterations=1500 features=none ...
"""

from __future__ import annotations

import json
import math
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
    fx, cx, cy = float(scene.Ks[0, 0, 0]), float(scene.Ks[0, 0, 2]), float(scene.Ks[0, 1, 2])
    assert np.allclose(scene.Ks[:, 0, 0], scene.Ks[:, 1, 1]) and (cx, cy) == (scene.width / 2, scene.height / 2)
    angle_x = 2 * math.atan(0.5 * scene.width / fx)
    for split, indices in (("train", scene.train_indices), ("test", scene.test_indices)):
        (out / split).mkdir(parents=True, exist_ok=True)
        frames = []
        for i in indices:
            c2w = np.linalg.inv(scene.viewmats[i].astype(np.float64)) @ np.diag([1.0, -1.0, -1.0, 1.0])
            name = f"r_{i:03d}"
            iio.imwrite(out / split / f"{name}.png", scene.images[i])
            frames.append(dict(file_path=f"./{split}/{name}", transform_matrix=c2w.tolist()))
        (out / f"transforms_{split}.json").write_text(json.dumps(dict(camera_angle_x=angle_x, frames=frames)))
    print(out)


if __name__ == "__main__":
    main(sys.argv[1])
