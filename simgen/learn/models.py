"""The regressors of thesis ch. 4 and the linear baselines, as torch modules.

- :class:`GarmentFitMLP`, R_G(beta) (section 4.2.2): one hidden layer of 20 units (ReLU), dropout
  0.2 on the hidden units, output the fit displacements Delta_G [m], shape (V, 3).
- :class:`WrinkleGRU`, R_L(beta, theta) (section 4.2.3): one GRU layer of 1500 units, dropout 0.2
  on its output, a linear layer to the wrinkle displacements Delta_L [m], shape (V, 3), per frame.
- :class:`LinearRegressor`: the thesis's LR baseline (a single linear layer from the motion
  descriptor to the unposed displacement Delta_G + Delta_L) and our variant that also sees beta.
- :class:`GarmentTemplate`: the garment's fixed arrays (T_r, T_c, faces, skinning weights, shape
  directions for the LBS baseline) as buffers, so that they save and load like the models.

Every module standardises its inputs and outputs with buffers set from the training data
(``set_normalization``), so a saved state_dict is all a later run needs. ``config()`` returns the
constructor arguments; ``simgen.learn.checkpoint`` stores them as JSON beside the weights.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from simgen.errors import InputError

__all__ = ["GarmentFitMLP", "WrinkleGRU", "LinearRegressor", "GarmentTemplate", "MODEL_KINDS", "INPUT_STD_FLOOR"]


#: Smallest standard deviation used to standardise an input feature (betas, radians, m/s, rad/s are all
#: O(0.1..1)): a feature that barely varies in training is not blown up when it varies at test time.
INPUT_STD_FLOOR = 0.05


def _stats(x: torch.Tensor, dim) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and standard deviation over ``dim``, the deviation floored at :data:`INPUT_STD_FLOOR`."""
    mean = x.mean(dim=dim)
    std = x.std(dim=dim, unbiased=False) if x.numel() > mean.numel() else torch.ones_like(mean)
    return mean, std.clamp_min(INPUT_STD_FLOOR)


class _Standardised(nn.Module):
    """Input standardisation and output de-standardisation buffers shared by the regressors.

    input_mean/input_std, shape (I,); output_mean [m], shape (V*3,); output_scale [m], shape (1,)
    (one scale for all coordinates, the RMS of the centred targets, so relative sizes are kept).
    """

    def _init_buffers(self, num_inputs: int, num_outputs: int) -> None:
        self.register_buffer("input_mean", torch.zeros(num_inputs))
        self.register_buffer("input_std", torch.ones(num_inputs))
        self.register_buffer("output_mean", torch.zeros(num_outputs))
        self.register_buffer("output_scale", torch.ones(1))

    @torch.no_grad()
    def set_normalization(self, inputs: torch.Tensor, targets: torch.Tensor) -> None:
        """inputs, shape (S, I); targets [m], shape (S, V*3) or (S, V, 3): training samples."""
        inputs = inputs.reshape(-1, self.input_mean.numel()).to(self.input_mean)
        targets = targets.reshape(-1, self.output_mean.numel()).to(self.output_mean)
        mean, std = _stats(inputs, 0)
        self.input_mean.copy_(mean)
        self.input_std.copy_(std)
        out_mean = targets.mean(dim=0)
        self.output_mean.copy_(out_mean)
        rms = (targets - out_mean).pow(2).mean().sqrt()
        self.output_scale.fill_(float(rms) if float(rms) > 1e-9 else 1.0)

    def normalize_inputs(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.input_mean) / self.input_std

    def normalize_targets(self, y: torch.Tensor) -> torch.Tensor:
        """targets [m], shape (..., V, 3) -> standardised, shape (..., V*3)."""
        return (y.reshape(y.shape[:-2] + (-1,)) - self.output_mean) / self.output_scale

    def denormalize(self, z: torch.Tensor) -> torch.Tensor:
        """standardised outputs (..., V*3) -> displacements [m], shape (..., V, 3)."""
        return (z * self.output_scale + self.output_mean).reshape(z.shape[:-1] + (-1, 3))


class GarmentFitMLP(_Standardised):
    """R_G: body shape -> garment fit displacements (thesis eq. 4.4 targets).

    num_betas: shape coefficients B; num_vertices: garment vertices V; hidden: hidden units (20);
    dropout: probability of disabling a hidden unit during training (0.2).
    """

    kind = "garment_fit"

    def __init__(self, num_betas: int, num_vertices: int, *, hidden: int = 20, dropout: float = 0.2):
        super().__init__()
        if num_betas < 1 or num_vertices < 1 or hidden < 1 or not 0.0 <= dropout < 1.0:
            raise InputError(f"bad garment fit MLP sizes: betas {num_betas}, vertices {num_vertices}, hidden "
                             f"{hidden}, dropout {dropout}")
        self.num_betas, self.num_vertices, self.hidden, self.dropout = num_betas, num_vertices, hidden, dropout
        self._init_buffers(num_betas, num_vertices * 3)
        self.hidden_layer = nn.Linear(num_betas, hidden)
        self.drop = nn.Dropout(dropout)
        self.output_layer = nn.Linear(hidden, num_vertices * 3)

    def config(self) -> dict:
        return {"num_betas": self.num_betas, "num_vertices": self.num_vertices, "hidden": self.hidden,
                "dropout": self.dropout}

    def forward_normalized(self, betas: torch.Tensor) -> torch.Tensor:
        """betas (N, B) -> standardised outputs (N, V*3) (what the loss compares)."""
        z = torch.relu(self.hidden_layer(self.normalize_inputs(betas)))
        return self.output_layer(self.drop(z))

    def forward(self, betas: torch.Tensor) -> torch.Tensor:
        """betas, shape (..., B) -> fit displacements Delta_G [m], shape (..., V, 3)."""
        lead = betas.shape[:-1]
        return self.denormalize(self.forward_normalized(betas.reshape(-1, self.num_betas))).reshape(
            lead + (self.num_vertices, 3))


