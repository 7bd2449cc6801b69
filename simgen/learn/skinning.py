"""Linear blend skinning of garments in torch (differentiable, batched, any device).

The same operation as :func:`simgen.garment.skinning.lbs` / ``inverse_lbs`` (numpy, float64), used
inside the learned models: the unposed garment T_c + R_G + R_L is posed with the garment's skinning
weights and the body's joint transforms A (thesis eq. 4.3).
"""

from __future__ import annotations

import torch

from simgen.errors import InputError

__all__ = ["blend_transforms", "lbs_torch", "inverse_lbs_torch"]


def blend_transforms(skin_weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """Per-vertex blended affine transforms sum_j w_vj A_j without the last row.

    skin_weights, shape (V, 24); transforms, shape (N, 24, 4, 4) -> shape (N, V, 3, 4).
    """
    if skin_weights.dim() != 2 or skin_weights.shape[1] != 24:
        raise InputError(f"skin_weights must have shape (V, 24), got {tuple(skin_weights.shape)}")
    if transforms.dim() != 4 or tuple(transforms.shape[1:]) != (24, 4, 4):
        raise InputError(f"transforms must have shape (N, 24, 4, 4), got {tuple(transforms.shape)}")
    n = transforms.shape[0]
    flat = transforms[:, :, :3, :].reshape(n, 24, 12)
    return torch.matmul(skin_weights, flat).reshape(n, skin_weights.shape[0], 3, 4)


def lbs_torch(rest: torch.Tensor, skin_weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """Pose rest-space garment vertices.

    rest [m], shape (N, V, 3) or (V, 3) (shared by all frames); skin_weights, shape (V, 24);
    transforms, shape (N, 24, 4, 4): the body's skinning transforms (shaped rest -> posed world,
    root translation included). Returns posed vertices [m], shape (N, V, 3).
    """
    t = blend_transforms(skin_weights, transforms)
    if rest.dim() == 2:
        rest = rest.expand(t.shape[0], -1, -1)
    return torch.einsum("nvab,nvb->nva", t[..., :3], rest) + t[..., 3]


def inverse_lbs_torch(posed: torch.Tensor, skin_weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """Unpose posed garment vertices (each vertex's blended transform inverted exactly).

    posed [m], shape (N, V, 3); skin_weights (V, 24); transforms (N, 24, 4, 4) -> rest [m] (N, V, 3).
    """
    t = blend_transforms(skin_weights, transforms)
    return torch.linalg.solve(t[..., :3], (posed - t[..., 3])[..., None])[..., 0]
