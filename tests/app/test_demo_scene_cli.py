"""cusgs-demo-scene (cusgs_jax.app.demo_scene): the command line on a tiny scene."""

from __future__ import annotations

import json
import os

import imageio.v3 as iio
import pycolmap
import pytest

from cusgs_jax.app.demo_scene import main


def _read(scene):
    return pycolmap.Reconstruction(str(scene / "sparse" / "0"))


def test_cli(tmp_path, capsys):
    out = tmp_path / "cli"
    assert main([str(out), "--views", "4", "--width", "32", "--height", "24"]) == 0
    assert "4 views 32x24" in capsys.readouterr().out
    assert sorted(os.listdir(out / "images")) == [f"view_{i:03d}.png" for i in range(4)]
    assert len(os.listdir(out / "depth")) == len(os.listdir(out / "object_ids")) == 4
    assert (out / "objects.json").is_file() and (out / "scene.json").is_file()
    rec = _read(out)
    cam = next(iter(rec.cameras.values()))
    assert rec.num_images() == 4 and (cam.width, cam.height) == (32, 24)
    assert iio.imread(out / "images" / "view_000.png").shape == (24, 32, 3)
    with pytest.raises(SystemExit) as e:  # refuses to overwrite without --overwrite
        main([str(out), "--views", "4", "--width", "32", "--height", "24"])
    assert e.value.code == 2
    assert main([str(out), "--views", "4", "--width", "32", "--height", "24", "--seed", "1",
                 "--overwrite"]) == 0
    assert json.loads((out / "scene.json").read_text())["seed"] == 1


def test_cli_lens(tmp_path, capsys):
    out = tmp_path / "lens"
    assert main([str(out), "--views", "2", "--width", "32", "--height", "24", "--points", "300",
                 "--lens", "opencv"]) == 0
    assert "2 views 32x24 (OPENCV" in capsys.readouterr().out
    cam = next(iter(_read(out).cameras.values()))
    assert cam.model.name == "OPENCV" and (cam.width, cam.height) == (32, 24)
    assert json.loads((out / "scene.json").read_text())["lens"] == "opencv"
    with pytest.raises(SystemExit) as e:  # an unknown lens is a usage error
        main([str(tmp_path / "x"), "--lens", "fisheye"])
    assert e.value.code == 2
