"""Image-quality metrics: PSNR, SSIM (Gaussian 11×11, σ = 1.5, data range 1), LPIPS when possible.

Images are ``[B, H, W, 3]`` (or ``[B, 3, H, W]`` with ``channels_last=False``) with values in
[0, 1]. SSIM is Wang et al.'s with the standard constants ``K1 = 0.01, K2 = 0.03``, the Gaussian
window and no padding (the mean over the valid region), computed with kornia; it matches
``skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
use_sample_covariance=False, data_range=1)``.

LPIPS needs pretrained network weights that this project does not download. :func:`lpips_status`
says whether they are available offline; evaluation reports LPIPS as skipped otherwise.
"""
from __future__ import annotations

import importlib.util
from pathlib import Path

import kornia
import torch

#: The LPIPS backbone we would use and the torchvision checkpoint file it needs.
LPIPS_BACKBONE = "alex"
_LPIPS_BACKBONE_FILE = "alexnet-owt-7be5be79.pth"


def _nchw(x: torch.Tensor, channels_last: bool) -> torch.Tensor:
    if x.dim() != 4:
        raise ValueError(f"images: expected a batch [B, H, W, C] or [B, C, H, W], got {list(x.shape)}")
    return x.permute(0, 3, 1, 2) if channels_last else x


def psnr(pred: torch.Tensor, target: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """Per-image PSNR in dB, ``[B]``: ``10 log10(range² / MSE)`` over all pixels and channels."""
    if pred.shape != target.shape:
        raise ValueError(f"pred/target: shapes differ: {list(pred.shape)} vs {list(target.shape)}")
    mse = ((pred.double() - target.double()) ** 2).flatten(1).mean(1)
    return 10.0 * torch.log10(data_range**2 / mse.clamp_min(1e-20))


def silhouette_band(masks: torch.Tensor, width: int = 3) -> torch.Tensor:
    """Pixels within ``width`` px of a silhouette edge: ``[B,H,W]`` bool from coverage ``masks [B,H,W]``
    (thresholded at 0.5; dilation minus erosion with a square kernel, kornia.morphology)."""
    m = (masks > 0.5).float()[:, None]
    kernel = torch.ones(2 * width + 1, 2 * width + 1, dtype=m.dtype, device=m.device)
    band = kornia.morphology.dilation(m, kernel) - kornia.morphology.erosion(m, kernel)
    return band[:, 0] > 0.5


def error_share(pred: torch.Tensor, target: torch.Tensor, region: torch.Tensor) -> torch.Tensor:
    """Per-image share of the squared error inside ``region [B,H,W]`` (bool), ``[B]`` in [0, 1]."""
    se = ((pred.double() - target.double()) ** 2).sum(-1)
    return (se * region).flatten(1).sum(1) / se.flatten(1).sum(1).clamp_min(1e-20)


def ssim(pred: torch.Tensor, target: torch.Tensor, *, channels_last: bool = True) -> torch.Tensor:
    """Per-image SSIM ``[B]`` (Gaussian 11×11 window, σ 1.5, data range 1, valid region)."""
    if pred.shape != target.shape:
        raise ValueError(f"pred/target: shapes differ: {list(pred.shape)} vs {list(target.shape)}")
    a, b = _nchw(pred.double(), channels_last), _nchw(target.double(), channels_last)
    if min(a.shape[-2:]) < 11:
        raise ValueError(f"images: SSIM needs sides >= 11 px, got {list(a.shape[-2:])}")
    smap = kornia.metrics.ssim(a, b, window_size=11, max_val=1.0, eps=0.0, padding="valid")
    return smap.flatten(1).mean(1)


def lpips_status() -> tuple[bool, str]:
    """``(available, message)``: whether LPIPS (``lpips`` package, AlexNet backbone) can run offline."""
    if importlib.util.find_spec("lpips") is None:
        return False, "skipped: no offline weights (the 'lpips' package is not installed)"
    weights = Path(torch.hub.get_dir()) / "checkpoints" / _LPIPS_BACKBONE_FILE
    if not weights.is_file():
        return False, f"skipped: no offline weights ({weights} is missing)"
    return True, f"lpips {LPIPS_BACKBONE}"


def lpips(pred: torch.Tensor, target: torch.Tensor, *, channels_last: bool = True) -> torch.Tensor:
    """Per-image LPIPS ``[B]`` (AlexNet backbone); raises ``RuntimeError`` if weights are unavailable."""
    ok, msg = lpips_status()
    if not ok:
        raise RuntimeError(f"LPIPS unavailable: {msg}")
    import lpips as lpips_pkg  # optional dependency

    net = lpips_pkg.LPIPS(net=LPIPS_BACKBONE, verbose=False).to(pred.device).eval()
    a, b = _nchw(pred.float(), channels_last), _nchw(target.float(), channels_last)
    with torch.no_grad():
        return net(a * 2 - 1, b * 2 - 1).flatten()
