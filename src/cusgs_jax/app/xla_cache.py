"""JAX's persistent compilation cache for runs (``train.compilation_cache``; docs/scaling.md#compilation-cache).

A compiled XLA program is stored on disk under a key of its HLO, compile options, devices and JAX
version; a later process that builds the same program (a rerun, the next job of a sweep, which share
the folder) loads it instead of compiling (JAX docs, "Persistent compilation cache"). The folder
holds executable code: use one you trust. Delete it to clear it; it never changes a result (the same
program is loaded, bit for bit).

``train.compilation_cache``: ``auto`` (the default) is ``$CUSGS_CACHE_DIR/xla`` or
``~/.cache/cusgs_jax/xla`` — unless this process already chose a folder (``JAX_COMPILATION_CACHE_DIR``,
or ``jax.config`` as the test suite does), which is kept; a path is that folder; null turns it off.
"""

from __future__ import annotations

import logging
import pathlib

import jax

from cusgs_jax.cache import default_cache_dir

log = logging.getLogger("cusgs_jax")

#: Programs that took at least this long to compile are stored (JAX's default is 1 s; most of a
#: run's compile seconds are in a few large programs, but its many small ones add up too).
MIN_COMPILE_SECONDS = 0.0


def resolve_cache_dir(setting: str | None) -> pathlib.Path | None:
    """The folder ``train.compilation_cache`` names (None: off). ``auto`` keeps a folder the process set."""
    if setting is None:
        return None
    if setting == "auto":
        current = jax.config.jax_compilation_cache_dir
        return pathlib.Path(current) if current else default_cache_dir() / "xla"
    return pathlib.Path(setting).expanduser()


def use_compilation_cache(setting: str | None) -> pathlib.Path | None:
    """Point JAX's persistent compilation cache at ``train.compilation_cache`` (or turn it off).

    Returns the folder in use, or None. A folder that cannot be created is reported and the run goes
    on without a cache (compiling is never wrong, only slower).
    """
    folder = resolve_cache_dir(setting)
    if folder is None:
        jax.config.update("jax_enable_compilation_cache", False)
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        log.warning("train.compilation_cache=%s: the folder cannot be created (%s); compiling without a persistent "
                    "cache (set train.compilation_cache to a writable folder, or null)", folder, error.strerror)
        jax.config.update("jax_enable_compilation_cache", False)
        return None
    jax.config.update("jax_enable_compilation_cache", True)
    if jax.config.jax_compilation_cache_dir != str(folder):
        jax.config.update("jax_compilation_cache_dir", str(folder))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    return folder
