"""io/ply.py and io/render.py: the standard 3DGS PLY (docs/formats.md#standard-3dgs-ply) in and out, and rendering one."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from cusgs_jax.errors import UserError
from cusgs_jax.io import PlyError, SplatModel, read_ply, render_splats, render_splats_exact, splat_colors, write_ply
from cusgs_jax.training import capacity
from cusgs_jax.splat import rasterize
from cusgs_jax.testing.scenes import make_scene
from cusgs_jax.testing.sh_reference import sh_to_rgb_reference
from cusgs_jax.types import Camera

FIELDS = [f.name for f in dataclasses.fields(SplatModel)]


def _model(seed=0, num=50, degree=3) -> SplatModel:
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    f32 = lambda a: np.asarray(a, np.float32)  # noqa: E731
    return SplatModel(means=f32(rng.normal(size=(num, 3)) * 100), quats=f32(rng.normal(size=(num, 4))),
                      log_scales=f32(rng.normal(-3, 1, (num, 3))), opacity_logits=f32(rng.normal(size=num)),
                      sh=f32(rng.normal(size=(num, k, 3))))


def _inria_vertex(means, quats, log_scales, logits, sh, *, normals=True, order=None, dtype="<f4"):
    """The vertex array of graphdeco's save_ply, built here property by property."""
    g, k = sh.shape[:2]
    values = {"x": means[:, 0], "y": means[:, 1], "z": means[:, 2]}
    if normals:
        values.update(nx=np.zeros(g), ny=np.zeros(g), nz=np.zeros(g))
    for c in range(3):
        values[f"f_dc_{c}"] = sh[:, 0, c]
    for c in range(3):  # channel-major: all R coefficients 1..K-1, then G, then B
        for j in range(1, k):
            values[f"f_rest_{c * (k - 1) + (j - 1)}"] = sh[:, j, c]
    values["opacity"] = logits
    for i in range(3):
        values[f"scale_{i}"] = log_scales[:, i]
    for i in range(4):
        values[f"rot_{i}"] = quats[:, i]
    names = list(values) if order is None else order(list(values))
    vertex = np.empty(g, dtype=[(n, dtype) for n in names])
    for n in names:
        vertex[n] = values[n]
    return vertex


def _write(path, vertex, **kw):
    PlyData([PlyElement.describe(vertex, "vertex")], **kw).write(str(path))
    return path


@pytest.mark.parametrize("degree", [0, 3])
def test_round_trip_is_bit_exact(tmp_path, degree):
    model = _model(degree=degree)
    path = write_ply(tmp_path / "m.ply", model)
    back = read_ply(path)
    for name in FIELDS:
        got = getattr(back, name)
        assert got.dtype == np.float32
        np.testing.assert_array_equal(got.view(np.uint32), getattr(model, name).view(np.uint32))
    assert back.sh_degree == degree and back.num_gaussians == 50
    ply = PlyData.read(str(path))
    vertex = ply["vertex"]
    assert [e.name for e in ply.elements] == ["vertex"] and ply.byte_order == "<" and not ply.text
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * ((degree + 1) ** 2 - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert [p.name for p in vertex.properties] == names
    assert all(vertex.data.dtype[n] == np.dtype("<f4") for n in names)
    assert not np.any(vertex.data["nx"]) and not np.any(vertex.data["nz"])
    # the writer's f_rest is channel-major (save_ply): the last R coefficient, then the first G one
    if degree:
        np.testing.assert_array_equal(vertex.data["f_rest_14"], model.sh[:, 15, 0])
        np.testing.assert_array_equal(vertex.data["f_rest_15"], model.sh[:, 1, 1])


def test_model_is_a_pytree():
    model = _model(num=4, degree=1)
    assert len(jax.tree_util.tree_leaves(model)) == 5
    doubled = jax.jit(lambda m: jax.tree_util.tree_map(lambda x: 2 * x, m))(model)
    assert isinstance(doubled, SplatModel)
    np.testing.assert_allclose(np.asarray(doubled.sh), 2 * model.sh)
    np.testing.assert_allclose(np.asarray(model.scales), np.exp(model.log_scales), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(model.opacities), 1 / (1 + np.exp(-model.opacity_logits)), rtol=1e-6)


@pytest.mark.parametrize("variant", ["inria", "no_normals_shuffled", "float64_big_endian", "ascii"])
def test_reads_an_inria_ply(tmp_path, variant):
    m = _model(seed=1, num=20, degree=2)
    kw, vkw = {}, {}
    if variant == "no_normals_shuffled":
        vkw = dict(normals=False, order=lambda names: names[::-1])
    elif variant == "float64_big_endian":
        vkw, kw = dict(dtype=">f8"), dict(byte_order=">")
    elif variant == "ascii":
        kw = dict(text=True)
    path = _write(tmp_path / "inria.ply", _inria_vertex(m.means, m.quats, m.log_scales, m.opacity_logits, m.sh,
                                                        **vkw), **kw)
    back = read_ply(path)
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(back, name), getattr(m, name), err_msg=name)


