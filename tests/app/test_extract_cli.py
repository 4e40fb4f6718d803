"""cusgs-extract (cusgs_jax.app.extract): the command line on a tiny demo scene."""

from __future__ import annotations

import pytest

from cusgs_jax.app.extract import main
from cusgs_jax.data.features import load_features

W, H, V = 40, 30, 4  # the size of the `demo` fixture (tests/conftest.py TINY_DEMO)


def test_cli(demo, names, capsys):
    assert main([str(demo), "--model", "gabor", "--lab", "--overwrite"]) == 0
    out, err = capsys.readouterr()
    assert "gabor features ->" in out and f"{V} views, {W}x{H}x54 float16" in out
    assert "cusgs-extract gabor" in err  # the progress bar
    assert load_features(demo, "gabor", names).dim == 54

    assert main([str(demo), "--model", "semantic", "--dim", "8", "--resolution", "20", "15",
                 "--dtype", "float32", "--overwrite", "--quiet"]) == 0
    fs = load_features(demo, "semantic", names)
    assert fs.dim == 8 and fs.resolution == (20, 15) and fs.meta["dtype"] == "float32"
    assert fs.meta["options"] == {"dim": 8, "seed": 0}


def test_cli_errors(demo, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main([str(tmp_path / "nowhere"), "--model", "daisy", "--quiet"])
    assert e.value.code == 2  # bad input: exit 2 with one line, like every CLI
    assert "cusgs-extract: error:" in capsys.readouterr().err
    main([str(demo), "--model", "hog", "--overwrite", "--quiet"])
    with pytest.raises(SystemExit) as e:
        main([str(demo), "--model", "hog", "--quiet"])
    assert e.value.code == 2 and "--overwrite" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main([str(demo), "--model", "semantic", "--lab"])
    assert e.value.code == 2 and "--lab applies to" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main([str(demo), "--model", "sift"])
    assert e.value.code == 2


def test_scene_errors_name_the_tools_own_arguments_not_data_path(demo, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main([str(tmp_path / "nowhere"), "--model", "daisy", "--quiet"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "set SCENE to a COLMAP scene" in err and "data." not in err
    with pytest.raises(SystemExit) as e:  # a COLMAP scene read as nerfstudio: --format names the layout
        main([str(demo), "--model", "daisy", "--format", "nerfstudio", "--overwrite", "--quiet"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "transforms.json does not exist" in err and "SCENE" in err and "data." not in err
    with pytest.raises(SystemExit) as e:
        main([str(demo), "--model", "daisy", "--downscale", "0"])
    assert e.value.code == 2 and "--downscale" in capsys.readouterr().err


@pytest.mark.parametrize("mode", ["crop", "mask"])
def test_a_fisheye_past_90_degrees_is_refused_by_every_cli_that_undistorts(tmp_path, capsys, monkeypatch, mode):
    """cusgs-extract, cusgs-render-ply and cusgs-train load a scene through the same loader, so each refuses a
    fisheye that no pinhole image can hold with one line (exit 2) instead of COLMAP's size mismatch."""
    import numpy as np

    from cusgs_jax.app.render_ply import main as render_ply
    from cusgs_jax.app.run import setup
    from cusgs_jax.compose import compose_config
    from cusgs_jax.errors import UserError
    from cusgs_jax.io import SplatModel, write_ply
    from cusgs_jax.testing.distorted_scenes import distorted_colmap_scene

    monkeypatch.setenv("CUSGS_CACHE_DIR", str(tmp_path / "cache"))
    scene = tmp_path / "fisheye"
    distorted_colmap_scene(scene, [("OPENCV_FISHEYE", (20.0, 20.0, 32.0, 24.0, 0.0, 0.0, 0.0, 0.0))])
    needle = "90° or more off the axis"
    with pytest.raises(SystemExit) as e:
        main([str(scene), "--model", "semantic", "--undistort", mode])
    err = capsys.readouterr().err
    assert e.value.code == 2 and needle in err and err.count("\n") == 1, err
    ply = tmp_path / "one.ply"  # cusgs-render-ply reads the PLY before the scene: a real one
    write_ply(ply, SplatModel(means=np.zeros((1, 3), np.float32), quats=np.float32([[1, 0, 0, 0]]),
                              log_scales=np.zeros((1, 3), np.float32), opacity_logits=np.zeros(1, np.float32),
                              sh=np.zeros((1, 1, 3), np.float32)))
    with pytest.raises(SystemExit) as e:
        render_ply([str(ply), "--scene", str(scene), "--undistort", mode, "--quiet"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and needle in err and err.count("\n") == 1, err
    with pytest.raises(UserError, match=needle):
        setup(compose_config([f"data.path={scene}", f"data.undistort={mode}", "features=none"]), tmp_path / "run")
    assert not (tmp_path / "run" / "checkpoints").exists() or not any((tmp_path / "run" / "checkpoints").iterdir())
