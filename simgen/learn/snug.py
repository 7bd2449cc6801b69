"""SNUG: self-supervised neural dynamic garments (Santesteban, Otaduy, Casas, CVPR 2022; thesis ch. 5).

The garment model of eqs. 5.1-5.2 with a recurrent displacement regressor R, trained without any
simulated data: the loss of a predicted 3-frame window is the backward-Euler objective (eq. 5.4)
written with the torch physics terms of :mod:`simgen.physics` (strain, bending, gravity, inertia,
collision), with the material and contact parameters of the simulation the datasets use.

    T(beta, phi) = T + S(beta) + R(beta, phi)                       (eq. 5.2, S: see below)
    M(beta, phi) = W(T(beta, phi), J(beta), theta, W_G)             (eq. 5.1, LBS with the garment's weights)

- T [m] (V, 3): the garment template (the rest shape the solver uses); W_G (V, 24): the garment's
  skinning weights; W: :func:`simgen.learn.skinning.lbs_torch` with the body's joint transforms.
- S(beta) [m] (V, 3): the body's shape blendshapes carried to the garment (the same directions as
  the LBS baseline of ch. 4, :class:`~simgen.learn.models.GarmentTemplate`). Eq. 5.2 has no such
  term; with it R starts from a garment that already fits the shaped body (``shape_blendshapes``,
  on by default; it is a fixed linear function of beta, so R(beta, phi) could absorb it).
- R: 4 stacked GRU layers of 256 units (tanh) and a linear layer to 3V values, times
  ``displacement_scale`` [m] (section 5.2.5). Inputs per frame: beta and the motion descriptor of
  :mod:`simgen.learn.features` ("pose_velocity": the joint rotations, the heading-free root
  rotation, the root's linear velocity and heading rate; "pose": the 72 axis-angles).

Training (section 5.3.1): windows of 3 consecutive frames of the training motions, each GRU's
initial hidden state drawn from N(0, 0.1) per window, a fresh body shape per window and epoch
(:func:`shape_range`), batch 16, Adam at 1e-3 for 10 epochs then 1e-4 until the validation loss
stops improving (:func:`converged`). See docs/learn.md, "SNUG (thesis ch. 5)".
"""

from __future__ import annotations

import io
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from simgen._fileio import atomic_write_bytes
from simgen.errors import InputError
from simgen.settings import setting, validate
from simgen.learn.checkpoint import load_model, save_model
from simgen.learn.collision import DEFAULT_CLEARANCE
from simgen.learn.features import FEATURE_MODES, feature_size, motion_features
from simgen.learn.garment_model import BodyCollision, Prediction, joint_transforms
from simgen.learn.models import INPUT_STD_FLOOR, MODEL_KINDS, GarmentTemplate
from simgen.learn.skinning import lbs_torch
from simgen.learn.train import STATE_FILE, _device, _load_state, _Logger

__all__ = ["SNUG_DIR", "LOSS_TERMS", "SnugConfig", "SnugPhysics", "SnugNet", "SnugModel", "SnugWindows",
           "SnugResult", "resolve_physics", "shape_range", "sample_shapes", "window_loss", "converged",
           "train_snug", "load_snug_model", "snug_tracks"]

SNUG_DIR = "snug"
LOSS_TERMS = ("strain", "bending", "gravity", "inertia", "collision")


