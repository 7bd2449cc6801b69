"""SoftSMPL's networks (thesis ch. 3): the soft-tissue autoencoder, the multimodal pose autoencoder and
the recurrent soft-tissue regressor, with their losses.

- :class:`SoftTissueAE` (section 3.2.2): Delta (V, 3) [m] -> code (``latent``) -> Delta. Encoder:
  a linear layer initialised with PCA of the training displacements (whitened: code_k =
  u_k . (Delta - mean) / s_k, s_k floored at 1e-3 of the largest; the layers see Delta in units of
  the largest scale, buffer ``unit``), then ``blocks`` residual units; the decoder mirrors it and ends with
  the inverse PCA layer. Each residual unit is x + L2(dropout(relu(L1(x)))) with L2 initialised
  to zero, so at initialisation the autoencoder *is* PCA (at full rank it reproduces its training
  data). Loss :func:`reconstruction_loss` (eqs. 3.6-3.8). Train it with
  :meth:`SoftTissueAE.param_groups`: Adam moves every weight by about the learning rate per step,
  which for the PCA layers' entries (~1/sqrt(3V)) would undo PCA in the first step.
- :class:`PoseAE` (section 3.3.1): E_mesh (posed zero-shape body -> 10-D code), E_pose (joint
  rotations -> code), D_mesh (code -> mesh); loss :func:`pose_ae_loss` (eq. 3.13). The deshaped
  pose is E_pose(theta).
- :class:`SoftTissueRegressor` (section 3.2.3): per frame, input [gamma, beta] -> GRU -> linear to
  the soft-tissue code, plus a linear residual shortcut from the input that skips the GRU. The
  state starts at zero at every sequence. Loss :func:`regression_loss` (eq. 3.10).
- :func:`motion_descriptor`: gamma of eq. 3.11.

The thesis's layer sizes are in its Fig. 3.2 / 3.3, which the text does not give (only the 10-D pose
code, the 25/50/100-D subspaces of Table 3.1, lambda_norm = 1000, dropout 0.1 in the autoencoder,
no dropout in the regressor). Widths and depths below are ours (declared in
:class:`~simgen.learn.softtissue.train.SoftTissueConfig`).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from simgen.errors import InputError
from simgen.learn.models import INPUT_STD_FLOOR, MODEL_KINDS

__all__ = ["pad_sequences", "LAMBDA_NORM", "ResidualUnit", "SoftTissueAE", "PoseAE", "SoftTissueRegressor", "face_normals",
           "normal_loss", "surface_loss", "reconstruction_loss", "pose_ae_loss", "regression_loss",
           "motion_descriptor", "pca_basis", "pca_frames", "PCA_FRAMES", "descriptor_size", "POSE_INPUTS",
           "pose_features"]

LAMBDA_NORM = 1000.0  # eq. 3.8


# ------------------------------------------------------------------------------------ losses
def face_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Unit face normals, (..., F, 3), of meshes ``vertices`` (..., V, 3) with ``faces`` (F, 3)."""
    a, b, c = vertices[..., faces[:, 0], :], vertices[..., faces[:, 1], :], vertices[..., faces[:, 2], :]
    n = torch.linalg.cross(b - a, c - a, dim=-1)
    return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def normal_loss(delta: torch.Tensor, delta_rec: torch.Tensor, template: torch.Tensor, faces: torch.Tensor):
    """L_norm (eq. 3.7): mean over faces (and samples) of |1 - N_f(Delta) . N_f(Delta_rec)|, where
    N_f(Delta) is the normal of face f of the displaced template ``template + Delta`` (template (V, 3)
    [m]: the body's rest mesh; displacements (N, V, 3) [m])."""
    na = face_normals(template + delta, faces)
    nb = face_normals(template + delta_rec, faces)
    return (1.0 - (na * nb).sum(-1)).abs().mean()


def surface_loss(delta: torch.Tensor, delta_rec: torch.Tensor) -> torch.Tensor:
    """L_surf (eq. 3.6) [m]: the L2 norm of the 3V-vector Delta - Delta_rec, mean over samples."""
    return (delta - delta_rec).flatten(1).norm(dim=1).mean()


def reconstruction_loss(delta, delta_rec, template, faces, lambda_norm: float = LAMBDA_NORM) -> dict:
    """L_rec = L_surf + lambda_norm L_norm (eq. 3.8); returns {"total", "surf", "norm"}."""
    surf = surface_loss(delta, delta_rec)
    norm = normal_loss(delta, delta_rec, template, faces)
    return {"total": surf + lambda_norm * norm, "surf": surf, "norm": norm}


