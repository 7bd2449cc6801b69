"""The full garment model of thesis ch. 4 and its baselines, ready for inference.

    M_c(beta, theta) = W(T_c + R_G(beta) + R_L(beta, theta), beta, theta, W_c)      (eqs. 4.2, 4.3)

followed by the collision post-process (:mod:`simgen.learn.collision`). A trained model folder
(``simgen train fit|wrinkle --out DIR``) holds:

    DIR/template/   the garment's T_r, T_c, faces, skinning weights, shape directions (buffers)
    DIR/fit/        R_G, the garment fit MLP
    DIR/wrinkle/    R_L, the wrinkle GRU
    DIR/lr_pose/, DIR/lr_shape_pose/   the linear baselines
    DIR/split.json  the split the models were trained on

:func:`load_garment_model` loads all of it in one call. Baselines: :func:`lbs_baseline` (the
relaxed template T_r carried to the shaped body and skinned, no learning) and
:func:`linear_baseline`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from simgen.errors import InputError
from simgen.learn.checkpoint import load_model
from simgen.learn.collision import DEFAULT_CLEARANCE, CollisionSurface, MeshSpread, push_out
from simgen.learn.features import motion_features
from simgen.learn.models import GarmentFitMLP, GarmentTemplate, LinearRegressor, WrinkleGRU
from simgen.learn.skinning import lbs_torch

__all__ = ["TEMPLATE_DIR", "FIT_DIR", "WRINKLE_DIR", "LR_DIRS", "SPLIT_FILE", "GarmentModel", "Prediction",
           "StreamState", "load_garment_model", "joint_transforms", "lbs_baseline", "linear_baseline"]

TEMPLATE_DIR, FIT_DIR, WRINKLE_DIR, SPLIT_FILE = "template", "fit", "wrinkle", "split.json"
LR_DIRS = {"pose": "lr_pose", "shape_pose": "lr_shape_pose"}


def joint_transforms(body, betas: torch.Tensor, pose: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
    """Skinning transforms A of a TorchBody without posing its vertices (cheaper per frame).

    betas (N, B'), pose axis-angle (N, 24, 3), trans [m] (N, 3) -> (N, 24, 4, 4); equal to the
    third output of ``TorchBody.forward``.
    """
    from simgen.body.torch_lbs import axis_angle_to_matrix_torch

    n = pose.shape[0]
    J = body.rest_joints(betas.expand(n, -1))
    G_rot, G_pos = body.kinematics(J, axis_angle_to_matrix_torch(pose))
    A_pos = G_pos - (G_rot @ J[..., None])[..., 0] + trans[:, None]
    top = torch.cat([G_rot, A_pos[..., None]], dim=-1)
    bottom = torch.zeros((n, 24, 1, 4), dtype=top.dtype, device=top.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def lbs_baseline(template: GarmentTemplate, betas: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """LBS of the template: T_r carried to the shaped body, skinned. betas (T, B), transforms
    (T, 24, 4, 4) -> vertices [m] (T, V, 3)."""
    return lbs_torch(template.lbs_rest(betas), template.skin_weights, transforms)


def linear_baseline(lr: LinearRegressor, template: GarmentTemplate, betas: torch.Tensor, features: torch.Tensor,
                    transforms: torch.Tensor) -> torch.Tensor:
    """Linear regression baseline: T_c + LR(inputs), skinned. betas (T, B), features (T, F),
    transforms (T, 24, 4, 4) -> vertices [m] (T, V, 3)."""
    return lbs_torch(template.template_smoothed + lr(betas, features), template.skin_weights, transforms)


@dataclass
class Prediction:
    """vertices [m] (T, V, 3) after the post-process (equal to raw without it); raw [m] (T, V, 3)
    before it; moved bool (T, V) or None; transforms (T, 24, 4, 4)."""

    vertices: torch.Tensor
    raw: torch.Tensor
    moved: torch.Tensor | None
    transforms: torch.Tensor


@dataclass
class StreamState:
    """Per-stream state of frame-by-frame inference: GRU hidden state and the previous frame."""

    hidden: torch.Tensor | None = None
    previous: tuple[torch.Tensor, torch.Tensor] | None = None


class BodyCollision(nn.Module):
    """What a garment model needs of the body at inference: the torch body (``body``), its collision
    surface (``surface``, kept on the module's device) and the post-process clearance [m]."""

    def __init__(self, body, clearance: float = DEFAULT_CLEARANCE):
        super().__init__()
        from simgen.body.torch_lbs import TorchBody

        self.body = TorchBody(body)
        self.surface = CollisionSurface(body.faces, body.v_template)
        self.clearance = float(clearance)

    def _apply(self, fn, recurse=True):
        out = super()._apply(fn, recurse)
        self.surface.to(self.body.v_template.device)
        return out

    def push_out_sequence(self, raw: torch.Tensor, betas: torch.Tensor, poses: torch.Tensor, trans: torch.Tensor,
                          chunk: int = 256, *, relax: bool = False):
        """The collision post-process over a sequence, ``chunk`` frames at a time, each push spread
        over the cloth around it (:class:`simgen.learn.collision.MeshSpread` of the template's
        faces): raw garment [m] (T, V, 3), betas (T, B), poses (T, 24, 3), trans (T, 3) ->
        (pushed-out vertices [m] (T, V, 3), moved (T, V) bool: the vertices that collided). With
        ``relax``, the metric post-process instead (:meth:`postprocess_frames`)."""
        out, moved = torch.empty_like(raw), torch.empty(raw.shape[:2], dtype=torch.bool, device=raw.device)
        for s in range(0, len(raw), chunk):
            sl = slice(s, s + chunk)
            bv = self.body(betas[sl], poses[sl], trans[sl])[0]
            out[sl], moved[sl] = self.postprocess_frames(raw[sl], bv, relax=relax)
        return out, moved

    def postprocess_frames(self, posed: torch.Tensor, body_vertices: torch.Tensor, *, relax: bool = False):
        """The post-process of frames: posed garments [m] (N, V, 3) on posed bodies [m] (N, Vb, 3) ->
        (garments [m] (N, V, 3), moved (N, V) bool). Without ``relax`` the thesis's: vertices closer
        than the clearance pushed out, the push spread over the cloth around them; with ``relax``
        the metric post-process: the triangles brought back to the metric of the relaxed template
        T_r near the prediction, with the body's contacts, then that push
        (:class:`simgen.learn.relax.MetricRelax`, built on first use: a (V, V) matrix on the device).
        moved: the vertices that collided (with ``relax``: those within the clearance at the start
        and those the final push moved, neighbours of colliding vertices included)."""
        dev = posed.device
        if getattr(self, "_spread", None) is None or self._spread.rows.device != dev:
            self._spread = MeshSpread(self.template.faces.cpu(), self.template.num_vertices).to(dev)
        if not relax:
            return push_out(posed, body_vertices, self.surface, clearance=self.clearance, spread=self._spread)
        if getattr(self, "_relax", None) is None or self._relax.device != dev:
            from simgen.learn.relax import MetricRelax

            self._relax = MetricRelax(self.template.template, self.template.faces, device=dev)
        return self._relax(posed, body_vertices, self.surface, clearance=self.clearance, spread=self._spread)


class GarmentModel(BodyCollision):
    """T_c + R_G + R_L skinned with the garment's weights, then the collision post-process.

    template: :class:`GarmentTemplate`; fit: R_G; wrinkle: R_L (None: fit only); body: the
    :class:`~simgen.body.model.BodyModel` the data was made with; clearance [m] of the post-process.
    """

    def __init__(self, template: GarmentTemplate, fit: GarmentFitMLP, wrinkle: WrinkleGRU | None, body, *,
                 clearance: float = DEFAULT_CLEARANCE):
        super().__init__(body, clearance)
        if fit.num_vertices != template.num_vertices or (wrinkle is not None
                                                         and wrinkle.num_vertices != template.num_vertices):
            raise InputError(f"the fit/wrinkle models predict {fit.num_vertices} vertices but the garment template "
                             f"has {template.num_vertices}")
        self.template, self.fit, self.wrinkle = template, fit, wrinkle
        self.eval()

    @property
    def device(self) -> torch.device:
        return self.template.template.device

    @property
    def feature_mode(self) -> str:
        return self.wrinkle.feature_mode if self.wrinkle is not None else "pose"

    def _tensor(self, x, dtype=torch.float32) -> torch.Tensor:
        return torch.as_tensor(x, dtype=dtype, device=self.device)

    def unposed(self, betas: torch.Tensor, features: torch.Tensor, hidden=None):
        """T_c + R_G + R_L for one or more streams: betas (N, T, B), features (N, T, F) ->
        (unposed garment [m] (N, T, V, 3), GRU hidden state)."""
        rest = self.template.template_smoothed + self.fit(betas)
        if self.wrinkle is None:
            return rest, None
        wrinkle, hidden = self.wrinkle(betas, features, hidden)
        return rest + wrinkle, hidden

    @torch.no_grad()
    def predict(self, betas, poses, trans, fps: float, *, postprocess: bool = True, relax: bool = False,
                chunk: int = 256) -> Prediction:
        """Garment over a whole sequence, the GRU run from rest.

        betas (T, B); poses axis-angle [rad] (T, 24, 3); trans [m] (T, 3); fps [1/s] of the sequence;
        postprocess: the collision post-process (relax: the metric one, :meth:`postprocess_frames`).
        """
        betas, poses, trans = self._tensor(betas), self._tensor(poses), self._tensor(trans)
        features = motion_features(poses, trans, fps, self.feature_mode)
        rest, _ = self.unposed(betas[None], features[None])
        a = joint_transforms(self.body, betas, poses, trans)
        raw = lbs_torch(rest[0], self.template.skin_weights, a)
        if not postprocess:
            return Prediction(raw, raw, None, a)
        out, moved = self.push_out_sequence(raw, betas, poses, trans, chunk, relax=relax)
        return Prediction(out, raw, moved, a)

    @torch.no_grad()
    def step(self, state: StreamState, betas, pose, trans, fps: float, *, postprocess: bool = True,
             relax: bool = False) -> torch.Tensor:
        """One frame for N streams (the runtime loop of thesis Table 4.1).

        betas (N, B); pose (N, 24, 3); trans (N, 3); state is updated in place. Returns vertices [m]
        (N, V, 3): with ``postprocess`` the thesis's per-vertex push-out, or with ``relax`` the metric
        post-process instead (:meth:`finish_frame`).
        """
        features = motion_features(pose[:, None], trans[:, None], fps, self.feature_mode, previous=state.previous)
        rest, state.hidden = self.unposed(betas[:, None], features, state.hidden)
        state.previous = (pose, trans)
        if not postprocess:
            a = joint_transforms(self.body, betas, pose, trans)
            return lbs_torch(rest[:, 0], self.template.skin_weights, a)
        bv, _, a = self.body(betas, pose, trans)
        return self.finish_frame(lbs_torch(rest[:, 0], self.template.skin_weights, a), bv, relax=relax)

    def finish_frame(self, posed: torch.Tensor, body_vertices: torch.Tensor, *, relax: bool = False) -> torch.Tensor:
        """The post-process of :meth:`step`: posed garments [m] (N, V, 3) on posed bodies [m] (N, Vb, 3)
        -> vertices [m] (N, V, 3), pushed out vertex by vertex (the thesis's), or with ``relax`` the
        metric post-process (:meth:`postprocess_frames`)."""
        if relax:
            return self.postprocess_frames(posed, body_vertices, relax=True)[0]
        return push_out(posed, body_vertices, self.surface, clearance=self.clearance)[0]


def load_garment_model(folder: str | Path, *, identity: dict | None = None, body=None, device="cpu",
                       clearance: float = DEFAULT_CLEARANCE) -> GarmentModel:
    """Load a trained model folder (template + fit + wrinkle) as one :class:`GarmentModel`.

    identity: refuse models trained for another garment or body (e.g. a dataset's identity);
    body: the BodyModel (default: the bundled one, checked against the models' body hash). A folder
    without wrinkle/ gives a fit-only model.
    """
    from simgen.learn.data import body_for_identity

    folder = Path(folder)
    if not (folder / TEMPLATE_DIR).is_dir() or not (folder / FIT_DIR).is_dir():
        raise InputError(f"{folder} holds no trained garment model (expected {TEMPLATE_DIR}/ and {FIT_DIR}/ from "
                         f"`simgen train fit`)")
    template = load_model(folder / TEMPLATE_DIR, identity=identity, kind="garment_template")
    own = {"garment": template.saved_config["garment"], "body": template.saved_config["body"]}
    fit = load_model(folder / FIT_DIR, identity=own, kind="garment_fit")
    wrinkle = None
    if (folder / WRINKLE_DIR / "config.json").is_file():
        wrinkle = load_model(folder / WRINKLE_DIR, identity=own, kind="garment_wrinkle")
    model = GarmentModel(template, fit, wrinkle, body_for_identity(own, body), clearance=clearance)
    model.folder = folder
    return model.to(device)


def load_split(folder: str | Path):
    """The split a model folder was trained on (``split.json``), or None."""
    from simgen.learn.data import Split

    path = Path(folder) / SPLIT_FILE
    if not path.is_file():
        return None
    return Split.from_dict(json.loads(path.read_text(encoding="utf-8")))


def load_linear_baselines(folder: str | Path, *, identity: dict | None = None, device="cpu") -> dict:
    """The linear baselines saved in a model folder: {"pose": LinearRegressor, "shape_pose": ...}."""
    out = {}
    for name, sub in LR_DIRS.items():
        if (Path(folder) / sub / "config.json").is_file():
            out[name] = load_model(Path(folder) / sub, identity=identity, kind="garment_linear", device=device)
    return out