# ------------------------------------------------------------------------------------ settings
@dataclass
class SnugConfig:
    """Every setting of a SNUG run (thesis sections 5.2.5, 5.3.1); each field declares its unit,
    bounds and doc (:func:`simgen.settings.setting`).

    physics: a dataset preset name (default "thesis-tshirt": its material, contact penalty and fps,
    so the loss is the energy the datasets' simulation minimises) or "snug" (thesis 5.3.1: its cotton (preset snug_cotton),
    k_collision = 250 J/m^3, margin 2 mm, flat rest angle; :func:`resolve_physics`). The five term
    switches are the ablations of thesis Table 5.2 (a switched-off term is still computed and
    logged, without gradient). inertia_start "skip" scores frame 2 of each 3-frame window,
    predicted from frames 0 and 1; "rest" also frame 1, with a zero velocity before frame 0.
    Shapes are drawn per window and epoch (:func:`shape_range`); the convergence criterion is
    :func:`converged`.
    """

    physics: str = setting("thesis-tshirt", doc="dataset preset whose material and contact the loss uses, or 'snug'")
    strain: bool = setting(True, doc="include the strain term (False: the ablation)")
    bending: bool = setting(True, doc="include the bending term (False: the ablation)")
    gravity: bool = setting(True, doc="include the gravity term (False: the ablation)")
    inertia: bool = setting(True, doc="include the inertia term (False: the ablation)")
    collision: bool = setting(True, doc="include the collision term (False: the ablation)")
    inertia_start: str = setting("skip", choices=("skip", "rest"), doc="which frames of a window the inertia scores")
    hidden: int = setting(256, low=1, doc="[units] per GRU layer")
    layers: int = setting(4, low=1, doc="stacked GRU layers")
    feature_mode: str = setting("pose_velocity", choices=FEATURE_MODES, doc="motion descriptor")
    shape_blendshapes: bool = setting(True, doc="add the body's shape blendshapes S(beta) to the template")
    displacement_scale: float = setting(0.01, low=0.0, inclusive=False, doc="[m] unit of the output layer")
    window: int = setting(3, low=2, doc="[frames] per training window")
    window_stride: int = setting(3, low=1, doc="[frames] between window starts")
    shape_range: float | None = setting(None, low=0.0, doc="betas ~ U(-r, r) (None: the body's range)")
    shape_components: int | None = setting(None, low=1, doc="leading shape components drawn (None: the body's)")
    hidden_init_std: float = setting(0.1, low=0.0, doc="sigma of the GRUs' initial state N(0, sigma)")
    val_motions: int = setting(2, low=0, doc="training motions kept out of training for the validation loss "
                               "(CRC-32 order, as the supervised models' --val-motions; at most all but one)")
    val_windows: int = setting(64, low=0, doc="validation windows of those motions (0: no validation)")
    batch_size: int = setting(16, low=1, doc="[windows] per optimiser step")
    lr: float = setting(1e-3, low=0.0, inclusive=False, doc="Adam learning rate of the first lr_epochs epochs")
    lr_epochs: int = setting(10, low=0, doc="[epochs] at lr before lr_final")
    lr_final: float = setting(1e-4, low=0.0, inclusive=False, doc="Adam learning rate afterwards")
    epochs: int = setting(200, low=1, doc="[epochs] at most, in all")
    patience: int = setting(5, low=1, doc="[epochs] of the convergence criterion")
    min_improvement: float = setting(1e-4, low=0.0, doc="[J per frame] of the convergence criterion")
    grad_clip: float | None = setting(None, low=0.0, inclusive=False, doc="gradient-norm clip (None: none)")
    seed: int = setting(0, doc="random seed")

    def check(self) -> None:
        """InputError for a setting out of its declared range, or a window too short for the inertia."""
        validate(self, "SNUG setting")
        if self.window < (3 if self.inertia_start == "skip" else 2):
            raise InputError(f"a window of {self.window} frames has no inertia term; use at least 3")


@dataclass
class SnugPhysics:
    """The loss's physical parameters, resolved: material (:class:`simgen.materials.Material`),
    contact (:class:`simgen.params.ContactParams`), gravity (:class:`simgen.params.GravityParams`),
    bending_rest ("template" or "flat"), fps [1/s] (the frame step dt = 1/fps of the inertia
    term; motions are resampled to it), source (the preset name or "snug")."""

    material: object
    contact: object
    gravity: object
    bending_rest: str
    fps: float
    source: str

    def to_dict(self) -> dict:
        return {"source": self.source, "material": self.material.to_dict(), "contact": asdict(self.contact),
                "gravity": list(self.gravity.gravity), "bending_rest": self.bending_rest, "fps": self.fps}


def resolve_physics(source: str, garment) -> SnugPhysics:
    """The material, contact and gravity parameters of a dataset preset's simulation, or SNUG's.

    source: a preset of ``simgen dataset`` (its [garment] material, else the garment's default
    material, with its overrides; its [solver.contact] and [solver.gravity] over the solver's
    defaults; the solver's template rest angle; its fps) or "snug" (thesis 5.3.1: the "snug_cotton"
    preset, i.e. 0.47 mm, 426 kg/m^3, lambda = 4.44e4 Pa, mu = 2.36e4 Pa, k_bend = 3.96e-5 N m;
    ContactParams.snug(): k = 250 J/m^3, margin 2 mm, power 3; flat rest angle; 30 fps).
    """
    from simgen.materials import get_material
    from simgen.params import ContactParams, GravityParams

    if source == "snug":
        return SnugPhysics(get_material("snug_cotton"), ContactParams.snug(), GravityParams(), "flat", 30.0, "snug")
    from simgen.dataset.spec import load_spec

    spec = load_spec(source)
    name = spec.material or (getattr(garment, "metadata", None) or {}).get("default_material") or "cotton"
    material = get_material(name)
    if spec.material_overrides:
        material = material.with_overrides(**spec.material_overrides)
    contact = ContactParams(**dict(spec.solver.get("contact") or {}))
    grav = dict(spec.solver.get("gravity") or {})
    if "gravity" in grav:
        grav["gravity"] = tuple(float(g) for g in grav["gravity"])
    return SnugPhysics(material, contact, GravityParams(**grav), "template", float(spec.fps), source)


def _live_components(body) -> int:
    """Number of leading shape components with non-zero blendshapes."""
    live = np.flatnonzero(np.abs(np.asarray(body.shapedirs)).reshape(-1, body.num_betas).max(axis=0) > 0)
    return int(live.max()) + 1 if len(live) else 0


