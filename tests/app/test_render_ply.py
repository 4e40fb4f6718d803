"""cusgs-render-ply (cusgs_jax.app.render_ply) on a tiny demo scene: JSON, PNGs, errors, a light --help."""

from __future__ import annotations

import json
import math
import os
import pathlib
import subprocess
import sys

import imageio.v3 as iio
import numpy as np
import pytest

import cusgs_jax
from cusgs_jax.app.render_ply import main
from cusgs_jax.config import DataConfig
from cusgs_jax.data.demo import generate_demo_scene
from cusgs_jax.data.loader import load_scene
from cusgs_jax.io import SplatModel, write_ply

C0 = 0.28209479177387814


@pytest.fixture(scope="module")
def scene_and_ply(tmp_path_factory):
    """The demo scene's SfM points as small isotropic degree-0 Gaussians, in the COLMAP frame."""
    root = tmp_path_factory.mktemp("render_ply")
    scene_dir = generate_demo_scene(root / "scene", num_views=4, width=32, height=24, num_points=300)
    scene = load_scene(scene_dir, DataConfig(format="colmap", holdout_every=0))
    points = scene.points.astype(np.float64)
    dist = np.linalg.norm(points[:, None] - points[None], axis=-1)
    np.fill_diagonal(dist, np.inf)
    sigma = 0.5 * float(np.median(dist.min(axis=1)))
    g = len(points)
    model = SplatModel(
        means=points.astype(np.float32),
        quats=np.tile(np.float32([1, 0, 0, 0]), (g, 1)),
        log_scales=np.full((g, 3), np.log(sigma), np.float32),
        opacity_logits=np.full(g, np.log(0.9 / 0.1), np.float32),
        sh=((scene.point_colors.astype(np.float32) / 255.0 - 0.5) / C0)[:, None, :])
    return scene_dir, write_ply(root / "points.ply", model)


