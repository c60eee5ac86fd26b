"""Chamfer/Hausdorff distances against hand-computed cases (both definitions)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from nsplat.evaluation.shape_metrics import bbox_diagonal, nn_distances, point_cloud_distances

# GT: two points with a 3-4-5 bounding box, diagonal 5.
GT = np.array([[0.0, 0.0, 0.0], [3.0, 4.0, 0.0]])


def test_diagonal_and_nearest_neighbours():
    assert bbox_diagonal(GT) == pytest.approx(5.0)
    d = nn_distances(np.array([[0.0, 0.0, 1.0], [3.0, 4.0, -2.0]]), GT)
    np.testing.assert_allclose(d, [1.0, 2.0])


def test_missing_part():
    # pred covers only the first GT point: pred→gt = [0], gt→pred = [0, 5] (÷5 → [0, 1]).
    m = point_cloud_distances(np.array([[0.0, 0.0, 0.0]]), GT)
    assert m["chamfer"] == pytest.approx(0.5 * (0.0 + 0.5))
    assert m["hausdorff"] == pytest.approx(1.0)
    assert m["chamfer_sq"] == pytest.approx(max(0.0, 0.5 * (0.0 + 1.0)))
    assert m["hausdorff_sq"] == pytest.approx(1.0)
    assert m["diagonal"] == pytest.approx(5.0)


def test_symmetric_offset():
    # One point moved by 1 along x: both directions [1/5, 0].
    m = point_cloud_distances(np.array([[1.0, 0.0, 0.0], [3.0, 4.0, 0.0]]), GT)
    assert m["chamfer"] == pytest.approx(0.1)
    assert m["hausdorff"] == pytest.approx(0.2)
    assert m["chamfer_sq"] == pytest.approx(0.02)
    assert m["hausdorff_sq"] == pytest.approx(0.04)


def test_outlier_distinguishes_max_and_mean_of_directions():
    # An outlier 5 away (1 diagonal): pred→gt = [0, 0, 1], gt→pred = [0, 0].
    pred = np.array([[0.0, 0.0, 0.0], [3.0, 4.0, 0.0], [3.0, 4.0, 5.0]])
    m = point_cloud_distances(pred, GT)
    assert m["chamfer"] == pytest.approx(0.5 * (1.0 / 3.0 + 0.0))   # mean of the directional means
    assert m["chamfer_sq"] == pytest.approx(1.0 / 3.0)              # max of the directional means
    assert m["hausdorff"] == pytest.approx(1.0)
    assert m["hausdorff_sq"] == pytest.approx(1.0)


def test_identical_clouds_are_zero_and_scale_invariant():
    rng = np.random.default_rng(0)
    gt = rng.normal(size=(200, 3))
    pred = gt + 0.01 * rng.normal(size=gt.shape)
    assert all(v == 0.0 for k, v in point_cloud_distances(gt, gt).items() if k != "diagonal")
    a = point_cloud_distances(pred, gt)
    b = point_cloud_distances(torch.as_tensor(7.0 * pred), torch.as_tensor(7.0 * gt))
    for k in ("chamfer", "hausdorff", "chamfer_sq", "hausdorff_sq"):
        assert a[k] == pytest.approx(b[k], rel=1e-9)
    assert a["chamfer"] > 0


@pytest.mark.parametrize("bad", [np.zeros((3, 2)), np.zeros((0, 3)), np.array([[np.nan, 0.0, 0.0]])])
def test_bad_input_names_argument(bad):
    with pytest.raises(ValueError, match="pred"):
        point_cloud_distances(bad, GT)
    with pytest.raises(ValueError, match="gt: bounding-box"):
        point_cloud_distances(GT, np.zeros((4, 3)))


def test_silhouette_band_and_error_share_by_hand():
    from nsplat.evaluation.image_metrics import error_share, silhouette_band

    masks = torch.zeros(1, 16, 16)
    masks[:, 4:12, 4:12] = 1.0  # an 8×8 square
    band = silhouette_band(masks, width=2)
    # Rows/columns 2..13 (dilated by 2) minus 6..9 (eroded by 2): 144 − 16 pixels.
    assert int(band.sum()) == 12 * 12 - 4 * 4
    assert bool(band[0, 2, 2]) and not bool(band[0, 7, 7]) and not bool(band[0, 1, 1])
    target = masks[..., None].expand(1, 16, 16, 3)
    share = error_share(torch.zeros_like(target), target, band)
    assert torch.allclose(share, torch.tensor([48 / 64], dtype=torch.float64))  # 48 of the square's 64 px
