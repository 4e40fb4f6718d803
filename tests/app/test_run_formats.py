"""End to end: a few training steps on a tiny Blender (NeRF-synthetic) scene through the app."""

from __future__ import annotations

import json

from cusgs_jax.app.run import run
from cusgs_jax.config import compose_config
from cusgs_jax.testing.transforms_scenes import write_blender_scene

TINY = ["train.iterations=6", "train.checkpoint_every=0", "train.progress=false", "eval.every=3",
        "eval.save_renders=false", "grow.stats_start=1", "grow.start=2", "grow.stop=6", "grow.interval=2",
        "model.n_offsets=4", "model.latent_dim=8", "model.hidden=16", "model.appearance_dim=8",
        "prune.start=2", "prune.interval=2", "prune.ratio=0.05", "data.random_points=1500"]


def test_blender_scene_trains_and_evaluates_on_its_test_split(tmp_path):
    truth = write_blender_scene(tmp_path / "lego", train=4, test=2, width=40, height=30)
    out = tmp_path / "run"
    result = run(compose_config([f"data.path={truth['root']}", *TINY]), out)  # voxel size auto, format auto

    saved = json.loads((out / "eval.json").read_text())
    assert saved["dataset_format"] == "blender" and saved["split"] == "transforms_test"
    assert saved["evaluated_on"] == "held_out" and saved["held_out_views"] == 2
    assert [row["name"] for row in saved["per_view"]] == ["test/r_0.png", "test/r_1.png"]
    assert saved["background"] == [1.0, 1.0, 1.0]  # splat.background not set: white for Blender
    assert 0 < saved["voxel_size"] < 0.2 and saved["alive_anchors"] > 100  # auto on the random points
    assert result["psnr"] == saved["psnr"] and saved["psnr"] > 0


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
    assert main([str(ply), "--colmap", str(truth["root"]), "--quiet"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["dataset_format"] == "blender" and result["split"] == "transforms_test"
    assert [r["name"] for r in result["per_view"]] == ["test/r_0.png", "test/r_1.png"]
    assert result["background"] == [1.0, 1.0, 1.0]
    out = tmp_path / "pngs"
    assert main([str(ply), "--colmap", str(truth["root"]), "--all", "--out-dir", str(out), "--background", "0", "0",
                 "0", "--quiet"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["background"] == [0.0, 0.0, 0.0] and result["num_views"] == 5
    assert sorted(p.name for p in out.iterdir()) == ["test_r_0.png", "test_r_1.png", "train_r_0.png",
                                                     "train_r_1.png", "train_r_2.png"]
