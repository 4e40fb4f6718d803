"""SfM-like points and their observations for the demo room, written as a COLMAP model
(:mod:`cusgs_jax.data.demo`).

Points are sampled from the rendered depth maps (pixel centres back-projected), observations are
decided by exact ray casting plus agreement with the depth / face maps, and the model is written
with pycolmap (imported lazily). Poses are world->camera ``(R, t)``, ``K = (fx, fy, cx, cy)``.
"""

from __future__ import annotations

import numpy as np

from cusgs_jax.data.demo.render import cast_rays, surface_colour

__all__ = ["observe", "sample_points", "write_colmap", "write_sfm_model"]

# An observation of a sampled point is kept only if the depth map (pixel-centre ray) at the pixel
# it projects into agrees with the point's depth to this relative tolerance. Occlusion itself is
# decided exactly by ray casting; this only drops observations whose pixel centre sees another
# surface (occlusion edges) or sees the same surface at an extreme grazing angle.
_OBS_DEPTH_RTOL = 1e-2


def sample_points(poses, K, depths, face_maps, num_points, seed):
    """Surface points where the cameras look, like an SfM point cloud.

    Draws ``num_points`` (view, pixel) pairs uniformly among the pixels that
    show a surface and back-projects each pixel centre with its depth, so every
    surface gets points in proportion to how much it is seen (a surface seen
    only at image edges still gets some), and every point lies exactly on the
    face it came from.

    Returns:
      (xyz [P, 3], face [P]).
    """
    rng = np.random.default_rng([seed, 1])
    fx, fy, cx, cy = K
    faces = np.stack(face_maps)  # [V, H, W]
    candidates = np.flatnonzero(faces.reshape(-1) >= 0)
    pick = rng.choice(candidates, size=min(num_points, len(candidates)), replace=False)
    view, rest = np.divmod(pick, faces.shape[1] * faces.shape[2])
    row, col = np.divmod(rest, faces.shape[2])
    z = np.stack(depths)[view, row, col].astype(np.float64)
    cam = np.stack([(col + 0.5 - cx) / fx * z, (row + 0.5 - cy) / fy * z, z], axis=-1)
    xyz = np.empty_like(cam)
    for v in np.unique(view):
        R, t = poses[v]
        sel = view == v
        xyz[sel] = (cam[sel] - t) @ R  # R^T (p_c - t)
    return xyz, faces[view, row, col]


def observe(scene, xyz, face, poses, K, width, height, depths, face_maps):
    """Which views see which points, and where.

    A point is observed in a view when it projects inside the image, the first surface along the
    camera ray towards it is the point itself (exact ray cast), and the centre ray of the pixel
    it falls in hits the same face at nearly the same depth (relative _OBS_DEPTH_RTOL), so every
    keypoint is consistent with the depth and object-id maps at its pixel.
    Returns visible [V, P] bool and pixel coordinates xy [V, P, 2] (COLMAP convention).
    """
    fx, fy, cx, cy = K
    V, N = len(poses), xyz.shape[0]
    visible = np.zeros((V, N), bool)
    xy = np.zeros((V, N, 2))
    for v, (R, t) in enumerate(poses):
        pc = xyz @ R.T + t
        z = pc[:, 2]
        front = z > 1e-6
        zs = np.where(front, z, 1.0)
        u = fx * pc[:, 0] / zs + cx
        w = fy * pc[:, 1] / zs + cy
        xy[v, :, 0], xy[v, :, 1] = u, w
        inimg = front & (u >= 0) & (u < width) & (w >= 0) & (w < height)
        idx = np.flatnonzero(inimg)
        if idx.size == 0:
            continue
        centre = -R.T @ t
        d = (xyz[idx] - centre) / z[idx, None]  # camera z = 1 -> t equals the depth
        th, fh = cast_rays(scene, centre, d)
        ok = (fh == face[idx]) & (np.abs(th - z[idx]) <= 1e-6 * z[idx])
        col = np.clip(np.floor(u[idx]).astype(np.int64), 0, width - 1)
        row = np.clip(np.floor(w[idx]).astype(np.int64), 0, height - 1)
        ok &= face_maps[v][row, col] == face[idx]
        dm = depths[v][row, col].astype(np.float64)
        ok &= np.abs(dm - z[idx]) <= _OBS_DEPTH_RTOL * z[idx]
        visible[v, idx[ok]] = True
    return visible, xy


