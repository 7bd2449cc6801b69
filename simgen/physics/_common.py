"""Shared helpers of the torch energies: reductions over frames and dtype/device matching."""

from __future__ import annotations

import torch

from simgen.errors import InputError

__all__ = ["REDUCTIONS", "reduce_frames", "like"]

REDUCTIONS = ("mean", "sum", "none")


def reduce_frames(per_frame: torch.Tensor, reduction: str) -> torch.Tensor:
    """Reduce per-frame energies [J], shape (...) = the leading (batch, time) dims of the positions.

    "mean" (default everywhere): the mean over every leading dim, i.e. joules per frame (each frame's
    energy is already summed over its vertices / triangles / hinges); "sum": the total over frames;
    "none": the per-frame values unchanged.
    """
    if reduction == "mean":
        return per_frame.mean()
    if reduction == "sum":
        return per_frame.sum()
    if reduction == "none":
        return per_frame
    raise InputError(f"reduction must be one of {REDUCTIONS}, got {reduction!r}")


def like(t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``t`` in x's floating dtype and on x's device (rest data follows the positions' precision)."""
    return t.to(device=x.device, dtype=x.dtype)
