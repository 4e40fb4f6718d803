"""io/refine.py: refining a standard-PLY model as plain 3DGS on a tiny demo scene.

The model refined here is a 3DGS-style initialisation from the scene's SfM points (one
isotropic Gaussian per point, its colour as the SH DC term, opacity 0.1), so these tests
need no training run: a refinement must fit it to the training views and generalise to the
held-out ones.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.config import DataConfig
from cusgs_jax.data.demo import generate_demo_scene
from cusgs_jax.data.loader import load_scene
from cusgs_jax.io import SplatModel, heldout_psnr, make_refine_step, recentre_splats, refine_splats, scene_camera
from cusgs_jax.io import refine as refine_module
from cusgs_jax.io.refine import RefineSettings, init_refine, join_params, refine_loss, split_params

C0 = 0.28209479177387814


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A 40×30 demo scene with 8 views, every 4th held out (views 0 and 4)."""
    path = generate_demo_scene(tmp_path_factory.mktemp("refine") / "scene", width=40, height=30, num_views=8,
                               num_points=600)
    return load_scene(path, DataConfig(holdout_every=4))


def _points_model(scene, degree: int = 1, opacity: float = 0.1) -> SplatModel:
    """3DGS's initialisation: a Gaussian per SfM point, σ = mean distance to 3 neighbours, DC from its colour."""
    pts = np.asarray(scene.points, np.float64)
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    d.sort(axis=1)
    g = len(pts)
    sh = np.zeros((g, (degree + 1) ** 2, 3), np.float32)
    sh[:, 0] = (np.asarray(scene.point_colors, np.float32) / 255.0 - 0.5) / C0
    return SplatModel(means=pts.astype(np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (g, 1)),
                      log_scales=np.repeat(np.log(d[:, 1:4].mean(1))[:, None], 3, 1).astype(np.float32),
                      opacity_logits=np.full(g, np.log(opacity / (1 - opacity)), np.float32), sh=sh)


@jax.jit
def _view_loss(params, camera, image):
    return refine_loss(params, camera, image, jnp.zeros(3), RefineSettings(steps=1), 10**5)[0]


def _train_loss(model, scene) -> float:
    """Mean training loss (0.8 L1 + 0.2 D-SSIM) over the training views."""
    moved, shift = recentre_splats(model, scene.camera_centers.mean(axis=0))
    params = split_params(moved)
    return float(np.mean([float(_view_loss(params, scene_camera(scene, int(view), shift),
                                           jnp.asarray(scene.images[view], jnp.float32) / 255.0))
                          for view in scene.train_indices]))


STEPS = 6  # the refinements below share this length, hence one compiled step (io.refine caches it)


@pytest.mark.slow
def test_refine_lowers_training_loss_and_raises_heldout_psnr(scene):
    model = _points_model(scene)
    history = []
    refined = refine_splats(model, scene, 120, history=history)
    assert refined.num_gaussians == model.num_gaussians and refined.sh_degree == model.sh_degree
    assert [h["step"] for h in history] == list(range(1, 121))
    np.testing.assert_allclose(np.linalg.norm(refined.quats, axis=1), 1.0, atol=1e-5)
    before, after = _train_loss(model, scene), _train_loss(refined, scene)
    psnr_before, psnr_after = heldout_psnr(model, scene), heldout_psnr(refined, scene)
    print(f"train loss {before:.4f} -> {after:.4f}; held-out PSNR {psnr_before:.2f} -> {psnr_after:.2f} dB")
    assert after < 0.8 * before
    assert psnr_after > psnr_before + 2.0  # measured: 13.70 -> 18.38 dB (18.02 with 3DGS's colour and shape rates)
    for name in ("means", "log_scales", "opacity_logits", "sh"):  # every group moved
        assert not np.allclose(getattr(refined, name), getattr(model, name)), name


