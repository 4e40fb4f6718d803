"""The web viewer (imperative shell): a viser server whose scene is our splatter's render at the browser's camera.

Each connected browser gets its own render: at every change of its camera, of the mode, of the
resolution, of a query or of the model, the view is rendered at the browser's camera
(:mod:`cusgs_jax.view.camera`), coloured for the mode (:mod:`cusgs_jax.view.modes`) and sent as
the scene's background image, which three.js stretches over the canvas (the render has the
canvas's aspect, so nothing is distorted).

The panel: the mode (RGB, depth, alpha, ``PCA <model>``, ``query <model>``), the resolution
(render height in pixels), the camera list (training then held-out views; picking one moves the
browser's camera there; the first training camera is where a browser starts), the render time of
the last frame, and a text box for text queries — enabled only with a CLIP text encoder, otherwise
disabled with the reason shown. Clicking the view takes the rendered feature at that pixel as the
query of the shown (or the first) feature model and switches to ``query <model>``.

Two ways to drive it: :meth:`Viewer.start` renders in a background thread (``cusgs-view``);
the training loop calls :meth:`Viewer.render_pending` itself between steps, within a time budget
(:mod:`cusgs_jax.view.live`). Either way every render happens on one thread.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time

import numpy as np

from cusgs_jax.view.camera import from_viser, look_at_point, render_size, to_viser
from cusgs_jax.view.modes import colourise, feature_of_mode, mode_names, pixel_at
from cusgs_jax.view.render import ViewModel, ViewRenderer

__all__ = ["Viewer", "SentFrame", "NO_CLIP_REASON"]

NO_CLIP_REASON = "text queries need a CLIP model: start cusgs-view with --clip WEIGHTS (local open_clip weights)"
log = logging.getLogger("cusgs_jax")
DEFAULT_HEIGHT = 480
"""Render height in pixels when none is given (the resolution slider's start)."""


@dataclasses.dataclass(frozen=True)
class SentFrame:
    """The last frame sent to a browser: what a test needs to render the same view offline.

    Attributes:
      seq: frames sent to this browser so far (1 = the first).
      camera: the :class:`~cusgs_jax.types.Camera` it was rendered at (W×H, K, world→camera).
      mode: the mode shown; picture: [H, W, 3] uint8 sent (before image compression).
      render_ms: milliseconds of the render (splatting + colouring, not the transfer).
      note: the panel's note about the picture.
    """

    seq: int
    camera: object
    mode: str
    picture: np.ndarray
    render_ms: float
    note: str


class Viewer:
    """A viser server showing ``model``; ``port=0`` picks a free port (see :attr:`port`).

    Args:
      model: the :class:`~cusgs_jax.view.render.ViewModel` to show (swap it with :meth:`set_model`).
      host, port: where to listen.
      height: the starting render height (pixels); None: the cameras' height, at most DEFAULT_HEIGHT.
      jpeg_quality: the JPEG quality of the frames sent (1–100); None sends PNG (lossless, larger).
      text_encoder: ``encode(text) -> [D]`` into the space of the feature model ``text_model``, or
        None (the text box then shows ``text_unavailable``).
    """

    def __init__(self, model: ViewModel, *, host: str = "127.0.0.1", port: int = 8080, height: int | None = None,
                 jpeg_quality: int | None = 90, text_encoder=None, text_model: str = "clip",
                 text_unavailable: str = NO_CLIP_REASON):
        import viser

        self.model, self.renderer = model, ViewRenderer(model.cfg)
        self.jpeg_quality = jpeg_quality
        self.frames: dict[int, SentFrame] = {}
        self.model_version = 0
        self._queries: dict[str, np.ndarray] = {}
        self._query_version = 0
        self._clicks: list = []
        self._seen: dict[int, tuple] = {}
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.set_up_direction(tuple(float(x) for x in model.up))
        self._text_encoder, self._text_model = text_encoder, text_model
        if text_encoder is not None and text_model not in model.feature_models:
            self._text_encoder = None
            text_unavailable = (f"text queries need a feature model named {text_model!r} in the run "
                                f"(it has: {', '.join(model.feature_models) or 'none'})")
        self._gui(height, text_unavailable)
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(lambda client: self.frames.pop(client.client_id, None))
        self.server.scene.on_click()(self._click)

    # --- panel ---------------------------------------------------------------------------

    def _gui(self, height: int | None, text_unavailable: str) -> None:
        gui = self.server.gui
        tallest = max([c[4] for c in self.model.cameras], default=DEFAULT_HEIGHT)
        start = int(height or min(tallest, DEFAULT_HEIGHT))
        self.gui_mode = gui.add_dropdown("Mode", tuple(mode_names(self.model.feature_models)), initial_value="RGB")
        self.gui_resolution = gui.add_slider("Resolution", min=16, max=max(2160, start), step=1, initial_value=start,
                                             hint="render height in pixels (the width follows the window)")
        labels = [c[0] for c in self.model.cameras] or ["(no camera recorded)"]
        self.gui_camera = gui.add_dropdown("Camera", tuple(labels), initial_value=labels[0],
                                           hint="move to a training or held-out camera")
        self.gui_time = gui.add_text("Render time", "", disabled=True)
        self.gui_note = gui.add_markdown("")
        enabled = self._text_encoder is not None
        self.gui_text = gui.add_text("Text query", "", disabled=not enabled,
                                     hint=None if enabled else text_unavailable)
        self.gui_text_note = gui.add_markdown("" if enabled else f"*{text_unavailable}*")
        self.gui_camera.on_update(lambda event: self._jump(event.client, self.gui_camera.value))
        self.gui_text.on_update(lambda event: self._text_query(self.gui_text.value))

    @property
    def port(self) -> int:
        return int(self.server.get_port())

    @property
    def url(self) -> str:
        return f"http://{self.server.get_host()}:{self.port}"

    # --- events (viser's threads: they only record what to do) ----------------------------

    def _connect(self, client) -> None:
        if self.model.cameras:
            self._jump(client, self.model.cameras[0][0])

    def _jump(self, client, label: str) -> None:
        """Move ``client``'s camera (or every browser's, for None) to the camera called ``label``."""
        found = [c for c in self.model.cameras if c[0] == label]
        if not found:
            return
        _, K, viewmat, _, height = found[0]
        wxyz, position, fov = to_viser(K, viewmat, height)
        for c in ([client] if client is not None else list(self.server.get_clients().values())):
            with c.atomic():
                c.camera.fov = fov
                c.camera.position = position
                c.camera.wxyz = wxyz
                c.camera.look_at = look_at_point(viewmat, self.model.center)

    def _click(self, event) -> None:
        with self._lock:
            self._clicks.append((event.client.client_id, tuple(event.screen_pos)))

    def _text_query(self, text: str) -> None:
        if self._text_encoder is None or not text.strip():
            return
        vector = np.asarray(self._text_encoder(text), np.float32)
        self.set_query(self._text_model, vector)

    def set_query(self, model: str, vector) -> None:
        """Query the feature model ``model`` with ``vector`` [D] and show its heatmap."""
        with self._lock:
            self._queries[model] = np.asarray(vector, np.float32)
            self._query_version += 1
        self.gui_mode.value = f"query {model}"

    def set_model(self, model: ViewModel) -> None:
        """Show another state of the model (same networks' shapes; e.g. a later training step)."""
        with self._lock:
            self.model, self.model_version = model, self.model_version + 1

    # --- rendering (one thread) -----------------------------------------------------------

    def pending(self) -> bool:
        """Whether some browser's view (or a click) is waiting to be rendered."""
        return bool(self._clicks) or any(self._key(c) not in (None, self._seen.get(c.client_id))
                                         for c in list(self.server.get_clients().values()))

    def _key(self, client):
        try:
            stamp = client.camera.update_timestamp
        except AssertionError:  # no camera message from this browser yet
            return None
        return (stamp, self.gui_mode.value, int(self.gui_resolution.value), self._query_version, self.model_version)

    def render_pending(self) -> int:
        """Render every browser whose view is out of date (clicks first); returns the frames sent."""
        self._take_clicks()
        sent = 0
        for client in list(self.server.get_clients().values()):
            key = self._key(client)
            if key is None or key == self._seen.get(client.client_id):
                continue
            self._render_client(client, key)
            sent += 1
        return sent

    def _camera_of(self, client):
        cam = client.camera
        width, height = render_size(cam.aspect, int(self.gui_resolution.value))
        return from_viser(cam.wxyz, cam.position, cam.fov, width, height)

    def _render_client(self, client, key) -> None:
        mode, model = key[1], self.model
        camera = self._camera_of(client)
        start = time.perf_counter()
        frame = self.renderer.render(model, camera, features=feature_of_mode(mode) is not None)
        picture, note = colourise(mode, frame, self._queries.get(feature_of_mode(mode) or ""))
        ms = 1e3 * (time.perf_counter() - start)
        if self.jpeg_quality is None:
            client.scene.set_background_image(picture, format="png")
        else:
            client.scene.set_background_image(picture, format="jpeg", jpeg_quality=int(self.jpeg_quality))
        previous = self.frames.get(client.client_id)
        self.frames[client.client_id] = SentFrame(seq=1 + (previous.seq if previous else 0), camera=camera, mode=mode,
                                                  picture=picture, render_ms=ms, note=note)
        self._seen[client.client_id] = key
        self.gui_time.value = f"{ms:.0f} ms at {camera.width}×{camera.height}"
        self.gui_note.content = note

    def _take_clicks(self) -> None:
        """A click's pixel feature becomes the query of the shown (else the first) feature model."""
        with self._lock:
            clicks, self._clicks = self._clicks, []
        models = self.model.feature_models
        for client_id, screen_pos in clicks:
            client = self.server.get_clients().get(client_id)
            if client is None:
                continue
            if not models:
                self.gui_note.content = "this model has no feature field: nothing to query"
                continue
            target = feature_of_mode(self.gui_mode.value) or models[0]
            camera = self._camera_of(client)
            frame = self.renderer.render(self.model, camera, features=True)
            row, col = pixel_at(screen_pos, camera.width, camera.height)
            self.set_query(target, frame.features[target][row, col])

    def start(self) -> Viewer:
        """Render in a background thread until :meth:`stop`."""
        def loop():
            while not self._stop.is_set():
                try:
                    busy = self.render_pending()
                except Exception as e:  # noqa: BLE001 — keep serving; the panel and the log say what failed
                    log.exception("cusgs-view: a frame failed")
                    self.gui_note.content = f"render failed: {type(e).__name__}: {e}"
                    busy = False
                if not busy:
                    self._stop.wait(0.01)

        self._thread = threading.Thread(target=loop, name="cusgs-view-render", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop rendering and the server (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=30)
            self._thread = None
        self.server.stop()
