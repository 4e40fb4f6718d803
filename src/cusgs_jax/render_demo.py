"""``cusgs-render-demo``: render a built-in Gaussian scene from orbit cameras.

Until training exists this is the project's end-to-end job: it builds a small
room of flat Gaussians textured with photos that ship inside scikit-image
(no download), renders it from orbit cameras with :func:`cusgs_jax.rasterize`
and writes PNGs plus a contact sheet and a JSON summary.

    cusgs-render-demo --out outputs/render_demo --views 8
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import imageio.v3 as iio
import jax
import jax.numpy as jnp
import numpy as np
from skimage import data as skdata
from skimage.transform import resize
from tqdm import tqdm

from cusgs_jax.splat import check_inputs, rasterize


def _textured_plane(image, origin, axis_u, axis_v, size_u, size_v, spacing):
    """Flat Gaussians on a rectangle, coloured by ``image``.

    Returns means [n,3], quats [n,4], scales [n,3], colors [n,3].
    """
    nu, nv = max(int(size_u / spacing), 2), max(int(size_v / spacing), 2)
    tex = resize(image if image.ndim == 3 else np.stack([image] * 3, -1), (nv, nu), anti_aliasing=True)
    tex = np.asarray(tex[..., :3], np.float64)
    if tex.max() > 1.0:
        tex = tex / 255.0
    u = (np.arange(nu) + 0.5) / nu * size_u
    v = (np.arange(nv) + 0.5) / nv * size_v
    uu, vv = np.meshgrid(u, v)
    axis_u, axis_v = np.asarray(axis_u, float), np.asarray(axis_v, float)
    means = np.asarray(origin, float) + uu[..., None] * axis_u + vv[..., None] * axis_v
    normal = np.cross(axis_u, axis_v)
    rot = np.stack([axis_u, axis_v, normal], axis=1)  # columns: local x, y, z
    # rotation matrix → wxyz quaternion (rot is proper and well conditioned here)
    w = np.sqrt(max(1e-12, 1 + np.trace(rot))) / 2
    quat = np.array([w, (rot[2, 1] - rot[1, 2]) / (4 * w), (rot[0, 2] - rot[2, 0]) / (4 * w),
                     (rot[1, 0] - rot[0, 1]) / (4 * w)])
    n = nu * nv
    scales = np.tile([0.6 * spacing, 0.6 * spacing, 0.05 * spacing], (n, 1))
    return means.reshape(n, 3), np.tile(quat, (n, 1)), scales, tex.reshape(n, 3)


def demo_gaussians(spacing: float = 0.03) -> dict[str, np.ndarray]:
    """A room (floor, two walls) and a box, each face with its own photo.

    Returns float32 arrays means [G,3], quats [G,4], scales [G,3],
    opacities [G], colors [G,3].
    """
    planes = [
        (skdata.brick(), (-1.5, 1.0, -1.5), (1, 0, 0), (0, 0, 1), 3.0, 3.0),  # floor (y down)
        (skdata.astronaut(), (-1.5, -1.0, 1.5), (1, 0, 0), (0, 1, 0), 3.0, 2.0),  # back wall
        (skdata.coffee(), (-1.5, -1.0, -1.5), (0, 0, 1), (0, 1, 0), 3.0, 2.0),  # left wall
        (skdata.chelsea(), (-0.3, 0.4, -0.3), (1, 0, 0), (0, 1, 0), 0.6, 0.6),  # box front
        (skdata.rocket(), (-0.3, 0.4, -0.3), (0, 0, 1), (1, 0, 0), 0.6, 0.6),  # box top
    ]
    parts = [_textured_plane(img, o, u, v, su, sv, spacing) for img, o, u, v, su, sv in planes]
    means, quats, scales, colors = (np.concatenate(p) for p in zip(*parts))
    opacities = np.full(len(means), 0.9)
    return {k: v.astype(np.float32) for k, v in
            dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors).items()}


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """[4,4] world→camera matrix (OpenCV axes) of a camera at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(x, float) for x in (eye, target, up))
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rot = np.stack([right, down, forward])  # rows: camera axes in world
    view = np.eye(4)
    view[:3, :3] = rot
    view[:3, 3] = -rot @ eye
    return view


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="outputs/render_demo", help="output folder")
    parser.add_argument("--views", type=int, default=8, help="number of orbit views")
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    args = parser.parse_args(argv)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    scene = demo_gaussians()
    focal = 0.9 * args.width
    K = np.array([[focal, 0, args.width / 2], [0, focal, args.height / 2], [0, 0, 1]], np.float32)
    frames, times = [], []
    for i in tqdm(range(args.views), desc="rendering", unit="view"):
        angle = np.deg2rad(-25 + 80 * i / max(args.views - 1, 1))
        eye = (2.6 * np.sin(angle), -0.6 - 0.3 * np.cos(3 * angle), -2.6 * np.cos(angle) + 0.3)
        view = look_at(eye, (0.0, 0.2, 0.2)).astype(np.float32)
        check_inputs(*scene.values(), view, K, args.width, args.height)
        start = time.perf_counter()
        result = rasterize(*(jnp.asarray(v) for v in scene.values()), jnp.asarray(view), jnp.asarray(K),
                           args.width, args.height, background=jnp.full(3, 0.05))
        image = np.asarray(jax.block_until_ready(result.image))
        times.append(time.perf_counter() - start)
        if int(result.overflow):
            tqdm.write(f"view {i}: {int(result.overflow)} tile pairs overflowed; raise max_pairs")
        frame = (np.clip(image, 0, 1) * 255).astype(np.uint8)
        iio.imwrite(out / f"view_{i:03d}.png", frame)
        frames.append(frame)
    cols = min(4, len(frames))
    rows = -(-len(frames) // cols)
    sheet = np.zeros((rows * args.height, cols * args.width, 3), np.uint8)
    for i, frame in enumerate(frames):
        r, c = divmod(i, cols)
        sheet[r * args.height:(r + 1) * args.height, c * args.width:(c + 1) * args.width] = frame
    iio.imwrite(out / "contact_sheet.png", sheet)
    summary = dict(gaussians=int(len(scene["means"])), views=args.views, width=args.width, height=args.height,
                   first_render_s_including_compile=times[0],
                   median_render_s=float(np.median(times[1:])) if len(times) > 1 else None)
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary))
    print(f"wrote {len(frames)} views and contact_sheet.png to {out}")


if __name__ == "__main__":
    main()
