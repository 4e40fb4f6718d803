"""The lens of a distorted COLMAP camera, for rasterising through it (``data.undistort=lens``).

:func:`lens_of_camera` turns a pycolmap camera into the coefficients and the trusted box of
:class:`cusgs_jax.splat.lens.Lens`; :func:`scene_lens` stacks them per view. The box is computed
with COLMAP's own projection functions (``Camera.cam_from_img`` / ``img_from_cam``), independent of
the JAX lens code, so a mistake in either shows up as a disagreement in the tests.

**The trusted box.** The image border is unprojected to the undistorted plane (``cam_from_img``),
giving the box the image covers; it is widened on every side by a share of its half-size — 100 %,
or the largest of 50 / 25 / 10 / 0 % for which the lens is still one-to-one there, checked as a
positive Jacobian determinant of COLMAP's projection on a 97×97 grid over the box. Gaussians centred
outside it are culled and anchors outside it are invisible (:mod:`cusgs_jax.splat.lens`), which
plays the part of the pinhole projection's 30 % frustum clamp. A lens that is not one-to-one even
over the image itself (a calibration that folds the frame) is refused. Fisheye boxes are capped at
``|u|, |v| ≤`` :data:`MAX_TAN` (84° off the axis): the rest of a wider fisheye is not rendered.

Shapes: V views.
"""

from __future__ import annotations

import numpy as np

import logging
from typing import NamedTuple

from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.undistort import camera_model_name

__all__ = ["LENS_MODELS", "MAX_TAN", "WIDENINGS", "SceneLens", "check_undistortable", "lens_coefficients",
           "lens_of_camera", "scene_lens"]

# COLMAP models the lens mode renders through: {model: (fisheye, names of its distortion params)}.
LENS_MODELS = {
    "SIMPLE_PINHOLE": (False, ()), "PINHOLE": (False, ()),
    "SIMPLE_RADIAL": (False, ("k1",)), "RADIAL": (False, ("k1", "k2")),
    "OPENCV": (False, ("k1", "k2", "p1", "p2")), "OPENCV_FISHEYE": (True, ("k1", "k2", "k3", "k4")),
    # the polynomial part only: its rational denominator (k4, k5, k6) must be zero (lens_of_camera)
    "FULL_OPENCV": (False, ("k1", "k2", "p1", "p2", "k3", "k4_rational", "k5_rational", "k6_rational")),
}
WIDENINGS = (1.0, 0.5, 0.25, 0.1, 0.0)  # tried in order (module docstring)
MAX_TAN = 10.0
_ORDER = ("k1", "k2", "k3", "k4", "p1", "p2")  # cusgs_jax.splat.lens.COEFFICIENTS
log = logging.getLogger("cusgs_jax")


class SceneLens(NamedTuple):
    """The lenses of a scene's views, on the host (``SceneData.lens``; one camera's
    :class:`cusgs_jax.splat.lens.Lens` is ``Lens.of_views(table, view)``).

    Attributes:
      coeffs: [V, 6] float32 (k1, k2, k3, k4, p1, p2).
      bounds: [V, 4] float32 trusted box (u_min, u_max, v_min, v_max) (module docstring).
      fisheye: the OPENCV_FISHEYE model (all views) instead of the radial–tangential one.
    """

    coeffs: np.ndarray
    bounds: np.ndarray
    fisheye: bool

    def as_dict(self, idx) -> dict:
        """Views ``idx`` as JSON: ``{"coeffs": [V][6], "bounds": [V][4], "fisheye"}`` (a checkpoint's camera lists)."""
        return dict(coeffs=np.asarray(self.coeffs, np.float64)[idx].tolist(),
                    bounds=np.asarray(self.bounds, np.float64)[idx].tolist(), fisheye=bool(self.fisheye))


def lens_coefficients(camera) -> tuple[np.ndarray, bool]:
    """([6] float64 (k1, k2, k3, k4, p1, p2), fisheye) of a pycolmap camera of :data:`LENS_MODELS`."""
    model = camera_model_name(camera)
    fisheye, names = LENS_MODELS[model]
    params = np.asarray(camera.params, np.float64)
    extra = dict(zip(names, params[len(params) - len(names):])) if names else {}  # names not in _ORDER: ignored
    return np.array([extra.get(k, 0.0) for k in _ORDER]), fisheye