@pytest.mark.slow
def test_refine_uses_training_views_only(scene):
    """Scrambling the held-out images changes nothing: they never reach the optimiser."""
    model = _points_model(scene)
    images = scene.images.copy()
    images[scene.test_indices] = 255 - images[scene.test_indices]
    scrambled = dataclasses.replace(scene, images=images)
    a = refine_splats(model, scene, STEPS, seed=3)
    b = refine_splats(model, scrambled, STEPS, seed=3)
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    images = scene.images.copy()
    images[scene.train_indices] = 255 - images[scene.train_indices]  # the training views do matter
    c = refine_splats(model, dataclasses.replace(scene, images=images), STEPS, seed=3)
    assert not np.allclose(a.sh, c.sh)


def test_zero_steps_returns_the_model_and_negative_steps_are_refused(scene):
    model = _points_model(scene)
    assert refine_splats(model, scene, 0) is model
    with pytest.raises(ValueError, match="steps"):
        refine_splats(model, scene, -1)


def _step_inputs(scene, model):
    settings = RefineSettings(steps=STEPS, extent=float(scene.extent))
    moved, shift = recentre_splats(model, scene.camera_centers.mean(axis=0))
    params, opt_state = init_refine(moved, settings)
    view = int(scene.train_indices[0])
    image = jnp.asarray(scene.images[view], jnp.float32) / 255.0
    return settings, params, opt_state, scene_camera(scene, view, shift), image


