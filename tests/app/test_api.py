"""cusgs_jax.train (app/api.py): the CLI's run as a library function — its config argument, its console log, and
the model and record it returns (what load_trained and read_eval read back)."""

from __future__ import annotations

import json
import logging
import sys

import numpy as np
import pytest

import cusgs_jax as cg
from cusgs_jax.app.api import LOG_FORMAT, as_config, console_log
from cusgs_jax.errors import ConfigError

QUICK = ["train.iterations=4", "train.progress=false", "eval.every=2", "train.checkpoint_every=0",
         "train.log_every=2", "eval.save_renders=false", "model.n_offsets=4", "model.latent_dim=8", "model.hidden=16",
         "model.appearance_dim=8", "features=none"]


def test_config_is_a_config_a_list_of_overrides_or_none():
    cfg = cg.compose_config(["train.iterations=7"])
    assert as_config(cfg) is cfg
    assert as_config(["train.iterations=7"]) == cfg
    assert as_config(None) == cg.compose_config([])
    for bad in ("train.iterations=7", [1, 2], {"train": 1}):
        with pytest.raises(ConfigError, match="list of overrides"):
            as_config(bad)


def bare_logging(monkeypatch):
    """No logging configured but absl's bare basicConfig() handler on the root (as after importing orbax); set in
    the test's body (pytest's log capture adds its own root handlers for the call)."""
    root, package = logging.getLogger(), logging.getLogger("cusgs_jax")
    bare = logging.StreamHandler(sys.stderr)
    bare.setFormatter(logging.Formatter(logging.BASIC_FORMAT))
    monkeypatch.setattr(root, "handlers", [bare])
    monkeypatch.setattr(package, "handlers", [])
    monkeypatch.setattr(package, "level", logging.NOTSET)
    return package


def test_the_log_is_printed_as_the_cli_prints_it_only_where_nobody_configured_logging(monkeypatch):
    package = bare_logging(monkeypatch)
    with console_log():
        (handler,) = package.handlers
        assert handler.formatter._fmt == LOG_FORMAT and package.getEffectiveLevel() == logging.INFO
        assert not package.propagate  # not printed a second time by the bare root handler
    assert package.handlers == [] and package.propagate and package.level == logging.NOTSET  # put back
    with console_log(enabled=False):
        assert package.handlers == []
    mine = logging.StreamHandler(sys.stdout)
    monkeypatch.setattr(logging.getLogger(), "handlers", [mine])  # the caller's own configuration is left alone
    with console_log():
        assert package.handlers == []


def test_train_returns_the_model_load_trained_reads_and_the_record_read_eval_reads(tmp_path, tiny_scene):
    model, record = cg.train([f"data.path={tiny_scene}", *QUICK], tmp_path / "run", log=False)
    assert record == cg.read_eval(tmp_path / "run")
    loaded = cg.load_trained(tmp_path / "run")
    assert model.step == loaded.step == 4 and model.world == loaded.world and model.cfg == loaded.cfg
    for a, b in zip(jax_leaves(model.anchors) + jax_leaves(model.nets), jax_leaves(loaded.anchors)
                    + jax_leaves(loaded.nets)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(model.cameras.world_to_camera, loaded.cameras.world_to_camera)
    np.testing.assert_array_equal(model.held_out_cameras.K, loaded.held_out_cameras.K)
    assert model.checkpoint_bytes == loaded.checkpoint_bytes > 0
    # every loss term: in each metrics.jsonl row (weighted; they sum to the loss) and summed in eval.json
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [row["step"] for row in rows] == [2, 4]
    for row in rows:
        assert set(row["terms"]) == {"l1", "ssim", "volume"}
        np.testing.assert_allclose(sum(row["terms"].values()), row["loss"], rtol=1e-5)
    assert record.loss_terms["steps"] == 4 and set(record.loss_terms["sum"]) == {"l1", "ssim", "volume"}
    assert record.appearance == "nearest"


def jax_leaves(tree) -> list[np.ndarray]:
    import jax

    return [np.asarray(leaf) for leaf in jax.tree_util.tree_leaves(tree)]
