"""Orbax checkpoints of the whole training state (training/checkpoint.py)."""

from __future__ import annotations

import errno
import gc
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.config import Config
from cusgs_jax.densify import ops
from cusgs_jax.densify.factory import make_strategies
from cusgs_jax.errors import CheckpointError
from cusgs_jax.training.checkpoint import Checkpointer, quiet_orbax
from cusgs_jax.training.state import TrainState, init_train_state

CFG = Config().replace(train=dict(iterations=10),
                       model=dict(voxel_size=0.25, n_offsets=4, latent_dim=8, hidden=16, appearance_dim=8))


@pytest.fixture(scope="module")
def fresh():
    pts = np.random.default_rng(0).uniform(-1, 1, (300, 3))
    return init_train_state(CFG, pts, 2, 2.0, make_strategies(CFG))


def _perturbed(state, seed):
    """A state whose every float leaf differs from the fresh one (and counters moved)."""
    key = jax.random.PRNGKey(seed)
    leaves, treedef = jax.tree_util.tree_flatten(state)
    keys = jax.random.split(key, len(leaves))
    leaves = [x + jax.random.normal(k, x.shape, x.dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x
              for x, k in zip(leaves, keys)]
    state = jax.tree_util.tree_unflatten(treedef, leaves)
    return state.replace(step=jnp.int32(7 + seed), skipped=jnp.int32(seed))


def _assert_same(a, b):
    leaves_a, leaves_b = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    assert jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b)
    assert len(leaves_a) == len(leaves_b) > 0
    for x, y in zip(leaves_a, leaves_b):
        assert np.asarray(x).dtype == np.asarray(y).dtype
        np.testing.assert_array_equal(x, y)


def test_save_restore_round_trip_is_exact(fresh, tmp_path):
    template, _ = fresh
    saved = _perturbed(template, 1)
    ckpt = Checkpointer(tmp_path / "ckpt")
    assert ckpt.latest_step() is None
    ckpt.save(8, saved, {"step": 8, "curve": [{"step": 5, "psnr": 12.5}], "capacity": saved.anchors.capacity})
    assert ckpt.latest_step() == 8 and ckpt.step_bytes() > 0
    assert ckpt.metadata() == {"step": 8, "curve": [{"step": 5, "psnr": 12.5}], "capacity": saved.anchors.capacity}
    restored, meta = ckpt.restore(template)
    ckpt.close()
    assert isinstance(restored, TrainState) and meta["step"] == 8
    _assert_same(restored, saved)
    # a new Checkpointer on the same folder (a resumed process) finds it too
    again = Checkpointer(tmp_path / "ckpt")
    assert again.latest_step() == 8
    _assert_same(again.restore(template)[0], saved)
    again.close()


def test_keeps_the_newest_and_restores_any_kept_step(fresh, tmp_path):
    template, _ = fresh
    ckpt = Checkpointer(tmp_path / "ckpt", max_to_keep=2)
    states = {step: _perturbed(template, step) for step in (1, 2, 3)}
    for step, state in states.items():
        ckpt.save(step, state, {"step": step})
    assert ckpt.latest_step() == 3
    assert sorted(int(p.name) for p in (tmp_path / "ckpt").iterdir() if p.name.isdigit()) == [2, 3]
    _assert_same(ckpt.restore(template, step=2)[0], states[2])
    assert ckpt.metadata(2) == {"step": 2}
    ckpt.close()


def test_half_written_checkpoint_is_ignored(fresh, tmp_path):
    template, _ = fresh
    ckpt = Checkpointer(tmp_path / "ckpt")
    ckpt.save(4, _perturbed(template, 4), {"step": 4})
    ckpt.close()
    partial = tmp_path / "ckpt" / "9.orbax-checkpoint-tmp-1234"
    partial.mkdir()
    (partial / "junk").write_text("partial")
    resumed = Checkpointer(tmp_path / "ckpt")
    assert resumed.latest_step() == 4
    assert resumed.metadata() == {"step": 4}
    resumed.close()


