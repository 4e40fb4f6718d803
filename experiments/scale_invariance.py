"""Scale invariance on the demo scene: the same capture as SfM might have reconstructed it ×1000 and ×0.001.

Writes copies of the built-in demo scene whose COLMAP model is moved by a
similarity transform (pycolmap ``Reconstruction.transform``; images and
everything else unchanged), trains each with default settings as a user scene
(``cusgs-train data.path=...``, one Hydra sweep, jobs one after another), and
runs ``cusgs-report`` on the sweep. Prints the held-out PSNR of each run and its
difference to the unscaled scene as JSON.

    python experiments/scale_invariance.py                       # scales 1, 1000, 0.001; default iterations
    python experiments/scale_invariance.py --iterations 1000 --out multirun/scale_invariance/quick
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys
import time

from cusgs_jax.data.demo import demo_scene_path
from cusgs_jax.run_folder import read_eval
from cusgs_jax.testing.scenes import transformed_scene


def scenes(root: pathlib.Path, scales: list[float]) -> dict[float, pathlib.Path]:
    """{scale: scene folder}; scale 1 is the demo scene itself, others moved copies (made once)."""
    demo = pathlib.Path(demo_scene_path())
    out = {}
    for scale in scales:
        if scale == 1.0:
            out[scale] = demo
            continue
        folder = root / f"demo_x{scale:g}"
        if not (folder / "sparse" / "0").is_dir():
            # a far-off origin too: COLMAP models are rarely centred
            transformed_scene(demo, folder, scale=scale, translation=(7.0 * scale, -4.0 * scale, 3.0 * scale))
        out[scale] = folder
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scales", type=float, nargs="+", default=[1.0, 1000.0, 0.001])
    parser.add_argument("--iterations", type=int, default=None, help="default: the config's train.iterations")
    parser.add_argument("--scenes", type=pathlib.Path, default=pathlib.Path.home() / ".cache/cusgs_jax/scale_invariance")
    parser.add_argument("--out", type=pathlib.Path, default=None, help="sweep folder (default multirun/scale_invariance/<time>)")
    args = parser.parse_args(argv)

    folders = scenes(args.scenes, args.scales)
    sweep = args.out or pathlib.Path("multirun/scale_invariance") / time.strftime("%Y-%m-%d_%H-%M-%S")
    bin_dir = pathlib.Path(sys.executable).parent
    cmd = [str(bin_dir / "cusgs-train"), "-m", "data.path=" + ",".join(str(folders[s]) for s in args.scales),
           f"hydra.sweep.dir={sweep}", "train.progress=false"]
    if args.iterations:
        cmd.append(f"train.iterations={args.iterations}")
    subprocess.run(cmd, check=True)
    subprocess.run([str(bin_dir / "cusgs-report"), str(sweep)], check=True)

    runs = {}
    for job, scale in enumerate(args.scales):
        result = read_eval(sweep / str(job)).to_json()  # the run-folder contract (cusgs_jax/run_folder.py)
        runs[f"{scale:g}"] = dict(psnr=result["psnr"], ssim=result["ssim"], alive_anchors=result["alive_anchors"],
                                  voxel_size=result["voxel_size"], world_scale=result["world_transform"]["scale"],
                                  iterations=result["iterations"], train_wall_s=result["train_wall_s"])
    base = runs[f"{args.scales[0]:g}"]["psnr"]
    for row in runs.values():
        row["psnr_minus_unscaled"] = row["psnr"] - base
    summary = dict(sweep=str(sweep), command=" ".join(cmd), runs=runs)
    (sweep / "scale_invariance.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
