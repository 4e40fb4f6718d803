"""load_trained (io/load_run.py) on a tiny trained run: the model without the scene, the checkpoint's metadata
standing in for eval.json, the cameras from the scene for older runs, the PSC banks file, errors naming the
folder; the package root exports it."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

import cusgs_jax
from cusgs_jax.errors import CheckpointError, UserError
from cusgs_jax.io.load_run import BANKS_FILE, TrainedModel, load_trained


def test_load_trained_reads_the_model_without_the_scene(small_run):
    _, run_dir = small_run
    ev = json.loads((run_dir / "eval.json").read_text())
    model = load_trained(run_dir)
    assert model.step == 30 and model.run_dir == run_dir.absolute() and model.evaluation.psnr == ev["psnr"]
    m = model.cfg.model
    assert (m.n_offsets, m.latent_dim, m.hidden, m.appearance_dim) == (4, 8, 16, 8)
    assert m.voxel_size == pytest.approx(ev["voxel_size"])
    assert model.num_anchors == ev["alive_anchors"] and model.anchors.capacity % 64 == 0
    assert model.anchors.params.offsets.shape == (model.anchors.capacity, 4, 3)
    assert model.world.as_dict() == ev["world_transform"]
    assert model.nets["appearance"].shape[1] == 8 and model.mean_appearance().shape == (8,)
    assert model.checkpoint_bytes == ev["checkpoint_bytes"]
    assert not (run_dir / "checkpoints" / "30.damaged").exists()


def test_load_trained_without_eval_json_uses_the_checkpoint_metadata(small_run, tmp_path):
    _, run_dir = small_run
    copy = tmp_path / "run"
    shutil.copytree(run_dir / "checkpoints", copy / "checkpoints")  # no eval.json, no .hydra
    model = load_trained(copy)
    full = load_trained(run_dir)
    assert model.evaluation is None and model.world == full.world and model.cfg == full.cfg
    np.testing.assert_array_equal(np.asarray(model.anchors.centers), np.asarray(full.anchors.centers))


def test_cameras_come_from_the_scene_when_the_checkpoint_has_none(small_run, tmp_path):
    scene, run_dir = small_run
    copy = tmp_path / "run"
    shutil.copytree(run_dir / "checkpoints", copy / "checkpoints")
    shutil.copy(run_dir / "eval.json", copy / "eval.json")
    meta_file = copy / "checkpoints" / "30" / "meta" / "metadata"
    meta = json.loads(meta_file.read_text())
    recorded = load_trained(run_dir).cameras
    del meta["train_cameras"]
    meta_file.write_text(json.dumps(meta))
    model = load_trained(copy)
    assert model.cameras_from == str(scene) and (model.cameras.width, model.cameras.height) == (40, 30)
    np.testing.assert_allclose(np.asarray(model.cameras.world_to_camera), np.asarray(recorded.world_to_camera),
                               atol=1e-6)
    np.testing.assert_allclose(np.asarray(model.cameras.K), np.asarray(recorded.K))


def test_load_trained_errors_name_the_folder(tmp_path):
    with pytest.raises(UserError, match=str(tmp_path / "missing")):
        load_trained(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match=f"{tmp_path / 'empty'}.*no checkpoints/"):
        load_trained(tmp_path / "empty")
    (tmp_path / "none" / "checkpoints").mkdir(parents=True)
    with pytest.raises(UserError, match=f"no checkpoint in {tmp_path / 'none' / 'checkpoints'}"):
        load_trained(tmp_path / "none")
    assert not list((tmp_path / "none" / "checkpoints").iterdir())  # read-only: nothing written


def test_the_package_root_exports_the_library_loader():
    assert cusgs_jax.load_trained is load_trained and cusgs_jax.TrainedModel is TrainedModel


def test_banks_and_held_out_cameras_come_from_the_run_folder(small_run, feature_run, tmp_path):
    assert load_trained(small_run[1]).banks is None  # no feature model: no banks file
    model = load_trained(feature_run)
    with np.load(feature_run / BANKS_FILE) as stored:
        assert sorted(model.banks) == sorted(stored.files) == ["semantic"]
        np.testing.assert_array_equal(model.banks["semantic"], stored["semantic"])
    assert model.banks["semantic"].dtype == np.float32 and model.banks["semantic"].ndim == 2
    assert model.held_out_cameras is not None and len(model.held_out_cameras.K) == 1  # every 8th of 6 views
    copy = tmp_path / "run"
    shutil.copytree(feature_run, copy)
    (copy / BANKS_FILE).write_bytes(b"not an npz file")
    with pytest.raises(CheckpointError, match=f"{copy / BANKS_FILE} cannot be read"):
        load_trained(copy)


def teststored_cameras_keep_a_lens_run_s_lenses():
    """A data.undistort=lens run records its cameras' lenses with them (app/run.py _cameras); they come back as
    the batched Camera's Lens, and a lens table of the wrong size is not trusted."""
    from cusgs_jax.io.load_run import stored_cameras

    stored = dict(viewmats=np.tile(np.eye(4), (2, 1, 1)).tolist(), Ks=np.tile(np.eye(3), (2, 1, 1)).tolist(),
                  width=8, height=6)
    assert stored_cameras(stored).lens is None
    lens = dict(coeffs=[[0.1, 0, 0, 0, 0, 0], [0.2, 0, 0, 0, 0, 0]], bounds=[[-1, 1, -1, 1]] * 2, fisheye=False)
    cameras = stored_cameras(dict(stored, lens=lens))
    np.testing.assert_allclose(cameras.lens.coeffs[:, 0], [0.1, 0.2])
    assert cameras.lens.bounds.shape == (2, 4) and cameras.lens.fisheye is False
    assert stored_cameras(dict(stored, lens=dict(lens, coeffs=[[0.1, 0, 0, 0, 0, 0]]))) is None


def test_a_step_that_is_not_an_int_is_a_type_error_naming_it(tmp_path):
    with pytest.raises(TypeError, match=r"step must be an int .* got '10' \(str\); e.g. step=10"):
        load_trained(tmp_path, step="10")
    with pytest.raises(TypeError, match="step must be an int"):
        load_trained(tmp_path, step=1.5)
