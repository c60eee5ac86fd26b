"""The diagnosis of a stage 1 that cannot learn: where the surfels are against the cameras' view, in words
(:func:`where_surfels`), and what to set, in the :class:`~nsplat.errors.DataError` of the two checks that stop such
a run: before fitting, when most training views see almost none of the initial surfels (:func:`check_seen`, called
by :func:`nsplat.tasks.neural.starts.initial_geometry`); during fitting, when the val PSNR neither rises nor beats
a flat image (``geometry.stall_epochs``; :data:`STALL_DB`, :data:`STALL_MIN_STEPS`, :func:`stall_message`, checked
by :func:`nsplat.tasks.neural.geometry.fit_geometry`)."""
from __future__ import annotations

import torch

from nsplat.data.views import PosedViews
from nsplat.errors import DataError
from nsplat.scene import SurfelScene
from nsplat.tasks.neural.background import project
from nsplat.tasks.neural.capture import FAR_POINTS, prepare, start_kind
from nsplat.tasks.neural.config import Config

#: A view sees the surfels when at least this share of them projects inside its image.
MIN_SEEN_SHARE = 0.01
#: Rise over the start, and margin over a flat image, below which stage 1 learns nothing (dB).
STALL_DB = 1.0
#: The stall check waits for at least this many fitter steps as well as ``geometry.stall_epochs`` epochs (a
#: few dozen steps of a tiny schedule may not move the PSNR yet).
STALL_MIN_STEPS = 100
#: A capture's stage 1 whose val PSNR ends this far below its training PSNR (dB) gets a one-line warning
#: (:func:`gap_message`): it fits the training photos without a scene that predicts the others.
GAP_DB = 6.0


def share_inside(means: torch.Tensor, views: PosedViews, chunk: int = 32) -> torch.Tensor:
    """``[V]`` float64: the share of ``means [N,3]`` in front of each camera of ``views`` and inside its image."""
    return torch.cat([project(means, views.subset(range(i, min(i + chunk, len(views)))))[2].double().mean(1)
                      for i in range(0, len(views), chunk)])


def _fmt(x: torch.Tensor) -> str:
    return "(" + ", ".join(f"{float(v):.2f}" for v in x) + ")"


def where_surfels(cfg: Config, means: torch.Tensor, views: PosedViews) -> str:
    """Where the surfels ``means [N,3]`` are against the cameras of ``views`` (training frame), in words: their
    median and 5-95 % extent, ``geometry.bbox``, the share a view sees and, for a capture, the frame's centre,
    what placed it and where the cameras aim (``capture_frame.json``)."""
    x = means.detach().double().cpu()
    share = share_inside(x, views)
    lo, hi = torch.quantile(x, 0.05, dim=0), torch.quantile(x, 0.95, dim=0)
    box = "from the data" if cfg.geometry.bbox is None else list(cfg.geometry.bbox)
    text = (f"the {len(x)} surfels lie about {_fmt(x.median(0).values)} (5-95 % extent {_fmt(hi - lo)}; geometry.bbox "
            f"{box}); a training view sees {float(share.median()):.0%} of them (median), "
            f"{int((share < MIN_SEEN_SHARE).sum())} of {len(views)} views under {MIN_SEEN_SHARE:.0%}")
    if cfg.data.is_capture():
        prep = prepare(cfg)
        centre, radius = prep.centre()
        f = prep.frame
        aim = prep.to_training(f.look_at[None])[0]
        placed = {"points": "from the SfM points seen near the middle of most views",
                  "look-at": "from the cameras' look-at point", "all points": "from all SfM points"}[f.source]
        text += (f"; the capture's centre {_fmt(centre)} ({placed}; {f.core} such core SfM points), "
                 f"cameras {radius:.2f} from it, aiming at {_fmt(aim)}, {f.diagnosis()['look_at_offset_radii']:.2f} "
                 f"camera distances off")
    return text


