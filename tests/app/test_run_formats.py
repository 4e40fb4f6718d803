"""End to end: a few training steps on a tiny Blender (NeRF-synthetic) scene through the app."""

from __future__ import annotations

import json

import pytest

from cusgs_jax.app.run import run
from cusgs_jax.config import DataConfig
from cusgs_jax.compose import compose_config
from cusgs_jax.testing.transforms_scenes import write_blender_scene

# eval.every=6: the held-out curve is evaluated once, at the last step (no test reads a mid-run point, and one at
# step 3 compiles a renderer for that step's anchor capacity: 9 of this module's 32 s)
TINY = ["train.iterations=6", "train.checkpoint_every=0", "train.progress=false", "eval.every=6",
        "eval.save_renders=false", "grow.stats_start=1", "grow.start=2", "grow.stop=6", "grow.interval=2",
        "model.n_offsets=4", "model.latent_dim=8", "model.hidden=16", "model.appearance_dim=8",
        "prune.start=2", "prune.interval=2", "prune.ratio=0.05", "data.random_points=1500"]


@pytest.fixture(scope="module")
def blender_run(build_once):
    """(scene truth, run folder, run result) of a 6-step run on a tiny Blender scene (voxel size and format auto);
    trained once per session (tests/conftest.py built_once): read only."""

    def build(root):
        truth = write_blender_scene(root / "lego", train=6, test=2, width=40, height=30)
        return truth, run(compose_config([f"data.path={truth['root']}", *TINY]), root / "run")

    root, (truth, result) = build_once("blender", build)
    return truth, root / "run", result


@pytest.mark.slow  # end to end, ~20 s: in .ci/run's -m slow pass, out of the default run (kept under 8 minutes)
def test_blender_scene_trains_and_evaluates_on_its_test_split(blender_run):
    truth, out, result = blender_run

    saved = json.loads((out / "eval.json").read_text())
    assert saved["dataset_format"] == "blender" and saved["split"] == "transforms_test"
    assert saved["evaluated_on"] == "held_out" and saved["held_out_views"] == 2
    assert [row["name"] for row in saved["per_view"]] == ["test/r_0.png", "test/r_1.png"]
    assert saved["background"] == [1.0, 1.0, 1.0]  # splat.background not set: white for Blender
    assert 0 < saved["voxel_size"] < 0.2 and saved["alive_anchors"] > 100  # auto on the random points
    assert saved["initial_points"] == "cube"  # data.random_init=auto on a Blender scene
    assert result.psnr == saved["psnr"] and saved["psnr"] > 0