def pose_ae_loss(model: "PoseAE", meshes: torch.Tensor, joint_rotations: torch.Tensor) -> dict:
    """Eq. 3.13: |M - D_mesh(E_mesh(M))|_2 + |M - D_mesh(E_pose(theta))|_2, each the L2 norm of the
    3V-vector [m], mean over samples; meshes (N, V, 3) = M(theta, 0) (:meth:`PoseAE.mesh_input`),
    joint_rotations (N, 69) [rad]."""
    rec_mesh = model.decode(model.encode_mesh(meshes))
    rec_pose = model.decode(model.encode_pose(joint_rotations))
    a = (meshes - rec_mesh).flatten(1).norm(dim=1).mean()
    b = (meshes - rec_pose).flatten(1).norm(dim=1).mean()
    return {"total": a + b, "mesh_path": a, "pose_path": b}


def _differences(x: torch.Tensor, order: int) -> torch.Tensor:
    for _ in range(order):
        x = x[:, 1:] - x[:, :-1]
    return x


def regression_loss(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> dict:
    """Eq. 3.10: L_pos + L_vel + L_acc, mean squared errors of the latent codes, of their first and of
    their second differences over frames (per frame: the unit of fps is folded into the weights).
    pred, target (N, T, K); mask (N, T) bool (padded frames False)."""
    out = {}
    for name, order in (("pos", 0), ("vel", 1), ("acc", 2)):
        d = _differences(pred - target, order)
        if mask is not None:
            T = mask.shape[1]
            m = mask[:, order:]
            for k in range(1, order + 1):  # a difference is valid where all the frames it spans are
                m = m & mask[:, order - k:T - k]
            out[name] = ((d ** 2).sum(-1) * m).sum() / (m.sum().clamp_min(1) * d.shape[-1])
        else:
            out[name] = (d ** 2).mean() if d.numel() else d.sum()
    out["total"] = out["pos"] + out["vel"] + out["acc"]
    return out


def pad_sequences(items: list, num_betas: int) -> tuple:
    """Batch of the regressor: items [(gamma (T_i, F), codes (T_i, K), betas (B_i,))], each on one
    device, -> (gamma (N, T, F), betas (N, num_betas), codes (N, T, K), mask (N, T) bool), zero-padded
    to the longest sequence (mask False there) and betas to ``num_betas``."""
    Tm = max(len(g) for g, _, _ in items)
    F, K, dev = items[0][0].shape[1], items[0][1].shape[1], items[0][0].device
    gamma = torch.zeros(len(items), Tm, F, device=dev)
    codes = torch.zeros(len(items), Tm, K, device=dev)
    mask = torch.zeros(len(items), Tm, dtype=torch.bool, device=dev)
    betas = torch.zeros(len(items), num_betas, device=dev)
    for k, (g, c, b) in enumerate(items):
        gamma[k, :len(g)], codes[k, :len(g)], mask[k, :len(g)] = g, c, True
        betas[k, :len(b)] = b
    return gamma, betas, codes, mask


# ------------------------------------------------------------------------------------ networks
class ResidualUnit(nn.Module):
    """x + L2(dropout(relu(L1(x)))), L2 zero-initialised (the unit starts as the identity)."""

    def __init__(self, width: int, hidden: int, dropout: float = 0.0):
        super().__init__()
        self.l1 = nn.Linear(width, hidden)
        self.l2 = nn.Linear(hidden, width)
        self.drop = nn.Dropout(dropout)
        nn.init.zeros_(self.l2.weight)
        nn.init.zeros_(self.l2.bias)

    def forward(self, x):
        return x + self.l2(self.drop(torch.relu(self.l1(x))))


#: Frames PCA is computed from at most (evenly strided): an SVD of N x 3V costs N^2 3V, and a store
#: of 48k frames of a 13k-vertex body would not fit in memory as float64.
PCA_FRAMES = 2000


def pca_frames(displacements) -> np.ndarray:
    """At most :data:`PCA_FRAMES` frames of ``displacements`` (an array (N, ...) or a list of
    sequences (T_i, ...), taken as one), evenly strided (all when fewer), without copying the rest."""
    parts = [displacements] if isinstance(displacements, np.ndarray) else list(displacements)
    sizes = np.array([len(p) for p in parts])
    total = int(sizes.sum())
    pick = np.arange(total) if total <= PCA_FRAMES else np.linspace(0, total - 1, PCA_FRAMES).round().astype(int)
    owner = np.searchsorted(np.cumsum(sizes), pick, side="right")
    local = pick - np.r_[0, np.cumsum(sizes)][owner]
    return np.stack([parts[o][i] for o, i in zip(owner, local)]) if total else np.zeros((0,))


def pca_basis(displacements: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mean (3V,), components (k, 3V) orthonormal rows, scales (k,) = singular values / sqrt(N)) of
    the rows of ``displacements`` (N, V, 3) or (N, 3V), at most :data:`PCA_FRAMES` of them
    (:func:`pca_frames`). Components beyond the data's rank are random orthonormal directions with
    scale 0 (the data has nothing along them)."""
    displacements = pca_frames(displacements)
    X = np.asarray(displacements, dtype=np.float64).reshape(len(displacements), -1)
    mean = X.mean(0)
    _, s, Vt = np.linalg.svd(X - mean, full_matrices=False)
    comps = np.zeros((k, X.shape[1]))
    scales = np.zeros(k)
    r = min(k, len(s))
    comps[:r] = Vt[:r]
    scales[:r] = s[:r] / np.sqrt(max(len(X), 1))
    if r < k:  # complete with random orthonormal directions so the layer stays well defined
        rng = np.random.default_rng(0)
        extra = rng.normal(size=(k - r, X.shape[1]))
        extra -= extra @ comps[:r].T @ comps[:r]
        q, _ = np.linalg.qr(extra.T)
        comps[r:] = q.T[:k - r]
    return mean, comps, scales


class SoftTissueAE(nn.Module):
    """The soft-tissue autoencoder (module docstring). num_vertices V; latent: code size; hidden:
    units of each residual unit; blocks: residual units in the encoder and in the decoder; dropout
    (thesis: 0.1)."""

    kind = "softtissue_ae"

    def __init__(self, num_vertices: int, latent: int = 100, hidden: int = 256, blocks: int = 2,
                 dropout: float = 0.1):
        super().__init__()
        self.num_vertices, self.latent, self.hidden, self.blocks, self.dropout = (
            num_vertices, latent, hidden, blocks, dropout)
        n = 3 * num_vertices
        self.enc_in = nn.Linear(n, latent)
        self.enc_blocks = nn.Sequential(*[ResidualUnit(latent, hidden, dropout) for _ in range(blocks)])
        self.dec_blocks = nn.Sequential(*[ResidualUnit(latent, hidden, dropout) for _ in range(blocks)])
        self.dec_out = nn.Linear(latent, n)
        # [m]: the layers see Delta / unit (unit: the largest PCA scale), so that the decoder's weights
        # are not ~1e-6 in metres, where every Adam step (~lr per weight) would be larger than they are.
        self.register_buffer("unit", torch.ones(()))

    def config(self) -> dict:
        return {"num_vertices": self.num_vertices, "latent": self.latent, "hidden": self.hidden,
                "blocks": self.blocks, "dropout": self.dropout}

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # Weights saved before ``unit`` existed are in metres: unit = 1 reads them exactly.
        state_dict.setdefault(prefix + "unit", torch.ones(()))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @torch.no_grad()
    def init_pca(self, displacements: np.ndarray) -> None:
        """Set the first and last layers from PCA of training displacements (N, V, 3) [m]. Scales are
        floored at 1e-3 of the largest: a direction the training data barely spans would otherwise
        blow a held-out displacement's code up by its inverse (the product of the two layers is the
        projection whatever the scale)."""
        mean, comps, scales = pca_basis(displacements, self.latent)
        unit = max(float(scales[0]), 1e-8)
        rel = np.maximum(scales / unit, 1e-3)           # scales in units of the largest
        W = comps / rel[:, None]
        dt = self.enc_in.weight.dtype
        self.unit.fill_(unit)
        self.enc_in.weight.copy_(torch.as_tensor(W, dtype=dt))
        self.enc_in.bias.copy_(torch.as_tensor(-W @ (mean / unit), dtype=dt))
        self.dec_out.weight.copy_(torch.as_tensor((comps * rel[:, None]).T, dtype=dt))
        self.dec_out.bias.copy_(torch.as_tensor(mean / unit, dtype=dt))

    def param_groups(self, lr: float) -> list[dict]:
        """Adam parameter groups at learning rate ``lr``: the PCA layers' weights and the decoder's
        3V-vector bias at lr / sqrt(3V), everything else at lr. Adam's step is about lr per entry
        whatever the gradient; the PCA layers' entries are ~1/sqrt(3V) (unit rows in units of the
        largest scale), so at lr their first step alone would undo much of the PCA start
        (BENCHMARKS.md). Scaled, each step changes every layer by the same relative amount."""
        big = [self.enc_in.weight, self.dec_out.weight, self.dec_out.bias]
        ids = {id(q) for q in big}
        return [{"params": [q for q in self.parameters() if id(q) not in ids], "lr": lr},
                {"params": big, "lr": lr / float(np.sqrt(3 * self.num_vertices))}]

    def encode(self, delta: torch.Tensor) -> torch.Tensor:
        """(N, V, 3) [m] -> (N, latent)."""
        return self.enc_blocks(self.enc_in(delta.flatten(1) / self.unit))

    def decode(self, code: torch.Tensor) -> torch.Tensor:
        """(..., latent) -> (..., V, 3) [m]."""
        out = self.dec_out(self.dec_blocks(code)) * self.unit
        return out.reshape(*code.shape[:-1], self.num_vertices, 3)

    def forward(self, delta):
        return self.decode(self.encode(delta))


def _mlp(sizes: list[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


class PoseAE(nn.Module):
    """The multimodal pose autoencoder (module docstring). Meshes enter as M(theta, 0) - T (the posed
    zero-shape body without root rotation and translation, minus the template) [m], so its input
    is the pose's deformation only; poses enter as the 69 joint axis-angles [rad] (the root's
    orientation is left out: it is not a subject feature, and gamma carries the root's motion).
    num_vertices V; latent (thesis: 10); hidden: units of the two hidden layers of each network."""

    kind = "softtissue_pose_ae"

    def __init__(self, num_vertices: int, latent: int = 10, hidden: int = 256):
        super().__init__()
        self.num_vertices, self.latent, self.hidden = num_vertices, latent, hidden
        self.e_mesh = _mlp([3 * num_vertices, hidden, hidden, latent])
        self.e_pose = _mlp([69, hidden, hidden, latent])
        self.d_mesh = _mlp([latent, hidden, hidden, 3 * num_vertices])

    def config(self) -> dict:
        return {"num_vertices": self.num_vertices, "latent": self.latent, "hidden": self.hidden}

    def encode_mesh(self, meshes: torch.Tensor) -> torch.Tensor:
        return self.e_mesh(meshes.flatten(1))

    def encode_pose(self, joint_rotations: torch.Tensor) -> torch.Tensor:
        """(..., 69) [rad] -> (..., latent): the deshaped pose theta-bar (eq. 3.12)."""
        return self.e_pose(joint_rotations)

    def decode(self, code: torch.Tensor) -> torch.Tensor:
        return self.d_mesh(code).reshape(*code.shape[:-1], self.num_vertices, 3)

    @staticmethod
    def mesh_input(tb, poses: torch.Tensor) -> torch.Tensor:
        """M(theta, 0) - T, (N, V, 3) [m], for poses (N, 72) [rad] with the root rotation zeroed."""
        p = poses.reshape(len(poses), 72).clone()
        p[:, :3] = 0.0
        v, _, _ = tb(None, p, None)
        return v - tb.v_template


#: What stands for the pose in gamma: "code", the pose autoencoder's deshaped code (section 3.3.1, the
#: static pose disentangling), or "pose", the 69 joint axis-angles themselves (the ablation of Fig. 3.7).
POSE_INPUTS = ("code", "pose")


def descriptor_size(pose_size: int) -> int:
    """Values per frame of gamma (eq. 3.11): 3 x pose features + root velocity and acceleration (3 + 3);
    pose_size: the pose code's size, or 69 for raw joint rotations."""
    return 3 * pose_size + 6