class WrinkleGRU(_Standardised):
    """R_L: body shape and motion -> wrinkle displacements, one GRU layer (thesis section 4.2.3).

    num_betas B and num_features F (the motion descriptor, see ``simgen.learn.features``) make the
    per-frame input; hidden: GRU units (1500); dropout: on the GRU output (0.2);
    feature_mode: name of the motion descriptor, kept with the model so that inference builds the
    same inputs.
    """

    kind = "garment_wrinkle"

    def __init__(self, num_betas: int, num_features: int, num_vertices: int, *, hidden: int = 1500,
                 dropout: float = 0.2, feature_mode: str = "pose_velocity"):
        super().__init__()
        if min(num_betas, num_features, num_vertices, hidden) < 1 or not 0.0 <= dropout < 1.0:
            raise InputError(f"bad wrinkle GRU sizes: betas {num_betas}, features {num_features}, vertices "
                             f"{num_vertices}, hidden {hidden}, dropout {dropout}")
        self.num_betas, self.num_features, self.num_vertices = num_betas, num_features, num_vertices
        self.hidden, self.dropout, self.feature_mode = hidden, dropout, feature_mode
        self._init_buffers(num_betas + num_features, num_vertices * 3)
        self.gru = nn.GRU(num_betas + num_features, hidden, num_layers=1, batch_first=True)
        self.drop = nn.Dropout(dropout)
        self.output_layer = nn.Linear(hidden, num_vertices * 3)

    def config(self) -> dict:
        return {"num_betas": self.num_betas, "num_features": self.num_features, "num_vertices": self.num_vertices,
                "hidden": self.hidden, "dropout": self.dropout, "feature_mode": self.feature_mode}

    def forward_normalized(self, inputs: torch.Tensor, h0: torch.Tensor | None = None):
        """inputs (N, T, B+F) (betas then features) -> (standardised outputs (N, T, V*3), h (1, N, H))."""
        y, h = self.gru(self.normalize_inputs(inputs), h0)
        return self.output_layer(self.drop(y)), h

    def forward(self, betas: torch.Tensor, features: torch.Tensor, h0: torch.Tensor | None = None):
        """betas (N, T, B), features (N, T, F), h0 (1, N, H) or None (zeros: the body at rest).

        Returns (wrinkle displacements Delta_L [m], shape (N, T, V, 3), final hidden state (1, N, H)).
        """
        z, h = self.forward_normalized(torch.cat([betas, features], dim=-1), h0)
        return self.denormalize(z), h