def _border(width: int, height: int, samples: int = 65) -> np.ndarray:
    """[4·samples, 2] pixel positions along the image's outer edge (COLMAP pixel coordinates)."""
    xs, ys = np.linspace(0.0, width, samples), np.linspace(0.0, height, samples)
    return np.concatenate([np.stack([xs, np.zeros_like(xs)], -1), np.stack([xs, np.full_like(xs, height)], -1),
                           np.stack([np.zeros_like(ys), ys], -1), np.stack([np.full_like(ys, width), ys], -1)])


def _one_to_one(camera, box: np.ndarray, samples: int = 97) -> bool:
    """COLMAP's projection has a positive Jacobian determinant all over ``box`` (u0, u1, v0, v1)."""
    u, v = np.meshgrid(np.linspace(box[0], box[1], samples), np.linspace(box[2], box[3], samples))
    uv = np.stack([u.ravel(), v.ravel()], -1)
    step = 1e-6 * max(1.0, float(np.max(np.abs(box))))

    def project(points):
        return camera.img_from_cam(np.concatenate([points, np.ones((len(points), 1))], -1))

    du = (project(uv + [step, 0.0]) - project(uv - [step, 0.0])) / (2 * step)
    dv = (project(uv + [0.0, step]) - project(uv - [0.0, step])) / (2 * step)
    det = du[:, 0] * dv[:, 1] - du[:, 1] * dv[:, 0]
    return bool(np.all(np.isfinite(det)) and np.all(det > 0))


def lens_of_camera(camera, where: str) -> tuple[np.ndarray, np.ndarray, bool]:
    """(coeffs [6], bounds [4] (u_min, u_max, v_min, v_max), fisheye) of a pycolmap camera.

    Args:
      camera: a pycolmap Camera of one of :data:`LENS_MODELS`.
      where: how a message names the camera, e.g. "camera 1 in sparse/0/cameras.bin".
    Raises:
      SceneError: when the lens folds the image itself (not one-to-one over the frame).
    """
    model = camera_model_name(camera)
    if model == "FULL_OPENCV" and np.any(np.asarray(camera.params, np.float64)[9:12] != 0):
        raise SceneError(
            f"{where}: its FULL_OPENCV lens {np.asarray(camera.params).tolist()} has a rational part (k4, k5, k6 ≠ 0), "
            "which data.undistort=lens does not model; use data.undistort=crop (or mask) to undistort it with COLMAP")
    coeffs, fisheye = lens_coefficients(camera)
    width, height = int(camera.width), int(camera.height)
    border = _border(width, height)
    uv = np.asarray(camera.cam_from_img(border), np.float64)

    def reaches(points):  # COLMAP's projection of the directions `points` gives the border pixels back
        back = camera.img_from_cam(np.concatenate([points, np.ones((len(points), 1))], -1))
        return np.all(np.isfinite(points), -1) & np.all(np.abs(back - border) < 1e-3 * max(width, height), -1)

    lost = ~reaches(uv)  # no direction in front of the camera maps to these border pixels
    capped = np.zeros(len(uv), bool)
    if fisheye:  # past MAX_TAN (or 90°) off the axis: the pixel's direction at the cap (not rendered beyond it)
        direction = (border - [camera.principal_point_x, camera.principal_point_y]) / [camera.focal_length_x,
                                                                                        camera.focal_length_y]
        norm = np.maximum(np.abs(direction).max(-1, keepdims=True), 1e-12)
        capped = lost | np.any(np.abs(uv) > MAX_TAN, -1)
        uv = np.where(capped[:, None], direction / norm * MAX_TAN, uv)
        lost = np.zeros_like(lost)
    reached = ~lost
    if np.any(capped):
        log.warning("%s: its %s lens sees more than %.0f° off the axis; data.undistort=lens renders only the part "
                    "within it (the rest of each image stays background) — use data.undistort=crop to undistort "
                    "instead", where, camera_model_name(camera), np.degrees(np.arctan(MAX_TAN)))
    image_box = np.array([uv[:, 0].min(), uv[:, 0].max(), uv[:, 1].min(), uv[:, 1].max()])
    half = np.repeat([(image_box[1] - image_box[0]) / 2, (image_box[3] - image_box[2]) / 2], 2)
    for widen in WIDENINGS if np.all(reached) else ():
        box = np.clip(image_box + np.array([-1, 1, -1, 1]) * widen * half, -MAX_TAN, MAX_TAN)
        if _one_to_one(camera, box):
            return coeffs, box, fisheye
    raise SceneError(_folds_message(camera, where))