def shape_range(body, config: SnugConfig) -> tuple[float, int]:
    """(r, K): training betas are drawn from U(-r, r) on the first K components, the rest are 0.

    The bundled open body: r = 2 on its 5 live components (its betas have unit variance over the
    sampled population, which spans about -3..+3.5; within +-2 every joint stays inside the body,
    beyond it anatomy fails, e.g. beta 2 = -3 puts the spine joints at the skin of the back:
    docs/body.md). A user's SMPL file: r = 3 on the first 10 components (thesis 5.3.1: U(-3, 3),
    on SMPL's 10 betas). ``config.shape_range`` / ``shape_components`` override either.
    """
    from simgen.assets import body_asset_id

    is_open = body_asset_id(body) == "open"
    r = config.shape_range if config.shape_range is not None else (2.0 if is_open else 3.0)
    k = config.shape_components if config.shape_components is not None else min(
        _live_components(body), 5 if is_open else 10)
    if not 0 <= k <= body.num_betas:
        raise InputError(f"shape_components {k} is outside 0..{body.num_betas} for body {body.name!r}")
    return float(r), int(k)


def sample_shapes(n: int, num_betas: int, r: float, k: int, generator: torch.Generator) -> torch.Tensor:
    """n body shapes (n, num_betas) [-]: U(-r, r) on the first k components, 0 on the rest."""
    betas = torch.zeros((n, num_betas))
    betas[:, :k] = (torch.rand((n, k), generator=generator) * 2.0 - 1.0) * r
    return betas


