"""cusgs-render-path: a trained run (the session fixture ``small_run``, 40×30 images) rendered along a camera path
to PNG frames and an MP4; bad arguments exit 2 with one line."""

import contextlib
import io
import json

import numpy as np
import pytest

imageio = pytest.importorskip("imageio.v3")

from cusgs_jax.app.render_path import main  # noqa: E402

W, H = 40, 30  # small_run's image size


def frames_of(folder):
    return sorted(p.name for p in folder.iterdir() if p.suffix == ".png")


def read_frames(folder, count):
    return np.stack([imageio.imread(folder / f"frame_{k:05d}.png") for k in range(count)])


@pytest.fixture(scope="module")
def orbit_render(small_run, tmp_path_factory):
    """(exit code, printed result, output folder) of ``cusgs-render-path RUN --frames 4 --batch 3 --out DIR``."""
    out = tmp_path_factory.mktemp("render_path") / "orbit"
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = main([str(small_run[1]), "--frames", "4", "--batch", "3", "--out", str(out)])
    return code, json.loads(stdout.getvalue()), out


def test_main_writes_png_frames_and_an_mp4(orbit_render):
    code, result, out = orbit_render
    assert code == 0
    assert result == dict(frames=4, out=str(out), video=str(out / "path.mp4"), size=[W, H])
    assert frames_of(out) == [f"frame_{k:05d}.png" for k in range(4)]
    assert sorted(p.name for p in out.iterdir()) == [*frames_of(out), "path.mp4"]
    frames = read_frames(out, 4)
    assert frames.shape == (4, H, W, 3) and frames.dtype == np.uint8
    assert all(frames[k].std() > 2 for k in range(4))  # not blank
    assert all(np.abs(frames[k].astype(int) - frames[k + 1]).mean() > 1 for k in range(3))  # the camera moves
    video = imageio.imread(out / "path.mp4", index=None)
    assert video.shape == (4, H, W, 3) and video.dtype == np.uint8
    # the same frames in the same order, up to the codec's loss
    error = np.abs(video.astype(float) - frames).mean(axis=(1, 2, 3))
    assert np.all(error < 8), error
    assert error[0] < np.abs(video[0].astype(float) - frames[2]).mean()


def test_no_video_writes_the_same_pngs_only(small_run, orbit_render, tmp_path, capsys):
    out = tmp_path / "pngs"
    assert main([str(small_run[1]), "--frames", "4", "--batch", "4", "--no-video", "--out", str(out)]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["video"] is None and result["frames"] == 4
    assert sorted(p.name for p in out.iterdir()) == [f"frame_{k:05d}.png" for k in range(4)]
    # another batch size, the same frames (a float32 ulp of the compositing may round a level differently)
    difference = np.abs(read_frames(out, 4).astype(int) - read_frames(orbit_render[2], 4))
    assert difference.max() <= 1 and np.mean(difference > 0) < 1e-3


def test_frames_are_cg_render_of_the_orbit(small_run, orbit_render):
    import cusgs_jax as cg

    model = cg.load_trained(small_run[1])
    cameras = cg.camera_path(model.cameras, "orbit", 4)
    out = cg.render(model, cameras, capacities=cg.fit_render(model, cameras, appearance="mean"), appearance="mean")
    expected = (np.clip(np.asarray(out.image), 0, 1) * 255).round().astype(np.uint8)
    difference = np.abs(expected.astype(int) - read_frames(orbit_render[2], 4))
    assert difference.max() <= 1 and np.mean(difference > 0) < 1e-3


def one_error_line(capsys, argv):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    errors = [line for line in captured.err.splitlines() if "error:" in line]
    assert len(errors) == 1 and errors[0].startswith("cusgs-render-path: error: "), captured.err
    return errors[0], captured.err


def test_too_few_frames_exit_2(small_run, tmp_path, capsys):
    line, _ = one_error_line(capsys, [str(small_run[1]), "--frames", "1", "--out", str(tmp_path / "x")])
    assert "--frames" in line and "2" in line
    assert not (tmp_path / "x").exists()
    line, _ = one_error_line(capsys, [str(small_run[1]), "--size", "4", "4", "--out", str(tmp_path / "x")])
    assert "--size" in line


@pytest.mark.parametrize("appearance,says", [("foo", "'foo'"), ("99", "5 training views")])
def test_bad_appearance_exit_2_with_one_line(small_run, tmp_path, capsys, appearance, says):
    line, err = one_error_line(capsys, [str(small_run[1]), "--appearance", appearance, "--frames", "2",
                                        "--out", str(tmp_path / "x")])
    assert err == line + "\n"  # the one line, no usage or traceback
    assert "--appearance" in line and says in line
    assert not list((tmp_path / "x").glob("*.png"))


def test_a_run_folder_that_does_not_exist_is_named(tmp_path, capsys):
    missing = tmp_path / "no such run"
    line, err = one_error_line(capsys, [str(missing), "--frames", "2"])
    assert err == line + "\n" and str(missing) in line
    assert not missing.exists()  # nothing written for it either


def test_a_folder_that_is_not_a_run_is_named(small_run, capsys):
    scene = small_run[0]
    line, err = one_error_line(capsys, [str(scene), "--frames", "2", "--no-video"])
    assert err == line + "\n" and str(scene) in line and "checkpoints" in line
