"""cusgs-view: --help without JAX, errors as one line with exit 2, the run folder read alone, text queries."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from cusgs_jax.app.view import main, open_viewer

pytest.importorskip("viser", reason="the viewer extra is not installed (pip install -e '.[viewer]')")


def test_help_does_not_import_jax():
    code = ("import json, sys\nfrom cusgs_jax.app.view import main\ntry:\n    main(['--help'])\n"
            "except SystemExit:\n    pass\nprint(json.dumps('jax' in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "cusgs-view" in out and json.loads(out.splitlines()[-1]) is False


def test_a_bad_run_folder_is_one_line_and_exit_2(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main([str(tmp_path / "missing"), "--port", "0"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.startswith("cusgs-view: error: ") and err.count("\n") == 1
    with pytest.raises(SystemExit) as e:
        main([str(tmp_path), "--jpeg-quality", "0"])
    assert e.value.code == 2


def _need_open_clip():
    import importlib.util

    if importlib.util.find_spec("open_clip") is None:  # not importorskip: torchvision needs pretrained.py's care
        pytest.skip("the pretrained extra (open_clip) is not installed")


def _tiny_clip(embed_dim: int):
    """A randomly initialised open_clip CLIP (real text tower, one layer; the real BPE vocabulary size)."""
    from cusgs_jax.extract.pretrained import _require_modules

    torch, open_clip = _require_modules("clip", ("torch", "open_clip"))
    torch.manual_seed(0)
    return open_clip.CLIP(embed_dim=embed_dim, vision_cfg=dict(layers=1, width=32, patch_size=16, image_size=32,
                                                              head_width=16),
                          text_cfg=dict(context_length=77, vocab_size=49408, width=32, heads=2, layers=1))


def test_the_viewer_reads_the_run_folder_alone(feature_run, tmp_path):
    import shutil

    copy = tmp_path / "run"  # no scene beside it: the cameras and banks come from the run folder
    shutil.copytree(feature_run, copy)
    viewer = open_viewer(copy, port=0)
    try:
        model = viewer.model
        assert model.feature_models == ["semantic"]
        assert [c[0] for c in model.cameras] == ["train 0", "train 1", "train 2", "train 3", "train 4", "held-out 0"]
        assert viewer.gui_text.disabled and "--clip" in viewer.gui_text_note.content
        assert viewer.gui_mode.options == ("RGB", "depth", "alpha", "PCA semantic", "query semantic")
    finally:
        viewer.stop()


def test_a_clip_model_without_a_clip_feature_field_says_so(feature_run):
    _need_open_clip()
    viewer = open_viewer(feature_run, port=0, clip_net=_tiny_clip(16))
    try:
        assert viewer.gui_text.disabled and "feature model named 'clip'" in viewer.gui_text_note.content
    finally:
        viewer.stop()


def test_a_text_query_becomes_the_query_of_its_feature_model(feature_run):
    _need_open_clip()
    from cusgs_jax.io.load_run import load_trained
    from cusgs_jax.extract.pretrained import clip_text_encoder
    from cusgs_jax.view.render import from_trained
    from cusgs_jax.view.server import Viewer

    model = from_trained(load_trained(feature_run))
    dim = int(model.banks["semantic"].shape[1])
    encode = clip_text_encoder(net=_tiny_clip(dim))
    viewer = Viewer(model, port=0, text_encoder=encode, text_model="semantic")  # semantic stands in for clip
    try:
        assert not viewer.gui_text.disabled
        viewer._text_query("a red chair")
        assert viewer.gui_mode.value == "query semantic"
        np.testing.assert_allclose(viewer._queries["semantic"], encode("a red chair"), rtol=1e-5)
    finally:
        viewer.stop()


def test_a_busy_port_is_said_when_the_viewer_moves_to_another(feature_run, caplog):
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with caplog.at_level("WARNING", logger="cusgs_jax"):
            viewer = open_viewer(feature_run, port=port)
        try:
            assert viewer.port != port
            assert f"port {port} on 127.0.0.1 is busy: serving on port {viewer.port} instead" in caplog.text
        finally:
            viewer.stop()


@pytest.mark.parametrize("host, port, message", [
    ("127.0.0.1", 70000, "--port 70000: must be 0-65535"),
    ("999.1.1.1", 0, "--host 999.1.1.1: does not resolve"),
    ("192.0.2.1", 0, "--host 192.0.2.1: cannot listen there"),  # TEST-NET-1: never an address of this machine
])
def test_an_address_the_server_cannot_listen_on_is_refused_before_it_starts(host, port, message):
    from cusgs_jax.app.view import _check_address
    from cusgs_jax.errors import UserError

    with pytest.raises(UserError, match=message):
        _check_address(host, port)


def test_serving_every_interface_is_warned_about(caplog):
    from cusgs_jax.app.view import _check_address

    _check_address("127.0.0.1", 0)
    assert not caplog.records
    _check_address("0.0.0.0", 0)
    assert "every network interface, without a login" in caplog.text
