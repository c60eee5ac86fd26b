"""What a 3DGS renderer shows of nsplat's exports and nsplat of 3DGS files (:mod:`nsplat.gaussians.kernel`), checked
with the 3DGS reference renderer :mod:`tests.gs_reference`, itself checked here against closed forms.

With one camera the view average is that camera's own kernel, so the conversion is exact: for surfels facing
the camera (nsplat's per-pixel depth is then the centre depth 3DGS sorts by) the reference render of the
export equals nsplat's dense render up to float32 rounding of the file, once the rasteriser's shortcuts are
turned off; with them on, the difference is what those shortcuts drop. Several cameras (a trained run):
tests/test_gaussian_ply.py and benchmarks/export_fidelity.py."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from nsplat.gaussians.export import write_3dgs
from nsplat.gaussians.fit import FitSettings
from nsplat.gaussians.kernel import GS_LOWPASS, surfels_of_gaussians
from nsplat.gaussians.ply import read_gaussian_ply, write_gaussian_ply
from nsplat.gaussians.raster import rasterize
from nsplat.ops import splat_dense
from nsplat.render.renderer import RenderConfig
from nsplat.render.sh import view_colour
from nsplat.render.view_model import TrainingCameras, ViewModel
from tests.gs_reference import SH_C0, gaussians_of_ply, quat_to_rotmat, render_3dgs, sh_to_rgb

W = H = 32
F = 40.0


def _camera() -> tuple[torch.Tensor, torch.Tensor]:
    """An OpenCV camera at the origin looking down +z: ``viewmat [4,4]``, ``K [3,3]``."""
    return torch.eye(4), torch.tensor([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("antialiased", [False, True])
def test_reference_renderer_blends_two_gaussians_as_the_closed_form(antialiased):
    """Both modes: classic (the peak is the opacity) and antialiased (Mip-Splatting's compensation: the opacity
    times ``sqrt(det Σ'₀ / det(Σ'₀ + 0.3 I))``, Σ'₀ the projected covariance before the dilation)."""
    viewmat, K = _camera()
    means = torch.tensor([[0.05, -0.02, 2.0], [-0.03, 0.04, 3.0]], dtype=torch.float64)
    s = torch.tensor([0.04, 0.06], dtype=torch.float64)                     # isotropic std-devs (world)
    logits = torch.tensor([1.5, 0.3], dtype=torch.float64)
    sh = torch.zeros(2, 1, 3, dtype=torch.float64)
    sh[0, 0], sh[1, 0] = torch.tensor([1.0, -1.0, 0.2]), torch.tensor([-0.5, 0.8, 0.0])
    bg = torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64)
    quats = torch.tensor([[0.3, 0.5, -0.1, 0.8], [1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)  # isotropic: any
    img = render_3dgs(means, quats, s.log()[:, None].expand(2, 3), logits, sh, viewmat, K, W, H, bg,
                      min_alpha=0.0, min_transmittance=0.0, cull=False, antialiased=antialiased)
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5,
                          indexing="ij")
    T, out = torch.ones(H, W, 1, dtype=torch.float64), torch.zeros(H, W, 3, dtype=torch.float64)
    for k in range(2):                                                      # nearest first
        x, y, z = means[k]
        J = torch.tensor([[F / z, 0, -F * x / z**2], [0, F / z, -F * y / z**2]], dtype=torch.float64)
        cov0 = s[k] ** 2 * J @ J.T                                          # EWA of an isotropic Gaussian
        cov = cov0 + 0.3 * torch.eye(2, dtype=torch.float64)                # + 0.3 px²
        peak = torch.sigmoid(logits[k]) * (torch.sqrt(cov0.det() / cov.det()) if antialiased else 1.0)
        d = torch.stack([u - (F * x / z + W / 2), v - (F * y / z + H / 2)], -1)
        a = peak * torch.exp(-0.5 * (d @ torch.linalg.inv(cov) * d).sum(-1))
        a = a.clamp(max=0.999)[..., None]
        out += T * a * (0.5 + SH_C0 * sh[k, 0])
        T = T * (1 - a)
    torch.testing.assert_close(img, out + T * bg, rtol=0, atol=1e-12)


def _facing_scene(n: int = 60, seed: int = 0, smallest: float = 0.1) -> dict[str, torch.Tensor]:
    """Surfels facing the camera of :func:`_camera` at distinct depths, std-devs from ``smallest`` to three
    pixels, most anisotropic, with a degree-1 view-dependent colour."""
    g = torch.Generator().manual_seed(seed)
    z = 2.0 + 2.0 * torch.rand(n, generator=g)
    xy = (torch.rand(n, 2, generator=g) - 0.5) * 0.8 * W / F * z[:, None]
    px = z / F                                                              # world size of a pixel at the surfel
    scales = px[:, None] * torch.exp(torch.empty(n, 2).uniform_(math.log(smallest), math.log(3.0), generator=g))
    normals = torch.zeros(n, 3)
    normals[:, 2] = torch.where(torch.rand(n, generator=g) < 0.5, -1.0, 1.0)
    features = torch.cat([torch.rand(n, 3, generator=g), 0.2 * torch.randn(n, 9, generator=g)], 1)
    return {"means": torch.cat([xy, z[:, None]], 1), "normals": normals, "scales": scales,
            "opacities": 0.3 + 0.65 * torch.rand(n, generator=g), "features": features}


def _nsplat(sc: dict[str, torch.Tensor], lowpass: float, bg: torch.Tensor) -> torch.Tensor:
    viewmat, K = _camera()
    colours = view_colour(sc["features"], sc["means"], viewmat)
    return splat_dense(sc["means"], sc["normals"], sc["scales"], sc["opacities"], colours, viewmat[None], K[None],
                       W, H, background=bg, lowpass=lowpass).image[0].double()


def _reference(path, bg: torch.Tensor, **kw) -> torch.Tensor:
    viewmat, K = _camera()
    g = gaussians_of_ply(path)
    return render_3dgs(g["means"], g["quats"], g["log_scales"], g["opacity_logits"], g["sh"], viewmat, K, W, H, bg,
                       **kw)


@pytest.mark.parametrize("lowpass", [GS_LOWPASS, 1.0])
def test_export_for_one_camera_renders_as_nsplat_in_3dgs(tmp_path, lowpass):
    sc, bg = _facing_scene(), torch.tensor([1.0, 1.0, 1.0])
    viewmat, K = _camera()
    model = ViewModel(**sc, background=bg, render_cfg=RenderConfig(renderer="dense", lowpass=lowpass),
                      cameras=TrainingCameras(viewmat[None], K[None], W, H), sh_degree=1)
    path = write_3dgs(model, tmp_path / "point_cloud.ply")
    ours = _nsplat(sc, lowpass, bg)
    exact = _reference(path, bg, min_alpha=0.0, min_transmittance=0.0, cull=False)
    # float32 file values (log-scales, logits) and the flat axis (1e-3 of the larger std-dev): measured 2.4e-7
    assert float((exact - ours).abs().max()) < 2e-6
    # with 3DGS's shortcuts on, what they drop: each skipped alpha (< 1/255) moves a pixel by less than 1/255 of
    # a colour difference (colours within [0, 1.6] here) and the tiles outside 3σ hold alphas below 0.011·o';
    # measured 0.0084 max and 0.0010 mean (λ = 1), 0.0069 and 0.0006 (λ = 0.3)
    shortcuts = _reference(path, bg)
    assert float((shortcuts - ours).abs().max()) < 0.02 and float((shortcuts - ours).abs().mean()) < 2e-3
    # the surfels written as they are, without the conversion: measured 0.50 (λ = 0.3) and 0.60 (λ = 1) max
    raw = write_gaussian_ply(tmp_path / "raw.ply", *(sc[k].numpy() for k in ("means", "normals", "scales",
                                                                              "opacities", "features")))
    assert float((_reference(raw, bg, min_alpha=0.0, min_transmittance=0.0, cull=False) - ours).abs().max()) > 0.3


def test_another_tools_flat_gaussians_import_to_the_render_3dgs_shows(tmp_path):
    """A 3DGS file of flat Gaussians facing the camera, peak opacities as 3DGS means them, imported with the
    inverse conversion: nsplat's dense render equals the reference render of the file. (Gaussians of at least a
    pixel with opacities up to 0.75: nsplat's peak factor κ is then above 0.77, so ``o'/κ`` is an opacity;
    a brighter sub-pixel Gaussian has no surfel equivalent, its opacity saturates at 1.)"""
    sc, bg = _facing_scene(seed=1, smallest=1.0), torch.tensor([0.0, 0.0, 0.0])
    sc["opacities"] = 0.3 + 0.45 * torch.rand(sc["opacities"].shape[0], generator=torch.Generator().manual_seed(2))
    n = sc["means"].shape[0]
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3"]
    arr = np.zeros(n, dtype=[(k, "<f4") for k in names])
    for i, k in enumerate("xyz"):
        arr[k] = sc["means"][:, i].numpy()
    for i in range(3):
        arr[f"f_dc_{i}"] = ((sc["features"][:, i] - 0.5) / SH_C0).numpy()
    arr["opacity"] = torch.logit(sc["opacities"]).numpy()
    arr["scale_0"], arr["scale_1"] = sc["scales"][:, 0].log().numpy(), sc["scales"][:, 1].log().numpy()
    arr["scale_2"] = np.log(1e-6)
    arr["rot_0"] = 1.0                                                       # the z axis is flat: normal (0, 0, 1)
    path = tmp_path / "theirs.ply"
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(path))
    g = read_gaussian_ply(path)
    viewmat, K = _camera()
    scales, opacities = surfels_of_gaussians(g["means"], g["normals"], g["scales"], g["opacities"], viewmat[None],
                                             K[None], W, H, lowpass=GS_LOWPASS)
    imported = {"means": g["means"].float(), "normals": g["normals"].float(), "scales": scales.float(),
                "opacities": opacities.float(), "features": g["features"].float()}
    assert float(opacities.max()) < 0.99                                     # o'/κ stays an opacity here
    ours = _nsplat(imported, GS_LOWPASS, bg)
    theirs = _reference(path, bg, min_alpha=0.0, min_transmittance=0.0, cull=False)
    assert float((theirs - ours).abs().max()) < 2e-5                         # measured 2e-6