def start_words(cfg: Config, kind: str) -> str:
    """What the start ``kind`` (:func:`nsplat.tasks.neural.capture.start_kind`) of a ``transforms.json`` folder was
    and the likely cure when it cannot learn, in one clause; ``""`` for other captures and scenes."""
    if cfg.data.source != "transforms":
        return ""
    prep = prepare(cfg)
    if kind == "view_fill":
        why = f" ({prep.note})" if prep.note else ""
        return (f"the start was {cfg.geometry.max_points} random points in the training cameras' common view, not the "
                f"scene's surfaces{why}: give the folder points (a COLMAP model in sparse/0 beside transforms.json, "
                f"ply_file_path in it, or geometry.init: ply) or, with pycolmap, photos with texture for "
                f"geometry.init: auto to triangulate")
    if kind == "triangulated":
        return (f"the start was the {len(prep.points)} points triangulated from the training photos with the "
                f"file's poses: if few lie on the scene, the poses or intrinsics of transforms.json do not match "
                f"the photos (check them, e.g. by running COLMAP into sparse/0 beside it)")
    if kind == "sfm":
        return (f"the start was the {len(prep.points)} SfM points of {prep.origin}, moved onto the file's cameras: "
                f"check that the model belongs to these photos")
    if kind == "capture_ply":
        return f"the start was the point cloud {prep.ply}: it must lie in the file's world"
    return ""


def _advice(cfg: Config, kind: str) -> str:
    if kind == "ply":
        return "geometry.ply must hold points in the capture's (or scene's) world"
    words = start_words(cfg, kind)
    if words:
        return words
    if cfg.data.is_capture():
        return ("check the SfM model (data.capture.sparse picks another; a model whose poses do not match the "
                "photos cannot train), set geometry.bbox to where the object is, geometry.background.radius "
                "(camera distances) to the backdrop, or data.capture.normalize: false to train in SfM's own world")
    return "check the cameras and geometry.bbox"


def check_seen(cfg: Config, means: torch.Tensor, train: PosedViews, kind: str) -> None:
    """Raise a :class:`DataError` when more than half the ``train`` views see under :data:`MIN_SEEN_SHARE` of
    the initial surfels ``means [N,3]`` (before the background): nothing to fit there."""
    share = share_inside(means.double(), train)
    blind = int((share < MIN_SEEN_SHARE).sum())
    if 2 * blind > len(train):
        raise DataError(f"geometry.init: {kind}: {blind} of {len(train)} training views see almost none of the "
                        f"initial surfels: {where_surfels(cfg, means, train)}; {_advice(cfg, kind)}")


def gap_message(cfg: Config, trained: float, val: float, gap: float) -> str:
    """The one-line note of a capture's stage 1 whose val PSNR ends more than :data:`GAP_DB` below its training
    PSNR: the figures, what the start was and its likely cure (:func:`start_words`), or the photos' coverage."""
    words = start_words(cfg, start_kind(cfg))
    return (f"train {trained:.2f} dB, val {val:.2f} dB ({gap:.1f} dB apart) after stage 1; "
            + (words if words else "the val photos see parts few training photos see, or the poses are off")
            + " (docs/capture.md)")


def stall_message(cfg: Config, scene: SurfelScene, train: PosedViews, epochs: float, value: float, start: float,
             flat: float) -> str:
    """The one-line message of a stage 1 that learns nothing (``geometry.stall_epochs``): the val PSNR, where the
    surfels are and what the start was with its likely cure (:func:`start_words`, :func:`_advice`)."""
    means = scene.means.detach().double().cpu()
    if cfg.data.is_capture():  # the scene's surfels, not the background sphere's
        centre, radius = prepare(cfg).centre()
        near = means[(means - centre).norm(dim=1) < FAR_POINTS * radius]
        means = near if len(near) else means
    return (f"stage 1 learns nothing: after {epochs:.1f} epochs the val PSNR is {value:.2f} dB (at the start "
            f"{start:.2f} dB; a flat image of the val views' mean colour scores {flat:.2f} dB): "
            f"{where_surfels(cfg, means, train.to('cpu'))}; {_advice(cfg, start_kind(cfg))} "
            f"(geometry.stall_epochs: 0 turns this check off)")