def test_a_step_is_jitted_pure_and_deterministic(scene):
    settings, params, opt_state, camera, image = _step_inputs(scene, _points_model(scene))
    step = make_refine_step(settings, 10**5)  # a fresh factory call: a new jitted function
    assert hasattr(step, "lower")  # a jax.jit-wrapped function
    step.lower(params, opt_state, camera, image, jnp.zeros(3)).compile()
    copy = jax.tree_util.tree_map(np.array, params)
    p1, s1, m1 = step(params, opt_state, camera, image, jnp.zeros(3))
    p2, s2, m2 = step(params, opt_state, camera, image, jnp.zeros(3))
    for a, b in zip(jax.tree_util.tree_leaves((p1, s1, m1)), jax.tree_util.tree_leaves((p2, s2, m2))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    for name, value in copy.items():  # the inputs are untouched (no donation, no mutation)
        np.testing.assert_array_equal(np.asarray(params[name]), value)
    assert bool(m1["applied"]) and int(m1["overflow"]) == 0
    assert not np.allclose(np.asarray(p1["sh_dc"]), copy["sh_dc"])
    # the first Adam step moves every element by about its group's learning rate: 3DGS's for position and
    # opacity, 4× 3DGS's for colour and shape (RefineSettings)
    assert (settings.lr_sh_dc, settings.lr_scaling, settings.lr_rotation) == pytest.approx((4 * 2.5e-3, 4 * 5e-3, 4e-3))
    for name, rate in (("sh_dc", settings.lr_sh_dc), ("opacity_logits", 0.05), ("log_scales", settings.lr_scaling),
                       ("quats", settings.lr_rotation)):
        moved = np.abs(np.asarray(p1[name]) - copy[name])
        assert np.max(moved) == pytest.approx(rate, rel=1e-3), name
    moved = np.abs(np.asarray(p1["means"]) - copy["means"])
    assert np.max(moved) == pytest.approx(1.6e-4 * scene.extent, rel=1e-3)


@pytest.mark.slow
def test_a_valid_pixel_mask_makes_the_target_outside_it_irrelevant(scene):
    """data.undistort=mask: the refinement step's loss, PSNR and update ignore the target's invalid pixels."""
    settings, params, opt_state, camera, image = _step_inputs(scene, _points_model(scene))
    valid = np.ones(image.shape[:2], bool)
    valid[: image.shape[0] // 4] = False
    other = jnp.where(jnp.asarray(valid)[..., None], image, 1.0 - image)
    step = make_refine_step(settings, 10**5)
    outs = [step(params, opt_state, camera, target, jnp.zeros(3), mask)
            for target, mask in ((image, jnp.asarray(valid)), (other, jnp.asarray(valid)), (other, None))]
    for a, b in zip(jax.tree_util.tree_leaves(outs[0]), jax.tree_util.tree_leaves(outs[1])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert float(outs[2][2]["loss"]) != float(outs[1][2]["loss"])


@pytest.mark.slow
def test_an_overflowing_view_changes_nothing(scene):
    settings, params, opt_state, camera, image = _step_inputs(scene, _points_model(scene))
    p, s, m = make_refine_step(settings, 8)(params, opt_state, camera, image, jnp.zeros(3))
    assert int(m["overflow"]) > 0 and int(m["pairs"]) > 8 and not bool(m["applied"])
    for a, b in zip(jax.tree_util.tree_leaves((p, s)), jax.tree_util.tree_leaves((params, opt_state))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.slow  # end to end, ~20 s: in .ci/run's -m slow pass, out of the default run (kept under 8 minutes)
def test_refine_grows_the_pair_capacity_and_replays(scene, monkeypatch):
    """With no slack in the capacity, views overflow; the replays give exactly the unconstrained result."""
    model = _points_model(scene)
    free = refine_splats(model, scene, STEPS, seed=1)
    capacities = []

    def tight(per, num):
        capacities.append(max(1, int(per * num)))
        return capacities[-1]

    monkeypatch.setattr(refine_module, "max_pairs", tight)
    tight_model = refine_splats(model, scene, STEPS, seed=1, pairs_per_gaussian=2.0)
    print("pair capacities", sorted(set(capacities)))
    assert len(set(capacities)) > 1  # the capacity grew
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_allclose(getattr(tight_model, name), getattr(free, name), rtol=1e-5, atol=1e-6)


@pytest.mark.slow
def test_the_step_gradient_matches_finite_differences(scene, x64):
    """∂loss/∂params of the refine step's loss (float64) against central differences along random directions."""
    model = _points_model(scene, degree=1, opacity=0.5)
    keep = np.arange(0, model.num_gaussians, 12)  # 50 Gaussians: fast, and each pixel sees several
    model = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float64)[keep], model)
    rng = np.random.default_rng(0)  # anisotropic, turned Gaussians with some view dependence: every group matters
    model = dataclasses.replace(model, log_scales=model.log_scales + rng.normal(0, 0.5, model.log_scales.shape),
                                quats=rng.normal(size=model.quats.shape), sh=model.sh + rng.normal(0, 0.3, model.sh.shape))
    moved, shift = recentre_splats(model, scene.camera_centers.mean(axis=0))
    moved = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float64), moved)
    view = int(scene.train_indices[1])
    camera = scene_camera(scene, view, shift)
    camera = dataclasses.replace(camera, K=jnp.asarray(camera.K, jnp.float64),
                                 world_to_camera=jnp.asarray(camera.world_to_camera, jnp.float64))
    image = jnp.asarray(scene.images[view], jnp.float64) / 255.0
    settings = RefineSettings(steps=1)
    params = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), split_params(moved))
    assert params["means"].dtype == jnp.float64

    def loss(p):
        return refine_loss(p, camera, image, jnp.zeros(3, jnp.float64), settings, 10**5)[0]

    grads = jax.jit(jax.grad(loss))(params)
    f = jax.jit(loss)
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        direction = {k: jnp.zeros_like(v) for k, v in params.items()}
        direction[name] = jnp.asarray(rng.normal(size=params[name].shape))
        eps = 1e-6
        plus = f(jax.tree_util.tree_map(lambda p, d: p + eps * d, params, direction))
        minus = f(jax.tree_util.tree_map(lambda p, d: p - eps * d, params, direction))
        numeric = float(plus - minus) / (2 * eps)
        analytic = float(jnp.sum(grads[name] * direction[name]))
        assert abs(analytic) > 1e-6, name  # the group does influence the loss
        assert analytic == pytest.approx(numeric, rel=1e-4, abs=1e-8), name
    assert join_params(params).sh.shape == (len(keep), 4, 3)