def test_render_ply_cli(scene_and_ply, tmp_path, capsys):
    scene_dir, ply = scene_and_ply
    out_dir = tmp_path / "pngs"
    assert main([str(ply), "--scene", str(scene_dir), "--holdout-every", "2", "--out-dir", str(out_dir),
                 "--background", "0", "0", "0", "--quiet"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert {"ply", "scene", "num_gaussians", "sh_degree", "evaluated_on", "num_views", "psnr", "ssim",
            "per_view"} <= set(result)
    assert result["evaluated_on"] == "holdout" and result["num_views"] == 2 and result["sh_degree"] == 0
    assert [r["name"] for r in result["per_view"]] == ["view_000.png", "view_002.png"]
    assert math.isfinite(result["psnr"]) and math.isfinite(result["ssim"])
    # the SfM points as small Gaussians cover part of each view: they must beat a blank (black background)
    # render of the same views by 1.2 dB. Measured: blank 8.59 dB, the render 10.53 dB (+1.94)
    scene = load_scene(scene_dir, DataConfig(format="colmap", holdout_every=2))
    targets = scene.images[scene.test_indices].astype(np.float64) / 255
    blank = np.mean([-10 * np.log10(np.mean(t ** 2)) for t in targets])
    assert result["psnr"] > blank + 1.2, (result["psnr"], blank)
    assert all(math.isfinite(r["psnr"]) and -1 <= r["ssim"] <= 1 for r in result["per_view"])
    assert np.isclose(result["psnr"], np.mean([r["psnr"] for r in result["per_view"]]))
    assert sorted(os.listdir(out_dir)) == ["view_000.png", "view_002.png"]
    assert iio.imread(out_dir / "view_000.png").shape == (24, 64, 3)  # render | ground truth


def test_missing_ply_exits_2_naming_it(scene_and_ply, tmp_path, capsys):
    scene_dir, _ = scene_and_ply
    missing = tmp_path / "nowhere" / "model.ply"
    with pytest.raises(SystemExit) as e:
        main([str(missing), "--scene", str(scene_dir)])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("cusgs-render-ply: error: ") and str(missing) in err and err.count("\n") == 1


def test_bad_scene_exits_2(scene_and_ply, tmp_path, capsys):
    _, ply = scene_and_ply
    with pytest.raises(SystemExit) as e:
        main([str(ply), "--scene", str(tmp_path / "no scene"), "--quiet"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "no scene" in err
    assert "set --scene to a COLMAP scene" in err and "data." not in err  # its own flag, not cusgs-train's option
    with pytest.raises(SystemExit) as e:
        main([str(ply), "--scene", str(scene_and_ply[0]), "--format", "blender", "--quiet"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "set --scene to such a folder, or --format to the layout" in err and "data." not in err


def test_images_smaller_than_the_ssim_window_exit_2_naming_downscale(scene_and_ply, capsys):
    scene_dir, ply = scene_and_ply
    with pytest.raises(SystemExit) as e:  # 32x24 / 3 = 11x8: no SSIM
        main([str(ply), "--scene", str(scene_dir), "--downscale", "3", "--quiet"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1
    assert "11x8 pixels with --downscale=3" in err and "use a smaller --downscale (e.g. --downscale=2)" in err


def test_the_old_colmap_flag_still_works_and_says_it_is_deprecated(scene_and_ply, capsys):
    scene_dir, ply = scene_and_ply
    assert main([str(ply), "--colmap", str(scene_dir), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "cusgs-render-ply: warning: --colmap is deprecated (it reads every layout): use --scene" in captured.err
    assert json.loads(captured.out)["psnr"] > 0


def test_help_does_not_import_jax():
    src = str(pathlib.Path(cusgs_jax.__file__).parents[1])
    code = ("import sys\nfrom cusgs_jax.app.render_ply import main\ntry:\n    main(['--help'])\n"
            "except SystemExit:\n    pass\nprint('JAX' if 'jax' in sys.modules else 'NOJAX')")
    env = dict(os.environ, PYTHONPATH=src + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True).stdout
    assert "--scene" in out and out.strip().endswith("NOJAX")


def test_undistort_mask_keeps_the_frame_and_scores_its_valid_pixels(scene_and_ply, tmp_path, capsys, monkeypatch):
    """--undistort mask on the demo through a SIMPLE_RADIAL lens (same poses and points as the scene of the
    PLY): the full 32x24 frame, scored on its valid pixels, as well as the pinhole scene is (the same
    Gaussians, the same views); --undistort crop scores a smaller image."""
    from cusgs_jax.data.demo.lens import lens_camera, write_lens_demo

    monkeypatch.setenv("CUSGS_CACHE_DIR", str(tmp_path / "cache"))
    scene_dir, ply = scene_and_ply
    lens = write_lens_demo(tmp_path / "lens", *lens_camera("simple_radial", 32, 24), num_views=4, width=32,
                           height=24, num_points=300)
    scores = {}
    for name, folder, mode in (("pinhole", scene_dir, "crop"), ("mask", lens, "mask"), ("crop", lens, "crop")):
        assert main([str(ply), "--scene", str(folder), "--all", "--undistort", mode, "--quiet"]) == 0
        scores[name] = json.loads(capsys.readouterr().out)
    assert (scores["mask"]["width"], scores["mask"]["height"]) == (32, 24)
    assert scores["crop"]["width"] < 32 and scores["crop"]["height"] < 24
    assert abs(scores["mask"]["psnr"] - scores["pinhole"]["psnr"]) < 1.5, scores
    with pytest.raises(SystemExit) as exit_info:
        main([str(ply), "--scene", str(lens), "--undistort", "blur"])
    assert exit_info.value.code == 2


def test_undistort_lens_renders_through_the_lens_over_the_whole_frame(scene_and_ply, tmp_path, capsys, monkeypatch):
    """--undistort lens on the demo through an OPENCV lens: the PLY (fitted to the pinhole scene) is drawn
    through the lens itself and scored on every pixel of the images as captured, about as well as on the
    pinhole scene."""
    from cusgs_jax.data.demo.lens import lens_camera, write_lens_demo

    monkeypatch.setenv("CUSGS_CACHE_DIR", str(tmp_path / "cache"))
    scene_dir, ply = scene_and_ply
    model, params = lens_camera("opencv", 32, 24)
    params = list(params)
    params[4:6] = [0.3, 0.1]  # a strong lens, so ignoring it would show
    lens = write_lens_demo(tmp_path / "lens", model, params, num_views=4, width=32, height=24, num_points=300)
    scores = {}
    for name, folder, mode in (("pinhole", scene_dir, "crop"), ("lens", lens, "lens")):
        assert main([str(ply), "--scene", str(folder), "--all", "--undistort", mode, "--quiet"]) == 0
        scores[name] = json.loads(capsys.readouterr().out)
    assert (scores["lens"]["width"], scores["lens"]["height"]) == (32, 24)
    assert abs(scores["lens"]["psnr"] - scores["pinhole"]["psnr"]) < 1.0, scores