def test_render_ply_on_a_blender_scene(tmp_path, capsys):
    """cusgs-render-ply reads a Blender scene: its test frames, on white unless --background is given, and
    --all writes one PNG per frame though train/ and test/ share file names."""
    import numpy as np

    from cusgs_jax.app.render_ply import main
    from cusgs_jax.io import SplatModel, write_ply

    truth = write_blender_scene(tmp_path / "lego", train=3, test=2, width=24, height=18)
    g = 50
    rng = np.random.default_rng(0)
    ply = write_ply(tmp_path / "m.ply", SplatModel(
        means=rng.uniform(-1, 1, (g, 3)).astype(np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (g, 1)),
        log_scales=np.full((g, 3), np.log(0.1), np.float32), opacity_logits=np.zeros(g, np.float32),
        sh=rng.normal(size=(g, 1, 3)).astype(np.float32)))
    assert main([str(ply), "--scene", str(truth["root"]), "--quiet"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["dataset_format"] == "blender" and result["split"] == "transforms_test"
    assert [r["name"] for r in result["per_view"]] == ["test/r_0.png", "test/r_1.png"]
    assert result["background"] == [1.0, 1.0, 1.0]
    out = tmp_path / "pngs"
    assert main([str(ply), "--scene", str(truth["root"]), "--all", "--out-dir", str(out), "--background", "0", "0",
                 "0", "--quiet"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["background"] == [0.0, 0.0, 0.0] and result["num_views"] == 5
    assert sorted(p.name for p in out.iterdir()) == ["test_r_0.png", "test_r_1.png", "train_r_0.png",
                                                     "train_r_1.png", "train_r_2.png"]


@pytest.mark.slow  # end to end, ~20 s: in .ci/run's -m slow pass, out of the default run (kept under 8 minutes)
def test_blender_run_exports_to_the_scenes_own_frame(blender_run, tmp_path):
    """cusgs-export writes the PLY in the frame of transforms_*.json: the Blender-frame cameras (as the loader
    reads them) see every exported Gaussian at the pixel where the training cameras saw it in the normalised
    frame, and the PLY rendered at the test cameras scores as the run's own evaluation. (These noise images make
    the PSNR check weak: a PLY left in the normalised frame scores only ~0.5 dB lower; the projection check is
    the one that pins the frame.)"""
    import numpy as np

    from cusgs_jax.app.export import export_run
    from cusgs_jax.app.render_ply import evaluate_ply
    from cusgs_jax.data.loader import load_scene
    from cusgs_jax.data.normalize import normalize_scene
    from cusgs_jax.io import read_ply

    truth, out, _ = blender_run
    saved = json.loads((out / "eval.json").read_text())
    # the plain bake (refine=0): refinement would move the Gaussians of each file independently
    scene_frame = export_run(out, tmp_path / "scene_frame.ply", progress=False, refine=0)
    normalised = export_run(out, tmp_path / "normalised.ply", colmap_frame=False, progress=False, refine=0)

    raw = load_scene(truth["root"], DataConfig(random_points=2))  # the Blender frame, as every tool reads it
    trained, _ = normalize_scene(raw)

    def pixels(points, viewmats, Ks):
        cam = np.einsum("vij,gj->vgi", viewmats[:, :3, :3].astype(np.float64), points) + viewmats[:, None, :3, 3]
        return np.einsum("vij,vgj->vgi", Ks.astype(np.float64), cam / cam[..., 2:])[..., :2]

    a = pixels(read_ply(scene_frame["ply"]).means.astype(np.float64), raw.viewmats, raw.Ks)
    b = pixels(read_ply(normalised["ply"]).means.astype(np.float64), trained.viewmats, trained.Ks)
    np.testing.assert_allclose(a, b, atol=1e-2)
    right = evaluate_ply(scene_frame["ply"], truth["root"], progress=False)
    print(f"run {saved['psnr']:.2f} dB, PLY in the scene frame {right['psnr']:.2f} dB")
    assert right["dataset_format"] == "blender" and right["background"] == [1.0, 1.0, 1.0]
    assert right["psnr"] > saved["psnr"] - 1.5  # the export tolerance of tests/app/test_export.py


@pytest.mark.slow  # end to end, ~20 s: in .ci/run's -m slow pass
def test_a_lens_demo_trains_through_its_lens_on_the_whole_frame(tmp_path, monkeypatch):
    """data.undistort=lens on the demo through the OPENCV lens: nothing undistorted, the full frame trained
    and scored through the lens (eval.json camera_frame "lens", every pixel)."""
    monkeypatch.setenv("CUSGS_CACHE_DIR", str(tmp_path / "cache"))
    overrides = ["data.demo.lens=opencv", "data.demo.views=6", "data.demo.width=48", "data.demo.height=36",
                 "data.holdout_every=3", "features=none", *TINY[:-1]]
    result = run(compose_config([*overrides, "data.undistort=lens"]), tmp_path / "lens")
    assert (result.width, result.height) == (48, 36) and result.camera_frame == "lens"
    assert result.valid_pixels == 1.0 and result.psnr > 8
    assert not (tmp_path / "cache" / "undistorted").exists()
    from cusgs_jax import load_trained

    trained = load_trained(tmp_path / "lens")  # the recorded training cameras keep their lens
    assert trained.cameras.lens is not None and trained.cameras.lens.coeffs.shape == (len(trained.cameras.K), 6)
    cropped = run(compose_config([*overrides, "data.undistort=crop"]), tmp_path / "crop")
    assert cropped.camera_frame == "crop" and cropped.width < 48


@pytest.mark.parametrize("ply", [pytest.param(False, id="random_points"),
                                 pytest.param(True, id="ply_points", marks=pytest.mark.slow)])
def test_nerfstudio_scene_trains_and_evaluates(tmp_path, ply):
    """A tiny nerfstudio scene (OPENCV, no distortion) trains and is scored on its every-8th hold-out: without
    ply_file_path from random points along the training rays (data.random_init=auto), with it from the PLY's."""
    from cusgs_jax.testing.transforms_scenes import write_nerfstudio_scene

    truth = write_nerfstudio_scene(tmp_path / "ns", n=9, width=40, height=30, fl=(35.0, 37.5), c=(20.0, 16.25),
                                   ply=ply)
    result = run(compose_config([f"data.path={truth['root']}", *TINY]), tmp_path / "run")
    saved = json.loads((tmp_path / "run" / "eval.json").read_text())
    assert saved["dataset_format"] == "nerfstudio" and saved["split"] == "every_8th"
    assert saved["evaluated_on"] == "held_out" and saved["held_out_views"] == 2  # frames 0 and 8 of 9
    assert saved["initial_points"] == ("scene_points" if ply else "cube_and_rays")
    assert saved["background"] == [0.0, 0.0, 0.0] and saved["camera_frame"] == "crop"
    assert result.psnr == saved["psnr"] and saved["psnr"] > 0 and saved["alive_anchors"] > 0
