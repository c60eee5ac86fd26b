"""Exports of a trained run: a standard point-cloud PLY, a 3D Gaussian splatting PLY and an NPZ of the raw
tensors.

PLY layout (binary little endian, one ``vertex`` element, one row per surfel)::

    x y z                    float   position (world units)
    nx ny nz                 float   unit normal
    red green blue           uchar   colour 0–255 (first three feature channels clamped to [0, 1];
                                     for the neural task these start as the stage-1 colours and are
                                     then learned, so they are only an approximate colour)
    opacity                  float   opacity in [0, 1]
    scale_0 scale_1          float   tangent standard deviations (world units, not log)
    f_0 … f_{C-1}            float   all C features (RGB albedo, or the learned neural features)

The first nine properties are what MeshLab, CloudCompare, Open3D and Blender read as a coloured point
cloud with normals; the rest are extra properties those tools ignore or list as scalar fields.
Note: unlike :meth:`nsplat.scene.SurfelScene.save_ply` (the training-internal layout: log-scales,
opacity logits, raw features), every value here is op-ready.

3DGS (``--format 3dgs``): 3D Gaussian splatting's ``point_cloud.ply`` layout, which Gaussian-splatting
viewers open (:mod:`nsplat.gaussians.ply`): every surfel as a flat Gaussian with its colour as spherical
harmonics. Two files: the classic one (header ``SplatRenderMode: default``), its opacity and tangent std-devs
converted from nsplat's low-pass-compensated kernel to 3DGS's (:mod:`nsplat.gaussians.kernel`: exact per view,
averaged over the training cameras because a file holds one opacity per Gaussian) and then fitted to nsplat's
renders of the training cameras (:mod:`nsplat.gaussians.fit`); and the antialiased one (``antialiased``; header
``SplatRenderMode: mip`` and ``train_flags antialiasing``) for rasterisers with Mip-Splatting's opacity
compensation, which is nsplat's κ: the surfels' own opacities. What each shows is measured in docs/results.md
("3DGS export"). It needs a colour model: the point-only
model (RGB or SH colour; Lambert-shaded tasks export their albedo); for the neural task, stage 1's surfels and
view colour (the U-Net is not in the file: a 3DGS viewer shows the stage-1 model).

NPZ: ``means [N,3]``, ``normals [N,3]``, ``scales [N,2]``, ``opacities [N]``, ``features [N,C]``,
``colours [N,3]`` (float, [0, 1]), ``background [C]`` and, when known, the training cameras
``viewmats [V,4,4]`` (OpenCV world→camera), ``Ks [V,3,3]``, ``image_size [2]`` (width, height).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from nsplat.gaussians.fit import FitSettings, Gaussians, fit_gaussians, nsplat_targets
from nsplat.gaussians.kernel import antialiased_of_surfels, to_gaussian, view_statistics
from nsplat.gaussians.ply import write_gaussian_ply
from nsplat.render.view_model import ViewModel

FORMATS = ("ply", "3dgs", "npz")
#: Default file name per format, in ``RUN/export/``.
FILE_NAMES = {"ply": "surfels.ply", "3dgs": "point_cloud.ply", "npz": "surfels.npz"}


def surfel_arrays(model: ViewModel) -> dict[str, np.ndarray]:
    """The op-ready per-point tensors of ``model`` as float32 NumPy arrays (plus ``colours [N,3]``)."""
    with torch.no_grad():
        t = {"means": model.means, "normals": model.normals, "scales": model.scales,
             "opacities": model.opacities, "features": model.features, "colours": model.rgb_colours()}
        return {k: v.detach().float().cpu().contiguous().numpy() for k, v in t.items()}


def write_ply(model: ViewModel, path: str | Path) -> Path:
    """Write ``model``'s surfels in the documented PLY layout; returns the path."""
    a = surfel_arrays(model)
    N, C = a["features"].shape
    rgb = np.clip(np.round(a["colours"] * 255.0), 0, 255).astype(np.uint8)
    cols: list[tuple[str, str, np.ndarray]] = []
    cols += [(n, "f4", a["means"][:, i]) for i, n in enumerate("xyz")]
    cols += [(n, "f4", a["normals"][:, i]) for i, n in enumerate(("nx", "ny", "nz"))]
    cols += [(n, "u1", rgb[:, i]) for i, n in enumerate(("red", "green", "blue"))]
    cols += [("opacity", "f4", a["opacities"]), ("scale_0", "f4", a["scales"][:, 0]),
             ("scale_1", "f4", a["scales"][:, 1])]
    cols += [(f"f_{c}", "f4", a["features"][:, c]) for c in range(C)]
    arr = np.empty(N, dtype=[(n, t) for n, t, _ in cols])
    for n, _, v in cols:
        arr[n] = v
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(arr, "vertex")], text=False, byte_order="<").write(str(path))
    return path


