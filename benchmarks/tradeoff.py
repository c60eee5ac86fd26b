"""Speed/accuracy trade of the sampled op: sample size m, ε, the Hermite expansion settings and the
backward mode, on the DSS bunny (8171 surfels with normals) rendered from a few views.

Per configuration it measures, in one process and one run:

* time of the forward (project + sample + composite) and of the backward of a linear image loss:
  ``process_time`` (CPU seconds of all threads) and wall, minimum over ``--repeats``; threads noted;
* peak resident memory of one forward+backward (Linux ``VmHWM`` after resetting it), minus the
  resident size before;
* mean ``work`` (exact kernel evaluations per pixel);
* forward error against :func:`nsplat.ops.splat_dense` (the exact oracle): mean absolute error and
  PSNR of the alpha-composited image, of the additive (Horvitz–Thompson) image, and the relative
  error of the total estimate ``Λ̂`` (median and max over pixels);
* the fraction of pixels whose sample differs from the exact SPS sample (``sps`` brute force with the
  same RNG) on a fixed pixel subset;

and, for each estimator, the gradient bias (mean over R seeds minus the dense gradient, in units of
its standard error) and the gradient variance, in additive mode with a linear loss. It also times
the deterministic two-pass backward against the single-pass atomic-scatter one. Results go to
``benchmarks/results/tradeoff.json``, plots to ``docs/images/tradeoffs/``.

    OMP_NUM_THREADS=1 python -m benchmarks.tradeoff                 # the full run (~15 min, 2 cores)
    OMP_NUM_THREADS=1 python -m benchmarks.tradeoff --tiny          # a quick check of the script
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import re
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import IMAGES, RESULTS, machine
from nsplat.cameras import intrinsics_from_fov, look_at
from nsplat.data.pointclouds import load_dss_shape
from nsplat.ops import project, splat, splat_dense
from nsplat.ops.reference import pixel_centres
from nsplat.ops.rng import uniforms
from nsplat.scene import knn_spacing

SAMPLES = (1, 2, 4, 8, 16, 32, 64)
EPS = (0.1, 0.01, 0.001)
HERMITE = ((0, 1e-3), (4, 1e-3), (4, 1e-2), (8, 1e-3), (8, 1e-2))  # (order, tol); order 0 = no expansion
ESTIMATORS = ("ht", "paper", "sampled")
BG = (1.0, 1.0, 1.0)


# ---------------------------------------------------------------------------------------------- scene
def bunny_scene(points: int | None) -> dict[str, torch.Tensor]:
    """GT-like bunny surfels: isotropic std-dev = mean 3-NN spacing, opacity 0.9, colour from the normal."""
    pc = load_dss_shape("bunny")
    idx = torch.arange(pc.points.shape[0])
    if points is not None and points < idx.numel():
        idx = torch.randperm(idx.numel(), generator=torch.Generator().manual_seed(0))[:points]
    centre, radius = pc.center, pc.radius
    means = ((pc.points[idx] - centre) / radius).float()
    normals = pc.normals[idx].float()
    sp = torch.as_tensor(knn_spacing(means), dtype=torch.float32)
    n = means.shape[0]
    return dict(means=means, normals=normals, scales=sp[:, None].expand(n, 2).contiguous(),
                opacities=torch.full((n,), 0.9), features=(0.5 + 0.5 * normals).clamp(0, 1))


def cameras(views: int, res: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``views`` cameras on a ring at 20° elevation, 3 radii from the centre, 40° field of view."""
    ang = torch.arange(views, dtype=torch.float32) * 2 * math.pi / views + 0.3
    eye = torch.stack([3 * torch.cos(ang), 3 * torch.sin(ang) * 0.94, torch.full_like(ang, 1.03)], -1)
    V = look_at(eye, torch.zeros_like(eye), torch.tensor([0.0, 0.0, 1.0]))
    K = intrinsics_from_fov(math.radians(40.0), res, res, batch=views)
    return V, K


def args_of(sc: dict[str, torch.Tensor], V: torch.Tensor, K: torch.Tensor, res: int) -> tuple:
    return (sc["means"], sc["normals"], sc["scales"], sc["opacities"], sc["features"], V, K, res, res)


