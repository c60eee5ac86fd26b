"""The native stages registered as PyTorch custom ops (``torch.library``), namespace ``nsplat``.

Registered ops (schemas inferred from the type hints below; CPU and CUDA kernels, fake kernels for
tracing, autograd for the compositor):

    nsplat::sample              per-pixel SPS sample (no gradient)
    nsplat::composite_forward   compositing of a given sample; differentiable (autograd registered)
    nsplat::composite_backward  the estimator's backward of ``composite_forward`` (its own gradient is an error)
    nsplat::project             the EWA projection (differentiable, autograd registered)
    nsplat::project_backward    its hand-derived backward
    nsplat::view_colour         view-dependent SH colour (differentiable, autograd registered)
    nsplat::view_colour_backward  its hand-derived backward

Because these are custom ops, ``torch.compile`` traces a model containing :class:`nsplat.ops.Splatter`
without graph breaks (the fake kernels give the output shapes), and autograd / AOTAutograd see one node
per stage. The kernels for a device kind call the compiled module :func:`native` returns for it (the CPU
module with its counting sort and atomic-scatter backward; the CUDA module without them); the tests of
the CUDA host emulation replace :func:`native` to route CPU tensors through the emulated CUDA module.

The public, validated entry points are in :mod:`nsplat.ops.functional`; the ops here trust their inputs.
"""
from __future__ import annotations

import dataclasses
from types import ModuleType

import torch
from torch import Tensor

from .build import backend
from .host_reads import host_read

__all__ = ["Native", "native", "sample_op", "composite_forward_op", "composite_backward_op", "project_op",
           "project_backward_op", "view_colour_op", "view_colour_backward_op"]


@dataclasses.dataclass(frozen=True)
class Native:
    """A compiled backend module and the optional functions the kernels use from it.

    Attributes:
        module: the extension (``sample``, ``composite_forward``, ``composite_backward_pixels``,
            ``composite_backward_points``; the CPU one also ``entries_by_point`` and
            ``composite_backward_scatter``).
        counting_sort: group the backward's slots by point with the native stable counting sort
            (else :func:`_entries_by_point_sorted`, a device sort).
        scatter_backward: ``deterministic=False`` uses the single-pass atomic-scatter backward (else the
            deterministic two-pass backward is used whatever ``deterministic`` says).
    """

    module: ModuleType
    counting_sort: bool
    scatter_backward: bool


def native(kind: str) -> Native:
    """The native backend the ``kind`` ("cpu" or "cuda") kernels of the custom ops call."""
    if kind == "cpu":
        return Native(backend(torch.device("cpu")), counting_sort=True, scatter_backward=True)
    return Native(backend(torch.device("cuda")), counting_sort=False, scatter_backward=False)


def _contiguous(*ts: Tensor) -> list[Tensor]:
    return [t.contiguous() for t in ts]


# ----------------------------------------------------------------------------------------------------------
# nsplat::sample


