"""Shared test fixtures. Random scenes live in :mod:`cusgs_jax.testing.scenes`."""

from __future__ import annotations

import os
import pickle
import shutil

import filelock
import pytest

# Two virtual CPU devices in every test process (set before JAX starts), so the tests of views
# sharded over devices (training/parallel.py, the batched step) run on any machine. Single-device
# code runs on the first of them, as before.
if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip()
# The same numbers every time on a GPU too: XLA:GPU's scatter-adds (gradients, statistics) use atomics whose
# order varies from run to run unless non-deterministic ops are excluded (a CPU ignores the flag). Seen on an
# H200: two identical train steps differed in the last bit (tests/training/test_step.py).
if "nondeterministic_ops" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] += " --xla_gpu_exclude_nondeterministic_ops=true"


def built_once(tmp_path_factory, name: str, build):
    """``(folder, value)``: ``build(folder)`` run ONCE per test session, even with pytest-xdist.

    Without xdist, ``build`` runs in a fresh ``tmp_path_factory`` folder. Under xdist every worker
    would otherwise train its own copy of the same run (a session- or module-scoped fixture runs once
    per worker, and ``--dist load`` splits a module's tests over the workers): the first worker to ask
    builds the folder under the session's temporary root, which the workers share, while the others wait
    on a lock and then read it. ``value`` (what ``build`` returned; it must pickle) comes back pickled
    beside the folder, so every worker sees the builder's return value, not one re-read from the folder.
    The folder is shared: tests must only read it (copy it to change or resume it).
    """
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if worker is None:
        folder = tmp_path_factory.mktemp(name)
        return folder, build(folder)
    root = tmp_path_factory.getbasetemp().parent / "built_once"  # pytest-N/: common to this session's workers
    root.mkdir(exist_ok=True)
    folder, done = root / name, root / f"{name}.pickle"
    with filelock.FileLock(root / f"{name}.lock"):  # one builder; the other workers wait here
        if not done.is_file():
            if folder.exists():  # left by a build that failed
                shutil.rmtree(folder)
            folder.mkdir()
            value = build(folder)
            done.write_bytes(pickle.dumps(value))
            return folder, value
    return folder, pickle.loads(done.read_bytes())


@pytest.fixture(scope="session")
def build_once(tmp_path_factory):
    """:func:`built_once` for fixtures of the test modules: ``build_once(name, build) -> (folder, value)``."""
    return lambda name, build: built_once(tmp_path_factory, name, build)


@pytest.fixture(scope="module")
def tiny_scene(build_once):
    """The 9-view 40×30 demo scene of the shell's end-to-end tests (app/, benchmarks/), generated once per session
    (built_once; the runs of tests/app/test_run record its path, so every xdist worker resumes them on the same
    folder). The feature tests extract into its features/ folder, which the library serialises across processes
    (extract.scene.ensure_extracted)."""
    from cusgs_jax.data.demo import generate_demo_scene

    _, scene = build_once("run_scene", lambda root: generate_demo_scene(
        root / "demo", num_views=9, width=40, height=30, num_points=1500))
    return scene


@pytest.fixture
def two_devices():
    """Skip, saying why, unless the default backend has two devices: the views of a sharded step go to
    ``jax.devices()``. On CPU this file makes two virtual devices; a machine whose default backend is one
    GPU has one, and a single GPU cannot show a two-device sharding."""
    import jax

    if jax.device_count() < 2:
        pytest.skip(f"needs two devices of the default backend ({jax.default_backend()} has "
                    f"{jax.device_count()}); on CPU tests/conftest.py makes two virtual ones")


TINY_DEMO = dict(width=40, height=30, num_views=4, num_points=1500)
"""The tiny demo scene of the ``demo`` fixture (W, H, V as the extract tests use them)."""


@pytest.fixture(scope="session", autouse=True)
def compilation_cache(tmp_path_factory):
    """JAX's persistent compilation cache, in a folder new to this test session and shared by its xdist workers.

    Most of the suite's time is XLA compiling: each run, step or renderer a test builds is a new jitted function,
    and under xdist both workers compile what the other already has (a module split over the two, the shared
    fixtures of conftest). With the cache, a program compiled once in the session (same canonical HLO, options
    and devices) is loaded instead of compiled again: the same executable, so the same numbers. It starts
    empty every session, so every program is compiled once per session and nothing is carried between runs;
    the compile counts the tests inspect (the ``compiles`` fixture) count a cache load as a compile. Writes are locked
    (filelock, when installed) so that one worker never reads an entry the other is still writing.
    CUSGS_TEST_COMPILATION_CACHE=0 turns it off (every program compiled in the process that runs it).
    """
    import jax

    if os.environ.get("CUSGS_TEST_COMPILATION_CACHE", "1") == "0":
        yield None
        return

    worker = os.environ.get("PYTEST_XDIST_WORKER")
    base = tmp_path_factory.getbasetemp()
    folder = (base.parent if worker else base) / "jax_compilation_cache"  # pytest-N/: common to the workers
    folder.mkdir(exist_ok=True)
    before = {name: getattr(jax.config, name) for name in (
        "jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs", "jax_compilation_cache_max_size")}
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    jax.config.update("jax_compilation_cache_max_size", 16 * 2**30)  # a size limit turns on the cache's file lock
    yield folder
    for name, value in before.items():
        jax.config.update(name, value)


