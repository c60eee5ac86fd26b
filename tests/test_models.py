"""Networks and losses: U-Net shader and PatchGAN shapes, ranges and odd sizes; loss values."""
from __future__ import annotations

import math

import pytest
import torch
from skimage.metrics import structural_similarity

from nsplat.evaluation.image_metrics import lpips_status, psnr, ssim
from nsplat.models import PatchDiscriminator, PatchGANConfig, UNet, UNetConfig
from nsplat.models.losses import discriminator_loss, generator_loss, l1_loss


@pytest.mark.parametrize("size", [(32, 32), (37, 53), (9, 70), (1, 5)])
@pytest.mark.parametrize("norm,upsample", [("instance", "transpose"), ("group", "bilinear"), ("none", "bilinear")])
def test_unet_any_size_shape_and_range(size, norm, upsample):
    torch.manual_seed(0)
    net = UNet(5, 3, UNetConfig(depth=3, width=8, norm=norm, upsample=upsample))
    x = torch.randn(2, 5, *size) * 10
    y = net(x)
    assert y.shape == (2, 3, *size)
    assert bool((y > 0).all() and (y < 1).all())


def test_unet_output_range_dropout_and_gradients():
    torch.manual_seed(0)
    net = UNet(4, 2, UNetConfig(depth=2, width=8, dropout=0.5, output_range=(-1.0, 2.0)))
    x = torch.randn(3, 4, 20, 12, requires_grad=True)
    y = net(x * 50)
    assert y.shape == (3, 2, 20, 12)
    v = y.detach()
    assert float(v.min()) >= -1.0 and float(v.max()) <= 2.0 and float(v.max() - v.min()) > 2.0
    y.sum().backward()
    assert x.grad is not None and bool(x.grad.abs().sum() > 0)
    net.eval()  # dropout off: deterministic
    assert torch.equal(net(x), net(x))
    net.train()  # dropout on: stochastic
    assert not torch.equal(net(x), net(x))


def test_unet_pads_and_crops_in_place():
    """A 21×21 input is padded to 24×24 (replicate) and cropped back: with a zero border the result
    must equal running the network on the input embedded in zeros at the padding offset."""
    torch.manual_seed(0)
    net = UNet(2, 3, UNetConfig(depth=3, width=4)).eval()
    x = torch.zeros(1, 2, 21, 21)
    x[0, :, 6:15, 4:17] = torch.randn(2, 9, 13)
    big = torch.zeros(1, 2, 24, 24)
    big[..., 1:22, 1:22] = x  # pad 3 = 1 before + 2 after
    assert torch.allclose(net(x), net(big)[..., 1:22, 1:22], atol=1e-6)


def test_unet_rejects_bad_arguments():
    with pytest.raises(ValueError, match="depth"):
        UNetConfig(depth=0)
    with pytest.raises(ValueError, match="output_range"):
        UNetConfig(output_range=(1.0, 0.0))
    with pytest.raises(ValueError, match="norm"):
        UNetConfig(norm="layer")
    with pytest.raises(ValueError, match="x"):
        UNet(3, cfg=UNetConfig(depth=1, width=4))(torch.zeros(3, 8, 8))


@pytest.mark.parametrize("layers,size,patches", [(3, (64, 64), (6, 6)), (2, (37, 53), (7, 11)), (1, (12, 12), (4, 4))])
def test_patchgan_shapes(layers, size, patches):
    d = PatchDiscriminator(7, 3, PatchGANConfig(width=8, layers=layers))
    out = d(torch.randn(2, 7, *size), torch.rand(2, 3, *size))
    assert out.shape == (2, 1, *patches)
    assert d.min_size() == 3 * 2**layers


def test_patchgan_rejects_mismatch_and_small_inputs():
    d = PatchDiscriminator(4, 3, PatchGANConfig(width=8, layers=3))
    with pytest.raises(ValueError, match="cond/image"):
        d(torch.randn(1, 4, 32, 32), torch.rand(1, 3, 30, 32))
    with pytest.raises(ValueError, match="channels"):
        d(torch.randn(1, 5, 32, 32), torch.rand(1, 3, 32, 32))
    with pytest.raises(ValueError, match=">= 24"):
        d(torch.randn(1, 4, 20, 32), torch.rand(1, 3, 20, 32))


def test_losses_hand_values():
    pred, target = torch.zeros(1, 3, 2, 2), torch.full((1, 3, 2, 2), 0.25)
    assert l1_loss(pred, target).item() == pytest.approx(0.25)
    ones, zeros = torch.ones(2, 1, 3, 3), torch.zeros(2, 1, 3, 3)
    # LSGAN: perfect discriminator → 0; generator fooling it completely → 0.
    assert discriminator_loss(ones, zeros, "lsgan").item() == pytest.approx(0.0)
    assert discriminator_loss(zeros, ones, "lsgan").item() == pytest.approx(1.0)
    # BCE on logits 0 (p = 0.5): log 2 each.
    assert discriminator_loss(zeros, zeros, "bce").item() == pytest.approx(math.log(2.0))
    parts = generator_loss(pred, target, zeros, lambda_l1=100.0, adv_weight=2.0, mode="lsgan")
    assert parts["l1"].item() == pytest.approx(0.25) and parts["adv"].item() == pytest.approx(1.0)
    assert parts["total"].item() == pytest.approx(100.0 * 0.25 + 2.0 * 1.0)
    assert set(generator_loss(pred, target, None)) == {"l1", "total"}
    with pytest.raises(ValueError, match="mode"):
        discriminator_loss(ones, zeros, "wgan")


def test_image_metrics():
    a = torch.rand(3, 24, 30, 3, generator=torch.Generator().manual_seed(0))
    b = (a + 0.1).clamp(0, 1)
    mse = ((a.double() - b.double()) ** 2).flatten(1).mean(1)
    assert torch.allclose(psnr(a, b), -10 * torch.log10(mse))
    assert torch.allclose(ssim(a, a), torch.ones(3, dtype=torch.float64))
    assert bool((ssim(a, b) < 1).all())
    ref = [structural_similarity(a[i].numpy(), b[i].numpy(), gaussian_weights=True, sigma=1.5,
                                         use_sample_covariance=False, data_range=1.0, channel_axis=2)
           for i in range(3)]
    assert torch.allclose(ssim(a, b), torch.tensor(ref, dtype=torch.float64), atol=1e-5)
    ok, msg = lpips_status()
    assert isinstance(ok, bool) and (ok or msg.startswith("skipped: "))


def test_unet_residual_around_base():
    torch.manual_seed(0)
    net = UNet(6, 3, UNetConfig(depth=2, width=8, output_range=(-1.0, 1.0)))
    x = torch.randn(2, 6, 13, 10)
    base = torch.rand(2, 3, 13, 10) * 1.6 - 0.8
    torch.nn.init.zeros_(net.head.weight)
    torch.nn.init.zeros_(net.head.bias)
    assert torch.allclose(net(x, base=base), base, atol=1e-5)  # zero head reproduces the base
    with pytest.raises(ValueError, match="base"):
        net(x, base=base[:, :2])
