"""End-to-end runs on a tiny demo scene: outputs, exact resume, interrupted saves, the Hydra app."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import jax
import numpy as np
import pytest
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from cusgs_jax.checkpoint import Checkpointer
from cusgs_jax.data.demo import generate_demo_scene
from cusgs_jax.runner import run, view_order

TINY = ["train.iterations=30", "train.checkpoint_every=10", "train.progress=false", "eval.every=15",
        "grow.stats_start=2", "grow.start=10", "grow.stop=30", "grow.interval=10",
        "model.n_offsets=4", "model.latent_dim=8", "model.hidden=16", "model.appearance_dim=8",
        "model.voxel_size=0.15", "prune.start=10", "prune.interval=10", "prune.ratio=0.05"]


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return generate_demo_scene(tmp_path_factory.mktemp("scene") / "demo", num_views=9, width=40, height=30,
                               num_points=1500)


def _cfg(scene, *extra):
    with initialize_config_module("cusgs_jax.conf", version_base="1.3"):
        cfg = compose("config", overrides=[f"data.path={scene}", *TINY, *extra])
    return OmegaConf.to_container(cfg, resolve=True)


def _final_state_leaves(run_dir):
    ckpt = Checkpointer(run_dir / "checkpoints")
    step = ckpt.latest_step()
    path = run_dir / "checkpoints" / str(step)
    ckpt.close()
    import orbax.checkpoint as ocp

    restored = ocp.StandardCheckpointer().restore(path / "state")
    return step, jax.tree_util.tree_leaves(restored)


def test_view_order_is_a_permutation_per_epoch():
    seq = [view_order(3, 7, s) for s in range(14)]
    assert sorted(seq[:7]) == list(range(7)) and sorted(seq[7:]) == list(range(7))
    assert seq == [view_order(3, 7, s) for s in range(14)]


def test_run_writes_all_outputs(tiny_scene, tmp_path):
    result = run(_cfg(tiny_scene), tmp_path)
    assert np.isfinite(result["psnr"]) and result["psnr"] > 8
    for name in ("metrics.jsonl", "eval_curve.jsonl", "eval.json", "error_vs_time.png"):
        assert (tmp_path / name).is_file(), name
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == list(range(10, 31, 10))
    assert {"wall_s", "loss", "train_psnr", "alive_anchors"} <= set(rows[0])
    curve = [json.loads(line) for line in (tmp_path / "eval_curve.jsonl").read_text().splitlines()]
    assert [c["step"] for c in curve] == [15, 30]
    evaluation = json.loads((tmp_path / "eval.json").read_text())
    assert len(evaluation["per_view"]) == 2 and evaluation["params"]["total"] > 0
    assert evaluation["checkpoint_bytes"] > 0 and evaluation["render_ms_per_view"] > 0
    # feature-aware pruning ran at steps 10, 20, 30 and its count matches the anchors lost
    assert evaluation["prune"]["passes"] == 3 and evaluation["prune"]["pruned"] > 0
    assert evaluation["render_ms_before_prune"] > 0
    assert rows[-1]["pruned"] == evaluation["prune"]["pruned"]
    assert curve[-1]["alive_anchors"] == evaluation["alive_anchors"]
    assert len(list((tmp_path / "renders").glob("*.png"))) == 2


def test_resume_continues_exactly(tiny_scene, tmp_path):
    straight = tmp_path / "straight"
    run(_cfg(tiny_scene), straight)
    interrupted = tmp_path / "interrupted"
    run(_cfg(tiny_scene), interrupted)
    # pretend the run died after step 20: drop the last checkpoint, and leave a
    # half-written one behind as a kill during a save would
    shutil.rmtree(interrupted / "checkpoints" / "30")
    (interrupted / "checkpoints" / "30.orbax-checkpoint-tmp-1234").mkdir()
    (interrupted / "checkpoints" / "30.orbax-checkpoint-tmp-1234" / "junk").write_text("partial")
    run(_cfg(tiny_scene, "train.resume=true"), interrupted)
    step_a, leaves_a = _final_state_leaves(straight)
    step_b, leaves_b = _final_state_leaves(interrupted)
    assert step_a == step_b == 30
    assert len(leaves_a) == len(leaves_b)
    for a, b in zip(leaves_a, leaves_b):
        np.testing.assert_array_equal(a, b)


def test_hydra_app_runs_and_reports_bad_paths(tiny_scene, tmp_path):
    cmd = [sys.executable, "-m", "cusgs_jax.train", f"data.path={tiny_scene}", *TINY,
           "train.iterations=10", "eval.every=10", f"hydra.run.dir={tmp_path / 'app'}"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert (tmp_path / "app" / "eval.json").is_file()
    missing = tmp_path / "no_such_scene"
    cmd = [sys.executable, "-m", "cusgs_jax.train", f"data.path={missing}", f"hydra.run.dir={tmp_path / 'bad'}"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 2
    assert str(missing) in done.stderr + done.stdout


# per_gaussian drives the refilled-slot query reset through growing end to end (45 s: slow;
# test_feature_field covers refill_query_table and reset_rows(group="table") in the default run)
@pytest.mark.parametrize("granularity", ["per_anchor", pytest.param("per_gaussian", marks=pytest.mark.slow)])
def test_feature_run_reports_table2_metrics_and_retrieval(tiny_scene, tmp_path, granularity):
    result = run(_cfg(tiny_scene, "features=demo", "features.sample_pixels=200", "train.iterations=20",
                      "eval.every=20", f"model.query_granularity={granularity}"), tmp_path)
    feats = result["features"]
    assert set(feats["models"]) == {"daisy", "semantic"}
    for row in feats["models"].values():
        assert all(np.isfinite(row[k]) for k in ("cosine", "l2", "baseline_cosine", "baseline_l2"))
    assert {"rendered", "ground_truth"} <= set(feats["retrieval"])
    assert (tmp_path / "features.md").read_text().count("|") > 10
    assert len(list((tmp_path / "features").glob("*.png"))) == 4  # 2 models × 2 held-out views
    params = json.loads((tmp_path / "eval.json").read_text())["params"]
    assert params["query_heads"] > 0 and params["memory_banks"] > 0 and params["adapters"] > 0
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert np.isfinite(rows[-1]["feature_loss"])
