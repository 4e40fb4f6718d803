"""The README's first command, end to end at a tiny size."""

from __future__ import annotations

import json

import imageio.v3 as iio

from cusgs_jax.render_demo import main


def test_render_demo_writes_views_and_summary(tmp_path):
    main(["--out", str(tmp_path), "--views", "2", "--width", "48", "--height", "32"])
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["views"] == 2 and summary["gaussians"] > 1000
    frame = iio.imread(tmp_path / "view_000.png")
    assert frame.shape == (32, 48, 3)
    assert frame.std() > 10  # textured, not blank
    assert iio.imread(tmp_path / "contact_sheet.png").shape == (32, 96, 3)
