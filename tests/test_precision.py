"""``neural.precision``: bfloat16 autocast of the U-Net and the discriminator against float32.

Tolerances (bfloat16 keeps 8 significant bits: unit roundoff ``u = 2**-8``):

* Network outputs: every convolution rounds its input and weights to bfloat16 (relative error ≤ u each) and
  accumulates in float32, so to first order an ``L``-convolution path is off by at most about ``2·L·u`` of the
  output's scale. We require ``‖Δy‖ / ‖y‖ ≤ L·u`` (U-Net, depth 2: L = 6, 0.023; PatchGAN, 2 layers: L = 4, 0.016;
  measured over seeds 0–5 at 24 px: 0.0021–0.0023 and 0.0076–0.0116).
* Gradients: each weight's gradient is a sum over all pixels of products rounded to bfloat16, so its error is
  relative to the sum of the terms' magnitudes, not to the (much smaller, cancelling) sum: measured 3–25 % per
  weight, 5–15 % on the input's gradient. We require the whole gradient (weights and input) to point the same
  way: cosine ≥ 0.98 (measured 0.989–0.998) and ``‖Δg‖ / ‖g‖ ≤ 0.25``. A wrong layer, dtype or layout gives
  cosines far below.
* Training: 30 stage-2 steps on the tiny scene (GAN from step 15) with each precision end within 5 % of each
  other in train-view L1: the spread of three float32 runs that differ only in their batch seed (measured
  0.0547–0.0574; bfloat16 against float32 at equal seeds: 2.0 % and 0.4 %).
"""
from __future__ import annotations

import logging
import re
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from nsplat.config import ConfigError, load_config
from nsplat.models import PatchDiscriminator, PatchGANConfig, UNet, UNetConfig
from nsplat.models.losses import discriminator_loss, l1_loss
from nsplat.run.context import RunContext
from nsplat.tasks.neural import precision
from nsplat.tasks.neural.config import Config
from nsplat.tasks.neural.data import load_views
from nsplat.tasks.neural.evaluation import render_split
from nsplat.tasks.neural.geometry import fit_geometry
from nsplat.tasks.neural.model import neural_scene_from
from nsplat.tasks.neural.training import build, train_step
from tests.test_neural import _tiny

U = 2.0**-8  # bfloat16's unit roundoff
CPU = torch.device("cpu")


def _run(net: torch.nn.Module, args: tuple[torch.Tensor, ...], dtype: torch.dtype, loss) -> tuple[torch.Tensor,
                                                                                                      torch.Tensor]:
    """``(output, gradient of loss over the weights and the first input)``, both float32."""
    net.zero_grad(set_to_none=True)
    args = tuple(a.detach().clone().requires_grad_(i == 0) for i, a in enumerate(args))
    with precision.autocast(dtype, "cpu"):
        y = net(*args)
    assert y.dtype == dtype
    loss(y.float()).backward()
    grads = [p.grad.flatten() for p in net.parameters()] + [args[0].grad.flatten()]
    return y.detach().float(), torch.cat(grads)


def _nets(seed: int) -> list[tuple[str, torch.nn.Module, tuple[torch.Tensor, ...], object, int]]:
    """The tiny U-Net and PatchGAN with their inputs, training losses and convolutions on the longest path."""
    g = torch.Generator().manual_seed(seed)
    feats, image, target = (torch.rand(2, c, 24, 24, generator=g) for c in (5, 3, 3))
    torch.manual_seed(seed)
    unet = UNet(5, 3, UNetConfig(depth=2, width=8))  # random head: the output depends on every layer
    disc = PatchDiscriminator(5, 3, PatchGANConfig(width=8, layers=2))
    return [("unet", unet, (feats,), lambda y: l1_loss(y, target), 6),
            ("discriminator", disc, (feats, image), lambda y: discriminator_loss(y, -y, "lsgan"), 4)]


@pytest.mark.parametrize("seed", [0, 3])
def test_bfloat16_networks_equal_float32_within_tolerance(seed):
    for name, net, args, loss, layers in _nets(seed):
        y32, g32 = _run(net, args, torch.float32, loss)
        y16, g16 = _run(net, args, torch.bfloat16, loss)
        assert not torch.equal(y16, y32), f"{name}: autocast had no effect"
        out_err = float((y16 - y32).norm() / y32.norm())
        assert out_err <= layers * U, (name, out_err)
        assert float(F.cosine_similarity(g16, g32, 0)) >= 0.98, name
        assert float((g16 - g32).norm() / g32.norm()) <= 0.25, name
        assert all(p.dtype == torch.float32 for p in net.parameters())


@pytest.mark.parametrize("caps,expected,reason", [
    ({"avx2", "avx512f", "amx_tile", "amx_bf16"}, torch.bfloat16, "amx_bf16"),
    ({"avx2", "avx512f", "avx512_bf16"}, torch.bfloat16, "avx512_bf16"),
    ({"avx2", "avx512f", "avx512_bf16", "amx_bf16"}, torch.bfloat16, "amx_bf16 and avx512_bf16"),
    ({"avx2", "avx512f", "avx512_vnni"}, torch.float32, "neither"),
    ({"avx2", "fma"}, torch.float32, "neither"),
    (set(), torch.float32, "neither")])