def write_colmap(sparse_dir, poses, K, width, height, names, xyz, colours, visible, xy, lens=None):
    """Write the demo views and points as a COLMAP binary model into ``sparse_dir``.

    One camera: PINHOLE ``K``, or ``lens = (COLMAP model name, params)`` (e.g. ``("OPENCV",
    [fx, fy, cx, cy, k1, k2, p1, p2])``) when given; image v (id v + 1, named ``names[v]``) with pose ``poses[v]``
    and as keypoints ``xy[v]`` of the points it sees (in point order), and every point p with
    ``xyz[p]`` [P, 3], ``colours[p]`` uint8 [P, 3] and the track of views where ``visible``
    [V, P] bool. Returns the pycolmap Reconstruction.
    """
    import pycolmap

    rec = pycolmap.Reconstruction()
    model, params = lens if lens is not None else ("PINHOLE", K)
    cam = pycolmap.Camera(model=model, width=width, height=height,
                          params=[float(k) for k in params], camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    # point2D index of point p in view v (points are listed in increasing point order).
    obs_idx = np.cumsum(visible, axis=1) - 1
    for v, (R, t) in enumerate(poses):
        kp = xy[v, visible[v]]
        img = pycolmap.Image(name=names[v], keypoints=np.ascontiguousarray(kp, np.float64),
                             camera_id=1, image_id=v + 1)
        pose = pycolmap.Rigid3d(rotation=pycolmap.Rotation3d(np.ascontiguousarray(R)),
                                translation=np.asarray(t, np.float64))
        rec.add_image_with_trivial_frame(img, pose)
    for p in range(xyz.shape[0]):
        track = pycolmap.Track()
        for v in np.flatnonzero(visible[:, p]):
            track.add_element(int(v + 1), int(obs_idx[v, p]))
        rec.add_point3D(xyz[p], track, colours[p])  # also links the images' points2D
    if hasattr(rec, "update_point_3d_errors"):
        rec.update_point_3d_errors()
    sparse_dir.mkdir(parents=True, exist_ok=True)
    rec.write(str(sparse_dir))
    return rec


def write_sfm_model(sparse_dir, scene, poses, K, width, height, names, depths, face_maps, num_points, seed,
                    lens=None):
    """Sample ``num_points`` surface points, keep those observed in ≥ 2 views, colour them and write
    the COLMAP model into ``sparse_dir`` (the SfM stand-in of every demo scene).

    Points and observations come from the pinhole camera ``K`` and its ``depths`` / ``face_maps``
    [V, H, W]. With ``lens = (COLMAP model name, params)`` the model's camera is that lens instead
    and every keypoint is the lens's projection of its point (``img_from_cam``; it may then lie
    just outside the image, where the lens sees less than the pinhole): the same points and
    tracks, seen through another camera (:mod:`cusgs_jax.data.demo.lens`).

    Returns:
      (xyz [P, 3] kept points, visible [V, P] bool observations).
    """
    xyz, face = sample_points(poses, K, depths, face_maps, num_points, seed)
    visible, xy = observe(scene, xyz, face, poses, K, width, height, depths, face_maps)
    keep = visible.sum(axis=0) >= 2
    xyz, face, visible, xy = xyz[keep], face[keep], visible[:, keep], xy[:, keep]
    colours = np.round(np.clip(surface_colour(scene, xyz, face), 0, 1) * 255).astype(np.uint8)
    if lens is not None:
        xy = _lens_keypoints(lens, width, height, poses, xyz, visible, xy)
    write_colmap(sparse_dir, poses, K, width, height, names, xyz, colours, visible, xy, lens)
    return xyz, visible


def _lens_keypoints(lens, width, height, poses, xyz, visible, xy):
    """``xy`` [V, P, 2] with the observed entries (``visible`` [V, P]) replaced by the projections of
    ``xyz`` [P, 3] through the lens ``(model, params)`` (pycolmap ``img_from_cam``)."""
    import pycolmap

    cam = pycolmap.Camera(model=lens[0], width=width, height=height, params=[float(k) for k in lens[1]])
    xy = xy.copy()
    for v, (R, t) in enumerate(poses):
        if visible[v].any():
            xy[v, visible[v]] = cam.img_from_cam(xyz[visible[v]] @ R.T + t)
    return xy
