"""``cusgs-view``: an interactive web viewer of a run folder (viser; :mod:`cusgs_jax.view`).

Reads the run folder the other tools read (checkpoint + config, :func:`cusgs_jax.io.load_run.load_trained`;
the feature models' PSC banks from ``feature_banks.npz``); the camera list comes from the checkpoint
(training and held-out views), and for runs older than that record from the scene's COLMAP model if it
is still there. Nothing else of the training data is read. Open the printed address in a browser;
Ctrl-C stops the server. Only argparse is imported before the arguments are parsed, so ``--help``
does not load JAX.
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
from collections.abc import Sequence

from cusgs_jax.app.argtypes import int_at_least
from cusgs_jax.errors import UserError
from cusgs_jax.extract.pretrained import clip_text_encoder

__all__ = ["main", "open_viewer"]

PROG = "cusgs-view"
log = logging.getLogger("cusgs_jax")


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog=PROG,
        description="Serve an interactive web viewer of a trained run: RGB, depth, alpha, PCA colours of each "
                    "feature model, click (or text) queries as cosine-similarity heatmaps thresholded with Otsu.")
    ap.add_argument("run_dir", help="output folder of a cusgs-train run (holds checkpoints/)")
    ap.add_argument("--port", type=int_at_least(0), default=8080, help="port to listen on; 0 picks a free one "
                    "(default 8080)")
    ap.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1; 0.0.0.0 for all)")
    ap.add_argument("--step", type=int_at_least(0), default=None, help="checkpoint step (default: the newest)")
    ap.add_argument("--height", type=int_at_least(16), default=None, metavar="PX",
                    help="starting render height in pixels (default: the cameras', at most 480)")
    ap.add_argument("--jpeg-quality", type=int_at_least(1), default=90, metavar="Q",
                    help="JPEG quality of the frames sent, 1-100 (default 90)")
    ap.add_argument("--png", action="store_true", help="send lossless PNG frames (larger, slower)")
    ap.add_argument("--clip", default=None, metavar="WEIGHTS",
                    help="local open_clip weights (file or folder) for text queries against the run's clip features")
    ap.add_argument("--clip-arch", default="ViT-B-16", metavar="ARCH", help="open_clip architecture (default ViT-B-16)")
    return ap


def _check_address(host: str, port: int) -> None:
    """Refuse, before the server starts, what would leave it waiting forever (viser's server thread dies on a
    bind it cannot make while the caller waits): a port outside 0-65535, a host that does not resolve or is
    not an address of this machine. Warn when every interface is served (the viewer has no login)."""
    import socket

    if not 0 <= int(port) <= 65535:
        raise UserError(f"--port {port}: must be 0-65535 (0 picks a free one)")
    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as e:
        raise UserError(f"--host {host}: does not resolve ({e}): give an address of this machine, e.g. "
                        "127.0.0.1 (the default) or 0.0.0.0 for every interface") from None
    family, *_, address = infos[0]
    try:
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            probe.bind((address[0], 0))
    except OSError as e:
        raise UserError(f"--host {host}: cannot listen there ({e.strerror or e}): give an address of this machine, "
                        "e.g. 127.0.0.1 (the default) or 0.0.0.0 for every interface") from None
    if address[0] in ("0.0.0.0", "::"):
        log.warning("--host %s serves the viewer on every network interface, without a login: anyone who can "
                    "reach this machine can watch the model; use 127.0.0.1 and an SSH tunnel where that matters",
                    host)


def open_viewer(run_dir, *, port: int = 8080, host: str = "127.0.0.1", step: int | None = None,
                height: int | None = None, jpeg_quality: int | None = 90, clip: str | None = None,
                clip_arch: str = "ViT-B-16", clip_net=None):
    """Start a :class:`~cusgs_jax.view.server.Viewer` of ``run_dir`` rendering in the background; stop it with ``.stop()``.

    ``clip_net``: an open_clip model handed over instead of ``clip`` weights (Python only).
    Raises:
      UserError: viser missing, a bad run folder or checkpoint, CLIP weights that do not load.
    """
    if importlib.util.find_spec("viser") is None:
        raise UserError("the viewer needs viser: pip install -e '.[viewer]'")
    if jpeg_quality is not None and not 1 <= jpeg_quality <= 100:
        raise UserError(f"--jpeg-quality {jpeg_quality}: must be 1-100")
    _check_address(host, port)
    # lazy: these import JAX (and orbax); keeps cusgs-view --help free of them
    from cusgs_jax.io.load_run import load_trained
    from cusgs_jax.view.render import from_trained
    from cusgs_jax.view.server import NO_CLIP_REASON, Viewer

    model = from_trained(load_trained(run_dir, step=step))
    encoder, reason = None, NO_CLIP_REASON
    if clip is not None or clip_net is not None:
        encoder = clip_text_encoder(clip, arch=clip_arch, net=clip_net)
    try:
        viewer = Viewer(model, host=host, port=port, height=height, jpeg_quality=jpeg_quality, text_encoder=encoder,
                        text_unavailable=reason)
    except OSError as e:
        raise UserError(f"cannot listen on {host}:{port} ({e.strerror or e}): pick another --port") from e
    if port and viewer.port != port:  # viser moves on to the next free port by itself
        log.warning("port %d on %s is busy: serving on port %d instead (--port picks another)", port, host,
                    viewer.port)
    return viewer.start()


def main(argv: Sequence[str] | None = None) -> int:
    """CLI: ``cusgs-view RUN_DIR [--port 8080] [--host H] [--step S] [--height PX] [--jpeg-quality Q | --png]
    [--clip WEIGHTS [--clip-arch ARCH]]``; serves until Ctrl-C."""
    import threading

    ap = _parser()
    args = ap.parse_args(argv)
    from cusgs_jax.training.checkpoint import quiet_orbax  # lazy: imports JAX and orbax; keeps --help free of them

    try:
        with quiet_orbax():  # orbax's repeats after a damaged checkpoint: dropped
            viewer = open_viewer(args.run_dir, port=args.port, host=args.host, step=args.step, height=args.height,
                                 jpeg_quality=None if args.png else args.jpeg_quality, clip=args.clip,
                                 clip_arch=args.clip_arch)
    except UserError as e:  # a bad run folder, checkpoint or setting: one line, exit 2 (as every CLI)
        ap.exit(2, f"{PROG}: error: {e}\n")
    print(f"{PROG}: serving {args.run_dir} at {viewer.url} (Ctrl-C stops)", flush=True)
    try:
        threading.Event().wait()
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