@pytest.mark.slow
def test_render_matches_rasterize_with_reference_colours(tmp_path, monkeypatch):
    s = make_scene(seed=3, num=60, width=40, height=28)
    rng = np.random.default_rng(4)
    sh = rng.normal(0, 0.3, (60, 16, 3))
    logits = np.log(s["opacities"] / (1 - s["opacities"]))
    path = _write(tmp_path / "scene.ply", _inria_vertex(s["means"], s["quats"], np.log(s["scales"]), logits, sh))
    model = read_ply(path)
    camera = Camera(jnp.asarray(s["K"], jnp.float32), jnp.asarray(s["viewmat"], jnp.float32), 40, 28)
    bg = np.array([0.2, 0.3, 0.4], np.float32)

    center = -s["viewmat"][:3, :3].T @ s["viewmat"][:3, 3]
    colors = sh_to_rgb_reference(sh.astype(np.float32), s["means"].astype(np.float32) - center)
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    direct = rasterize(f32(s["means"]), f32(s["quats"]), f32(s["scales"]), f32(s["opacities"]), f32(colors),
                       f32(s["viewmat"]), f32(s["K"]), 40, 28, background=f32(bg), tile_size=8, max_pairs=20000)
    assert int(direct.overflow) == 0 and float(direct.alpha.max()) > 0.5

    # render_splats, jitted by render_splats_exact, whose host loop grows a capacity that
    # overflows (no slack, so this tiny scene overflows at 0.5 pairs per Gaussian)
    monkeypatch.setattr(capacity, "PAIR_SLACK", 0)
    exact, pairs = render_splats_exact(model, camera, background=bg, pairs_per_gaussian=0.5)
    assert pairs > 0.5 and int(exact.overflow) == 0 and int(exact.num_pairs) <= pairs * 60
    np.testing.assert_allclose(np.asarray(exact.image), np.asarray(direct.image), rtol=0, atol=1e-5)
    # a lower degree uses only the first (d+1)² coefficients
    colors0 = sh_to_rgb_reference(sh[:, :1].astype(np.float32), s["means"])
    np.testing.assert_allclose(np.asarray(splat_colors(model, camera.center, sh_degree=0)), colors0, atol=1e-6)
    with pytest.raises(UserError, match="sh_degree"):
        render_splats(model, camera, background=bg, sh_degree=4)


def _standard(tmp_path, **vkw):
    m = _model(seed=2, num=5, degree=1)
    return _inria_vertex(m.means, m.quats, m.log_scales, m.opacity_logits, m.sh, **vkw)


def _drop(vertex, *names):
    keep = [n for n in vertex.dtype.names if n not in names]
    out = np.empty(len(vertex), dtype=[(n, vertex.dtype[n]) for n in keep])
    for n in keep:
        out[n] = vertex[n]
    return out