@pytest.fixture
def x64():
    """Run a test with float64 enabled in JAX."""
    import jax

    with jax.enable_x64(True):
        yield


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """A tiny demo scene, one per test module (tests write features with overwrite=True)."""
    from cusgs_jax.data.demo import generate_demo_scene

    return generate_demo_scene(tmp_path_factory.mktemp("demo"), **TINY_DEMO)


@pytest.fixture(scope="module")
def names(demo):
    """Image names of the ``demo`` fixture's scene."""
    from cusgs_jax.config import DataConfig
    from cusgs_jax.data.loader import load_scene

    return load_scene(demo, DataConfig(format="colmap", holdout_every=0)).names


@pytest.fixture(scope="session")
def feature_run(tmp_path_factory):
    """A 10-step run folder with the demo scene's semantic feature model (about 17 s on 2 cores; the viewer's tests).
    Trained once per session (:func:`built_once`): read only."""

    def build(root):
        from cusgs_jax.app.run import run
        from cusgs_jax.compose import compose_config
        from cusgs_jax.data.demo import generate_demo_scene

        scene = generate_demo_scene(root / "scene", num_views=6, width=40, height=30, num_points=800)
        cfg = compose_config([f"data.path={scene}", "train.iterations=10", "train.progress=false", "eval.every=0",
                              "eval.save_renders=false", "train.checkpoint_every=0", "model.n_offsets=4",
                              "model.latent_dim=8", "model.hidden=16", "model.appearance_dim=8",
                              "features.models=[{name: semantic}]", "features.sample_pixels=200"])
        run(cfg, root / "run")

    root, _ = built_once(tmp_path_factory, "view", build)
    return root / "run"


@pytest.fixture(scope="session")
def small_run(tmp_path_factory):
    """(scene folder, run folder) of a 30-step RGB run on a 6-view 40×30 demo scene (about 30 s on 2 cores;
    the exporter's and load_trained's tests). Trained once per session (:func:`built_once`): read only."""

    def build(root):
        from cusgs_jax.app.run import run
        from cusgs_jax.compose import compose_config
        from cusgs_jax.data.demo import generate_demo_scene

        scene = generate_demo_scene(root / "scene", num_views=6, width=40, height=30, num_points=800)
        cfg = compose_config([f"data.path={scene}", "train.iterations=30", "train.progress=false", "eval.every=0",
                              "train.checkpoint_every=0", "model.n_offsets=4", "model.latent_dim=8",
                              "model.hidden=16", "model.appearance_dim=8", "features=none"])
        run(cfg, root / "run")
        return scene

    root, scene = built_once(tmp_path_factory, "export", build)
    return scene, root / "run"


TINY_SWEEP = ["train.iterations=6", "train.checkpoint_every=0", "train.progress=false", "eval.every=6",
              "grow.stats_start=1", "grow.start=4", "grow.stop=6", "grow.interval=2", "prune.start=2",
              "prune.interval=2", "eval.save_renders=false", "model.n_offsets=4", "model.latent_dim=8",
              "model.hidden=16", "model.appearance_dim=8", "features=none"]


@pytest.fixture(scope="session")
def tiny_sweep(tmp_path_factory):
    """(scene folder, overrides) of a few-second ``cusgs-train`` job: the sweep tests' (launchers, Pareto sweeper)."""
    from cusgs_jax.data.demo import generate_demo_scene

    scene = generate_demo_scene(tmp_path_factory.mktemp("sweep_scene") / "demo", num_views=9, width=32, height=24,
                                num_points=800)
    return scene, list(TINY_SWEEP)


@pytest.fixture
def compiles():
    """Every XLA program compiled (or loaded from the persistent cache) during the test, by jitted function name
    (:class:`cusgs_jax.app.compiles.CompileLog`, JAX's public monitoring events): ``compiles.count("jit(f)")``."""
    from cusgs_jax.app.compiles import CompileLog

    with CompileLog() as log:
        yield log
