"""run_folder.py: the run folder's records round-trip, a folder written by revision 7f1a80c (before the
contract) still reads, and a newer version is refused with one line naming both versions."""

from __future__ import annotations

import json
import pathlib

import pytest

from cusgs_jax.errors import UserError
from cusgs_jax.run_folder import VERSION, CheckpointMeta, EvalRecord, read_eval, write_eval

OLD = pathlib.Path(__file__).parent / "fixtures" / "run_7f1a80c"  # eval.json and checkpoint metadata of its main job


def test_an_eval_record_round_trips_with_its_extra_keys_flat(tmp_path):
    old = json.loads((OLD / "eval.json").read_text())
    record = EvalRecord.from_json(old)
    assert record.version == 1 and record.time is None and record.compilations is None  # before the contract
    assert record.psnr == old["psnr"] and record.get("lpips_vgg") == old["lpips_vgg"]
    assert set(record.extra) == {"lpips_vgg", "lpips_alex", "render_ms_before_prune", "prune", "densify", "features"}
    new = EvalRecord.from_json({**record.to_json(), "version": VERSION, "time": {"total": 1.0}})
    write_eval(tmp_path, new)
    again = read_eval(tmp_path)
    assert again == new and again.to_json() == json.loads((tmp_path / "eval.json").read_text())
    assert {k: v for k, v in again.to_json().items() if k in old} == old  # every key of the old record kept
    assert read_eval(tmp_path / "missing") is None


def test_checkpoint_metadata_round_trips_and_the_old_one_reads():
    old = json.loads((OLD / "checkpoint_metadata.json").read_text())
    meta = CheckpointMeta.from_json(old)
    assert (meta.version, meta.step, meta.capacity, meta.scene_digest) == (1, 3000, old["capacity"], None)
    assert meta.train_cameras["width"] == 160 and meta.config["data"]["path"] is None
    assert CheckpointMeta.from_json(meta.to_json()) == meta
    assert meta.get("scene_digest", "absent") == "absent" and meta.get("curve") == old["curve"]


@pytest.mark.parametrize("record", [EvalRecord, CheckpointMeta])
def test_a_newer_version_is_refused_naming_both(record):
    with pytest.raises(UserError, match=rf"x\.json was written by a newer cusgs-jax \(run-folder version "
                                        rf"{VERSION + 1}; this one reads versions 1-{VERSION}\): upgrade"):
        record.from_json({"version": VERSION + 1}, "x.json")
    with pytest.raises(UserError, match="not a run-folder version"):
        record.from_json({"version": "two"}, "x.json")


def test_a_damaged_eval_json_is_named(tmp_path):
    (tmp_path / "eval.json").write_text("{not json")
    with pytest.raises(UserError, match=r"eval.json cannot be read \(JSONDecodeError"):
        read_eval(tmp_path)


def test_a_refused_runs_hydra_record_is_replaced_by_the_accepted_one(tmp_path):
    from cusgs_jax.run_folder import HYDRA_DIR, accept_hydra_record, restore_hydra_record

    assert not restore_hydra_record(tmp_path)  # nothing accepted yet (and no Hydra): nothing to do
    accept_hydra_record(tmp_path)
    assert not (tmp_path / HYDRA_DIR).exists()  # outside Hydra nothing is written
    record = tmp_path / HYDRA_DIR
    record.mkdir()
    for name, text in (("config.yaml", "a: 1\n"), ("overrides.yaml", "- a=1\n")):
        (record / name).write_text(text)
    accept_hydra_record(tmp_path)
    (record / "config.yaml").write_text("a: 2\n")  # a later, refused job's
    (record / "overrides.yaml").write_text("- a=2\n")
    assert restore_hydra_record(tmp_path)
    assert (record / "config.yaml").read_text() == "a: 1\n" and (record / "overrides.yaml").read_text() == "- a=1\n"