@torch.library.custom_op("nsplat::sample", mutates_args=(), device_types=("cpu", "cuda"))
def sample_op(mu: Tensor, con: Tensor, amp: Tensor, sig2: Tensor, nrm: Tensor, off: Tensor, zc: Tensor, Ks: Tensor,
              seed: Tensor, width: int, height: int, samples: int, eps: float, hermite_order: int,
              hermite_tol: float, inclusion: int, stratified: bool) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Per-pixel SPS sample of ``samples`` points of ``B`` cameras (see :func:`nsplat.ops.sample`).

    ``mu [B,N,2]``, ``con [B,N,3]``, ``amp [B,N]``, ``sig2 [B,N]``, ``nrm [B,N,3]``, ``off [B,N]``,
    ``zc [B,N]`` (one float dtype), ``Ks [B,3,3]``; ``seed`` a 0-dim integer tensor (a tensor so that a
    seed that changes every step, like :class:`~nsplat.ops.Splatter`'s, is a graph input, not a constant) or
    ``[B]``, one seed per camera (:func:`camera_streams`).
    Returns ``indices [B,H,W,m]`` int32, ``probs [B,H,W,m]``, ``total [B,H,W,1]``, ``work [B,H,W,1]`` int32.
    """
    streams = camera_streams(seed, amp.shape[0])
    if streams.numel() and not bool((streams[:, 0] >= 0).all()):
        raise ValueError(f"seed: expected values in [0, 2**63), got {int(streams[:, 0].min())}")
    args = _contiguous(mu, con, amp, sig2, nrm, off, zc, Ks)
    return tuple(native(mu.device.type).module.sample(*args, streams, width, height, samples, float(eps),
                                                      hermite_order, float(hermite_tol), inclusion, bool(stratified)))


def camera_streams(seed: Tensor, B: int) -> Tensor:
    """The native sampler's ``(seed, camera)`` pair of each of ``B`` cameras, ``[B,2]`` int64 on the CPU: a 0-dim
    ``seed`` gives ``(seed, b)`` (the cameras of one call draw independent streams), a ``[B]`` seed gives
    ``(seed[b], 0)`` (camera ``b`` draws as the only camera of a call with seed ``seed[b]``)."""
    s = seed.detach()
    s = (s if s.device.type == "cpu" else host_read(s)).to(torch.int64)  # a seed on a device: one counted read
    if s.dim() == 0:
        return torch.stack([s.expand(B), torch.arange(B, dtype=torch.int64)], 1).contiguous()
    return torch.stack([s, torch.zeros(B, dtype=torch.int64)], 1).contiguous()


@sample_op.register_fake
def _(mu, con, amp, sig2, nrm, off, zc, Ks, seed, width, height, samples, eps, hermite_order, hermite_tol,  # noqa: ANN001
      inclusion, stratified):
    B = amp.shape[0]
    shape, one = (B, height, width, samples), (B, height, width, 1)
    return (amp.new_empty(shape, dtype=torch.int32), amp.new_empty(shape), amp.new_empty(one),
            amp.new_empty(one, dtype=torch.int32))


# ----------------------------------------------------------------------------------------------------------
# nsplat::composite_forward (+ autograd) and nsplat::composite_backward


@torch.library.custom_op("nsplat::composite_forward", mutates_args=(), device_types=("cpu", "cuda"))
def composite_forward_op(mu: Tensor, con: Tensor, amp: Tensor, nrm: Tensor, off: Tensor, zc: Tensor, Ks: Tensor,
                         feat: Tensor, bg: Tensor, indices: Tensor, probs: Tensor, mode: int, estimator: int,
                         deterministic: bool) -> tuple[Tensor, Tensor, Tensor]:
    """Composite the sample ``indices``/``probs [B,H,W,m]`` of the projected surfels (``[B,N,...]`` as in
    :func:`sample_op`) with features ``feat [N,C]`` (every camera's) or ``[B,N,C]`` (camera ``b`` sees ``feat[b]``)
    over ``bg [C]``; ``mode`` 0 alpha, 1 additive.
    ``estimator`` (native code) and ``deterministic`` only select the backward.
    Returns ``image [B,H,W,C]``, ``alpha [B,H,W,1]``, ``depth [B,H,W,1]``."""
    args = _contiguous(mu, con, amp, nrm, off, zc, Ks, feat, bg, indices, probs)
    return tuple(native(mu.device.type).module.composite_forward(*args, mode))


@composite_forward_op.register_fake
def _(mu, con, amp, nrm, off, zc, Ks, feat, bg, indices, probs, mode, estimator, deterministic):  # noqa: ANN001
    B, H, W, _ = indices.shape
    return mu.new_empty((B, H, W, feat.shape[-1])), mu.new_empty((B, H, W, 1)), mu.new_empty((B, H, W, 1))


@torch.library.custom_op("nsplat::composite_backward", mutates_args=(), device_types=("cpu", "cuda"))
def composite_backward_op(mu: Tensor, con: Tensor, amp: Tensor, nrm: Tensor, off: Tensor, zc: Tensor, Ks: Tensor,
                          feat: Tensor, bg: Tensor, indices: Tensor, probs: Tensor, g_img: Tensor, g_alpha: Tensor,
                          g_depth: Tensor, mode: int, estimator: int,
                          deterministic: bool) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Gradients of ``composite_forward`` w.r.t. ``mu, con, amp, nrm, off, zc, feat, bg`` (shapes of those)
    given ``g_img [B,H,W,C]``, ``g_alpha``, ``g_depth [B,H,W,1]``, with the estimator's weights.

    Deterministic: pass 1 per pixel, pass 2 per point in a fixed (point, camera, slot) order, gradients
    bitwise identical across runs and thread counts (the CPU runs it camera by camera, in the same order).
    Non-deterministic (CPU only): one pass per pixel
    scattering into the per-point buffers with atomics (``csrc/cpu/scatter_cpu.cpp``)."""
    nat = native(mu.device.type)
    params = _contiguous(mu, con, amp, nrm, off, zc)
    Kc, feat_c, bg_c, idx, pr = _contiguous(Ks, feat, bg, indices, probs)
    g_img, g_alpha, g_depth = _contiguous(g_img, g_alpha, g_depth)
    if not deterministic and nat.scatter_backward:
        *grads, bgw = nat.module.composite_backward_scatter(*params, Kc, feat_c, bg_c, idx, pr, mode, estimator,
                                                            g_img, g_alpha, g_depth)
        return (*grads, (bgw * g_img).sum(dim=(0, 1, 2)))
    per_camera = feat_c.dim() == 3
    if not nat.counting_sort or idx.shape[0] == 1:
        *grads, bgw = _backward_two_pass(nat, params, Kc, feat_c, bg_c, idx, pr, mode, estimator, g_img, g_alpha,
                                         g_depth)
        return (*grads, (bgw * g_img).sum(dim=(0, 1, 2)))
    # The CPU backend: one camera at a time, so that the pixel pass's arrays that a point's entries index stay
    # cache-sized (a 12-view lego step: 0.56 s in one pass against 0.31 s). The same sums in the same order as one
    # pass over all cameras (pass 2 visits a point's cameras in order), so the same bits.
    parts: list[list[Tensor]] = []
    feat_grad = None
    for b in range(idx.shape[0]):
        one = [p[b:b + 1] for p in params]
        *grads, g_feat, bgw = _backward_two_pass(nat, one, Kc[b:b + 1], feat_c[b:b + 1] if per_camera else feat_c,
                                                 bg_c, idx[b:b + 1], pr[b:b + 1], mode, estimator, g_img[b:b + 1],
                                                 g_alpha[b:b + 1], g_depth[b:b + 1])
        parts.append([*grads, bgw])
        if per_camera:
            feat_grad = g_feat if feat_grad is None else torch.cat([feat_grad, g_feat])
        else:
            feat_grad = g_feat if feat_grad is None else feat_grad.add_(g_feat)
    *grads, bgw = (torch.cat(ts) for ts in zip(*parts))
    return (*grads, feat_grad, (bgw * g_img).sum(dim=(0, 1, 2)))


def _backward_two_pass(nat: Native, params: list[Tensor], Ks: Tensor, feat: Tensor, bg: Tensor, idx: Tensor,
                       probs: Tensor, mode: int, estimator: int, g_img: Tensor, g_alpha: Tensor,
                       g_depth: Tensor) -> list[Tensor]:
    """The deterministic backward of the cameras of ``idx``: pass 1 per pixel, the slots grouped by point, pass 2
    per point. Returns the gradients of ``mu, con, amp, nrm, off, zc, feat`` and the background weights
    ``[B,H,W,1]``."""
    B, H, W, m = idx.shape
    dalpha, wf, bgw = nat.module.composite_backward_pixels(*params, Ks, feat, bg, idx, probs, mode, estimator, g_img,
                                                           g_alpha, g_depth)
    entries, seg = _entries_by_point(idx, params[2].shape[1], nat)
    grads = nat.module.composite_backward_points(*params, Ks, entries, seg, dalpha, wf, g_img, g_depth, W, H,
                                                 estimator, feat.dim() == 3)
    return [*grads, bgw]


@composite_backward_op.register_fake
def _(mu, con, amp, nrm, off, zc, Ks, feat, bg, indices, probs, g_img, g_alpha, g_depth, mode, estimator,  # noqa: ANN001
      deterministic):
    return tuple(t.new_empty(t.shape) for t in (mu, con, amp, nrm, off, zc, feat, bg))  # contiguous, as the kernels


def _setup_forward(ctx, inputs, output) -> None:  # noqa: ANN001 - torch.library autograd signature
    mu, con, amp, nrm, off, zc, Ks, feat, bg, indices, probs, mode, estimator, deterministic = inputs
    ctx.save_for_backward(mu, con, amp, nrm, off, zc, Ks, feat, bg, indices, probs)
    ctx.mode, ctx.estimator, ctx.deterministic = mode, estimator, deterministic


def _backward_forward(ctx, g_img, g_alpha, g_depth):  # noqa: ANN001
    mu, con, amp, nrm, off, zc, Ks, feat, bg, indices, probs = ctx.saved_tensors
    B, H, W, _ = indices.shape
    if g_img is None:
        g_img = mu.new_zeros((B, H, W, feat.shape[-1]))
    if g_alpha is None:
        g_alpha = mu.new_zeros((B, H, W, 1))
    if g_depth is None:
        g_depth = mu.new_zeros((B, H, W, 1))
    grads = composite_backward_op(mu, con, amp, nrm, off, zc, Ks, feat, bg, indices, probs, g_img, g_alpha, g_depth,
                                  ctx.mode, ctx.estimator, ctx.deterministic)
    return (*grads[:6], None, grads[6], grads[7], None, None, None, None, None)


torch.library.register_autograd("nsplat::composite_forward", _backward_forward, setup_context=_setup_forward)


def _no_double_backward(ctx, *grads):  # noqa: ANN001
    raise RuntimeError("nsplat::composite_backward: double backward through the splatting op (nsplat.ops.splat / "
                       "composite_sample / Splatter) is not supported: its estimator gradients are not themselves "
                       "differentiable. Do not differentiate the op's gradients (create_graph=True is fine only "
                       "when the second derivative does not pass through the op).")


torch.library.register_autograd("nsplat::composite_backward", _no_double_backward)


# ----------------------------------------------------------------------------------------------------------
# The projection (ops/projection.py::project_torch is its reference and the path of devices without a kernel)


@torch.library.custom_op("nsplat::project", mutates_args=(), device_types=("cpu", "cuda"))
def project_op(means: Tensor, normals: Tensor, scales: Tensor, opacities: Tensor, viewmats: Tensor, Ks: Tensor,
               near: float, far: float, lowpass: float,
               backface_cull: bool) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Project surfels ``[N]`` into cameras ``[B]`` (the model of :mod:`nsplat.ops.projection`).

    Returns ``means2d [B,N,2]``, ``conics [B,N,3]``, ``amps``, ``normals_cam [B,N,3]``, ``plane_offsets``,
    ``depths``, ``sigma2``, ``valid`` (bool) and ``hazard`` (int8: 1 a visible splat overflows the dtype, 2 its
    screen covariance's determinant lies in (0, 1e-20) px⁴), ``[B,N]`` unless noted."""
    out = native(means.device.type).module.project_forward(
        *_contiguous(means, normals, scales, opacities, viewmats, Ks), near, far, lowpass, backface_cull)
    return tuple(out)


@project_op.register_fake
def _(means, normals, scales, opacities, viewmats, Ks, near, far, lowpass, backface_cull):  # noqa: ANN001
    B, N = viewmats.shape[0], means.shape[0]
    e = means.new_empty
    return (e((B, N, 2)), e((B, N, 3)), e((B, N)), e((B, N, 3)), e((B, N)), e((B, N)), e((B, N)),
            e((B, N), dtype=torch.bool), e((B, N), dtype=torch.int8))


@torch.library.custom_op("nsplat::project_backward", mutates_args=(), device_types=("cpu", "cuda"))
def project_backward_op(means: Tensor, normals: Tensor, scales: Tensor, opacities: Tensor, viewmats: Tensor,
                        Ks: Tensor, near: float, far: float, lowpass: float, backface_cull: bool, g_means2d: Tensor,
                        g_conics: Tensor, g_amps: Tensor, g_normals_cam: Tensor, g_plane_offsets: Tensor,
                        g_depths: Tensor, g_sigma2: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Gradients of :func:`project_op` w.r.t. ``means, normals, scales, opacities, viewmats, Ks`` given those of
    its first seven outputs. Per point summed over the cameras in order, per camera over fixed blocks of points:
    bitwise identical for any thread count."""
    args = _contiguous(means, normals, scales, opacities, viewmats, Ks)
    grads = _contiguous(g_means2d, g_conics, g_amps, g_normals_cam, g_plane_offsets, g_depths, g_sigma2)
    return tuple(native(means.device.type).module.project_backward(*args, near, far, lowpass, backface_cull, *grads))


@project_backward_op.register_fake
def _(means, normals, scales, opacities, viewmats, Ks, near, far, lowpass, backface_cull, *grads):  # noqa: ANN001
    return tuple(t.new_empty(t.shape) for t in (means, normals, scales, opacities, viewmats, Ks))


def _setup_project(ctx, inputs, output) -> None:  # noqa: ANN001 - torch.library autograd signature
    means, normals, scales, opacities, viewmats, Ks, near, far, lowpass, backface_cull = inputs
    ctx.save_for_backward(means, normals, scales, opacities, viewmats, Ks)
    ctx.settings = (near, far, lowpass, backface_cull)
    ctx.shapes = [o.shape for o in output[:7]]


def _backward_project(ctx, *grads):  # noqa: ANN001
    means = ctx.saved_tensors[0]
    g = [gi if gi is not None else means.new_zeros(shape) for gi, shape in zip(grads[:7], ctx.shapes)]
    out = project_backward_op(*ctx.saved_tensors, *ctx.settings, *g)
    return (*out, None, None, None, None)


torch.library.register_autograd("nsplat::project", _backward_project, setup_context=_setup_project)
def _no_double_backward_project(ctx, *grads):  # noqa: ANN001
    raise RuntimeError("nsplat::project_backward: double backward through the native projection is not supported; "
                       "nsplat.ops.projection.project_torch (pure PyTorch, same model) supports it.")


torch.library.register_autograd("nsplat::project_backward", _no_double_backward_project)


# ----------------------------------------------------------------------------------------------------------
# View-dependent colour (nsplat/render/sh.py::view_colour_torch is its reference and the path of devices without a
# kernel)


@torch.library.custom_op("nsplat::view_colour", mutates_args=(), device_types=("cpu", "cuda"))
def view_colour_op(features: Tensor, means: Tensor, viewmat: Tensor, degree: int) -> Tensor:
    """RGB ``[N,3]`` of points with SH colour ``features [N, 3·(L+1)²]`` (L = ``degree``, 1..3) seen from
    ``viewmat [4,4]`` (the model of :func:`nsplat.render.sh.view_colour`)."""
    return native(means.device.type).module.view_colour_forward(*_contiguous(features, means, viewmat), degree)


@view_colour_op.register_fake
def _(features, means, viewmat, degree):  # noqa: ANN001
    return means.new_empty((means.shape[0], 3))


@torch.library.custom_op("nsplat::view_colour_backward", mutates_args=(), device_types=("cpu", "cuda"))
def view_colour_backward_op(features: Tensor, means: Tensor, viewmat: Tensor, degree: int,
                            g_out: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Gradients of :func:`view_colour_op` w.r.t. ``features, means, viewmat`` (the viewmat's summed over fixed
    blocks of points: bitwise identical for any thread count)."""
    return tuple(native(means.device.type).module.view_colour_backward(*_contiguous(features, means, viewmat), degree,
                                                                       g_out.contiguous()))


@view_colour_backward_op.register_fake
def _(features, means, viewmat, degree, g_out):  # noqa: ANN001
    return features.new_empty(features.shape), means.new_empty(means.shape), viewmat.new_empty(viewmat.shape)


def _setup_view_colour(ctx, inputs, output) -> None:  # noqa: ANN001
    features, means, viewmat, degree = inputs
    ctx.save_for_backward(features, means, viewmat)
    ctx.degree = degree


def _backward_view_colour(ctx, g_out):  # noqa: ANN001
    return (*view_colour_backward_op(*ctx.saved_tensors, ctx.degree, g_out), None)


def _no_double_backward_view_colour(ctx, *grads):  # noqa: ANN001
    raise RuntimeError("nsplat::view_colour_backward: double backward through the native view colour is not "
                       "supported; nsplat.render.sh.view_colour_torch (pure PyTorch, same model) supports it.")


torch.library.register_autograd("nsplat::view_colour", _backward_view_colour, setup_context=_setup_view_colour)
torch.library.register_autograd("nsplat::view_colour_backward", _no_double_backward_view_colour)


# ----------------------------------------------------------------------------------------------------------
# The backward's per-point order


def _entries_by_point(indices: Tensor, N: int, nat: Native | None = None) -> tuple[Tensor, Tensor]:
    """Flat slot ids of the filled slots of ``indices [B,H,W,m]`` grouped by point, keeping their
    (camera, pixel, slot) order within a point, and per-point segment offsets ``seg [N+1]`` (int64).

    A backend with a native stable counting sort (the CPU one) uses it: 8 bytes per filled slot + 8 per
    point. Otherwise (CUDA): a stable device sort of every slot's int32 point id,
    :func:`_entries_by_point_sorted` (keys, sorted keys and the order: ≈ 16 bytes per slot at the peak; its
    ``entries`` also list the empty slots, after ``seg[N]``, which the backward never reads).
    ``nat`` defaults to :func:`native` of the device of ``indices``."""
    nat = native(indices.device.type) if nat is None else nat
    if nat.counting_sort:
        entries, seg = nat.module.entries_by_point(indices.contiguous(), N)
        return entries, seg
    return _entries_by_point_sorted(indices, N)


#: Slots sorted at once by :func:`_entries_by_point_sorted` (torch's device sort refuses more than 2^31 - 1).
SORT_CHUNK = 2**30


def _entries_by_point_sorted(indices: Tensor, N: int, chunk: int | None = None) -> tuple[Tensor, Tensor]:
    """:func:`_entries_by_point` by a stable device sort of all ``B·H·W·m`` slots (any device; the reference for
    the native one), with no device→host copy: no size depends on the data. Empty slots are keyed ``N``, so
    they sort after every point's: ``entries [B·H·W·m]`` int64 holds the filled slots grouped by point in
    ``entries[:seg[N]]``, then the empty ones; ``seg [N+1]`` int64 are the points' segment offsets.

    The slots are sorted in runs of at most ``chunk`` (default :data:`SORT_CHUNK`; ``torch.sort`` handles at most
    2^31 - 1 elements); each run's slots of key ``k`` then go, in order, after those of the earlier runs within key
    ``k``'s segment, which is the order one stable sort of all the slots gives (tested at a small ``chunk``)."""
    chunk = SORT_CHUNK if chunk is None else chunk
    flat = indices.reshape(-1)
    total, dev = flat.numel(), flat.device
    bounds = torch.arange(N + 1, dtype=flat.dtype, device=dev)  # key k's slots: [seg[k], seg[k + 1])
    if total <= chunk:
        keys, entries = torch.sort(torch.where(flat >= 0, flat, N), stable=True)
        return entries, torch.searchsorted(keys, bounds)
    counts = torch.zeros(N + 1, dtype=torch.int64, device=dev)  # slots per key (N: the empty ones)
    one = counts.new_ones(())
    for start in range(0, total, chunk):
        part = flat[start:start + chunk]
        # not torch.bincount: on CUDA it reads the keys' min and max back to the host (a synchronisation a run)
        counts.index_add_(0, torch.where(part >= 0, part, N), one.expand(part.numel()))
    seg = torch.zeros(N + 1, dtype=torch.int64, device=dev)
    seg[1:] = torch.cumsum(counts[:-1], 0)
    before = torch.zeros(N + 1, dtype=torch.int64, device=dev)  # each key's slots in the earlier runs
    entries = torch.empty(total, dtype=torch.int64, device=dev)
    for start in range(0, total, chunk):
        part = flat[start:start + chunk]
        keys, order = torch.sort(torch.where(part >= 0, part, N), stable=True)
        run_seg = torch.searchsorted(keys, torch.cat([bounds, bounds.new_full((1,), N + 1)]))
        # a run's slot of key k at rank r within the run's key-k slots goes to seg[k] + before[k] + r
        shift = seg + before - run_seg[:-1]
        entries[shift[keys] + torch.arange(keys.numel(), dtype=torch.int64, device=dev)] = order + start
        before += run_seg[1:] - run_seg[:-1]
    return entries, seg
