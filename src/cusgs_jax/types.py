"""The naming table of array shapes, and the :class:`Camera` pytree.

Every public docstring writes shapes with these letters:

| letter | meaning |
|---|---|
| A | anchor capacity (slots of :class:`cusgs_jax.model.anchors.AnchorState`; ``alive`` says which hold an anchor) |
| N | Gaussians (offsets) per anchor |
| S | visible slots: anchors gathered for one view before decoding, ``ceil(visible_fraction · A)`` |
| G | Gaussians of one render (``S·N`` after decoding, or any count given to the splatter) |
| Ga | G_act, active Gaussians: the decoded ones that pass the opacity mask, compacted before rasterising (``model/active.py``) |
| F | anchor latent size |
| E | appearance-embedding size |
| Q | feature-query channels, Σ over feature models of their slice |
| M | memory-bank (PSC) entries of one feature model |
| D | feature dimension of one feature model |
| V | views (cameras) of a scene |
| P | sampled pixels |
| C | colour/feature channels composited by the splatter |
| K | spherical-harmonic coefficients per colour channel, (d+1)² for SH degree d (standard 3DGS PLY) |
| H, W | image height and width in pixels |
| T | tiles |
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.splat.lens import Lens


def camera_center(world_to_camera: jax.Array) -> jax.Array:
    """[..., 3] camera positions ``−Rᵀ t`` of [..., 4, 4] world→camera matrices, elementwise (no matmul, so
    full float32 on every backend: :mod:`cusgs_jax.precision`)."""
    rot, trans = world_to_camera[..., :3, :3], world_to_camera[..., :3, 3]
    return -jnp.sum(rot * trans[..., :, None], axis=-2)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Camera:
    """A perspective camera: OpenCV axes (+z forward, +y down), gsplat conventions (docs/rasterizer.md#projection).

    Attributes:
      K: [3, 3] intrinsics.
      world_to_camera: [4, 4] world→camera matrix.
      width, height: image size in pixels (static: part of the tree structure, never traced).
      lens: the lens distortion (:class:`cusgs_jax.splat.lens.Lens`) the camera renders through, or
        None for a pinhole camera (``data.undistort=lens`` keeps it; the other modes undistort the
        images to pinholes instead).
    """

    K: jax.Array
    world_to_camera: jax.Array
    width: int = dataclasses.field(metadata=dict(static=True))
    height: int = dataclasses.field(metadata=dict(static=True))
    lens: Lens | None = None

    @property
    def center(self) -> jax.Array:
        """[3] camera position in world coordinates."""
        return camera_center(self.world_to_camera)

    @staticmethod
    def of_scene(scene, view: int) -> Camera:
        """The camera of ``scene`` view ``view`` (a :class:`cusgs_jax.data.scene_data.SceneData`)."""
        lens = None if getattr(scene, "lens", None) is None else Lens.of_views(scene.lens, view)
        return Camera(jax.device_put(np.asarray(scene.Ks[view], np.float32)),
                      jax.device_put(np.asarray(scene.viewmats[view], np.float32)), scene.width, scene.height, lens)