class LinearRegressor(_Standardised):
    """Linear baseline: unposed displacement Delta_G + Delta_L [m] = linear map of the inputs.

    inputs: "pose" (the thesis's LR: the motion descriptor alone) or "shape_pose" (betas and the
    motion descriptor). Fitted in closed form (ridge least squares, :meth:`fit`), the optimum of the
    single-layer network the thesis trains.
    """

    kind = "garment_linear"
    INPUTS = ("pose", "shape_pose")

    def __init__(self, num_betas: int, num_features: int, num_vertices: int, *, inputs: str = "pose",
                 feature_mode: str = "pose_velocity"):
        super().__init__()
        if inputs not in self.INPUTS:
            raise InputError(f"linear regressor inputs {inputs!r} is not one of {', '.join(self.INPUTS)}")
        self.num_betas, self.num_features, self.num_vertices = num_betas, num_features, num_vertices
        self.inputs, self.feature_mode = inputs, feature_mode
        n_in = num_features + (num_betas if inputs == "shape_pose" else 0)
        self._init_buffers(n_in, num_vertices * 3)
        self.linear = nn.Linear(n_in, num_vertices * 3)

    def config(self) -> dict:
        return {"num_betas": self.num_betas, "num_features": self.num_features, "num_vertices": self.num_vertices,
                "inputs": self.inputs, "feature_mode": self.feature_mode}

    def assemble(self, betas: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """The regressor's input (..., I) from betas (..., B) and features (..., F)."""
        return torch.cat([betas, features], dim=-1) if self.inputs == "shape_pose" else features

    def forward(self, betas: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """betas (..., B), features (..., F) -> unposed displacement [m], shape (..., V, 3)."""
        return self.denormalize(self.linear(self.normalize_inputs(self.assemble(betas, features))))

    @torch.no_grad()
    def fit(self, chunks, *, ridge: float = 1e-3) -> None:
        """Least squares over training samples, streamed.

        chunks: a callable returning a fresh iterable of (betas (S, B), features (S, F), targets [m]
        (S, V, 3)) blocks (it is walked twice: statistics, then normal equations, so the samples
        never have to fit in memory at once). Minimises |X W - Y|^2 + ridge * S |W|^2 on
        standardised inputs and outputs (the ridge keeps collinear descriptors, e.g. a joint that
        never moves, from blowing the weights up).
        """
        n_in, n_out = self.input_mean.numel(), self.output_mean.numel()
        count, sx, sxx = 0, torch.zeros(n_in, dtype=torch.float64), torch.zeros(n_in, dtype=torch.float64)
        sy, syy = torch.zeros(n_out, dtype=torch.float64), 0.0
        for betas, features, targets in chunks():
            x = self.assemble(betas, features).double().cpu()
            y = targets.reshape(len(x), -1).double().cpu()
            count += len(x)
            sx += x.sum(0)
            sxx += (x * x).sum(0)
            sy += y.sum(0)
            syy += float((y * y).sum())
        if count == 0:
            raise InputError("the linear regressor got no training samples")
        mean_x = sx / count
        std_x = (sxx / count - mean_x ** 2).clamp_min(0).sqrt().clamp_min(INPUT_STD_FLOOR)
        mean_y = sy / count
        rms = max(syy / (count * n_out) - float((mean_y ** 2).mean()), 0.0) ** 0.5
        scale = rms if rms > 1e-9 else 1.0
        gram = torch.zeros((n_in, n_in), dtype=torch.float64)
        cross = torch.zeros((n_in, n_out), dtype=torch.float64)
        for betas, features, targets in chunks():
            xs = (self.assemble(betas, features).double().cpu() - mean_x) / std_x
            ys = (targets.reshape(len(xs), -1).double().cpu() - mean_y) / scale
            gram += xs.T @ xs
            cross += xs.T @ ys
        gram += ridge * count * torch.eye(n_in, dtype=torch.float64)
        weight = torch.linalg.solve(gram, cross)  # (I, V*3); standardised targets have zero mean
        self.input_mean.copy_(mean_x.float())
        self.input_std.copy_(std_x.float())
        self.output_mean.copy_(mean_y.float())
        self.output_scale.fill_(scale)
        self.linear.weight.copy_(weight.T.to(self.linear.weight))
        self.linear.bias.zero_()


class GarmentTemplate(nn.Module):
    """The garment's fixed data as buffers (no parameters).

    template [m] (V, 3): the relaxed garment T_r on the template body; template_smoothed [m] (V, 3):
    T_c; faces int64 (F, 3); skin_weights (V, 24); shape_directions [m] (V, 3, B): the body's shape
    blendshapes carried to the garment (LBS baseline: T_r + shape_directions . beta, skinned).
    """

    kind = "garment_template"

    def __init__(self, num_vertices: int, num_faces: int, num_betas: int):
        super().__init__()
        self.num_vertices, self.num_faces, self.num_betas = num_vertices, num_faces, num_betas
        self.register_buffer("template", torch.zeros(num_vertices, 3))
        self.register_buffer("template_smoothed", torch.zeros(num_vertices, 3))
        self.register_buffer("faces", torch.zeros(num_faces, 3, dtype=torch.int64))
        self.register_buffer("skin_weights", torch.zeros(num_vertices, 24))
        self.register_buffer("shape_directions", torch.zeros(num_vertices, 3, num_betas))

    def config(self) -> dict:
        return {"num_vertices": self.num_vertices, "num_faces": self.num_faces, "num_betas": self.num_betas}

    @classmethod
    def from_arrays(cls, template, template_smoothed, faces, skin_weights, shape_directions) -> "GarmentTemplate":
        t = np.asarray(template, dtype=np.float32)
        sd = np.asarray(shape_directions, dtype=np.float32)
        f = np.asarray(faces, dtype=np.int64)
        out = cls(len(t), len(f), sd.shape[2])
        with torch.no_grad():
            out.template.copy_(torch.from_numpy(t))
            out.template_smoothed.copy_(torch.from_numpy(np.asarray(template_smoothed, dtype=np.float32)))
            out.faces.copy_(torch.from_numpy(f))
            out.skin_weights.copy_(torch.from_numpy(np.asarray(skin_weights, dtype=np.float32)))
            out.shape_directions.copy_(torch.from_numpy(sd))
        return out

    def lbs_rest(self, betas: torch.Tensor) -> torch.Tensor:
        """Rest garment of the LBS baseline: T_r carried to the shaped body. betas (N, B) -> (N, V, 3)."""
        b = betas[..., : self.num_betas]
        return self.template + torch.einsum("vcb,nb->nvc", self.shape_directions[..., : b.shape[-1]], b)


MODEL_KINDS = {cls.kind: cls for cls in (GarmentFitMLP, WrinkleGRU, LinearRegressor, GarmentTemplate)}
