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