# ---------------------------------------------------------------------------------------------- memory
def _status(key: str) -> int:
    text = Path("/proc/self/status").read_text()
    m = re.search(rf"{key}:\s+(\d+)", text)
    return int(m.group(1)) * 1024 if m else -1


def _libc():
    import ctypes
    import ctypes.util

    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None


_LIBC = _libc()
if _LIBC is not None and hasattr(_LIBC, "mallopt"):
    # glibc: serve every allocation >= 64 KiB by mmap (fixed threshold, no dynamic raise), so freed
    # buffers go back to the OS and the resident size tracks live memory
    _LIBC.mallopt(-3, 64 * 1024)  # M_MMAP_THRESHOLD
    _LIBC.mallopt(-1, 128 * 1024)  # M_TRIM_THRESHOLD


def peak_rss(fn) -> tuple[int, int]:
    """``(peak RSS during fn − RSS before, peak RSS)`` in bytes (Linux; (-1, -1) elsewhere)."""
    if _LIBC is not None and hasattr(_LIBC, "malloc_trim"):
        _LIBC.malloc_trim(0)
    try:
        Path("/proc/self/clear_refs").write_text("5")  # resets VmHWM to the current RSS
    except OSError:
        fn()
        return -1, -1
    before = _status("VmRSS")
    fn()
    peak = _status("VmHWM")
    return peak - before, peak


# ---------------------------------------------------------------------------------------------- oracles
def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float((a.double() - b.double()).square().mean())
    return float("inf") if mse == 0 else 10 * math.log10(1.0 / mse)


def sps_oracle(sc, V, K, res: int, stride: int, kmax: int, seed: int = 0) -> list[dict]:
    """Per camera: a pixel subset (every ``stride``-th pixel whose exact total Λ exceeds 10× the
    documented floor 1e-10) and, per pixel, the ``kmax`` smallest exact SPS keys ``log u − log λ`` with
    their point ids. λ is evaluated in log space in float64 from the op's own (float32) projected
    values, exactly as the sampler's leaves do (csrc/core/ewa.h ``log_size``)."""
    with torch.no_grad():
        proj = project(sc["means"], sc["normals"], sc["scales"], sc["opacities"], V, K, near=0.01, far=1e10,
                       lowpass=1.0)
    pix_all = pixel_centres(res, res, torch.float64, torch.device("cpu")).numpy()
    ids = np.arange(0, res * res, stride)
    N = sc["means"].shape[0]
    out = []
    for b in range(V.shape[0]):
        mu = proj.means2d[b].double().numpy()
        con = proj.conics[b].double().numpy()
        amp = proj.amps[b].double().numpy()
        ok = amp > 0
        with np.errstate(divide="ignore"):
            log_a = np.where(ok, np.log(np.where(ok, amp, 1.0)), -np.inf)
        keys_l, idx_l, keep_l = [], [], []
        for s in range(0, ids.size, 256):
            pid = ids[s:s + 256]
            dx = pix_all[pid, :1] - mu[None, :, 0]
            dy = pix_all[pid, 1:] - mu[None, :, 1]
            q = con[None, :, 0] * dx * dx + 2.0 * con[None, :, 1] * dx * dy + con[None, :, 2] * dy * dy
            log_lam = np.minimum(math.log(0.99), log_a[None, :] - 0.5 * q)
            total = np.exp(log_lam).sum(1)
            u = uniforms(seed, b, pid, np.arange(N))
            key = np.log(u) - log_lam  # +inf where λ = 0 (culled or zero opacity)
            k = min(kmax, N)
            part = np.argpartition(key, k - 1, axis=1)[:, :k]
            pk = np.take_along_axis(key, part, 1)
            order = np.argsort(pk, axis=1, kind="stable")
            keys_l.append(np.take_along_axis(pk, order, 1))
            idx_l.append(np.take_along_axis(part, order, 1))
            keep_l.append(total > 1e-9)
        keep = np.concatenate(keep_l)
        out.append({"pixels": ids[keep], "keys": np.concatenate(keys_l)[keep], "idx": np.concatenate(idx_l)[keep],
                    "subset": int(ids.size)})
    return out


