"""run_folder.py: the run folder's records round-trip, a folder written by revision 7f1a80c (before the
contract) still reads, a newer version is refused with one line naming both versions, and a current record
with a key it does not define is refused naming the key."""

from __future__ import annotations

import json
import pathlib

import pytest

from cusgs_jax.errors import UserError
from cusgs_jax.run_folder import VERSION, CheckpointMeta, EvalRecord, read_eval, write_eval

OLD = pathlib.Path(__file__).parent / "fixtures" / "run_7f1a80c"  # eval.json and checkpoint metadata of its main job


def test_an_eval_record_round_trips_and_the_old_one_reads_every_key_typed(tmp_path):
    old = json.loads((OLD / "eval.json").read_text())
    record = EvalRecord.from_json(old)
    assert record.version == 1 and record.time is None and record.compilations is None  # before the contract
    assert record.psnr == old["psnr"] and record.lpips_vgg == old["lpips_vgg"] and record.prune == old["prune"]
    assert record.extra == {} and record.features == old["features"] and record.densify == old["densify"]
    new = EvalRecord.from_json({**record.to_json(), "version": VERSION, "time": {"total": 1.0}})
    write_eval(tmp_path, new)
    again = read_eval(tmp_path)
    assert again == new and again.to_json() == json.loads((tmp_path / "eval.json").read_text())
    assert {k: v for k, v in again.to_json().items() if k in old} == old  # every key of the old record kept
    assert read_eval(tmp_path / "missing") is None


def test_an_unknown_key_is_refused_in_a_current_record_and_kept_in_an_older_one(tmp_path):
    with pytest.raises(UserError, match=r"x\.json: 'psnrr' is not a key of the run's record \(run-folder version "
                                        rf"{VERSION}; its keys are .*psnr.*\): the file was edited"):
        EvalRecord.from_json({"version": VERSION, "psnrr": 30.0}, "x.json")
    with pytest.raises(UserError, match=r"'a', 'b' are not keys of a checkpoint's metadata"):
        CheckpointMeta.from_json({"version": VERSION, "step": 3, "a": 1, "b": 2}, "x.json")
    (tmp_path / "eval.json").write_text(json.dumps({"version": VERSION, "psnr": 30.0, "psnrr": 1}))
    with pytest.raises(UserError, match="'psnrr' is not a key"):
        read_eval(tmp_path)  # every reader goes through read_eval
    older = EvalRecord.from_json({"version": 2, "psnr": 30.0, "time": {"total": 9.0}, "counted_views": 4},
                                 "x.json")  # a v2 strategy's key
    assert older.extra == {"counted_views": 4} and older.get("counted_views") == 4
    assert older.to_json()["counted_views"] == 4  # written back flat, as version 2 wrote it


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


@pytest.mark.parametrize("time, message", [
    (None, rf"'time' is missing \(run-folder version {VERSION} records hold the run's time budget from version 2 on\)"),
    ({"total": 9.0, "compile_wait": -5.0}, r"time\.compile_wait=-5\.0 is not a number of seconds >= 0"),
    ({"total": float("nan")}, r"time\.total=nan is not a number of seconds >= 0"),
    ({"total": "9"}, r"time\.total='9' is not a number of seconds >= 0"),
    ({"total": 9.0, "load": True}, r"time\.load=True is not a number of seconds >= 0"),
    ({"total": 9.0, "other": None}, r"time\.other=None is not a number of seconds >= 0"),
    ([9.0], r"time=\[9\.0\] is not a JSON object of seconds per stage"),
])
def test_eval_json_time_entries_are_seconds_and_present_from_version_2(tmp_path, time, message):
    data = {"version": VERSION, "psnr": 30.0, **({} if time is None else {"time": time})}
    (tmp_path / "eval.json").write_text(json.dumps(data))
    with pytest.raises(UserError, match=rf"^{tmp_path / 'eval.json'}: {message}: the file was edited"):
        read_eval(tmp_path)
    good = {"total": 9.0, "compile_wait": 0, "train_steps": 5.5, "compile": None}  # compile: compiles not told apart
    assert EvalRecord.from_json(dict(data, time=good)).time == good
    assert EvalRecord.from_json({"psnr": 30.0}).time is None  # version 1 (unversioned) records predate it
