"""Output files that are whole or absent: written beside their name, then moved over it in one step.

A kill during a write (Ctrl-C, a job's time limit) must not leave a header-only PLY that every viewer
then fails on: :func:`atomic_path` hands out a temporary name in the same folder (so the final
``os.replace`` is one rename on one file system) and removes it when the write fails.
:func:`require_writable` checks an output before any long work, so a bad path costs nothing.
"""

from __future__ import annotations

import contextlib
import os
import pathlib
import tempfile

from cusgs_jax.errors import UserError


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """``with atomic_path(p) as tmp:`` write ``tmp``; on success it becomes ``p``, on an error it is removed."""
    path = pathlib.Path(path)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.partial{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def require_writable(path: str | os.PathLike, what: str) -> pathlib.Path:
    """``path`` checked before any work: not a folder, and its folder exists (created) and takes a file.

    Raises:
      UserError: naming ``what`` (the option or argument) and the reason.
    """
    path = pathlib.Path(path)
    if path.is_dir():
        raise UserError(f"{what} {path} is a folder: name the file to write (e.g. {path / 'model.ply'})")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{path.name}.", suffix=".check"):
            pass
    except OSError as e:
        raise UserError(f"{what} {path}: cannot write there ({e.strerror or e}); pass a writable path") from e
    return path
