"""``data.undistort`` for the layouts with lens distortion (COLMAP, nerfstudio): one rule for both.

Given the views' pycolmap cameras, :func:`frame_cameras` decides in which camera frame the images
are read (``config.CAMERA_FRAMES``):

* no camera is distorted — the cameras as they are;
* ``lens`` — the cameras as captured, with the per-view lenses the splatter renders through
  (:func:`cusgs_jax.data.lenses.scene_lens`);
* ``crop`` / ``mask`` — every distorted camera checked undistortable first (a folding lens or a
  fisheye past 90° is refused before any work: :func:`cusgs_jax.data.lenses.check_undistortable`),
  the source cameras checked to share one size (COLMAP's undistorter makes one common size from
  them), then the undistorted PINHOLE cameras (no I/O) and the layout's function that undistorts
  the images into the cache on first use (:mod:`cusgs_jax.data.undistort`).
"""

from __future__ import annotations

import functools
import pathlib
from typing import Any, Callable, NamedTuple

from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.lenses import SceneLens, check_undistortable, scene_lens
from cusgs_jax.data.undistort import needs_undistortion, undistorted_cameras

__all__ = ["FramedCameras", "frame_cameras"]


class FramedCameras(NamedTuple):
    """The cameras the images are read with, and how.

    Attributes:
      cameras: {camera id: pycolmap.Camera} — as given, or undistorted PINHOLE (crop / mask).
      undistorted: for crop / mask, ``() -> folder`` whose ``images/`` hold the undistorted images
        (undistorting them on the first call only); else None.
      lens: for ``lens`` with a distorted camera, the per-view lenses; else None.
    """

    cameras: dict[int, Any]
    undistorted: Callable[[], pathlib.Path] | None
    lens: SceneLens | None


def frame_cameras(cameras: dict[int, Any], view_cameras: list[int], where: dict[int, str], view_where: list[str],
                  mode: str, undistort_images: Callable[[], pathlib.Path], source) -> FramedCameras:
    """The views' cameras in the frame ``mode`` (``data.undistort``) asks for (module rules).

    Args:
      cameras: {camera id: pycolmap.Camera} of the views.
      view_cameras: [V] each view's camera id.
      where, view_where: how a message names a camera ({id: "camera 3 in …/cameras.bin"}) and a view's camera.
      mode: "crop", "mask" or "lens".
      undistort_images: the layout's ``() -> folder`` running :func:`cusgs_jax.data.undistort.undistorted_images`.
      source: the file the cameras come from (named when their sizes differ).
    Raises:
      SceneError: a lens that cannot be kept or undistorted, or distorted cameras of several sizes.
    """
    if not any(needs_undistortion(camera) for camera in cameras.values()):
        return FramedCameras(cameras, None, None)
    if mode == "lens":
        return FramedCameras(cameras, None, scene_lens([cameras[cid] for cid in view_cameras], view_where))
    for cid, camera in cameras.items():
        if needs_undistortion(camera):  # a folding lens, or a fisheye past 90°: refused before any work
            check_undistortable(camera, where[cid], mode)
    sizes = {cid: (int(camera.width), int(camera.height)) for cid, camera in cameras.items()}
    first = next(iter(sizes))
    other = next((cid for cid in sizes if sizes[cid] != sizes[first]), None)
    if other is not None:
        (w0, h0), (w1, h1) = sizes[first], sizes[other]
        raise SceneError(
            f"the cameras of {source} do not share one size ({where[first]} is {w0}x{h0}, {where[other]} {w1}x{h1}), "
            f"and data.undistort={mode} undistorts them to one common size: resize/crop the images to one size "
            "(and their cameras with them), or keep them as captured with data.undistort=lens")
    return FramedCameras(undistorted_cameras(cameras, mode=mode), functools.cache(undistort_images), None)