def pose_features(pose_ae: "PoseAE", pose_input: str, poses: torch.Tensor) -> torch.Tensor:
    """The pose part of gamma, (T, K): E_pose(theta) (pose_input "code") or theta's 69 joint
    axis-angles [rad] ("pose"); poses (T, 72) [rad]."""
    if pose_input == "code":
        return pose_ae.encode_pose(poses[:, 3:])
    if pose_input == "pose":
        return poses[:, 3:]
    raise InputError(f"pose_input must be one of {POSE_INPUTS}, got {pose_input!r}")


def motion_descriptor(pose_codes: torch.Tensor, poses: torch.Tensor, trans: torch.Tensor, fps: float) -> torch.Tensor:
    """gamma (eq. 3.11), (T, 3K + 6): [theta-bar, d theta-bar/dt, d^2 theta-bar/dt^2, dX/dt, d^2X/dt^2].

    pose_codes (T, K): :func:`pose_features` of each frame; poses (T, 72) [rad] (the root orientation gives the
    local frame); trans (T, 3) [m]. Derivatives are backward differences times fps, the body at rest
    before frame 0 (frame 0 has zero velocity and acceleration; frame 1's acceleration is its velocity
    times fps); the root's velocity [m/s] and
    acceleration [m/s^2] are rotated into the root's local frame (R_root^T v), so gamma does not
    depend on where the body faces."""
    from simgen.body.torch_lbs import axis_angle_to_matrix_torch

    def deriv(x):
        d = torch.zeros_like(x)
        d[1:] = (x[1:] - x[:-1]) * fps
        return d

    v_code = deriv(pose_codes)
    a_code = deriv(v_code)
    vel = deriv(trans)
    acc = deriv(vel)
    R = axis_angle_to_matrix_torch(poses.reshape(-1, 72)[:, :3])
    local = lambda x: torch.einsum("tji,tj->ti", R, x)  # noqa: E731
    return torch.cat([pose_codes, v_code, a_code, local(vel), local(acc)], dim=-1)