def test_restore_into_a_grown_capacity(fresh, tmp_path):
    """A run whose capacity grew is restored into a template padded to the saved capacity."""
    template, tx = fresh
    grown = _perturbed(ops.grow_capacity(template, tx, template.anchors.capacity + 17), 5)
    ckpt = Checkpointer(tmp_path / "ckpt")
    ckpt.save(5, grown, {"capacity": grown.anchors.capacity})
    capacity = ckpt.metadata()["capacity"]
    restored, _ = ckpt.restore(ops.grow_capacity(template, tx, capacity))
    ckpt.close()
    assert restored.anchors.capacity == template.anchors.capacity + 17
    _assert_same(restored, grown)


# --- robustness: damaged checkpoints, changed model, full disk, unwritable folder --------------


@pytest.fixture(scope="module")
def saved_pair(fresh, tmp_path_factory):
    """A pristine folder with checkpoints 1 and 2 (copied by each test before damaging it)."""
    template, _ = fresh
    folder = tmp_path_factory.mktemp("pair") / "ckpt"
    states = {step: _perturbed(template, step) for step in (1, 2)}
    ckpt = Checkpointer(folder)
    for step, state in states.items():
        ckpt.save(step, state, {"step": step})
    ckpt.close()
    return folder, states


def _copy(saved_pair, tmp_path):
    folder, states = saved_pair
    shutil.copytree(folder, tmp_path / "ckpt")
    return tmp_path / "ckpt", states


def _largest_data_file(step_folder):
    """The biggest array data file (TensorStore/OCDBT keeps them in ``d/`` folders)."""
    return max((f for f in (step_folder / "state").rglob("*") if f.is_file() and f.parent.name == "d"),
               key=lambda f: f.stat().st_size)