def _folds_message(camera, where: str) -> str:
    return (f"{where}: its {camera_model_name(camera)} lens {np.asarray(camera.params).tolist()} is not one-to-one "
            "over the image (the distortion folds the frame back on itself), so nothing can be rendered through it, "
            "and undistorting it (data.undistort=crop or mask) would fill the image with a mirrored copy of its "
            "ring — check the calibration")


def check_undistortable(camera, where: str, mode: str) -> None:
    """Refuse, for ``data.undistort=crop|mask``, a distorted camera whose images no pinhole image can hold.

    A perspective lens must be one-to-one over the image (COLMAP would otherwise undistort the folded
    part into a mirrored ring that the crop keeps and the mask scores as valid); a fisheye must see
    less than 90° off the axis at every border pixel (a pinhole image cannot hold a direction at or
    beyond 90°; COLMAP's undistorter then produces images of another size than its cameras say).

    Raises:
      SceneError: naming ``where`` (e.g. "camera 1 in sparse/0/cameras.bin"), the lens and the fix.
    """
    fisheye = LENS_MODELS.get(camera_model_name(camera), (False,))[0]
    width, height = int(camera.width), int(camera.height)
    border = _border(width, height)
    with np.errstate(all="ignore"):
        uv = np.asarray(camera.cam_from_img(border), np.float64)
        back = camera.img_from_cam(np.concatenate([uv, np.ones((len(uv), 1))], -1))
    reached = np.all(np.isfinite(uv), -1) & np.all(np.abs(back - border) < 1e-3 * max(width, height), -1)
    if fisheye:
        if not np.all(reached):
            raise SceneError(
                f"{where}: its OPENCV_FISHEYE lens {np.asarray(camera.params).tolist()} sees 90° or more off the axis, "
                f"which no pinhole image can hold, so data.undistort={mode} cannot undistort it: use "
                f"data.undistort=lens (it renders such a lens up to {np.degrees(np.arctan(MAX_TAN)):.0f}° off the "
                "axis)")
        return
    box = np.array([uv[:, 0].min(), uv[:, 0].max(), uv[:, 1].min(), uv[:, 1].max()]) if np.all(reached) else None
    if box is None or not _one_to_one(camera, box):
        raise SceneError(_folds_message(camera, where))


def scene_lens(cameras: list, wheres: list[str]) -> SceneLens:
    """The :class:`SceneLens` of the views' pycolmap cameras ``cameras`` [V] (one lens per distinct camera).

    Raises:
      SceneError: for a lens :func:`lens_of_camera` refuses, or when fisheye and perspective
        cameras are mixed (one render cannot use both models).
    """
    lenses, per_view = {}, []
    for camera, where in zip(cameras, wheres):
        key = (camera_model_name(camera), tuple(np.asarray(camera.params).tolist()), int(camera.width),
               int(camera.height))
        if key not in lenses:
            lenses[key] = lens_of_camera(camera, where)
        per_view.append(lenses[key])
    kinds = {fisheye for _, _, fisheye in per_view}
    if len(kinds) > 1:
        raise SceneError(
            f"{wheres[0]} and others mix OPENCV_FISHEYE cameras with perspective ones, which data.undistort=lens cannot "
            "render in one model; use data.undistort=crop (or mask) to undistort them all to pinholes")
    models = sorted({key[0] for key in lenses})
    log.info("keeping %d images %s as captured (data.undistort=lens): rendered through %d lens model(s), nothing "
             "undistorted", len(per_view), "/".join(models), len(lenses))
    return SceneLens(np.stack([c for c, _, _ in per_view]).astype(np.float32),
                     np.stack([b for _, b, _ in per_view]).astype(np.float32), fisheye=kinds.pop())