def read_ply(path: str | Path) -> dict[str, torch.Tensor]:
    """Read a PLY written by :func:`write_ply`: ``means, normals, scales, opacities, features`` (float32)
    and ``colours [N,3]`` (uint8)."""
    v = PlyData.read(str(path))["vertex"]
    names = v.data.dtype.names

    def stack(keys: list[str], dtype=np.float32) -> torch.Tensor:
        return torch.from_numpy(np.stack([np.asarray(v[k], dtype) for k in keys], 1))

    C = sum(1 for n in names if n.startswith("f_"))
    return {"means": stack(list("xyz")), "normals": stack(["nx", "ny", "nz"]),
            "colours": stack(["red", "green", "blue"], np.uint8), "opacities": stack(["opacity"])[:, 0],
            "scales": stack(["scale_0", "scale_1"]), "features": stack([f"f_{c}" for c in range(C)])}


def write_npz(model: ViewModel, path: str | Path) -> Path:
    """Write ``model``'s raw tensors (and training cameras) as an uncompressed NPZ; returns the path."""
    out = surfel_arrays(model)
    out["background"] = model.background.detach().float().cpu().numpy()
    if model.cameras is not None:
        c = model.cameras
        out.update(viewmats=c.viewmats.detach().float().cpu().numpy(), Ks=c.Ks.detach().float().cpu().numpy(),
                   image_size=np.array([c.width, c.height], np.int64))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        np.savez(fh, **out)
    return path


def read_npz(path: str | Path) -> dict[str, torch.Tensor]:
    """Read an NPZ written by :func:`write_npz` as tensors."""
    with np.load(str(path)) as z:
        return {k: torch.from_numpy(z[k]) for k in z.files}


def write_3dgs(model: ViewModel, path: str | Path, *, antialiased: bool = False,
               fit: FitSettings | None = None) -> Path:
    """Write ``model``'s surfels and colour in 3D Gaussian splatting's PLY layout (:mod:`nsplat.gaussians.ply`),
    with nsplat's kernel converted to 3DGS's (opacities and scales, :mod:`nsplat.gaussians.kernel`: averaged
    over the model's training cameras, with its ``render_cfg.lowpass``).

    ``antialiased``: for a rasteriser with Mip-Splatting's compensation (the surfels' own opacities when the
    low-pass is 0.3; the header says so). ``fit``: then fit the Gaussians to nsplat's renders of the training
    cameras (:mod:`nsplat.gaussians.fit`; ``None`` or 0 epochs: the conversion alone).

    Raises ``ValueError`` when the model's features are not a colour (a shader turns them into RGB) or it
    has no training cameras."""
    C = model.features.shape[1]
    if model.shader is not None or (model.sh_degree is None and C != 3):
        raise ValueError(f"--format 3dgs: the {model.task or 'run'}'s {C} features are not a colour (its shader makes "
                         "the RGB); a 3DGS file holds a colour per point")
    if model.cameras is None:
        raise ValueError(f"--format 3dgs: the {model.task or 'run'}'s model has no training cameras; converting "
                         "nsplat's kernel to 3DGS's averages over them")
    a = surfel_arrays(model)
    cams, rc = model.cameras, model.render_cfg
    t = {k: torch.from_numpy(a[k]) for k in ("means", "normals", "scales", "opacities")}
    args = (t["means"], t["normals"], t["scales"])
    views = (cams.viewmats.cpu(), cams.Ks.cpu(), cams.width, cams.height)
    kw = dict(lowpass=float(rc.lowpass), near=rc.near, far=rc.far)
    if antialiased:
        scales, opacities = antialiased_of_surfels(*args, t["opacities"], *views, **kw)
    else:
        kappa, pixel, _ = view_statistics(*args, *views, **kw)
        scales, opacities = to_gaussian(t["scales"], t["opacities"], kappa, pixel, kw["lowpass"])
    g = Gaussians(t["means"], t["normals"], scales, opacities, torch.from_numpy(a["features"]))
    if fit is not None and fit.epochs > 0:
        targets = nsplat_targets(model, fit.draws).cpu()
        g, _ = fit_gaussians(g, *views[:2], cams.width, cams.height, targets, model.background.detach().cpu()[:3],
                             fit, antialiased=antialiased)
    return write_gaussian_ply(path, *(x.detach().numpy() for x in (g.means, g.normals, g.scales, g.opacities,
                                                                    g.features)), antialiased=antialiased)


def export(model: ViewModel, fmt: str, path: str | Path, *, antialiased: bool = False,
           fit: FitSettings | None = None) -> Path:
    """Write ``model`` as ``fmt`` (``ply``, ``3dgs`` or ``npz``) to ``path`` (``antialiased``, ``fit``: ``3dgs``
    only, :func:`write_3dgs`)."""
    if fmt != "3dgs" and (antialiased or fit is not None):
        raise ValueError(f"--format {fmt}: the render mode and the fit are options of --format 3dgs")
    if fmt == "ply":
        return write_ply(model, path)
    if fmt == "3dgs":
        return write_3dgs(model, path, antialiased=antialiased, fit=fit)
    if fmt == "npz":
        return write_npz(model, path)
    raise ValueError(f"--format: expected one of {list(FORMATS)}, got {fmt!r}")
