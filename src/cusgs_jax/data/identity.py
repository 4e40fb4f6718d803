"""Which scene a run trained on: a digest of its training cameras, and the test that two camera sets are one.

A run folder records its training cameras (checkpoint metadata ``train_cameras``: world→camera
matrices and intrinsics in the normalised training frame, and the image size) and their digest
(``scene_digest``). Resuming a run, or refining its export, against another scene — even one with
as many views — would train on other poses and points with no error; :func:`same_cameras` compares
the cameras of the scene at hand with the recorded ones, so those commands refuse it instead.
"""

from __future__ import annotations

import hashlib

import numpy as np

#: Largest difference of a camera-matrix entry still taken as "the same camera": the normalised frame
#: has extent 1, so 1e-4 is a tenth of a millimetre in a 1 m scene — far below any real re-capture,
#: far above the float round-off of loading the same files again through another path.
CAMERA_TOLERANCE = 1e-4


def scene_digest(viewmats, Ks, width: int, height: int) -> str:
    """A short hex digest of training cameras [V, 4, 4] world→camera and [V, 3, 3] intrinsics at W×H
    (rounded to 1e-6 first, so the same files give the same digest on every machine)."""
    h = hashlib.sha256()
    h.update(f"{int(width)}x{int(height)}:{len(viewmats)}".encode())
    for array in (viewmats, Ks):
        h.update(np.round(np.asarray(array, np.float64), 6).astype(np.float64).tobytes())
    return h.hexdigest()[:16]


def same_poses(recorded_viewmats, viewmats) -> str | None:
    """None when the world→camera matrices [V, 4, 4] equal the recorded ones (:data:`CAMERA_TOLERANCE`);
    otherwise what differs, in a few words."""
    saved = np.asarray(recorded_viewmats, np.float64)
    if len(saved) != len(viewmats):
        return f"{len(saved)} training views, not {len(viewmats)}"
    pose = float(np.max(np.abs(saved - np.asarray(viewmats, np.float64)))) if len(viewmats) else 0.0
    if pose > CAMERA_TOLERANCE:
        return f"other camera poses (differing by up to {pose:.3g} in the normalised frame)"
    return None


def same_cameras(recorded: dict, viewmats, Ks, width: int, height: int) -> str | None:
    """None when the cameras equal the ``recorded`` ones ({"viewmats", "Ks", "width", "height"}, as the
    checkpoint stores them); otherwise what differs, in a few words."""
    if (int(recorded["width"]), int(recorded["height"])) != (int(width), int(height)):
        return f"{recorded['width']}x{recorded['height']} images, not {width}x{height}"
    poses = same_poses(recorded["viewmats"], viewmats)
    if poses is not None:
        return poses
    saved_ks = np.asarray(recorded["Ks"], np.float64)
    focal = float(np.max(np.abs(saved_ks - np.asarray(Ks, np.float64)) / np.maximum(np.abs(saved_ks), 1.0)))
    if focal > CAMERA_TOLERANCE:
        return f"other intrinsics (differing by up to {focal:.3g} relative)"
    return None