def test_auto_follows_the_cpus_native_bfloat16(monkeypatch, caplog, tmp_path, caps, expected, reason):
    monkeypatch.setattr(precision, "cpu_capabilities", lambda: frozenset(caps))
    cfg = load_config(Config, _tiny(tmp_path, steps=1))
    assert cfg.neural.precision == "auto"
    with caplog.at_level(logging.INFO, logger="nsplat.tasks.neural.precision"):
        assert precision.resolve(cfg.neural.precision, CPU) == expected
    assert re.search(rf"neural.precision: auto -> {str(expected)[6:]} \(.*{reason}", caplog.text), caplog.text
    # CUDA: float32 whatever the CPU; the fixed settings ignore the CPU.
    assert precision.resolve("auto", torch.device("cuda")) == torch.float32
    assert precision.resolve("float32", CPU) == torch.float32 and precision.resolve("bfloat16", CPU) == torch.bfloat16


def test_capabilities_agree_with_the_kernels_cpu_flags(monkeypatch):
    """torch's cpuinfo and the fallback (``/proc/cpuinfo``, torch without ``get_capabilities``) see the same
    native-bfloat16 features as the kernel does."""
    flags = set(re.search(r"^flags\s*:\s*(.+)$", Path("/proc/cpuinfo").read_text(), re.M).group(1).split())
    kernel = {f for f in precision.NATIVE_BF16 if f in flags}
    assert {f for f in precision.NATIVE_BF16 if f in precision.cpu_capabilities()} == kernel
    monkeypatch.delattr(torch.cpu, "get_capabilities")
    assert {f for f in precision.NATIVE_BF16 if f in precision.cpu_capabilities()} == kernel


def test_the_setting_is_validated_naming_its_key(tmp_path):
    for bad in ("float16", "bf16", "true"):
        with pytest.raises(ConfigError, match=r"neural\.precision: expected one of \['auto', 'float32', 'bfloat16'\]"):
            load_config(Config, _tiny(tmp_path), [f"neural.precision={bad}"])
    with pytest.raises(ConfigError, match="neural.precision"):
        precision.resolve("half", CPU)


def test_stage2_with_each_precision_reaches_the_same_loss(tmp_path):
    """30 stage-2 steps (GAN from step 15) with float32 and bfloat16 from the same stage 1: the U-Net and the
    discriminator compute in the setting's dtype (in training and in the renders), the op's feature images are
    identical (it runs in float32 under either), the networks' outputs reach the losses in float32, the
    train-view L1 ends within 5 % (module docstring), and weights and optimiser state stay float32."""
    ends, conds = {}, {}
    geo = None
    for name in ("float32", "bfloat16"):
        cfg = load_config(Config, _tiny(tmp_path / "scenes", steps=30, lr=3e-3, precision=name,
                                        learn={"features": 0.05},
                                        gan={"width": 8, "layers": 2, "start": 0.5, "weight": 0.1}))
        ctx = RunContext(run_dir=tmp_path / name, device=CPU, seed=0)
        torch.manual_seed(0)
        train = load_views(cfg, "train", CPU)
        geo = geo if geo is not None else fit_geometry(cfg, ctx, train)
        t = build(cfg, neural_scene_from(cfg, geo, seed=0))
        model = t.modules["model"]
        assert model.compute_dtype == getattr(torch, name)
        computed: dict[str, set[torch.dtype]] = {"unet": set(), "discriminator": set()}
        for label, layer in (("unet", model.unet.head), ("discriminator", t.modules["disc"])):
            layer.register_forward_hook(lambda m, args, out, seen=computed[label]: seen.add(out.dtype))
        rgb, conds[name] = render_split(model, train, seed=123)
        assert rgb.dtype == conds[name].dtype == torch.float32
        before = float((rgb - train.images).abs().mean())
        for k in range(cfg.neural.steps):
            train_step(cfg.neural, t, train, k)
        ends[name] = float((render_split(model, train, seed=123)[0] - train.images).abs().mean())
        assert computed == {"unet": {model.compute_dtype}, "discriminator": {model.compute_dtype}}, computed
        assert ends[name] < 0.8 * before, (name, before, ends[name])
        for module in t.modules.values():
            assert all(v.dtype == torch.float32 for v in module.state_dict().values() if v.is_floating_point())
        for opt in t.optimizers.values():
            assert all(v.dtype == torch.float32 for st in opt.state.values() for v in st.values()
                       if torch.is_tensor(v) and v.is_floating_point() and v.dim() > 0)
    assert torch.equal(conds["float32"], conds["bfloat16"])
    assert abs(ends["bfloat16"] - ends["float32"]) <= 0.05 * ends["float32"], ends
