"""cusgs_jax.render / fit_render on a trained run: the held-out numbers of eval.json, jit/vmap, appearance, capacities,
meta and gradients (the session fixture ``small_run``: 30 steps on a 6-view 40×30 demo scene, 1 held-out view)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cusgs_jax as cg
from cusgs_jax.eval import metrics
from cusgs_jax.eval.views import nearest_train_view
from cusgs_jax.rendering import RenderCapacityError, Rendered, appearance_index
from cusgs_jax.training.capacity import Capacities
from cusgs_jax.training.inputs import load_data
from cusgs_jax.training.render import view_needs
from cusgs_jax.types import camera_center

TOO_SMALL = Capacities(visible_fraction=1 / 16, active_fraction=1 / 16, pairs_per_active=0.5)


@pytest.fixture(scope="module")
def model(small_run):
    return cg.load_trained(small_run[1])


@pytest.fixture(scope="module")
def scene(model):
    scene, _ = load_data(model.cfg)
    return scene


@pytest.fixture(scope="module")
def views(model):
    """Every camera of the scene as one batch: the held-out ones, then the training ones."""
    held, train = model.held_out_cameras, model.cameras
    return cg.stack_cameras([one(held, b) for b in range(len(held.world_to_camera))]
                            + [one(train, b) for b in range(len(train.world_to_camera))])


@pytest.fixture(scope="module")
def caps(model, views):
    return cg.fit_render(model, views)


@pytest.fixture(scope="module")
def batch(model, views, caps):
    return cg.render(model, views, capacities=caps)


def one(cameras, b):
    return jax.tree_util.tree_map(lambda x: x[b], cameras)


def with_nets(model, **nets):
    return dataclasses.replace(model, nets={**model.nets, **nets})


def test_held_out_psnr_equals_eval_json(model, scene):
    cameras = model.held_out_cameras
    assert len(cameras.world_to_camera) == len(scene.test_indices) == len(model.evaluation.per_view) >= 1
    capacities = cg.fit_render(model, cameras)
    out = cg.render(model, cameras, capacities=capacities)  # appearance="nearest": the held-out protocol
    assert isinstance(out, Rendered)
    assert out.image.shape == (len(scene.test_indices), scene.height, scene.width, 3)
    for i, view in enumerate(scene.test_indices):
        target = scene.images[view].astype(np.float32) / 255.0
        row = model.evaluation.per_view[i]
        assert row["name"] == scene.names[view]
        # bit for bit: the same program decodes and rasterises the same Gaussians in the same order (measured: equal)
        assert float(metrics.psnr(np.asarray(out.image[i]), target)) == row["psnr"]
    for value in out.dropped.values():
        np.testing.assert_array_equal(np.asarray(value), 0)
    # eval.json's capacities are fractions of the training run's anchor capacity, not of the compacted model's:
    # they do not fit this view (render's docstring says so)
    assert model.anchors.capacity < model.evaluation.capacity
    with pytest.raises(RenderCapacityError, match="anchors"):
        cg.render(model, cameras, capacities=Capacities(**model.evaluation.capacities))


def test_one_camera_batch_and_jit_vmap_agree(model, views, caps, batch):
    count = len(views.world_to_camera)
    assert batch.image.shape == (count, views.height, views.width, 3)
    assert batch.alpha.shape == batch.depth.shape == (count, views.height, views.width)
    assert batch.ids.shape[0] == count and batch.features == {}
    vmapped = jax.jit(jax.vmap(lambda camera: cg.render(model, camera, capacities=caps)))(views)
    for b in range(count):
        single = cg.render(model, one(views, b), capacities=caps)
        assert single.image.shape == (views.height, views.width, 3)
        for name in ("image", "alpha", "depth", "means2d", "radii", "ids"):
            # the batch renders its views one after another in one program (lax.map): bit for bit one camera's
            np.testing.assert_array_equal(np.asarray(getattr(single, name)), np.asarray(getattr(batch, name))[b],
                                          err_msg=f"{name} of view {b}: one camera vs the batch")
        for name in ("means2d", "radii", "ids"):  # the same Gaussians, projected identically
            np.testing.assert_array_equal(np.asarray(getattr(vmapped, name))[b], np.asarray(getattr(batch, name))[b],
                                          err_msg=f"{name} of view {b}: jit(vmap) vs the batch")
        # jit(vmap) batches the compositing, which XLA compiles differently: the float32 sums may round differently
        # (measured on CPU: at most 3e-7, a few ulp; the held-out PSNR is unchanged)
        for name in ("image", "alpha", "depth"):
            np.testing.assert_allclose(np.asarray(getattr(vmapped, name))[b], np.asarray(getattr(batch, name))[b],
                                       rtol=0, atol=1e-6, err_msg=f"{name} of view {b}: jit(vmap) vs the batch")
    assert float(jnp.max(batch.image)) <= 1.0 and float(jnp.min(batch.image)) >= 0.0
    assert float(jnp.std(batch.image)) > 0.01  # not a blank render


def test_nearest_appearance_is_the_evaluations_choice(model, scene, views):
    centers = jax.vmap(camera_center)(model.cameras.world_to_camera)
    np.testing.assert_allclose(np.asarray(centers), scene.camera_centers[scene.train_indices], atol=1e-5)
    for i, view in enumerate(scene.test_indices):
        center = camera_center(model.held_out_cameras.world_to_camera[i])
        expected = nearest_train_view(scene.camera_centers, scene.train_indices, view)
        assert int(appearance_index("nearest", centers, center)) == expected
        assert int(appearance_index("nearest", np.asarray(centers), np.asarray(center))) == expected
        assert int(jax.jit(lambda c, p: appearance_index("nearest", c, p))(centers, center)) == expected
    # a training camera borrows its own embedding
    for k in range(len(scene.train_indices)):
        assert int(appearance_index("nearest", centers, centers[k])) == k
    with pytest.raises(ValueError, match="appearance='farthest'"):
        appearance_index("farthest", centers, centers[0])


def test_appearance_mean_and_index(model, scene, views, caps, batch):
    table = np.asarray(model.nets["appearance"])
    assert table.shape[0] == len(scene.train_indices) >= 2
    held = one(views, 0)  # the held-out view
    nearest = nearest_train_view(scene.camera_centers, scene.train_indices, int(scene.test_indices[0]))
    other = (nearest + 1) % table.shape[0]
    image = np.asarray(cg.render(model, held, capacities=caps).image)  # appearance="nearest"
    by_index = np.asarray(cg.render(model, held, capacities=caps, appearance=nearest).image)
    np.testing.assert_array_equal(by_index, image)  # "nearest" is that index
    other_image = np.asarray(cg.render(model, held, capacities=caps, appearance=other).image)
    mean_image = np.asarray(cg.render(model, held, capacities=caps, appearance="mean").image)
    assert np.max(np.abs(other_image - image)) > 1e-3
    assert np.max(np.abs(mean_image - image)) > 1e-3
    # index k is the model with only row k of the table; "mean" is the model with only the mean row
    only_k = with_nets(model, appearance=jnp.asarray(table[other:other + 1]))
    np.testing.assert_array_equal(np.asarray(cg.render(only_k, held, capacities=caps, appearance=0).image),
                                  other_image)
    only_mean = with_nets(model, appearance=jnp.asarray(table.mean(axis=0, keepdims=True)))
    np.testing.assert_allclose(np.asarray(cg.render(only_mean, held, capacities=caps, appearance=0).image),
                               mean_image, atol=1e-6)


def test_too_small_capacities_raise_outside_jit_and_report_inside(model, views):
    with pytest.raises(RenderCapacityError, match="fit_render") as info:
        cg.render(model, views, capacities=TOO_SMALL)
    assert isinstance(info.value, ValueError)
    out = jax.jit(lambda cameras: cg.render(model, cameras, capacities=TOO_SMALL))(views)
    dropped = {key: np.asarray(value) for key, value in out.dropped.items()}
    assert set(dropped) == {"anchors", "gaussians", "pairs"}
    assert all(value.shape == (len(views.world_to_camera),) for value in dropped.values())
    assert np.all(dropped["anchors"] > 0)  # 1/16 of the slots: every view sees more anchors than that
    # the truncated image holds at most the capacity's Gaussians
    assert out.ids.shape[-1] == TOO_SMALL.active_gaussians(model.anchors.capacity, model.cfg.model.n_offsets)


def test_fitted_capacities_cover_every_view(model, views, caps, batch):
    for value in batch.dropped.values():
        np.testing.assert_array_equal(np.asarray(value), 0)
    train_centers = np.asarray(jax.vmap(camera_center)(model.cameras.world_to_camera))
    indices = [appearance_index("nearest", train_centers, np.asarray(camera_center(views.world_to_camera[b])))
               for b in range(len(views.world_to_camera))]
    needs = view_needs(model.anchors, model.nets, [(one(views, b), np.int32(index)) for b, index in enumerate(indices)],
                       model.cfg)
    A, N = model.anchors.capacity, model.cfg.model.n_offsets
    for need in needs:  # capacities cover every view's need
        assert need["visible_anchors"] <= caps.visible_slots(A)
        assert need["active_gaussians"] <= caps.active_gaussians(A, N)
        assert need["pairs"] <= caps.pairs(A, N)


def test_meta_ids_radii_means2d(model, views, caps, batch):
    A, N = model.anchors.capacity, model.cfg.model.n_offsets
    g_act = caps.active_gaussians(A, N)
    assert batch.means2d.shape == batch.radii.shape == (len(views.world_to_camera), g_act, 2)
    assert batch.ids.shape == (len(views.world_to_camera), g_act)
    assert batch.ids.dtype == jnp.int32 and batch.radii.dtype == jnp.int32
    alive = np.asarray(model.anchors.alive)
    centers = np.asarray(model.anchors.centers, np.float64)
    offsets = np.asarray(model.anchors.params.offsets, np.float64)
    scaling = np.exp(np.asarray(model.anchors.params.log_scaling, np.float64))
    centers_of_views = jax.vmap(camera_center)(model.cameras.world_to_camera)
    for b in range(len(views.world_to_camera)):
        camera = one(views, b)
        index = appearance_index("nearest", np.asarray(centers_of_views),
                                 np.asarray(camera_center(camera.world_to_camera)))
        (need,) = view_needs(model.anchors, model.nets, [(camera, np.int32(index))], model.cfg)
        ids, radii = np.asarray(batch.ids[b]), np.asarray(batch.radii[b])
        means2d = np.asarray(batch.means2d[b], np.float64)
        count = need["active_gaussians"]
        assert 0 < count < g_act  # some entries are empty (fit_render's headroom)
        # the active Gaussians first, the empty entries (-1) after them: -1 exactly where there is none
        assert np.all(ids[:count] >= 0) and np.all(ids[count:] == -1)
        valid = ids[:count]
        assert len(np.unique(valid)) == count and np.all(valid < A * N)
        assert np.all(alive[valid // N])  # only alive anchors' Gaussians
        np.testing.assert_array_equal(radii[count:], 0)  # an empty entry is not drawn
        assert np.any(radii[:count] > 0)
        # means2d of an entry is the projection of that Gaussian: μ = x_a + Δx_{a,o} · exp(s_a[:3])
        a, o = valid // N, valid % N
        mu = centers[a] + offsets[a, o] * scaling[a, :3]
        viewmat, K = np.asarray(camera.world_to_camera, np.float64), np.asarray(camera.K, np.float64)
        x = mu @ viewmat[:3, :3].T + viewmat[:3, 3]
        pix = (x @ K.T)[:, :2] / x[:, 2:3]
        drawn = radii[:count].max(axis=-1) > 0
        np.testing.assert_allclose(means2d[:count][drawn], pix[drawn], atol=2e-2, rtol=1e-4)


def test_render_is_differentiable_in_the_anchor_latents(model, views, caps):
    camera = one(views, 0)
    params = model.anchors.params

    def mean_image(latent):
        anchors = dataclasses.replace(model.anchors, params=dataclasses.replace(params, latent=latent))
        return jnp.mean(cg.render(dataclasses.replace(model, anchors=anchors), camera, capacities=caps).image)

    base, grad = jax.value_and_grad(mean_image)(params.latent)
    base, grad = float(base), np.asarray(grad)
    assert grad.shape == params.latent.shape
    assert np.all(np.isfinite(grad))
    assert np.any(grad != 0)
    alive = np.asarray(model.anchors.alive)
    np.testing.assert_array_equal(grad[~alive], 0)  # dead padding slots take no part in the image
    # the gradient is the slope: a small step along it raises the mean image by about |grad|² · step
    step = 1e-2 / np.linalg.norm(grad)
    moved = float(mean_image(params.latent + step * grad))
    assert moved - base == pytest.approx(step * np.sum(grad * grad), rel=0.3)


def test_not_a_trained_model_is_a_type_error(model, views, caps):
    with pytest.raises(TypeError, match="model"):
        cg.render(model.anchors, views, capacities=caps)
    with pytest.raises(TypeError, match="model"):
        cg.fit_render({"anchors": model.anchors}, views)