def _random_gaussians(n: int = 300, seed: int = 0) -> dict[str, torch.Tensor]:
    """Gaussians of any orientation in front of :func:`_camera`, from a tenth of a pixel to three pixels, some
    flat, with degree-1 colour and opacities spread over (0, 1) (float64)."""
    g = torch.Generator().manual_seed(seed)
    z = 2.0 + 2.0 * torch.rand(n, generator=g, dtype=torch.float64)
    xy = (torch.rand(n, 2, generator=g, dtype=torch.float64) - 0.5) * 1.4 * W / F * z[:, None]
    log_s = torch.log(z[:, None] / F) + torch.empty(n, 3, dtype=torch.float64).uniform_(math.log(0.1), math.log(3.0),
                                                                                          generator=g)
    log_s[: n // 2, 2] -= 6.0                                                # flat
    return {"means": torch.cat([xy, z[:, None]], 1), "quats": torch.randn(n, 4, generator=g, dtype=torch.float64),
            "log_scales": log_s, "opacity_logits": 2.0 * torch.randn(n, generator=g, dtype=torch.float64),
            "sh": 0.5 * torch.randn(n, 4, 3, generator=g, dtype=torch.float64)}


@pytest.mark.parametrize("antialiased", [False, True])
def test_differentiable_rasteriser_renders_and_differentiates_as_the_reference(antialiased):
    """:func:`nsplat.gaussians.raster.rasterize` (pixel-Gaussian pairs) against the reference (tiles), both modes, its
    shortcuts on; its gradient against central differences of the reference."""
    g, (viewmat, K) = _random_gaussians(), _camera()
    viewmat, K = viewmat.double(), K.double()
    bg = torch.tensor([0.2, 0.5, 1.0], dtype=torch.float64)
    R = quat_to_rotmat(g["quats"])

    def ours(logits: torch.Tensor, means: torch.Tensor) -> torch.Tensor:
        M = R * torch.exp(g["log_scales"])[:, None, :]
        colours = sh_to_rgb(g["sh"], torch.nn.functional.normalize(means, dim=-1))   # camera at the origin
        return rasterize(means, M @ M.transpose(1, 2), torch.sigmoid(logits), colours, viewmat, K, W, H, bg,
                         antialiased=antialiased)

    def theirs(logits: torch.Tensor, means: torch.Tensor) -> torch.Tensor:
        return render_3dgs(means, g["quats"], g["log_scales"], logits, g["sh"], viewmat, K, W, H, bg,
                           antialiased=antialiased)

    logits, means = g["opacity_logits"].clone().requires_grad_(), g["means"].clone().requires_grad_()
    img = ours(logits, means)
    assert float((img.detach() - theirs(g["opacity_logits"], g["means"])).abs().max()) < 1e-12  # measured 4e-14
    weights = torch.rand(img.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    (img * weights).sum().backward()
    h = 1e-6
    for k in torch.argsort(logits.grad.abs(), descending=True)[:5].tolist():           # the most influential
        step = torch.zeros_like(logits)
        step[k] = h
        fd = float(((theirs(logits.detach() + step, g["means"]) - theirs(logits.detach() - step, g["means"]))
                    * weights).sum()) / (2 * h)
        assert abs(fd - float(logits.grad[k])) < 1e-5 * max(1.0, abs(fd)), (k, fd, float(logits.grad[k]))
        step3 = torch.zeros_like(means)
        step3[k, 0] = h
        fd = float(((theirs(g["opacity_logits"], means.detach() + step3)
                     - theirs(g["opacity_logits"], means.detach() - step3)) * weights).sum()) / (2 * h)
        assert abs(fd - float(means.grad[k, 0])) < 1e-5 * max(1.0, abs(fd)), (k, fd, float(means.grad[k, 0]))


def test_antialiased_export_renders_as_nsplat_from_every_distance(tmp_path):
    """Two cameras, the second twice as far: every splat's nsplat peak factor κ differs between them, so no
    one opacity (the classic file) reproduces both; the antialiased file (the surfels' own opacities, 0.3 px²)
    rendered with Mip-Splatting's compensation does, in both, and imports as the surfels it came from."""
    sc, bg = _facing_scene(seed=3), torch.tensor([1.0, 1.0, 1.0])
    viewmat, K = _camera()
    far = viewmat.clone()
    far[2, 3] = 3.0                                                          # 3 units further back: z from 5 to 7
    cams = TrainingCameras(torch.stack([viewmat, far]), K[None].expand(2, 3, 3), W, H)
    model = ViewModel(**sc, background=bg, render_cfg=RenderConfig(renderer="dense", lowpass=GS_LOWPASS),
                      cameras=cams, sh_degree=1)
    aa, classic = (write_3dgs(model, tmp_path / f"{name}.ply", antialiased=name == "aa") for name in ("aa", "classic"))
    with torch.no_grad():                                                    # the fit turns gradients on itself
        fitted = write_3dgs(model, tmp_path / "fitted.ply", fit=FitSettings(epochs=10, draws=1))
    g = gaussians_of_ply(aa)
    assert g["antialiased"] and not gaussians_of_ply(classic)["antialiased"]
    assert PlyData.read(str(aa)).comments == ["SplatRenderMode: mip", "train_flags antialiasing"]
    errors = {}
    for v, vm in enumerate((viewmat, far)):
        colours = view_colour(sc["features"], sc["means"], vm)
        ours = splat_dense(sc["means"], sc["normals"], sc["scales"], sc["opacities"], colours, vm[None], K[None],
                           W, H, background=bg, lowpass=GS_LOWPASS).image[0].double()
        for name, path in (("aa", aa), ("classic", classic), ("fitted", fitted)):
            f = gaussians_of_ply(path)
            img = render_3dgs(f["means"], f["quats"], f["log_scales"], f["opacity_logits"], f["sh"], vm, K, W, H, bg,
                              antialiased=f["antialiased"], min_alpha=0.0, min_transmittance=0.0, cull=False)
            errors[name, v] = float((img - ours).abs().max())
            errors["mse", name] = errors.get(("mse", name), 0.0) + float(((img - ours) ** 2).mean())
    assert max(errors["aa", 0], errors["aa", 1]) < 2e-6, errors     # float32 rounding of the file: measured 1.3e-6
    assert min(errors["classic", 0], errors["classic", 1]) > 0.05, errors   # κ̄ is neither view's κ: measured 0.13
    # a fit (under no_grad too) can only share κ's conflict between the views: measured 0.72× the squared error
    assert errors["mse", "fitted"] < 0.8 * errors["mse", "classic"], errors
    r = read_gaussian_ply(aa)
    assert r["antialiased"]
    scales, opacities = surfels_of_gaussians(r["means"], r["normals"], r["scales"], r["opacities"], cams.viewmats,
                                             cams.Ks, W, H, lowpass=GS_LOWPASS, antialiased=True)
    torch.testing.assert_close(opacities.float(), sc["opacities"], rtol=0, atol=1e-6)
    torch.testing.assert_close(scales.float(), sc["scales"], rtol=1e-5, atol=0)