@pytest.mark.parametrize("case, match", [
    ("missing", "missing vertex properties rot_3"),
    ("rest_count", "5 f_rest properties"),
    ("rest_gap", "not numbered"),
    ("not_ply", "not a readable PLY"),
    ("truncated", "not a readable PLY"),
    ("absent", "no such file"),
    ("no_vertex", "no 'vertex' element"),
    ("empty", "empty"),
    ("nan", "non-finite"),
])
def test_bad_files_raise_ply_error_naming_the_file(tmp_path, case, match):
    path = tmp_path / f"bad {case}.ply"
    vertex = _standard(tmp_path)
    if case == "missing":
        _write(path, _drop(vertex, "rot_3"))
    elif case == "rest_count":
        _write(path, _drop(vertex, *[f"f_rest_{i}" for i in range(5, 9)]))
    elif case == "rest_gap":
        renamed = vertex.copy()
        renamed.dtype.names = [("f_rest_99" if n == "f_rest_8" else n) for n in vertex.dtype.names]
        _write(path, renamed)
    elif case == "not_ply":
        path.write_text("this is not a PLY file\n")
    elif case == "truncated":
        _write(path, vertex)
        path.write_bytes(path.read_bytes()[:-7])
    elif case == "no_vertex":
        PlyData([PlyElement.describe(vertex, "splat")]).write(str(path))
    elif case == "empty":
        _write(path, vertex[:0])
    elif case == "nan":
        vertex["scale_1"][2] = np.nan
        _write(path, vertex)
    with pytest.raises(PlyError, match=match) as e:
        read_ply(path)
    assert str(path) in str(e.value) and isinstance(e.value, UserError)


def test_infinite_opacity_logits_read_as_opacity_one_or_zero(tmp_path):
    """Converters (PlayCanvas splat-transform, SPZ → PLY) write ±inf logits for 8-bit alpha 255 / 0."""
    from cusgs_jax.io.ply import OPACITY_LOGIT_LIMIT

    path = tmp_path / "inf.ply"
    vertex = _standard(tmp_path)
    vertex["opacity"][0], vertex["opacity"][1] = np.inf, -np.inf
    _write(path, vertex)
    logits = read_ply(path).opacity_logits
    assert logits[0] == OPACITY_LOGIT_LIMIT and logits[1] == -OPACITY_LOGIT_LIMIT
    np.testing.assert_array_equal(logits[2:], vertex["opacity"][2:])
    assert np.float32(1.0) / (1 + np.exp(-np.float32(logits[0]))) == 1.0  # opacity exactly 1 in float32
    vertex["scale_0"][3] = np.inf  # elsewhere an infinity is still refused
    _write(path, vertex)
    with pytest.raises(PlyError, match="scale_0 has 1 non-finite"):
        read_ply(path)


def test_write_errors(tmp_path):
    m = _model(num=3, degree=1)
    with pytest.raises(PlyError, match="quats has shape"):
        write_ply(tmp_path / "a.ply", dataclasses.replace(m, quats=m.quats[:, :3]))
    with pytest.raises(PlyError, match="K = 5"):
        write_ply(tmp_path / "a.ply", dataclasses.replace(m, sh=np.zeros((3, 5, 3), np.float32)))
    with pytest.raises(PlyError, match="non-finite"):
        write_ply(tmp_path / "a.ply", dataclasses.replace(m, means=np.full((3, 3), np.inf, np.float32)))
    with pytest.raises(PlyError, match="cannot write") as e:
        write_ply(tmp_path / "missing folder" / "a.ply", m)
    assert "missing folder" in str(e.value)


def test_rendering_something_that_is_not_a_model_names_the_argument_and_the_type():
    camera = Camera(jnp.asarray(np.diag([30.0, 30.0, 1.0]), jnp.float32), jnp.eye(4), 16, 12)
    for fn in (render_splats, render_splats_exact):
        with pytest.raises(TypeError, match=rf"{fn.__name__}\(\): model must be a cusgs_jax.io.SplatModel "
                                            r"\(e.g. from cusgs_jax.io.read_ply.*got NoneType"):
            fn(None, camera, background=np.zeros(3, np.float32))
        with pytest.raises(TypeError, match=r"camera must be a cusgs_jax.types.Camera.*got dict"):
            fn(_model(num=4, degree=0), {"K": camera.K}, background=np.zeros(3, np.float32))
    with pytest.raises(TypeError, match=r"splat_colors\(\): model must be a cusgs_jax.io.SplatModel"):
        splat_colors({"means": np.zeros((1, 3))}, camera.center)
