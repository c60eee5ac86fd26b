"""Per-frame affine exposure: ``image' = exp(g_b) ⊙ image + β_b`` per colour channel, for cameras with
auto-exposure and auto-white-balance (the TUM Kinects change both from frame to frame)."""
from __future__ import annotations

import torch


class Exposure(torch.nn.Module):
    """Log-gains ``g [B,C]`` and biases ``β [B,C]`` of ``B`` frames (zeros: the identity).

    Args:
        num_frames: frames B. channels: colour channels C.
        frozen: frame indices kept at the identity (the anchor that fixes the scale albedo and shading share with
            the gains).
    """

    def __init__(self, num_frames: int, channels: int = 3, frozen: list[int] | tuple[int, ...] = ()) -> None:
        super().__init__()
        if num_frames < 1:
            raise ValueError(f"num_frames must be >= 1, got {num_frames}")
        bad = [i for i in frozen if not 0 <= int(i) < num_frames]
        if bad:
            raise ValueError(f"frozen: frame indices {bad} out of range [0, {num_frames})")
        self.log_gain = torch.nn.Parameter(torch.zeros(num_frames, channels))
        self.bias = torch.nn.Parameter(torch.zeros(num_frames, channels))
        mask = torch.ones(num_frames, 1)
        mask[list(frozen)] = 0.0
        self.register_buffer("mask", mask, persistent=False)

    def forward(self, image: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        """``image [b,H,W,C]`` of frames ``index [b]`` → exposed ``[b,H,W,C]``."""
        m = self.mask[index]
        gain = torch.exp(self.log_gain[index] * m)[:, None, None, :]
        return image * gain + (self.bias[index] * m)[:, None, None, :]
