"""Fixed image pairs for the LPIPS cross-check (``tests/eval/lpips_reference.py`` computes them with
the PyTorch ``lpips`` package, ``tests/eval/test_lpips.py`` pins the values).

Built from images that ship with scikit-image, with NumPy operations only (crop, integer block
mean, seeded noise, box blur), so the pairs stay the same across library versions.
"""

from __future__ import annotations

import numpy as np
import skimage.data

__all__ = ["lpips_pairs"]


def _block_mean(image: np.ndarray, top: int, left: int, size: tuple[int, int], factor: int) -> np.ndarray:
    """Crop [top : top + size·factor] and average factor×factor blocks: uint8 [H0, W0, 3] → float64 [H, W, 3] in [0, 1]."""
    h, w = size
    crop = image[top:top + h * factor, left:left + w * factor, :3].astype(np.float64) / 255.0
    return crop.reshape(h, factor, w, factor, 3).mean(axis=(1, 3))


def _box_blur(image: np.ndarray) -> np.ndarray:
    """3×3 box blur with edge padding: [H, W, 3] → [H, W, 3]."""
    pad = np.pad(image, ((1, 1), (1, 1), (0, 0)), mode="edge")
    h, w = image.shape[:2]
    return sum(pad[i:i + h, j:j + w] for i in range(3) for j in range(3)) / 9.0


def lpips_pairs() -> dict[str, tuple[np.ndarray, np.ndarray, list[str]]]:
    """Two batches of three pairs each, one per image size.

    Returns:
      {"64x64": (img0 [3, 64, 64, 3], img1 [3, 64, 64, 3], names),
       "96x128": (img0 [3, 96, 128, 3], img1 [3, 96, 128, 3], names)} — float32 in [0, 1];
      the pairs are an image against itself with Gaussian noise (σ = 0.08, clipped), against its
      3×3 box blur, and against a different image.
    """
    rng = np.random.default_rng(13)
    out = {}
    sets = {"64x64": (_block_mean(skimage.data.astronaut(), 64, 64, (64, 64), 6),
                      _block_mean(skimage.data.chelsea(), 22, 100, (64, 64), 4), "astronaut", "chelsea"),
            "96x128": (_block_mean(skimage.data.coffee(), 8, 44, (96, 128), 4),
                       _block_mean(skimage.data.rocket(), 25, 64, (96, 128), 4), "coffee", "rocket")}
    for key, (base, other, name, other_name) in sets.items():
        noisy = np.clip(base + rng.normal(0.0, 0.08, base.shape), 0.0, 1.0)
        img0 = np.stack([base, base, base]).astype(np.float32)
        img1 = np.stack([noisy, _box_blur(base), other]).astype(np.float32)
        out[key] = (img0, img1, [f"{name}/noise", f"{name}/blur", f"{name}/{other_name}"])
    return out
