"""benchmarks/peer_bench.py's own logic (splax itself is not a dependency: its loader is checked
on fake source folders)."""

from __future__ import annotations

import pathlib
import sys

import jax.numpy as jnp
import numpy as np
import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2] / "benchmarks"))
import peer_bench  # noqa: E402

from cusgs_jax.errors import UserError  # noqa: E402


def test_psnr_of_known_error():
    a = np.zeros((4, 4, 3))
    assert peer_bench.psnr(a, a) == float("inf")
    assert peer_bench.psnr(a + 0.1, a) == pytest.approx(20.0)  # mse 0.01 -> 20 dB


def test_splax_pixel_grid_moves_only_the_principal_point():
    K = jnp.array([[100.0, 0, 64], [0, 90, 32], [0, 0, 1]])
    moved = np.asarray(peer_bench.splax_pixel_grid(K))
    np.testing.assert_array_equal(moved - np.asarray(K), [[0, 0, 1], [0, 0, 1], [0, 0, 0]])


def test_splax_tiles_cover_the_padded_image_row_by_row():
    tiles = np.asarray(peer_bench.splax_tiles(width=20, height=10, tile_size=8))
    assert tiles.shape == (3 * 2, 4)
    np.testing.assert_array_equal(tiles[:4], [[0, 0, 8, 8], [8, 0, 16, 8], [16, 0, 24, 8], [0, 8, 8, 16]])


def test_time_alternately_calls_each_program_once_per_round_after_a_warm_up():
    calls = []

    def program(name):
        def run(x):
            calls.append(name)
            return x
        return run

    medians = peer_bench.time_alternately({"a": program("a"), "b": program("b")}, [jnp.zeros(1)], rounds=3)
    assert set(medians) == {"a", "b"} and all(t >= 0 for t in medians.values())
    assert calls == ["a", "b", "a", "b", "b", "a", "a", "b"]


def _fake_splax(root: pathlib.Path, camera_source: str) -> pathlib.Path:
    package = root / "src" / "splax"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "_camera.py").write_text(camera_source)
    return package


def test_load_splax_names_a_folder_without_splax(tmp_path):
    with pytest.raises(UserError, match="--splax-src .*no splax/__init__.py"):
        peer_bench.load_splax(str(tmp_path))


def test_patched_copy_fixes_the_batched_diagonal_and_leaves_the_original(tmp_path):
    original = "R = q()\ncov = einsum(\n    R,\n    jnp.diag(gaussians.scale**2),\n    R.T,\n)\n"
    package = _fake_splax(tmp_path, original)
    copy, applied = peer_bench.patched_copy(package, peer_bench.SPLAX_PATCHES, tmp_path / "copy")
    patched = (copy / "_camera.py").read_text()
    assert "jnp.diag" not in patched and "    gaussians.scale**2,  # patched" in patched
    assert (package / "_camera.py").read_text() == original
    assert [p["file"] for p in applied] == ["_camera.py"]


def test_patched_copy_refuses_a_revision_the_patch_does_not_fit(tmp_path):
    package = _fake_splax(tmp_path, "cov = jnp.einsum('...j', scale)\n")
    with pytest.raises(UserError, match="--no-splax-patch"):
        peer_bench.patched_copy(package, peer_bench.SPLAX_PATCHES, tmp_path / "copy")


def test_main_exits_2_with_one_message_for_a_bad_splax_folder(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        peer_bench.main(["--splax-src", str(tmp_path / "nowhere"), "--quick"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--splax-src" in err[0]
