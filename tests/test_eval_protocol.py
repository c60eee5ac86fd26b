"""The evaluation protocols (:mod:`nsplat.evaluation.protocol`) against independent computations: the ``standard``
protocol's PSNR is that of the 8-bit PNGs a published table reads back, its SSIM that of 3D Gaussian
splatting (Gaussian 11×11 window, σ 1.5, zero padding, mean of the whole map; here with SciPy's filter),
the per-view CSV round-trips exactly, LPIPS that cannot run is a one-line note, and the comparison sheet
shows ground truth | render | error per view."""
from __future__ import annotations

import math

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter

from nsplat.evaluation.comparison_sheet import MIN_PANEL, spread, write_sheet
from nsplat.evaluation.image_metrics import lpips_status
from nsplat.evaluation.protocol import read_per_view_csv, score_views, summary, summary_text, write_per_view_csv


def _pair(seed: int = 0, B: int = 3, H: int = 24, W: int = 32) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    gt = torch.rand(B, H, W, 3, generator=g, dtype=torch.float64)
    render = (gt + 0.05 * torch.randn(B, H, W, 3, generator=g, dtype=torch.float64)).clamp(0, 1)
    return render, gt


def _ssim_3dgs(a: np.ndarray, b: np.ndarray) -> float:
    """3DGS's SSIM of two ``[H,W,3]`` images in [0, 1], written out with SciPy's Gaussian filter."""
    def blur(x: np.ndarray) -> np.ndarray:
        return np.stack([gaussian_filter(x[..., c], 1.5, mode="constant", cval=0.0, truncate=3.5)
                         for c in range(x.shape[-1])], -1)

    mu_a, mu_b = blur(a), blur(b)
    va, vb, cov = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2, blur(a * b) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    return float((((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (va + vb + c2))).mean())


def test_standard_protocol_scores_the_8_bit_pngs(tmp_path):
    render, gt = _pair()
    scores = score_views(render, gt, "standard")
    for i in range(render.shape[0]):
        # what a published table's script sees: PNGs written with round-half-up and read back
        for name, img in (("r", render[i]), ("g", gt[i])):
            iio.imwrite(tmp_path / f"{name}{i}.png", (img.numpy() * 255 + 0.5).astype(np.uint8))
        r = iio.imread(tmp_path / f"r{i}.png").astype(np.float64) / 255
        g = iio.imread(tmp_path / f"g{i}.png").astype(np.float64) / 255
        assert float(scores.per_view["psnr"][i]) == pytest.approx(-10 * math.log10(((r - g) ** 2).mean()), abs=1e-9)
        assert float(scores.per_view["ssim"][i]) == pytest.approx(_ssim_3dgs(r, g), abs=1e-9)
    # the float protocol differs: no quantisation, and SSIM over the valid region only
    plain = score_views(render, gt, "nsplat")
    mse = ((render - gt) ** 2).flatten(1).mean(1)
    assert torch.allclose(plain.per_view["psnr"], -10 * torch.log10(mse))
    assert not torch.allclose(plain.per_view["ssim"], scores.per_view["ssim"], atol=1e-3)
    with pytest.raises(ValueError, match="eval.protocol"):
        score_views(render, gt, "published")


def test_per_view_csv_round_trips_and_lpips_is_a_note_when_unavailable(tmp_path):
    render, gt = _pair(1)
    scores = score_views(render, gt, "standard")
    names = ["r_0.png", "a, name with a comma", "r_2"]
    rows = read_per_view_csv(write_per_view_csv(tmp_path / "per_view.csv", names, scores))
    assert [r["name"] for r in rows] == names
    for key, values in scores.per_view.items():
        assert [r[key] for r in rows] == values.tolist()  # exact floats
    s = summary(scores)
    assert s["protocol"] == "standard" and s["psnr"]["mean"] == pytest.approx(float(scores.per_view["psnr"].mean()))
    for net in ("vgg", "alex"):
        ok, msg = lpips_status(net)
        assert (f"lpips_{net}" in scores.per_view) == ok
        if not ok:
            assert s["lpips"][net] == msg and msg.startswith("skipped: ") and "\n" not in msg
            assert msg in summary_text(scores)


def test_comparison_sheet_rows_are_gt_render_error(tmp_path):
    render, gt = _pair(2, B=5, H=16, W=16)
    render[1] = gt[1]  # an exact view: its heat map is black
    scores = score_views(render, gt, "standard")
    path = write_sheet(tmp_path / "sheet.png", [f"v{i}" for i in range(5)], gt, render, scores.per_view["psnr"], 2)
    img = iio.imread(path)
    assert spread(5, 2) == [0, 4] and spread(3, 8) == [0, 1, 2]
    assert img.shape[1] >= 3 * MIN_PANEL and img.shape[0] >= 2 * MIN_PANEL  # two rows of three enlarged panels
    assert img.shape[0] < 3 * MIN_PANEL + 200
    exact = write_sheet(tmp_path / "exact.png", ["v1"], gt[1:2], render[1:2], torch.tensor([99.0]), 1)
    pic = iio.imread(exact)[..., :3].astype(int)
    right = pic[pic.shape[0] // 2 - 20: pic.shape[0] // 2 + 20, -pic.shape[1] // 3 + 40: -40]
    assert right.max() < 16  # inferno at zero error is black