def sps_differs(indices: torch.Tensor, oracle: list[dict], m: int) -> float:
    """Fraction of oracle pixels whose sampled set differs from the exact SPS set of size m."""
    diff = total = 0
    for b, o in enumerate(oracle):
        got = indices[b].reshape(-1, indices.shape[-1])[torch.as_tensor(o["pixels"])].numpy()
        k = min(m, o["idx"].shape[1])
        want = np.where(np.isfinite(o["keys"][:, :k]), o["idx"][:, :k], -1)
        a = np.sort(np.where(got[:, :m] >= 0, got[:, :m], -1), axis=1)
        w = np.full_like(a, -1)
        w[:, :k] = want
        w = np.sort(w, axis=1)
        diff += int((a != w).any(axis=1).sum())
        total += a.shape[0]
    return diff / max(1, total)


# ---------------------------------------------------------------------------------------------- timing
def timed(fn, repeats: int) -> dict[str, float]:
    best_cpu, best_wall = float("inf"), float("inf")
    for _ in range(repeats):
        c0, w0 = time.process_time(), time.perf_counter()
        fn()
        best_cpu = min(best_cpu, time.process_time() - c0)
        best_wall = min(best_wall, time.perf_counter() - w0)
    return {"cpu_s": best_cpu, "wall_s": best_wall}


def measure(sc, V, K, res, dense, oracle, *, samples, eps, hermite_order, hermite_tol, repeats,
            deterministic=True, extra=True) -> dict:
    leaves = [t.clone().requires_grad_() for t in (sc["means"], sc["normals"], sc["scales"], sc["opacities"],
                                                   sc["features"])]
    bg = torch.tensor(BG)
    kw = dict(samples=samples, eps=eps, hermite_order=hermite_order, hermite_tol=hermite_tol, background=bg,
              seed=0, deterministic=deterministic)
    g = torch.Generator().manual_seed(7)
    weights = torch.randn(V.shape[0], res, res, 3, generator=g)
    state = {}

    def fwd():
        state["out"] = splat(*leaves, V, K, res, res, **kw)

    def bwd():
        grads = torch.autograd.grad((state["out"].image * weights).sum(), leaves)
        state["grads"] = grads

    def both():
        fwd()
        bwd()

    t_f = {"cpu_s": float("inf"), "wall_s": float("inf")}
    t_b = dict(t_f)
    for _ in range(repeats):
        t = timed(fwd, 1)
        t_f = {k: min(t_f[k], t[k]) for k in t}
        t = timed(bwd, 1)
        t_b = {k: min(t_b[k], t[k]) for k in t}
    mem_delta, mem_peak = peak_rss(both)
    out = state["out"]
    rec = dict(samples=samples, eps=eps, hermite_order=hermite_order, hermite_tol=hermite_tol,
               deterministic=deterministic, forward=t_f, backward=t_b,
               total_cpu_s=t_f["cpu_s"] + t_b["cpu_s"], total_wall_s=t_f["wall_s"] + t_b["wall_s"],
               peak_rss_delta_mb=mem_delta / 2**20, peak_rss_mb=mem_peak / 2**20,
               work_mean=float(out.work.float().mean()), work_max=int(out.work.max()))
    if not extra:
        return rec
    img = out.image.detach()
    rec.update(alpha_mae=float((img - dense["alpha"].image).abs().mean()), alpha_psnr=psnr(img, dense["alpha"].image))
    lam = dense["alpha"].total
    mask = lam > 1e-6
    rel = ((out.total - lam).abs() / lam.clamp_min(1e-30))[mask]
    rec.update(total_rel_err_median=float(rel.median()) if rel.numel() else 0.0,
               total_rel_err_max=float(rel.max()) if rel.numel() else 0.0)
    with torch.no_grad():
        add = splat(*[t.detach() for t in leaves], V, K, res, res, composite="additive",
                    **{k: v for k, v in kw.items() if k != "deterministic"}).image
    rec.update(additive_mae=float((add - dense["additive"].image).abs().mean()),
               additive_psnr=psnr(add, dense["additive"].image))
    rec["sps_differs"] = sps_differs(out.indices, oracle, samples)
    return rec