def _truncate(path):
    with open(path, "r+b") as f:
        f.truncate(path.stat().st_size // 2)


DAMAGE = {
    "truncated array file": lambda step: _truncate(_largest_data_file(step)),
    "deleted array file": lambda step: _largest_data_file(step).unlink(),
    "corrupt metadata json": lambda step: (step / "meta" / "metadata").write_text("{not json"),
    "corrupt tree metadata": lambda step: (step / "state" / "_METADATA").write_text("{not json"),
    "deleted state folder": lambda step: shutil.rmtree(step / "state"),
}


def _warnings(caplog):
    return [r.getMessage() for r in caplog.records if r.name == "cusgs_jax" and r.levelno == logging.WARNING]


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_damaged_newest_checkpoint_falls_back_to_the_previous_one(fresh, saved_pair, tmp_path, caplog, damage):
    template, _ = fresh
    folder, states = _copy(saved_pair, tmp_path)
    DAMAGE[damage](folder / "2")
    ckpt = Checkpointer(folder)
    asked = []

    def make_template(meta):
        asked.append(meta["step"])
        return template

    with caplog.at_level(logging.WARNING):
        restored, meta = ckpt.restore_latest(make_template)
    _assert_same(restored, states[1])
    assert meta == {"step": 1}
    assert asked[-1] == 1  # the template is built from the metadata of the checkpoint it restores
    warned = _warnings(caplog)
    assert any(str(folder / "2") in w and "trying checkpoint 1" in w for w in warned), warned
    assert all("\n" not in w and len(w) < 600 for w in warned)
    assert not [r for r in caplog.records if r.name == "absl" and r.levelno >= logging.WARNING]
    # the damaged one is moved aside, so the resumed run can write its step again
    assert ckpt.latest_step() == 1 and (folder / "2.damaged").is_dir()
    ckpt.save(2, states[2], {"step": 2})
    _assert_same(ckpt.restore(template)[0], states[2])
    ckpt.close()


def test_old_interface_falls_back_too(fresh, saved_pair, tmp_path, caplog):
    """``metadata()`` then ``restore(template)`` (no step) skip a checkpoint with corrupt metadata."""
    template, _ = fresh
    folder, states = _copy(saved_pair, tmp_path)
    DAMAGE["corrupt metadata json"](folder / "2")
    ckpt = Checkpointer(folder)
    with caplog.at_level(logging.WARNING):
        assert ckpt.metadata() == {"step": 1}
        restored, meta = ckpt.restore(template)
    _assert_same(restored, states[1])
    assert meta == {"step": 1} and any(str(folder / "2") in w for w in _warnings(caplog))
    with pytest.raises(CheckpointError, match=re.escape(f"checkpoint {folder / '2'} cannot be restored (")):
        ckpt.metadata(2)
    ckpt.close()


def test_no_restorable_checkpoint_is_a_checkpoint_error(fresh, saved_pair, tmp_path, caplog):
    template, _ = fresh
    folder, _ = _copy(saved_pair, tmp_path)
    for step in (1, 2):
        DAMAGE["corrupt metadata json"](folder / str(step))
    ckpt = Checkpointer(folder)
    with caplog.at_level(logging.WARNING), pytest.raises(CheckpointError) as info:
        ckpt.restore_latest(lambda meta: template)
    message = str(info.value)
    assert str(folder) in message and "tried 2: JSONDecodeError" in message and "; 1: JSONDecodeError" in message
    assert "hydra.run.dir" in message and "\n" not in message
    assert len(_warnings(caplog)) == 2
    assert sorted(p.name for p in folder.iterdir()) == ["1", "2"]  # nothing moved when nothing restored
    ckpt.close()
    with pytest.raises(CheckpointError, match="no checkpoint in .* to restore"):
        Checkpointer(tmp_path / "empty").restore_latest(lambda meta: template)


def test_changed_model_shape_is_an_error_without_fallback(fresh, saved_pair, tmp_path, caplog):
    folder, _ = _copy(saved_pair, tmp_path)
    cfg = CFG.replace(model=dict(hidden=32))
    pts = np.random.default_rng(0).uniform(-1, 1, (300, 3))
    wider, _ = init_train_state(cfg, pts, 2, 2.0, make_strategies(cfg))
    ckpt = Checkpointer(folder)
    with caplog.at_level(logging.WARNING), pytest.raises(CheckpointError) as info:
        ckpt.restore_latest(lambda meta: wider)
    message = str(info.value)
    assert message.startswith(f"checkpoint {folder / '2'} does not fit this model: ")
    assert re.search(r"nets\.decoder\.\w+\.\w+ stored \(\d+(, \d+)?\), expected \(\d+(, \d+)?\)", message), message
    assert message.count(", expected (") == 3 and re.search(r"\(and \d+ more\)", message)
    assert "different model settings" in message and "hydra.run.dir" in message and "strict" not in message
    assert not _warnings(caplog)  # no fallback tried
    assert ckpt.latest_step() == 2 and sorted(p.name for p in folder.iterdir()) == ["1", "2"]
    with pytest.raises(CheckpointError, match="does not fit this model"):
        ckpt.restore(wider, step=1)
    ckpt.close()


def test_changed_tree_structure_names_missing_and_extra_leaves(tmp_path):
    ckpt = Checkpointer(tmp_path / "ckpt")
    ckpt.save(1, {"a": jnp.zeros(3), "b": jnp.zeros(2), "same": jnp.zeros((2, 2))}, {"step": 1})
    with pytest.raises(CheckpointError) as info:
        ckpt.restore({"a": jnp.zeros(4), "c": jnp.zeros(2), "same": jnp.zeros((2, 2))})
    message = str(info.value)
    assert "a stored (3,), expected (4,)" in message
    assert "c missing from the checkpoint, expected (2,)" in message
    assert "b stored (2,), not in this model" in message
    assert "same" not in message and "more)" not in message
    ckpt.close()


def _fail_tmp_writes(monkeypatch, code):
    """Make orbax's Python-side file writes into an unfinished checkpoint fail with OS error ``code``."""
    from orbax.checkpoint._src.path import async_path

    real = async_path.write_text

    async def write_text(path, text, *args, **kwargs):
        if ".orbax-checkpoint-tmp" in str(path):
            raise OSError(code, os.strerror(code), str(path))
        return await real(path, text, *args, **kwargs)

    monkeypatch.setattr(async_path, "write_text", write_text)


@pytest.mark.parametrize("code, expected", [
    (errno.ENOSPC, "disk full while writing checkpoint 2 into {dir}: free space or point train.checkpoint_dir at a "
                   "disk with room; the last complete checkpoint is 1 (resume with train.resume=true)"),
    (errno.EDQUOT, "disk quota exceeded while writing checkpoint 2 into {dir}: "),
    (errno.EACCES, "cannot write checkpoint 2 into {dir} (Permission denied): set train.checkpoint_dir (or "
                   "hydra.run.dir) to a writable folder; the last complete checkpoint is 1"),
])
def test_failed_save_removes_the_partial_checkpoint(fresh, tmp_path, monkeypatch, caplog, code, expected):
    template, _ = fresh
    folder = tmp_path / "ckpt"
    states = {step: _perturbed(template, step) for step in (1, 2)}
    ckpt = Checkpointer(folder)
    ckpt.save(1, states[1], {"step": 1})
    _fail_tmp_writes(monkeypatch, code)
    # as cusgs-train does: without quiet_orbax the same error arrives, followed by unraisable "Event loop is closed";
    # what quiet_orbax lets through during the failed save is recorded (orbax's later reads, which a loaded
    # machine's garbage collector may report at any time, are not this test's business)
    # what earlier tests' failed reads left unawaited is collected (and its log records forgotten) first, so that
    # what the block lets through can only be this save's
    gc.collect()
    caplog.clear()
    passed_through, outer = [], sys.unraisablehook
    sys.unraisablehook = passed_through.append
    try:
        with quiet_orbax(), caplog.at_level(logging.WARNING), pytest.raises(CheckpointError) as info:
            ckpt.save(2, states[2], {"step": 2})
            time.sleep(0.2)  # inside the block: orbax's abandoned writes report into closed loops meanwhile
    finally:
        sys.unraisablehook = outer
    assert not passed_through, [str(u.exc_value) for u in passed_through]
    assert str(info.value).startswith(expected.format(dir=folder)), str(info.value)
    assert not [r for r in caplog.records if r.name in ("absl", "asyncio") and r.levelno >= logging.WARNING]
    assert sorted(p.name for p in folder.iterdir()) == ["1"]
    assert ckpt.latest_step() == 1
    _assert_same(Checkpointer(folder).restore(template)[0], states[1])
    monkeypatch.undo()  # room again: the same Checkpointer saves
    ckpt.save(2, states[2], {"step": 2})
    _assert_same(ckpt.restore(template)[0], states[2])
    ckpt.close()


def _process_hooks():
    """What a library call must leave as it found: unraisable hook, warning filters, logger set-ups."""
    loggers = {name: logging.getLogger(name) for name in ("", "absl", "asyncio", "cusgs_jax")}
    return dict(unraisablehook=sys.unraisablehook, excepthook=sys.excepthook, warnings=list(warnings.filters),
                loggers={name: (list(lg.handlers), list(lg.filters), lg.level, lg.propagate, lg.disabled)
                         for name, lg in loggers.items()})


# outside quiet_orbax the failed save's leftovers reach pytest's unraisable hook: expected here
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_library_calls_leave_process_hooks_alone(fresh, saved_pair, tmp_path, monkeypatch):
    """Save, restore, a damaged restore, a failed save and read_arrays outside quiet_orbax change no global
    hook; quiet_orbax installs its filters only while its block runs."""
    from cusgs_jax.training.checkpoint import read_arrays

    template, _ = fresh
    before = _process_hooks()
    folder, states = _copy(saved_pair, tmp_path)
    DAMAGE["truncated array file"](folder / "2")
    ckpt = Checkpointer(folder)
    _assert_same(ckpt.restore_latest(lambda meta: template)[0], states[1])
    ckpt.save(3, states[2], {"step": 3})
    read_arrays(folder, step=3)
    _fail_tmp_writes(monkeypatch, errno.ENOSPC)
    with pytest.raises(CheckpointError, match="disk full"):
        ckpt.save(4, states[2], {"step": 4})
    monkeypatch.undo()
    ckpt.close()
    assert _process_hooks() == before
    with quiet_orbax():
        inside = _process_hooks()
        with quiet_orbax():  # nested: still installed after the inner block
            pass
        assert _process_hooks() == inside
    assert inside["unraisablehook"] != before["unraisablehook"]
    assert inside["loggers"]["absl"] != before["loggers"]["absl"]
    assert _process_hooks() == before


def test_saving_an_existing_step_is_a_checkpoint_error(fresh, tmp_path):
    template, _ = fresh
    ckpt = Checkpointer(tmp_path / "ckpt")
    ckpt.save(3, template, {"step": 3})
    with pytest.raises(CheckpointError, match=r"checkpoint 3 already exists in .*train\.resume=true"):
        ckpt.save(3, template, {"step": 3})
    ckpt.close()


DISK_FULL_SCRIPT = """
import json, os, pathlib, sys
import jax, jax.numpy as jnp
from cusgs_jax.errors import CheckpointError
from cusgs_jax.training.checkpoint import Checkpointer, quiet_orbax
mount = pathlib.Path(sys.argv[1])
state = {"w": jax.random.normal(jax.random.PRNGKey(0), (200, 256)), "n": jnp.int32(1)}
with quiet_orbax():  # as cusgs-train's main: orbax's repeats of the failure are dropped while it runs
    ckpt = Checkpointer(mount / "ckpt")
    ckpt.save(1, state, {"step": 1})
    with open(mount / "filler", "wb", buffering=0) as f:  # fill the disk, then leave 60 KiB: too little for step 2
        try:
            while True:
                f.write(b"x" * 4096)
        except OSError:
            pass
    os.truncate(mount / "filler", os.path.getsize(mount / "filler") - 60 * 1024)
    try:
        ckpt.save(2, jax.tree_util.tree_map(lambda x: x + 1, state), {"step": 2})
        error = None
    except CheckpointError as e:
        error = str(e)
        ckpt.close_after_error()  # as cusgs-train: orbax's threads stop before the interpreter does
    reader = Checkpointer(mount / "ckpt")
    restored, meta = reader.restore(state)
    reader.close()
print(json.dumps(dict(error=error, entries=sorted(p.name for p in (mount / "ckpt").iterdir()), meta=meta,
                      same=bool(jnp.array_equal(restored["w"], state["w"])))))
"""


def test_real_full_disk(tmp_path):
    """A save into a 1 MiB tmpfs that fills up (in a private mount namespace; skipped where unavailable)."""
    mount = tmp_path / "disk"
    mount.mkdir()
    mount_cmd = f"mount -t tmpfs -o size=1m tmpfs {mount}"
    if shutil.which("unshare") is None or subprocess.run(
            ["unshare", "-Urm", "sh", "-c", mount_cmd], capture_output=True).returncode != 0:
        pytest.skip("cannot mount a small tmpfs in a user namespace here")
    script = tmp_path / "fill.py"
    script.write_text(DISK_FULL_SCRIPT)
    run = subprocess.run(["unshare", "-Urm", "sh", "-c", f'{mount_cmd} && exec "$0" "$1" "$2"', sys.executable,
                          str(script), str(mount)], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    assert out["error"] == (f"disk full while writing checkpoint 2 into {mount / 'ckpt'}: free space or point "
                            f"train.checkpoint_dir at a disk with room; the last complete checkpoint is 1 "
                            f"(resume with train.resume=true)")
    assert out["entries"] == ["1"] and out["meta"] == {"step": 1} and out["same"]
    assert "Traceback" not in run.stderr and "absl" not in run.stderr, run.stderr[-3000:]


def test_os_error_is_found_anywhere_in_the_chain():
    from cusgs_jax.training.checkpoint import _os_error

    tensorstore = ValueError('RESOURCE_EXHAUSTED: Error writing local file "x": Failed to write 10 bytes: '
                             "No space left on device [os_error_code='28']")
    assert _os_error(tensorstore)[0] == errno.ENOSPC
    group = ExceptionGroup("writes", [ValueError("other"), OSError(errno.EDQUOT, "Disk quota exceeded")])
    try:
        raise RuntimeError("commit failed") from group
    except RuntimeError as e:
        assert _os_error(e)[0] == errno.EDQUOT
    try:
        try:
            raise PermissionError(errno.EACCES, "Permission denied")
        except PermissionError:
            raise ValueError("while committing")  # implicit __context__
    except ValueError as e:
        assert _os_error(e) == (errno.EACCES, "Permission denied")
    assert _os_error(ValueError("Requested shape (32,) is not compatible")) is None


def test_unwritable_checkpoint_folder_fails_at_construction(tmp_path, monkeypatch):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    for target in (blocker / "ckpt", blocker):
        with pytest.raises(CheckpointError) as info:
            Checkpointer(target)
        message = str(info.value)
        assert message.startswith(f"checkpoint folder {target} is not writable (")
        assert "set train.checkpoint_dir or hydra.run.dir to a writable folder" in message
    # a folder that exists but refuses files (read-only mount, no permission): the probe write fails
    import cusgs_jax.training.checkpoint as checkpoint

    def refuse(*args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", str(tmp_path / "ro"))

    monkeypatch.setattr(checkpoint.tempfile, "mkstemp", refuse)
    with pytest.raises(CheckpointError, match=re.escape(f"checkpoint folder {tmp_path / 'ro'} is not writable "
                                                        "(Permission denied)")):
        Checkpointer(tmp_path / "ro")


# --- read_arrays: template-free, read-only (cusgs-export, viewers) ------------------------------


def _listing(folder):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def _truncate_every_array_file(step_folder):
    for f in (step_folder / "state").rglob("*"):
        if f.is_file() and f.parent.name == "d":
            _truncate(f)


# read_arrays reads only some arrays: damage to a file holding only optimiser moments goes unnoticed (and
# does not matter), so array damage here hits every data file
READ_DAMAGE = {"truncated array files": _truncate_every_array_file,
               **{k: v for k, v in DAMAGE.items() if "array file" not in k}}


@pytest.mark.parametrize("damage", list(READ_DAMAGE))
def test_read_arrays_falls_back_without_touching_the_folder(saved_pair, tmp_path, caplog, damage):
    from cusgs_jax.training.checkpoint import read_arrays

    folder, states = _copy(saved_pair, tmp_path)
    READ_DAMAGE[damage](folder / "2")
    before = _listing(folder)
    with quiet_orbax(), caplog.at_level(logging.WARNING):  # as cusgs-export and cusgs-view
        step, arrays, meta = read_arrays(folder, ("anchors", "nets"))
        time.sleep(0.2)  # orbax's abandoned reads report into closed loops meanwhile
    assert step == 1 and meta == {"step": 1} and set(arrays) == {"anchors", "nets"}
    want = states[1]
    np.testing.assert_array_equal(arrays["anchors"]["centers"], want.anchors.centers)
    np.testing.assert_array_equal(arrays["anchors"]["params"]["latent"], want.anchors.params.latent)
    assert arrays["anchors"]["params"]["query_table"] is None
    np.testing.assert_array_equal(arrays["nets"]["decoder"]["cov"]["w1"], want.nets["decoder"]["cov"]["w1"])
    assert isinstance(arrays["anchors"]["alive"], np.ndarray) and arrays["anchors"]["alive"].dtype == bool
    assert any(str(folder / "2") in w and "trying checkpoint 1" in w for w in _warnings(caplog))
    assert not [r for r in caplog.records if r.name == "absl" and r.levelno >= logging.WARNING]
    assert _listing(folder) == before  # nothing moved aside, nothing created


def test_read_arrays_errors_name_the_folder(saved_pair, tmp_path, caplog):
    from cusgs_jax.training.checkpoint import read_arrays

    folder, _ = _copy(saved_pair, tmp_path)
    with pytest.raises(CheckpointError, match=re.escape(f"no checkpoint 5 in {folder} (steps there: 2, 1)")):
        read_arrays(folder, step=5)
    with pytest.raises(CheckpointError, match="has no queries in its state"):
        read_arrays(folder, ("anchors", "queries"))
    for step in (1, 2):
        DAMAGE["corrupt metadata json"](folder / str(step))
    with caplog.at_level(logging.WARNING), pytest.raises(CheckpointError, match=f"no checkpoint in {folder} can be"):
        read_arrays(folder)
    with pytest.raises(CheckpointError, match=re.escape(f"checkpoint {folder / '2'} cannot be read")):
        read_arrays(folder, step=2)
    with pytest.raises(CheckpointError, match="no checkpoint folder"):
        read_arrays(tmp_path / "missing")
    assert not (tmp_path / "missing").exists()
