"""Image-quality metrics: PSNR, SSIM, LPIPS when possible, and the 8-bit quantisation of published tables.

Images are ``[B, H, W, 3]`` (or ``[B, 3, H, W]`` with ``channels_last=False``) with values in
[0, 1]. Two SSIM variants, both Wang et al.'s with ``K1 = 0.01, K2 = 0.03``, data range 1 and a Gaussian
11×11 window of σ = 1.5, computed with kornia:

* :func:`ssim`: no padding, the mean over the valid region; it matches
  ``skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
  data_range=1)``;
* :func:`ssim_zero_padded`: the images padded with zeros to keep their size, the mean of the whole map:
  what 3D Gaussian splatting's metrics (``utils/loss_utils.py``) compute, and what the published
  NeRF-synthetic and Mip-NeRF 360 tables of 3DGS-style methods report.

:func:`quantise` rounds to 8-bit levels as saving a PNG does (``⌊255·x + ½⌋ / 255``).

LPIPS needs the ``lpips`` package (and a torchvision matching torch) and pretrained backbone weights that
this project does not download. :func:`lpips_status` says, per backbone (``vgg``: 3DGS's metrics;
``alex``: gsplat's trainer and nerfbaselines), whether it runs offline, else why not in one line.
"""
from __future__ import annotations

import importlib.util
from pathlib import Path

import kornia
import torch

#: LPIPS backbones and the torchvision checkpoint file each needs in ``torch.hub``'s cache.
LPIPS_BACKBONES = {"vgg": "vgg16-397923af.pth", "alex": "alexnet-owt-7be5be79.pth"}


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


def quantise(x: torch.Tensor) -> torch.Tensor:
    """``x`` (values in [0, 1], clamped) rounded to the 256 levels of an 8-bit image, as a PNG writer does:
    ``⌊255·x + ½⌋ / 255`` (float, same shape and dtype)."""
    return torch.floor(x.clamp(0.0, 1.0) * 255.0 + 0.5) / 255.0


def ssim_zero_padded(pred: torch.Tensor, target: torch.Tensor, *, channels_last: bool = True) -> torch.Tensor:
    """Per-image SSIM ``[B]`` as 3D Gaussian splatting computes it: Gaussian 11×11 window (σ 1.5) over
    zero-padded images ("same" size), the mean of the whole map over pixels and channels (data range 1)."""
    if pred.shape != target.shape:
        raise ValueError(f"pred/target: shapes differ: {list(pred.shape)} vs {list(target.shape)}")
    a, b = _nchw(pred.double(), channels_last), _nchw(target.double(), channels_last)
    window = kornia.filters.get_gaussian_kernel1d(11, 1.5, device=a.device, dtype=a.dtype)  # [1, 11]

    def blur(x: torch.Tensor) -> torch.Tensor:
        return kornia.filters.filter2d_separable(x, window, window, border_type="constant")

    c1, c2 = 0.01**2, 0.03**2
    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b, cov = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2, blur(a * b) - mu_a * mu_b
    smap = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    return smap.flatten(1).mean(1)


def lpips_status(net: str = "alex") -> tuple[bool, str]:
    """``(available, message)``: whether LPIPS with backbone ``net`` (``vgg`` or ``alex``) runs offline;
    the message says why not in one line (``skipped: ...``)."""
    if net not in LPIPS_BACKBONES:
        raise ValueError(f"net: expected one of {list(LPIPS_BACKBONES)}, got {net!r}")
    if importlib.util.find_spec("lpips") is None:
        return False, "skipped: the 'lpips' package is not installed (pip install 'nsplat[lpips]')"
    weights = Path(torch.hub.get_dir()) / "checkpoints" / LPIPS_BACKBONES[net]
    if not weights.is_file():
        return False, f"skipped: no offline weights ({weights} is missing)"
    try:
        import lpips as _  # noqa: F401 - optional dependency; it imports torchvision
    except Exception as exc:  # noqa: BLE001 - e.g. a torchvision built for another torch
        return False, (f"skipped: the 'lpips' package does not import "
                       f"({type(exc).__name__}: {' '.join(str(exc).split())})")
    return True, f"lpips {net}"


def lpips(pred: torch.Tensor, target: torch.Tensor, *, net: str = "alex", channels_last: bool = True) -> torch.Tensor:
    """Per-image LPIPS ``[B]`` with backbone ``net``; raises ``RuntimeError`` if it cannot run offline."""
    ok, msg = lpips_status(net)
    if not ok:
        raise RuntimeError(f"LPIPS unavailable: {msg}")
    import lpips as lpips_pkg  # optional dependency

    model = lpips_pkg.LPIPS(net=net, verbose=False).to(pred.device).eval()
    a, b = _nchw(pred.float(), channels_last), _nchw(target.float(), channels_last)
    with torch.no_grad():
        return model(a * 2 - 1, b * 2 - 1).flatten()
