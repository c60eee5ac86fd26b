"""The posed-views type every loader returns: images with cameras (and optional masks and GT poses)."""
from __future__ import annotations

import dataclasses
from typing import Sequence

import torch


@dataclasses.dataclass
class PosedViews:
    """A set of ``B`` posed images.

    Attributes:
        images: ``[B,H,W,C]`` float32 in [0, 1] (RGBA sources composited over ``background``).
        viewmats: ``[B,4,4]`` float32 OpenCV world→camera (the cameras to use: initial ones in refine).
        Ks: ``[B,3,3]`` float32 intrinsics in pixels.
        names: ``B`` frame names.
        masks: ``[B,H,W]`` float32 in [0, 1] or bool: coverage (the alpha of RGBA images) or valid
            pixels; ``None`` when every pixel counts.
        viewmats_gt: ``[B,4,4]`` ground-truth poses when ``viewmats`` are perturbed, else ``None``.
        background: ``[C]`` colour composited under RGBA images, else ``None``.
        depths: ``[B,H,W]`` float32 sensor depth (camera z, metres; 0 where none) of RGB-D frames, else ``None``.
        times: ``[B]`` float64 capture times in seconds (a sequence's timestamps), else ``None``.
    """

    images: torch.Tensor
    viewmats: torch.Tensor
    Ks: torch.Tensor
    names: list[str]
    masks: torch.Tensor | None = None
    viewmats_gt: torch.Tensor | None = None
    background: torch.Tensor | None = None
    depths: torch.Tensor | None = None
    times: torch.Tensor | None = None

    @property
    def width(self) -> int:
        """Image width in pixels."""
        return int(self.images.shape[2])

    @property
    def height(self) -> int:
        """Image height in pixels."""
        return int(self.images.shape[1])

    def __len__(self) -> int:
        return int(self.images.shape[0])

    def to(self, device: torch.device | str) -> "PosedViews":
        """Copy with every tensor on ``device``."""
        return dataclasses.replace(self, **{f.name: getattr(self, f.name).to(device) for f in dataclasses.fields(self)
                                            if isinstance(getattr(self, f.name), torch.Tensor)})

    def subset(self, index: Sequence[int] | torch.Tensor) -> "PosedViews":
        """The views ``index`` (in that order); ``background`` is shared."""
        idx = torch.as_tensor(index, dtype=torch.long)
        pick = {f: getattr(self, f) for f in ("images", "viewmats", "Ks", "masks", "viewmats_gt", "depths", "times")}
        out = {k: (None if v is None else v[idx.to(v.device)]) for k, v in pick.items()}
        return dataclasses.replace(self, names=[self.names[i] for i in idx.tolist()], **out)

    def spread(self, count: int) -> "PosedViews":
        """``count`` views evenly spread over the set (all of them when ``count >= len``)."""
        if count >= len(self):
            return self
        return self.subset(torch.linspace(0, len(self) - 1, count).round().long())
