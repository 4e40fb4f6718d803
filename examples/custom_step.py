"""Research code composing cusgs-jax's pure pieces into its own jitted step, without Hydra.

A toy variant of the training step: decode the scaffold, rasterise, and fit
with plain L1 + SSIM and a single Adam over every parameter, on the built-in
demo scene (or any COLMAP folder given as the first argument).

    python examples/custom_step.py [SCENE] [--steps 200]
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np
import optax

import cusgs_jax as cg


def main(argv=None) -> list[float]:
    """Train; returns the loss of every step."""
    parser = argparse.ArgumentParser()
    parser.add_argument("scene", nargs="?", default=None)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--views", type=int, default=12)
    parser.add_argument("--size", type=int, nargs=2, default=(80, 60))
    args = parser.parse_args(argv)

    path = args.scene or cg.demo_scene_path(num_views=args.views, width=args.size[0], height=args.size[1])
    # the scene as cusgs-train loads it, every view for training; then camera extent 1, any COLMAP scale
    scene, _ = cg.normalize_scene(cg.load_scene(path, cg.DataConfig(holdout_every=0)))
    decoder_cfg = cg.DecoderConfig(n_offsets=5, latent_dim=16, hidden=32, appearance_dim=0)
    anchors = cg.init_anchors(scene.points, voxel_size=0.04, n_offsets=5, latent_dim=16)  # an AnchorState
    # learnable: the per-anchor arrays (offsets, scaling, latents) and the decoder MLPs; the
    # anchor centres and the alive mask stay fixed (this toy never grows or prunes)
    params = {"anchor": anchors.params, "decoder": cg.init_decoder(jax.random.PRNGKey(0), decoder_cfg)}
    tx = optax.adam(3e-3)
    opt_state = tx.init(params)
    images = jnp.asarray(scene.images.astype(np.float32) / 255.0)
    viewmats, Ks = jnp.asarray(scene.viewmats), jnp.asarray(scene.Ks)
    width, height = scene.width, scene.height

    @jax.jit
    def step(params, opt_state, view):
        camera = cg.Camera(Ks[view], viewmats[view], width, height)

        def loss_fn(params):
            visible = cg.frustum_mask(anchors.centers, camera.world_to_camera, camera.K, width, height)
            g = cg.decode_gaussians(params["decoder"], params["anchor"], anchors.centers, visible & anchors.alive,
                                    camera.center, None, decoder_cfg)
            out = cg.rasterize(g.means, g.quats, g.scales, g.opacities, g.colors, camera.world_to_camera, camera.K,
                               width, height, tile_size=8)
            target = images[view]
            return 0.8 * cg.losses.l1(out.image, target) + 0.2 * cg.losses.ssim_loss(out.image, target)

        loss, grads = jax.value_and_grad(loss_fn)(params)
        updates, opt_state = tx.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    losses = []
    for i in range(args.steps):
        params, opt_state, loss = step(params, opt_state, jnp.int32(i % len(scene.names)))
        losses.append(float(loss))
        if (i + 1) % 50 == 0:
            print(f"step {i + 1}: loss {np.mean(losses[-50:]):.4f}")
    return losses


if __name__ == "__main__":
    main()