# ------------------------------------------------------------------------------------ the model
class SnugNet(nn.Module):
    """The unposed garment T(beta, phi) = T + S(beta) + R(beta, phi) (eq. 5.2), saved as one model.

    num_betas B, num_features F (the motion descriptor of ``feature_mode``), num_vertices V,
    num_faces (the template's triangles); hidden [units] and layers of the GRU stack;
    displacement_scale [m] per unit of the output layer; shape_blendshapes: add S(beta). Holds the
    garment as a :class:`GarmentTemplate` (T in ``template``, W_G, the shape directions) and the
    input standardisation (buffers), so the state_dict is all inference needs.
    """

    kind = "snug"

    def __init__(self, num_betas: int, num_features: int, num_vertices: int, num_faces: int, *, hidden: int = 256,
                 layers: int = 4, feature_mode: str = "pose_velocity", displacement_scale: float = 0.01,
                 shape_blendshapes: bool = True):
        super().__init__()
        if min(num_betas, num_features, num_vertices, num_faces, hidden, layers) < 1:
            raise InputError(f"bad SNUG sizes: betas {num_betas}, features {num_features}, vertices {num_vertices}, "
                             f"faces {num_faces}, hidden {hidden}, layers {layers}")
        self.num_betas, self.num_features, self.num_vertices, self.num_faces = (num_betas, num_features,
                                                                                  num_vertices, num_faces)
        self.hidden, self.layers, self.feature_mode = hidden, layers, feature_mode
        self.displacement_scale, self.shape_blendshapes = float(displacement_scale), bool(shape_blendshapes)
        self.template = GarmentTemplate(num_vertices, num_faces, num_betas)
        self.register_buffer("input_mean", torch.zeros(num_betas + num_features))
        self.register_buffer("input_std", torch.ones(num_betas + num_features))
        self.gru = nn.GRU(num_betas + num_features, hidden, num_layers=layers, batch_first=True)
        self.output_layer = nn.Linear(hidden, num_vertices * 3)
        with torch.no_grad():  # R = 0 at the start: the untrained model is the skinned T + S(beta), smooth
            self.output_layer.weight.zero_()
            self.output_layer.bias.zero_()

    def config(self) -> dict:
        return {"num_betas": self.num_betas, "num_features": self.num_features, "num_vertices": self.num_vertices,
                "num_faces": self.num_faces, "hidden": self.hidden, "layers": self.layers,
                "feature_mode": self.feature_mode, "displacement_scale": self.displacement_scale,
                "shape_blendshapes": self.shape_blendshapes}

    def initial_state(self, n: int, std: float = 0.0, generator: torch.Generator | None = None) -> torch.Tensor:
        """GRU initial states (layers, n, hidden): N(0, std) (training) or zeros (std = 0, inference)."""
        h = torch.randn((self.layers, n, self.hidden), generator=generator) * std if std > 0 else \
            torch.zeros((self.layers, n, self.hidden))
        return h.to(self.input_mean.device)

    def rest_garment(self, betas: torch.Tensor) -> torch.Tensor:
        """T + S(beta) [m]: betas (..., B) -> (..., V, 3)."""
        lead = betas.shape[:-1]
        if not self.shape_blendshapes:
            return self.template.template.expand(lead + (self.num_vertices, 3))
        return self.template.lbs_rest(betas.reshape(-1, betas.shape[-1])).reshape(lead + (self.num_vertices, 3))

    def forward(self, betas: torch.Tensor, features: torch.Tensor, h0: torch.Tensor | None = None):
        """betas (N, T, B), features (N, T, F), h0 (layers, N, hidden) or None (zeros).

        Returns (unposed garment T(beta, phi) [m], (N, T, V, 3), final GRU state (layers, N, hidden)).
        """
        x = (torch.cat([betas, features], dim=-1) - self.input_mean) / self.input_std
        y, h = self.gru(x, h0)
        disp = self.output_layer(y).reshape(y.shape[:-1] + (self.num_vertices, 3)) * self.displacement_scale
        return self.rest_garment(betas) + disp, h

    def posed(self, unposed: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
        """LBS with the garment's weights (eq. 5.1): unposed [m] (..., V, 3), transforms (..., 24, 4, 4)
        -> posed garment [m] (..., V, 3)."""
        lead = unposed.shape[:-2]
        x = lbs_torch(unposed.reshape((-1,) + unposed.shape[-2:]), self.template.skin_weights,
                      transforms.reshape(-1, 24, 4, 4))
        return x.reshape(lead + x.shape[-2:])


MODEL_KINDS[SnugNet.kind] = SnugNet  # so that checkpoint.load_model reads "snug" folders


class SnugModel(BodyCollision):
    """A trained SNUG garment ready for inference: :class:`SnugNet` + the body (TorchBody).

    fps [1/s]: the frame rate it was trained at (clips are resampled to it by :meth:`rollout`);
    clearance [m]: of the optional collision push-out (SNUG itself has none). Same interface as
    :class:`~simgen.learn.garment_model.GarmentModel` (``predict``, ``template``, ``body``,
    ``device``), so ``simgen export usd --compare`` and the evaluation take either.
    """

    def __init__(self, net: SnugNet, body, *, fps: float = 30.0, clearance: float = DEFAULT_CLEARANCE):
        super().__init__(body, clearance)
        self.net, self.fps = net, float(fps)
        self.eval()

    @property
    def template(self) -> GarmentTemplate:
        return self.net.template

    @property
    def device(self) -> torch.device:
        return self.net.input_mean.device

    @torch.no_grad()
    def predict(self, betas, poses, trans, fps: float, *, postprocess: bool = False) -> Prediction:
        """The garment over a whole sequence, the GRUs run from a zero state.

        betas (T, B) or (B,) [-]; poses axis-angle [rad] (T, 24, 3); trans [m] (T, 3); fps [1/s] of
        the sequence (velocities; it should be the training fps, ``self.fps``). Returns a
        :class:`Prediction` (vertices [m] (T, V, 3)); postprocess: push cloth out of the body.
        """
        poses, trans, betas = (torch.as_tensor(np.asarray(v.cpu() if isinstance(v, torch.Tensor) else v),
                                               dtype=torch.float32, device=self.device) for v in (poses, trans, betas))
        betas = betas.expand(len(poses), -1) if betas.dim() == 1 else betas
        features = motion_features(poses, trans, fps, self.net.feature_mode)
        unposed, _ = self.net(betas[None], features[None], self.net.initial_state(1))
        a = joint_transforms(self.body, betas, poses, trans)
        raw = self.net.posed(unposed[0], a)
        if not postprocess:
            return Prediction(raw, raw, None, a)
        out, moved = self.push_out_sequence(raw, betas, poses, trans)
        return Prediction(out, raw, moved, a)

    def rollout(self, clip, betas=None, *, postprocess: bool = False) -> Prediction:
        """A :class:`simgen.motion.MotionClip`, resampled to the training fps, for one body shape
        betas (B',) [-] (None: the mean shape). Returns a :class:`Prediction` ((T, V, 3) [m])."""
        from simgen.motion.ops import resample

        if abs(clip.fps - self.fps) > 1e-6:
            clip = resample(clip, self.fps)
        b = np.zeros(self.net.num_betas, dtype=np.float32)
        if betas is not None:
            given = np.asarray(betas, dtype=np.float32).reshape(-1)
            if len(given) > len(b):
                raise InputError(f"betas has {len(given)} values; the model takes {len(b)}")
            b[:len(given)] = given
        return self.predict(b, clip.poses, clip.trans, self.fps, postprocess=postprocess)


def load_snug_model(folder: str | Path, *, identity: dict | None = None, body=None, device="cpu",
                    clearance: float = DEFAULT_CLEARANCE) -> SnugModel:
    """Load a SNUG model folder (``train_snug``'s OUT, or OUT/snug) in one call.

    identity: refuse a model trained for another garment or body; body: the BodyModel (default: the
    bundled body, checked against the model's body hash).
    """
    from simgen.learn.data import body_for_identity

    folder = Path(folder)
    sub = folder / SNUG_DIR if (folder / SNUG_DIR / "config.json").is_file() else folder
    net = load_model(sub, identity=identity, kind=SnugNet.kind)
    own = {"garment": net.saved_config["garment"], "body": net.saved_config["body"]}
    fps = float(net.saved_config.get("training", {}).get("physics", {}).get("fps", 30.0))
    model = SnugModel(net, body_for_identity(own, body), fps=fps, clearance=clearance)
    model.folder = folder
    return model.to(device)


# ------------------------------------------------------------------------------------ data
class SnugWindows:
    """Motion clips cut into windows of consecutive frames (float32 tensors on ``device``).

    clips: MotionClips already at ``fps``; window, stride [frames]. poses [rad] (N, W, 24, 3),
    trans [m] (N, W, 3), features (N, W, F): the descriptor computed over the whole clip, so the
    velocities of a window's first frame use the frame before it (frame 0 of a clip: at rest).
    names: the clip of each window; starts: its first frame.
    """

    def __init__(self, clips, fps: float, feature_mode: str, *, window: int = 3, stride: int = 3, device="cpu"):
        poses, trans, feats, self.names, self.starts = [], [], [], [], []
        for clip in clips:
            p = torch.as_tensor(clip.poses, dtype=torch.float32)
            tr = torch.as_tensor(clip.trans, dtype=torch.float32)
            f = motion_features(p.double(), tr.double(), fps, feature_mode).float()
            for s in range(0, clip.num_frames - window + 1, stride):
                poses.append(p[s:s + window])
                trans.append(tr[s:s + window])
                feats.append(f[s:s + window])
                self.names.append(clip.name)
                self.starts.append(s)
        if not poses:
            raise InputError(f"no motion has {window} frames at {fps:g} fps")
        self.poses = torch.stack(poses).to(device)
        self.trans = torch.stack(trans).to(device)
        self.features = torch.stack(feats).to(device)

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    def subset(self, count: int) -> "SnugWindows":
        """``count`` windows spread evenly over all of them (validation)."""
        idx = torch.linspace(0, len(self) - 1, min(count, len(self))).round().long().unique()
        out = object.__new__(SnugWindows)
        out.poses, out.trans, out.features = (self.poses[idx.to(self.poses.device)],
                                              self.trans[idx.to(self.poses.device)],
                                              self.features[idx.to(self.poses.device)])
        out.names, out.starts = [self.names[i] for i in idx], [self.starts[i] for i in idx]
        return out


def _load_clips(motions, body, fps: float, split: str | None) -> list:
    """MotionClips at ``fps``: names of library clips or motion files (AMASS .npz, BVH, simgen .npz);
    None: split "train": every library clip (bundled and imported) not in the test split; "test":
    the test split's clips."""
    from simgen.assets import body_asset_id
    from simgen.motion import list_motions, load_motion, load_motion_file, resample

    body_id = body_asset_id(body)
    if motions is None:
        listed = list_motions(body_id)
        motions = [m["name"] for m in listed if (m["split"] == "test") == (split == "test")]
    clips = []
    for m in motions:
        path = Path(str(m)).expanduser()
        clip = load_motion_file(path, body=body) if path.suffix and path.is_file() else load_motion(str(m),
                                                                                                    body_id=body_id)
        clips.append(clip if abs(clip.fps - fps) < 1e-6 else resample(clip, fps))
    return clips


# ------------------------------------------------------------------------------------ loss
def window_loss(x: torch.Tensor, body_vertices: torch.Tensor, rest, surface, physics: SnugPhysics,
                config: SnugConfig) -> dict[str, torch.Tensor]:
    """SNUG's loss (eqs. 5.5-5.12) of predicted windows with :mod:`simgen.physics`.

    x [m] (N, W, V, 3): posed garments; body_vertices [m] (N, W, Vb, 3): the posed bodies; rest: the
    garment's ClothRest; surface: the body's BodySurface. Every term in J per frame: strain,
    bending, gravity and collision averaged over the N x W frames, inertia over the frames of
    ``config.inertia_start`` (dt = 1/physics.fps). "total": the sum of the terms switched on
    (the others are computed without gradient, for the log).
    """
    from simgen.physics import bending, contact, gravity, inertia_sequence, membrane

    fns = {"strain": lambda: membrane(x, rest), "bending": lambda: bending(x, rest),
           "gravity": lambda: gravity(x, rest, physics.gravity),
           "inertia": lambda: inertia_sequence(x, rest, 1.0 / physics.fps, start=config.inertia_start),
           "collision": lambda: contact(x, body_vertices, surface, physics.contact)}
    out, total = {}, x.new_zeros(())
    for name, fn in fns.items():
        if getattr(config, name):
            out[name] = fn()
            total = total + out[name]
        else:
            with torch.no_grad():
                out[name] = fn()
    out["total"] = total
    return out


def converged(val_losses: list[float], config: SnugConfig) -> bool:
    """The convergence criterion, on the validation loss after each epoch (J per frame).

    Only epochs at lr_final count (epoch index >= lr_epochs). Converged when the lowest loss of the
    last ``patience`` of them is not below the lowest loss of the earlier ones by more than
    ``min_improvement`` J per frame (so at least patience + 1 epochs at lr_final).
    """
    tail = [v for v in val_losses[config.lr_epochs:] if v == v]
    if len(tail) <= config.patience:
        return False
    return min(tail[-config.patience:]) > min(tail[:-config.patience]) - config.min_improvement


# ------------------------------------------------------------------------------------ training
@dataclass
class SnugResult:
    """What a run did: folder (OUT/snug), epochs completed in total, optimiser steps of this call,
    seconds of this call, why it stopped ("converged", "epochs" or "time budget"), the last epoch's
    mean training loss and validation loss [J per frame] (None when not measured)."""

    folder: Path
    epochs: int
    steps: int
    seconds: float
    stopped: str
    train_loss: float
    val_loss: float | None

    def to_dict(self) -> dict:
        d = asdict(self)
        d["folder"] = str(self.folder)
        return d


class _Run:
    """The pieces of one run: garment, body, physics, model, data, on one device.

    The training loop (:func:`_train_loop`) needs only what this class offers, so other losses of
    the same SnugNet subclass it (:mod:`simgen.learn.gru_l2`, the vertex-L2 GRU): ``method`` and
    ``terms`` (the log's loss columns) name the run; :meth:`_resolve_physics` and
    :meth:`_load_windows` supply the physics and the windows; :meth:`plan` and :meth:`batch_loss`
    the epoch's draws and a batch's loss; :meth:`training_facts` extra facts for config.json.
    """

    method = "SNUG (thesis ch. 5)"
    terms = LOSS_TERMS

    def __init__(self, garment, motions, config: SnugConfig, dev: torch.device, body):
        from simgen.body import load as load_body
        from simgen.body.torch_lbs import TorchBody
        from simgen.dataset.generate import garment_hash
        from simgen.garment import load_garment
        from simgen.learn.data import garment_shape_directions
        from simgen.physics import BodySurface, ClothRest

        self.body = body if body is not None else load_body("open")
        self.garment = load_garment(garment, body=self.body) if isinstance(garment, str) else garment
        g = self.garment
        self.physics = self._resolve_physics(config, g)
        self.identity = {"garment": {"name": g.name, "hash": garment_hash(g)},
                         "body": {"id": self.body.model_id, "hash": self.body.hash}}
        self.rest = ClothRest.from_garment(g, self.physics.material, bending_rest=self.physics.bending_rest,
                                           device=dev)
        self.surface = BodySurface.from_body(self.body).to(dev)
        self.torch_body = TorchBody(self.body, device=dev)
        self.range, self.components = shape_range(self.body, config)
        self._load_windows(motions, config, dev)
        tpl = GarmentTemplate.from_arrays(g.vertices, g.vertices, g.faces, g.skin_weights,
                                          garment_shape_directions(g.vertices, self.body))
        torch.manual_seed(config.seed)  # the weights' initialisation
        self.net = SnugNet(self.body.num_betas, feature_size(config.feature_mode), g.num_vertices, len(g.faces),
                           hidden=config.hidden, layers=config.layers, feature_mode=config.feature_mode,
                           displacement_scale=config.displacement_scale,
                           shape_blendshapes=config.shape_blendshapes)
        self.net.template.load_state_dict(tpl.state_dict())
        self._standardise(config)
        self.net.to(dev)

    def _resolve_physics(self, config: SnugConfig, garment) -> SnugPhysics:
        """The loss's parameters (:func:`resolve_physics` of ``config.physics``)."""
        return resolve_physics(config.physics, garment)

    def _load_windows(self, motions, config: SnugConfig, dev) -> None:
        """Set ``motions`` (clip names), ``windows`` (training) and ``val`` (validation, or None)."""
        from simgen.learn.data import pick_validation_motions

        clips = _load_clips(motions, self.body, self.physics.fps, "train")
        count = min(config.val_motions, len(clips) - 1) if config.val_windows else 0
        kept = set(pick_validation_motions([c.name for c in clips], count))
        train = [c for c in clips if c.name not in kept]
        self.motions = [c.name for c in train]
        self.validation_motions = sorted(kept)
        self.windows = SnugWindows(train, self.physics.fps, config.feature_mode, window=config.window,
                                   stride=config.window_stride, device=dev)
        self.val = None
        if kept:
            self.val = SnugWindows([c for c in clips if c.name in kept], self.physics.fps, config.feature_mode,
                                   window=config.window, stride=config.window, device=dev).subset(config.val_windows)

    def training_facts(self) -> dict:
        """Facts of the run for config.json's "training", beside the loop's own."""
        return {"validation_motions": self.validation_motions}

    @torch.no_grad()
    def _standardise(self, config: SnugConfig) -> None:
        f = self.windows.features.reshape(-1, self.windows.features.shape[-1]).cpu()
        b_std = torch.ones(self.body.num_betas)
        b_std[:self.components] = max(self.range / 3 ** 0.5, INPUT_STD_FLOOR)  # of U(-r, r)
        self.net.input_mean.copy_(torch.cat([torch.zeros(self.body.num_betas), f.mean(0)]))
        self.net.input_std.copy_(torch.cat([b_std, f.std(0, unbiased=False).clamp_min(INPUT_STD_FLOOR)]))

    def plan(self, n: int, config: SnugConfig, generator: torch.Generator, windows: SnugWindows | None = None):
        """One epoch's order, shapes (n, B) and GRU initial states (n, layers, hidden), drawn in this order.

        windows: the n windows planned (``self.windows`` when None; SNUG draws its shapes whatever they are)."""
        perm = torch.randperm(n, generator=generator)
        betas = sample_shapes(n, self.body.num_betas, self.range, self.components, generator)
        h0 = torch.randn((n, config.layers, config.hidden), generator=generator) * config.hidden_init_std
        return perm, betas, h0

    def batch_loss(self, windows: SnugWindows, idx, betas, h0, config: SnugConfig) -> dict[str, torch.Tensor]:
        """Loss of windows[idx] with shapes betas (n, B) and initial states h0 (n, layers, hidden)."""
        dev = windows.poses.device
        idx, betas, h0 = idx.to(dev), betas.to(dev), h0.to(dev)
        poses, trans, feats = windows.poses[idx], windows.trans[idx], windows.features[idx]
        n, w = poses.shape[:2]
        b_seq = betas[:, None].expand(n, w, -1)
        unposed, _ = self.net(b_seq, feats, h0.transpose(0, 1).contiguous())
        bv, _, a = self.torch_body(b_seq.reshape(n * w, -1), poses.reshape(n * w, 24, 3), trans.reshape(n * w, 3))
        x = self.net.posed(unposed, a.reshape(n, w, 24, 4, 4))
        return window_loss(x, bv.reshape(n, w, -1, 3), self.rest, self.surface, self.physics, config)

    @torch.no_grad()
    def val_loss(self, config: SnugConfig) -> float | None:
        """Validation loss [J per frame]: fixed windows, shapes and initial states (seed 12345)."""
        if self.val is None:
            return None
        g = torch.Generator().manual_seed(12345)
        _, betas, h0 = self.plan(len(self.val), config, g, self.val)
        total, n = 0.0, len(self.val)
        for s in range(0, n, config.batch_size):
            idx = torch.arange(s, min(s + config.batch_size, n))
            total += float(self.batch_loss(self.val, idx, betas[idx], h0[idx], config)["total"]) * len(idx)
        return total / n


def _save_state(folder: Path, run: _Run, optimizer, settings: dict, progress: dict, epoch_rng) -> None:
    buf = io.BytesIO()
    torch.save({"model": run.net.state_dict(), "optimizer": optimizer.state_dict(), "settings": json.dumps(settings),
                "progress": json.dumps(progress), "epoch_rng": epoch_rng}, buf)
    atomic_write_bytes(folder / STATE_FILE, buf.getvalue())


def train_snug(garment: str, out: str | Path, *, motions: list[str] | None = None, config: SnugConfig | None = None,
               device: str = "cpu", time_budget: float | None = None, resume: bool = True, body=None,
               progress=None, checkpoint_every: float = 120.0) -> SnugResult:
    """Train SNUG for a garment of the library; write the model folder OUT/snug/.

    garment: a garment name (or a Garment); motions: library clip names or motion files (AMASS .npz,
    BVH, simgen .npz; None: the library's train split and the user's imported clips); config:
    :class:`SnugConfig`; device: "cpu", "cuda", "cuda:N"; time_budget [s]: stop at the first step
    boundary after this long, everything saved; resume: continue from OUT/snug/train_state.pt (a
    run with other settings is refused; more ``epochs`` continue it); False starts over; body: the
    BodyModel (default: the bundled open body); progress(epochs_done (float), epochs, info) after
    every optimiser step; checkpoint_every [s]: save the model and train_state.pt this often.

    OUT/snug/ holds model.pt + config.json (:func:`load_snug_model`), log.csv (one row per epoch:
    lr, the mean of each loss term [J per frame], the validation loss) and train_state.pt (model,
    optimiser, position in the epoch, random state: a resumed run continues exactly).
    """
    config = config or SnugConfig()
    config.check()
    dev = _device(device)
    run = _Run(garment, motions, config, dev, body)  # checks garment, motions and physics: nothing written yet
    return _start(run, Path(out), config, dev, resume=resume, time_budget=time_budget, progress=progress,
                  checkpoint_every=checkpoint_every)


def _start(run: _Run, out: Path, config: SnugConfig, dev, *, resume: bool, time_budget, progress, checkpoint_every,
           settings: dict | None = None) -> SnugResult:
    """Create OUT/snug/, resume the run found there (same settings, else refused) and train.

    settings: what must not change between resumed calls (default: SNUG's config, physics,
    identity, motions and shape range)."""
    folder = out / SNUG_DIR
    folder.mkdir(parents=True, exist_ok=True)
    settings = settings if settings is not None else {
        "config": asdict(config), "physics": run.physics.to_dict(), "identity": run.identity,
        "motions": run.motions, "shape_range": [run.range, run.components]}
    optimizer = torch.optim.Adam(run.net.parameters(), lr=config.lr)
    generator = torch.Generator().manual_seed(config.seed)
    state = _load_state(folder, settings, resume, dev)
    prog = {"epoch": 0, "step": 0, "history": [], "val": [], "sums": {}, "count": 0}
    epoch_rng = None
    if state is not None:
        run.net.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        prog, epoch_rng = json.loads(state["progress"]), state["epoch_rng"].cpu()
        generator.set_state(epoch_rng)
    return _train_loop(run, folder, config, optimizer, generator, settings, prog, epoch_rng, time_budget,
                       progress, checkpoint_every)


def _train_loop(run: _Run, folder: Path, config: SnugConfig, optimizer, generator, settings, prog, epoch_rng,
                time_budget, progress, checkpoint_every) -> SnugResult:
    n = len(run.windows)
    batches = (n + config.batch_size - 1) // config.batch_size
    log = _Logger(folder, ["epoch", "steps", "lr", "loss", *run.terms, "val_loss", "seconds"], False)
    t0 = last_save = time.monotonic()
    steps, stopped = 0, "epochs"

    def save() -> None:
        _save_state(folder, run, optimizer, settings, prog, epoch_rng)
        save_model(run.net, folder, identity=run.identity, training={
            "method": run.method, "garment": run.garment.name, "motions": run.motions,
            "windows": n, "physics": run.physics.to_dict(), "config": asdict(config), "epochs": prog["epoch"],
            "shape_range": {"range": run.range, "components": run.components},
            "train_loss": prog["history"][-1] if prog["history"] else None,
            "val_loss": prog["val"][-1] if prog["val"] else None, **run.training_facts()})

    try:
        while prog["epoch"] < config.epochs and not converged(prog["val"], config):
            if prog["step"] == 0:
                epoch_rng = generator.get_state()
            generator.set_state(epoch_rng)
            perm, betas, h0 = run.plan(n, config, generator)
            lr = config.lr if prog["epoch"] < config.lr_epochs else config.lr_final
            for group in optimizer.param_groups:
                group["lr"] = lr
            run.net.train()
            while prog["step"] < batches:
                idx = perm[prog["step"] * config.batch_size:(prog["step"] + 1) * config.batch_size]
                terms = run.batch_loss(run.windows, idx, betas[idx], h0[idx], config)
                optimizer.zero_grad(set_to_none=True)
                terms["total"].backward()
                if config.grad_clip is not None:
                    torch.nn.utils.clip_grad_norm_(run.net.parameters(), config.grad_clip)
                optimizer.step()
                for k, v in terms.items():
                    prog["sums"][k] = prog["sums"].get(k, 0.0) + float(v.detach()) * len(idx)
                prog["count"] += len(idx)
                prog["step"] += 1
                steps += 1
                if progress is not None:
                    progress(prog["epoch"] + prog["step"] / batches, config.epochs,
                             {"loss": float(terms["total"].detach())})
                if time_budget is not None and time.monotonic() - t0 >= time_budget and prog["step"] < batches:
                    stopped = "time budget"
                    break
                if time.monotonic() - last_save >= checkpoint_every:
                    save()
                    last_save = time.monotonic()
            if stopped == "time budget":
                break
            _end_epoch(run, config, prog, log, lr, batches, t0)
            epoch_rng = generator.get_state()
            if time_budget is not None and time.monotonic() - t0 >= time_budget:
                stopped = "time budget"
                break
        if stopped != "time budget" and converged(prog["val"], config):
            stopped = "converged"
        save()
    finally:
        log.close()
    return SnugResult(folder, prog["epoch"], steps, time.monotonic() - t0, stopped,
                      prog["history"][-1] if prog["history"] else float("nan"),
                      prog["val"][-1] if prog["val"] else None)


def _end_epoch(run: _Run, config: SnugConfig, prog: dict, log, lr: float, batches: int, t0: float) -> None:
    """Close an epoch: means of the loss terms, the validation loss, one log row (steps: of the whole
    run; seconds: of this call); reset the sums."""
    means = {k: v / max(prog["count"], 1) for k, v in prog["sums"].items()}
    run.net.eval()
    val = run.val_loss(config)
    prog["epoch"] += 1
    prog["history"].append(means.get("total", float("nan")))
    prog["val"].append(val if val is not None else float("nan"))
    log.row({"epoch": prog["epoch"], "steps": prog["epoch"] * batches, "lr": lr, "loss": means.get("total"),
             **{k: means.get(k) for k in run.terms}, "val_loss": "" if val is None else val,
             "seconds": round(time.monotonic() - t0, 3)})
    prog.update(step=0, sums={}, count=0)


# ------------------------------------------------------------------------------------ export
@torch.no_grad()
def snug_tracks(model: SnugModel, clip, betas=None, *, postprocess: bool = False):
    """USD tracks of a clip played by the model: (MeshTracks [body, garment], metadata, fps).

    Write them with ``simgen.io.usd.write_usd(path, tracks, fps=fps, metadata=meta)``.
    """
    from simgen.io.usd import MeshTrack
    from simgen.motion.ops import resample

    clip = resample(clip, model.fps) if abs(clip.fps - model.fps) > 1e-6 else clip
    pred = model.rollout(clip, betas, postprocess=postprocess)
    b = torch.zeros(model.net.num_betas, device=model.device)
    if betas is not None:
        given = torch.as_tensor(np.asarray(betas, dtype=np.float32).reshape(-1))
        b[:len(given)] = given.to(b.device)
    bv = model.body(b, torch.as_tensor(clip.poses, dtype=torch.float32, device=model.device),
                    torch.as_tensor(clip.trans, dtype=torch.float32, device=model.device))[0]
    tracks = [MeshTrack(name="body", points=bv.cpu().numpy(), faces=model.body.faces.cpu().numpy(), role="body"),
              MeshTrack(name="garment", points=pred.vertices.cpu().numpy(), faces=model.template.faces.cpu().numpy(),
                        role="garment")]
    meta = {"model": str(getattr(model, "folder", "")), "motion": clip.name, "betas": b.cpu().tolist(),
            "method": "SNUG"}
    return tracks, meta, model.fps