# ---------------------------------------------------------------------------------------------- gradients
def _z_scores(G: torch.Tensor, ref: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Bias of the scalar statistics ``d·g`` in standard errors: ``(mean_r d·G_r − d·ref) / se``.

    Projections average many coordinates, so their sampling distribution is close to normal even
    for modest R (single coordinates of a Horvitz–Thompson gradient are heavy tailed: a point that
    is rarely sampled contributes a rare, large term, and R draws that missed it give a tiny,
    meaningless standard error). An unbiased estimator gives z ~ N(0, 1) for every direction."""
    P = G @ dirs.T  # [R, D]
    R = G.shape[0]
    se = P.std(0, unbiased=True) / math.sqrt(R)
    return (P.mean(0) - dirs @ ref) / se


def gradient_study(sc, V, K, res, R, samples_list, eps, directions: int = 32) -> list[dict]:
    """Bias (z-scores of projections) and variance of each estimator's gradient vs the dense gradient,
    additive mode, linear loss, float64; per parameter group and for the whole gradient."""
    names = ("means", "normals", "scales", "opacities", "features")
    g = torch.Generator().manual_seed(3)
    w_img = torch.randn(V.shape[0], res, res, 3, generator=g, dtype=torch.float64)
    bg = torch.tensor(BG, dtype=torch.float64)
    sc64 = {k: v.double() for k, v in sc.items()}

    def grads(fn):
        leaves = [sc64[n].clone().requires_grad_() for n in names]
        out = fn(leaves)
        return torch.cat([x.reshape(-1) for x in torch.autograd.grad((out.image * w_img).sum(), leaves)])

    ref = grads(lambda p: splat_dense(*p, V.double(), K.double(), res, res, composite="additive", background=bg))
    sizes = [sc[n].numel() for n in names]
    slices, off = {}, 0
    for n, sz in zip(names, sizes):
        slices[n] = slice(off, off + sz)
        off += sz
    # directions: the dense gradient itself and random Gaussian ones, per group and for everything
    dirs = {}
    for n, sl in list(slices.items()) + [("all", slice(0, off))]:
        d = torch.zeros(directions + 1, off, dtype=torch.float64)
        d[0, sl] = ref[sl] / ref[sl].norm().clamp_min(1e-300)
        d[1:, sl] = torch.randn(directions, sl.stop - sl.start, generator=g, dtype=torch.float64)
        d[1:] /= d[1:].norm(dim=1, keepdim=True)
        dirs[n] = d
    rows = []
    for est in ESTIMATORS:
        for m in samples_list:
            c0 = time.process_time()
            G = torch.stack([grads(lambda p: splat(*p, V.double(), K.double(), res, res, samples=m, eps=eps,
                                                   composite="additive", estimator=est, background=bg, seed=1000 + r))
                             for r in range(R)])
            mean, std = G.mean(0), G.std(0, unbiased=True)
            rec = dict(estimator=est, samples=m, eps=eps, R=R, directions=directions + 1,
                       cpu_s_per_grad=(time.process_time() - c0) / R)
            per = {}
            for n, d in dirs.items():
                sl = slices.get(n, slice(0, off))
                z = _z_scores(G, ref, d)
                per[n] = dict(z_along_dense=float(z[0]), z_rms=float(z.square().mean().sqrt()),
                              z_abs_max=float(z.abs().max()),
                              scale_ratio=float(mean[sl] @ ref[sl] / (ref[sl] @ ref[sl]).clamp_min(1e-300)),
                              rel_bias=float((mean[sl] - ref[sl]).norm() / ref[sl].norm().clamp_min(1e-300)),
                              rel_std=float(std[sl].square().mean().sqrt() / ref[sl].square().mean().sqrt()
                                            .clamp_min(1e-300)))
            rec.update({k: per["all"][k] for k in per["all"]})
            rec["noise_floor_rel_bias"] = rec["rel_std"] / math.sqrt(R)
            rec["per_parameter"] = {n: v for n, v in per.items() if n != "all"}
            rows.append(rec)
            print(f"  grad {est:8s} m={m:3d}: z rms {rec['z_rms']:6.2f} (along dense {rec['z_along_dense']:7.2f}, "
                  f"max {rec['z_abs_max']:6.2f})  E[g]·g*/|g*|² {rec['scale_ratio']:.3f}  rel bias "
                  f"{rec['rel_bias']:.3f} (noise {rec['noise_floor_rel_bias']:.3f})  rel std {rec['rel_std']:.3f}",
                  flush=True)
    return rows


# ---------------------------------------------------------------------------------------------- plots
def pareto(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points not dominated in (lower time, higher quality)."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], -points[i][1]))
    front, best = [], -float("inf")
    for i in order:
        if points[i][1] > best:
            front.append(i)
            best = points[i][1]
    return front


def make_plots(res: dict, folder: Path) -> list[str]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    files = []
    grid = res["samples_eps"]
    herm = res["hermite"]
    # 1. time vs error, all configs, per knob, with the Pareto front
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, key, label in ((axes[0], "alpha_psnr", "alpha-composited PSNR vs dense (dB)"),
                           (axes[1], "additive_psnr", "additive (HT) PSNR vs dense (dB)")):
        for eps, marker in zip(EPS, "os^"):
            rows = [r for r in grid if r["eps"] == eps]
            ax.plot([r["total_cpu_s"] for r in rows], [r[key] for r in rows], marker=marker, label=f"ε={eps}")
            for r in rows:
                ax.annotate(str(r["samples"]), (r["total_cpu_s"], r[key]), fontsize=7, xytext=(3, 2),
                            textcoords="offset points")
        ax.plot([r["total_cpu_s"] for r in herm], [r[key] for r in herm], "kx", label="hermite settings (m=16)")
        pts = [(r["total_cpu_s"], r[key]) for r in grid + herm]
        front = pareto(pts)
        ax.plot([pts[i][0] for i in front], [pts[i][1] for i in front], "r--", lw=1, label="Pareto front")
        ax.set_xscale("log")
        ax.set_xlabel("forward + backward CPU seconds (process_time)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("samples m (labels) × ε: time vs error")
    fig.tight_layout()
    p = folder / "time_vs_error.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    files.append(p.name)
    # 2. per knob: samples
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for eps in EPS:
        rows = [r for r in grid if r["eps"] == eps]
        m = [r["samples"] for r in rows]
        axes[0].plot(m, [r["total_cpu_s"] for r in rows], "o-", label=f"ε={eps}")
        axes[1].plot(m, [r["work_mean"] for r in rows], "o-", label=f"ε={eps}")
        axes[2].plot(m, [max(r["sps_differs"], 1e-5) for r in rows], "o-", label=f"ε={eps}")
        axes[2].axhline(eps, ls=":", lw=0.8)
    for ax, lab in zip(axes, ("fwd+bwd CPU s", "kernel evaluations / pixel", "fraction of pixels ≠ exact SPS")):
        ax.set_xscale("log", base=2)
        ax.set_xlabel("samples m")
        ax.set_ylabel(lab)
        ax.grid(alpha=0.3)
    axes[1].set_yscale("log")
    axes[2].set_yscale("log")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    p = folder / "samples_knob.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    files.append(p.name)
    # 3. hermite knob
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    labels = [f"p≤{r['hermite_order']}\ntol {r['hermite_tol']:g}" if r["hermite_order"] else "no\nexpansion"
              for r in herm]
    x = np.arange(len(herm))
    axes[0].bar(x, [r["forward"]["cpu_s"] for r in herm], label="forward")
    axes[0].bar(x, [r["backward"]["cpu_s"] for r in herm], bottom=[r["forward"]["cpu_s"] for r in herm],
                label="backward")
    axes[0].set_ylabel("CPU s")
    axes[0].legend(fontsize=8)
    axes[1].bar(x, [r["work_mean"] for r in herm])
    axes[1].set_ylabel("kernel evaluations / pixel")
    for ax in axes:
        ax.set_xticks(x, labels, fontsize=8)
        ax.grid(alpha=0.3, axis="y")
    fig.suptitle(f"Hermite expansion settings (m={herm[0]['samples']}, ε={herm[0]['eps']})")
    fig.tight_layout()
    p = folder / "hermite_knob.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    files.append(p.name)
    # 4. gradients
    gr = res["gradients"]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for est in ESTIMATORS:
        rows = [r for r in gr if r["estimator"] == est]
        m = [r["samples"] for r in rows]
        axes[0].plot(m, [r["z_rms"] for r in rows], "o-", label=est)
        axes[1].plot(m, [r["rel_bias"] for r in rows], "o-", label=est)
        axes[2].plot(m, [r["rel_std"] for r in rows], "o-", label=est)
    axes[0].axhline(1.0, ls=":", c="k", lw=0.8)
    for ax, lab in zip(axes, ("RMS z of 33 projections (≈1: no detectable bias)", "‖mean − dense‖ / ‖dense‖",
                              "per-sample RMS std / RMS dense")):
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_xlabel("samples m")
        ax.set_ylabel(lab)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"gradient bias and variance (additive mode, R={gr[0]['R']} seeds)")
    fig.tight_layout()
    p = folder / "gradients.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    files.append(p.name)
    return files


# ---------------------------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tiny", action="store_true", help="small scene, few configs (checks the script)")
    p.add_argument("--points", type=int, default=None, help="subsample the bunny (default: all 8171)")
    p.add_argument("--res", type=int, default=128)
    p.add_argument("--views", type=int, default=4)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--grad-res", type=int, default=64)
    p.add_argument("--grad-views", type=int, default=2)
    p.add_argument("--R", type=int, default=16, help="seeds per gradient estimate")
    p.add_argument("--sps-stride", type=int, default=8, help="SPS oracle on every k-th pixel")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--cache", default="/tmp/nsplat-bench-cache", help="folder caching the dense reference "
                   "and SPS oracle between runs ('' disables)")
    p.add_argument("--out", type=Path, default=RESULTS / "tradeoff.json")
    p.add_argument("--plots", type=Path, default=IMAGES / "tradeoffs")
    args = p.parse_args(argv)
    samples, eps_list, hermite, grad_m = SAMPLES, EPS, HERMITE, (1, 4, 16, 64)
    if args.tiny:
        args.points, args.res, args.views, args.repeats = args.points or 800, 32, 2, 1
        args.grad_res, args.R = 24, 4
        samples, grad_m = (1, 4, 16), (4, 16)
        args.out = Path("/tmp/nsplat_tradeoff_tiny.json")
        args.plots = Path("/tmp/nsplat_tradeoff_tiny_plots")
    torch.set_num_threads(args.threads)
    t_start = time.perf_counter()
    sc = bunny_scene(args.points)
    V, K = cameras(args.views, args.res)
    res = args.res
    print(f"bunny: {sc['means'].shape[0]} surfels, {args.views} views at {res}x{res}, "
          f"{torch.get_num_threads()} thread(s)", flush=True)
    key = f"{sc['means'].shape[0]}-{args.views}-{res}-{args.sps_stride}-{max(samples) + 1}"
    cache = Path(args.cache) / f"tradeoff-ref-{key}.pt" if args.cache else None
    if cache is not None and cache.is_file():
        saved = torch.load(cache, weights_only=False)
        dense, oracle, dense_cpu = saved["dense"], saved["oracle"], saved["dense_cpu"]
        print(f"dense reference and SPS oracle from {cache} (dense took {dense_cpu:.1f} CPU s)", flush=True)
    else:
        c0 = time.process_time()
        with torch.no_grad():
            dense = {c: splat_dense(*args_of(sc, V, K, res), composite=c, background=torch.tensor(BG))
                     for c in ("alpha", "additive")}
        dense_cpu = time.process_time() - c0
        print(f"dense reference: {dense_cpu:.1f} CPU s", flush=True)
        c0 = time.process_time()
        oracle = sps_oracle(sc, V, K, res, args.sps_stride, max(samples) + 1)
        print(f"SPS oracle on {len(oracle[0]['pixels'])} pixels/view: {time.process_time() - c0:.1f} CPU s",
              flush=True)
        if cache is not None:
            cache.parent.mkdir(parents=True, exist_ok=True)
            torch.save({"dense": dense, "oracle": oracle, "dense_cpu": dense_cpu}, cache)

    common = dict(repeats=args.repeats)
    grid = []
    for eps in eps_list:
        for m in samples:
            r = measure(sc, V, K, res, dense, oracle, samples=m, eps=eps, hermite_order=8, hermite_tol=1e-3, **common)
            grid.append(r)
            print(f"m={m:3d} ε={eps:<6g}: fwd {r['forward']['cpu_s']:.3f}s bwd {r['backward']['cpu_s']:.3f}s "
                  f"work {r['work_mean']:7.1f}  PSNR α {r['alpha_psnr']:5.1f} add {r['additive_psnr']:5.1f}  "
                  f"≠SPS {r['sps_differs']:.4f}  Λ̂ rel err med {r['total_rel_err_median']:.1e}  "
                  f"mem +{r['peak_rss_delta_mb']:.0f} MB", flush=True)
    herm_m = 16
    herm = []
    for order, tol in hermite:
        r = measure(sc, V, K, res, dense, oracle, samples=herm_m, eps=0.01, hermite_order=order, hermite_tol=tol,
                    **common)
        herm.append(r)
        print(f"hermite p≤{order} tol {tol:g}: fwd {r['forward']['cpu_s']:.3f}s work {r['work_mean']:.1f} "
              f"Λ̂ rel err med {r['total_rel_err_median']:.1e} max {r['total_rel_err_max']:.1e} "
              f"≠SPS {r['sps_differs']:.4f}", flush=True)
    backward_modes = []
    for threads in sorted({1, 2}):
        torch.set_num_threads(threads)
        for m in (16, 64) if not args.tiny else (16,):
            for det in (True, False):
                r = measure(sc, V, K, res, dense, oracle, samples=m, eps=0.01, hermite_order=8, hermite_tol=1e-3,
                            deterministic=det, extra=False, repeats=max(2, args.repeats))
                r["threads"] = threads
                backward_modes.append(r)
                print(f"threads {threads} m={m} deterministic={det}: bwd CPU {r['backward']['cpu_s']:.3f}s "
                      f"wall {r['backward']['wall_s']:.3f}s  mem +{r['peak_rss_delta_mb']:.0f} MB", flush=True)
    torch.set_num_threads(args.threads)
    Vg, Kg = cameras(args.grad_views, args.grad_res)
    print(f"gradients: {args.grad_views} views at {args.grad_res}², R={args.R}, float64", flush=True)
    grads = gradient_study(sc, Vg, Kg, args.grad_res, args.R, grad_m, 0.01)
    result = dict(
        setup=dict(scene="DSS bunny (bunny-8000.ply), isotropic std = mean 3-NN spacing, opacity 0.9, "
                         "RGB = 0.5 + 0.5·normal, white background",
                   points=int(sc["means"].shape[0]), views=args.views, res=res, repeats=args.repeats,
                   threads=args.threads, omp_num_threads=os.environ.get("OMP_NUM_THREADS"),
                   grad_views=args.grad_views, grad_res=args.grad_res, R=args.R, sps_stride=args.sps_stride,
                   sps_pixels_per_view=int(len(oracle[0]["pixels"])), dense_cpu_s=dense_cpu,
                   torch=torch.__version__, machine=platform.machine(), cpus=os.cpu_count(),
                   dtype="float32 (sweeps), float64 (gradients)",
                   loss="sum of image × fixed N(0,1) weights (linear)"),
        samples_eps=grid, hermite=herm, backward_modes=backward_modes, gradients=grads, machine=machine())
    result["setup"]["total_wall_s"] = time.perf_counter() - t_start
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    files = make_plots(result, args.plots)
    print(f"wrote {args.out} and {', '.join(files)} in {args.plots}; total {time.perf_counter() - t_start:.0f}s wall")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