class SoftTissueRegressor(nn.Module):
    """R(gamma, beta) (module docstring). num_features: |gamma|; num_betas; latent: the soft-tissue
    code size; hidden: GRU units; layers: stacked GRU layers; pose_input: what gamma's pose part is
    (:data:`POSE_INPUTS`). Inputs are standardised with the training statistics (buffers ``x_mean``,
    ``x_std``, the std floored like the garment models')."""

    kind = "softtissue_regressor"

    def __init__(self, num_features: int, num_betas: int, latent: int, hidden: int = 256, layers: int = 1,
                 pose_input: str = "code"):
        super().__init__()
        if pose_input not in POSE_INPUTS:
            raise InputError(f"pose_input must be one of {POSE_INPUTS}, got {pose_input!r}")
        self.num_features, self.num_betas, self.latent, self.hidden, self.layers = (
            num_features, num_betas, latent, hidden, layers)
        self.pose_input = pose_input
        n_in = num_features + num_betas
        self.gru = nn.GRU(n_in, hidden, num_layers=layers, batch_first=True)
        self.out = nn.Linear(hidden, latent)
        self.shortcut = nn.Linear(n_in, latent)
        self.register_buffer("x_mean", torch.zeros(n_in))
        self.register_buffer("x_std", torch.ones(n_in))

    def config(self) -> dict:
        return {"num_features": self.num_features, "num_betas": self.num_betas, "latent": self.latent,
                "hidden": self.hidden, "layers": self.layers, "pose_input": self.pose_input}

    @torch.no_grad()
    def set_standardisation(self, inputs: torch.Tensor) -> None:
        """inputs (M, num_features + num_betas): training frames."""
        self.x_mean.copy_(inputs.mean(0))
        self.x_std.copy_(inputs.std(0, unbiased=False).clamp_min(INPUT_STD_FLOOR))

    def inputs(self, gamma: torch.Tensor, betas: torch.Tensor) -> torch.Tensor:
        """[gamma, beta] per frame: gamma (N, T, F), betas (N, B) -> (N, T, F + B), unstandardised."""
        if betas.shape[-1] != self.num_betas:
            raise InputError(f"the regressor takes {self.num_betas} betas, got {betas.shape[-1]}")
        return torch.cat([gamma, betas[:, None, :].expand(-1, gamma.shape[1], -1)], dim=-1)

    def forward(self, gamma: torch.Tensor, betas: torch.Tensor) -> torch.Tensor:
        """gamma (N, T, F), betas (N, B) -> codes (N, T, latent). Each call starts every sequence from a
        zero state (the thesis resets it per sequence); padded frames after a sequence's end do not
        affect its earlier frames."""
        x = (self.inputs(gamma, betas) - self.x_mean) / self.x_std
        h, _ = self.gru(x)  # h0 = 0
        return self.out(h) + self.shortcut(x)


for _cls in (SoftTissueAE, PoseAE, SoftTissueRegressor):
    MODEL_KINDS[_cls.kind] = _cls  # so that checkpoint.load_model reads these folders
