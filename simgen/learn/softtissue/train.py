"""Training SoftSMPL (thesis section 3.4) and loading the trained model in one call.

Three stages, in order, into one model folder OUT/softtissue/:

1. ``pose_ae`` (:class:`~simgen.learn.softtissue.models.PoseAE`, eq. 3.13) on the poses of the
   training sequences (the thesis uses SURREAL's 76k poses; here the dataset's own), Adam 1e-3.
2. ``soft_ae`` (:class:`~simgen.learn.softtissue.models.SoftTissueAE`, eq. 3.8), first/last layers
   from PCA of the training displacements, Adam 1e-4, batch 256, dropout 0.1.
3. ``regressor`` (:class:`~simgen.learn.softtissue.models.SoftTissueRegressor`, eq. 3.10) on whole
   training sequences (state reset per sequence), batch 10, Adam 1e-3; inputs gamma (eq. 3.11,
   from the frozen pose encoder, or from the raw joint rotations with ``pose_input="pose"``) and
   beta, targets the frozen soft-tissue encoder's codes.

OUT/softtissue/ holds ``pose_ae/``, ``soft_ae/``, ``regressor/`` (each model.pt + config.json,
:mod:`simgen.learn.checkpoint`), ``log.csv`` (one row per epoch of each stage), ``split.json`` and
``train_state.pt`` (the stage, epoch and step reached, every model, the optimiser: rerunning resumes;
other settings are refused unless ``resume=False``). A simulated store has every shape perform every
motion and its mirror (what sections 3.3.2 and 3.4.1 add to Dyna). Dyna files are mirrored when read
(:func:`~simgen.learn.softtissue.dyna.read_dyna`), and with ``motion_transfer`` each subject plays the
clips it lacks with its own regressor (:mod:`~simgen.learn.softtissue.transfer`).
"""

from __future__ import annotations

import io
import json
import shutil
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from simgen._fileio import atomic_write_bytes
from simgen.body.torch_lbs import axis_angle_to_matrix_torch
from simgen.errors import InputError
from simgen.learn.checkpoint import check_identity, load_model, read_config, save_model
from simgen.learn.softtissue.data import SoftTissueData, one_shape_per_motion
from simgen.learn.softtissue.models import (LAMBDA_NORM, POSE_INPUTS, PoseAE, SoftTissueAE, SoftTissueRegressor,
                                            descriptor_size, motion_descriptor, pad_sequences, pca_frames,
                                            pose_ae_loss, pose_features, reconstruction_loss, regression_loss)
from simgen.learn.softtissue.transfer import transferred_items
from simgen.learn.train import STATE_FILE, _device, _load_state, _Logger
from simgen.settings import setting, validate

__all__ = ["SOFTTISSUE_DIR", "STAGES", "SoftTissueConfig", "SoftSMPL", "SoftTissueResult", "train_softtissue",
           "load_softtissue_model"]

SOFTTISSUE_DIR = "softtissue"
STAGES = ("pose_ae", "soft_ae", "regressor")
_LOG_FIELDS = ["stage", "epoch", "lr", "loss", "surf", "norm", "mesh_path", "pose_path", "pos", "vel", "acc",
               "val_loss", "seconds"]


@dataclass
class SoftTissueConfig:
    """Every setting of a SoftSMPL run (thesis section 3.4; widths and depths are ours: the thesis
    gives them only in figures)."""

    pose_latent: int = setting(10, low=1, doc="size of the deshaped pose code (thesis: 10)")
    pose_hidden: int = setting(256, low=1, doc="[units] of the pose autoencoder's hidden layers")
    pose_lr: float = setting(1e-3, low=0.0, inclusive=False, doc="Adam learning rate of the pose autoencoder")
    pose_epochs: int = setting(20, low=0, doc="[epochs] of the pose autoencoder (thesis: 20)")
    pose_batch: int = setting(256, low=1, doc="[frames] per pose-autoencoder step")
    ae_latent: int = setting(100, low=1, doc="size of the soft-tissue code (thesis Table 3.1: 25, 50, 100)")
    ae_hidden: int = setting(256, low=1, doc="[units] inside each residual unit")
    ae_blocks: int = setting(2, low=0, doc="residual units in the encoder and in the decoder")
    ae_dropout: float = setting(0.1, low=0.0, high=1.0, doc="dropout inside the residual units (thesis: 0.1)")
    ae_lr: float = setting(1e-4, low=0.0, inclusive=False, doc="Adam learning rate of the autoencoder")
    ae_epochs: int = setting(1000, low=0, doc="[epochs] of the autoencoder (thesis: 1000)")
    ae_batch: int = setting(256, low=1, doc="[frames] per autoencoder step (thesis: 256)")
    lambda_norm: float = setting(LAMBDA_NORM, low=0.0, doc="weight of the face-normal term (eq. 3.8; 1000)")
    reg_hidden: int = setting(256, low=1, doc="[units] of the regressor's GRU")
    reg_layers: int = setting(1, low=1, doc="stacked GRU layers")
    reg_lr: float = setting(1e-3, low=0.0, inclusive=False, doc="Adam learning rate of the regressor")
    reg_epochs: int = setting(100, low=0, doc="[epochs] of the regressor (thesis: 100)")
    reg_batch: int = setting(10, low=1, doc="[sequences] per regressor step (thesis: 10)")
    pose_input: str = setting("code", choices=POSE_INPUTS,
                              doc="the regressor's pose input: the pose AE's code (section 3.3.1) or the raw joint "
                                  "rotations (Fig. 3.7's ablation without static pose disentangling)")
    motion_transfer: bool = setting(True, doc="train the regressor on every shape doing every motion (section 3.3.2): "
                                              "clips a subject lacks are played by that subject's own regressor; "
                                              "False keeps one shape per motion (Fig. 3.7's ablation without dynamic "
                                              "pose disentangling)")
    base: str = setting("", doc="a trained SoftSMPL folder whose two autoencoders this run takes, training only the "
                                "regressor (ablations, leave-one-motion-out) with the base's autoencoder sizes; it "
                                "must not have trained on a held-out sequence of this run")
    test_motions: str = setting("", doc="held-out motion names, comma-separated")
    test_subjects: str = setting("", doc="held-out subject ids, comma-separated")
    seed: int = setting(0, doc="random seed")

    def check(self) -> None:
        validate(self, "soft-tissue setting")

    def epochs(self, stage: str) -> int:
        return {"pose_ae": self.pose_epochs, "soft_ae": self.ae_epochs, "regressor": self.reg_epochs}[stage]

    def held_out(self) -> tuple[list[str], list[str]]:
        def names(text):
            return [n.strip() for n in text.replace(" ", ",").split(",") if n.strip()]

        return names(self.test_motions), names(self.test_subjects)


@dataclass
class SoftTissueResult:
    """folder; stage and epoch reached; steps (this call); seconds (this call); stopped ("epochs" or
    "time budget"); losses: the last epoch's mean training loss of each stage trained."""

    folder: Path
    stage: str
    epoch: int
    steps: int
    seconds: float
    stopped: str
    losses: dict


# ------------------------------------------------------------------------------------ the model
class SoftSMPL(torch.nn.Module):
    """The runtime pipeline (thesis Fig. 3.2, eq. 3.9): Delta = D_soft(R(gamma, beta)) with gamma from
    E_pose (or the raw joint rotations: the regressor's ``pose_input``). ``predict`` plays one
    sequence from a zero state; ``posed`` adds Delta to the body."""

    def __init__(self, pose_ae: PoseAE, soft_ae: SoftTissueAE, regressor: SoftTissueRegressor, identity: dict):
        super().__init__()
        self.pose_ae, self.soft_ae, self.regressor, self.identity = pose_ae, soft_ae, regressor, identity

    @property
    def device(self) -> torch.device:
        return self.regressor.x_mean.device

    def descriptor(self, poses: torch.Tensor, trans: torch.Tensor, fps: float) -> torch.Tensor:
        """gamma (T, F) of one sequence: poses (T, 72) [rad], trans (T, 3) [m], fps [1/s]."""
        return motion_descriptor(pose_features(self.pose_ae, self.regressor.pose_input, poses), poses, trans, fps)

    @torch.no_grad()
    def predict(self, betas, poses, trans, fps: float) -> torch.Tensor:
        """Delta [m], (T, V, 3), for betas (B,), poses (T, 72) [rad], trans (T, 3) [m] at ``fps``."""
        dev = self.device
        poses = torch.as_tensor(np.asarray(poses, dtype=np.float32), device=dev).reshape(-1, 72)
        trans = torch.as_tensor(np.asarray(trans, dtype=np.float32), device=dev).reshape(-1, 3)
        gamma = self.descriptor(poses, trans, fps)
        codes = self.regressor(gamma[None], self.betas_input(betas)[None])[0]
        return self.soft_ae.decode(codes)

    def betas_input(self, betas) -> torch.Tensor:
        """The regressor's betas (num_betas,) on the model's device: ``betas`` cut or padded with zeros."""
        b = torch.zeros(self.regressor.num_betas, device=self.device)
        given = torch.as_tensor(np.asarray(betas, dtype=np.float32).reshape(-1))[:self.regressor.num_betas]
        b[:len(given)] = given.to(self.device)
        return b

    def stream(self, betas, fps: float) -> "SoftTissueStream":
        """A frame-by-frame player for betas (B,) at ``fps`` (an avatar's per-frame use, thesis 4.8 ms
        per frame): ``stream.step(pose, trans)`` returns that frame's Delta, equal to ``predict``'s
        frame of the same sequence."""
        return SoftTissueStream(self, betas, fps)

    @torch.no_grad()
    def posed(self, body, betas, poses, trans, fps: float) -> torch.Tensor:
        """Posed vertices [m], (T, V, 3): W(T + B_s + B_p + Delta) with the body model (eq. 3.2)."""
        from simgen.body.torch_lbs import TorchBody
        from simgen.learn.softtissue.dyna import posed_vertices

        tb = TorchBody(body, device=self.device)
        delta = self.predict(betas, poses, trans, fps)
        p = torch.as_tensor(np.asarray(poses, dtype=np.float32), device=self.device).reshape(-1, 72)
        t = torch.as_tensor(np.asarray(trans, dtype=np.float32), device=self.device).reshape(-1, 3)
        b = torch.as_tensor(np.asarray(betas, dtype=np.float32), device=self.device).reshape(-1)
        return posed_vertices(tb, delta, b, p, t)


class SoftTissueStream:
    """SoftSMPL one frame at a time (:meth:`SoftSMPL.stream`): keeps the previous frame's pose code,
    root position and their velocities (the backward differences of :func:`motion_descriptor`, the
    first frame at rest) and the GRU's state."""

    def __init__(self, model: SoftSMPL, betas, fps: float):
        self.model, self.fps = model, float(fps)
        self.betas = model.betas_input(betas)
        self.prev = None            # (pose code, trans, pose-code velocity, root velocity) of the last frame
        self.h = None               # GRU state, (layers, 1, hidden); None: zero

    @torch.no_grad()
    def step(self, pose, trans) -> torch.Tensor:
        """Delta [m], (V, 3), of the next frame: pose (72,) [rad], trans (3,) [m]."""
        m, dev, fps = self.model, self.model.device, self.fps
        pose = torch.as_tensor(np.asarray(pose, dtype=np.float32), device=dev).reshape(1, 72)
        trans = torch.as_tensor(np.asarray(trans, dtype=np.float32), device=dev).reshape(3)
        code = pose_features(m.pose_ae, m.regressor.pose_input, pose)[0]
        if self.prev is None:
            v_code, vel = torch.zeros_like(code), torch.zeros_like(trans)
            a_code, acc = v_code, vel
        else:
            p_code, p_trans, p_vcode, p_vel = self.prev
            v_code, vel = (code - p_code) * fps, (trans - p_trans) * fps
            a_code, acc = (v_code - p_vcode) * fps, (vel - p_vel) * fps
        self.prev = (code, trans, v_code, vel)
        R = axis_angle_to_matrix_torch(pose[:, :3])[0]
        gamma = torch.cat([code, v_code, a_code, R.T @ vel, R.T @ acc])
        r = m.regressor
        x = (torch.cat([gamma, self.betas]) - r.x_mean) / r.x_std
        h, self.h = r.gru(x[None, None], self.h)
        return m.soft_ae.decode(r.out(h[0, 0]) + r.shortcut(x))


def load_softtissue_model(folder: str | Path, *, identity: dict | None = None, device="cpu") -> SoftSMPL:
    """Load a trained SoftSMPL model folder (OUT or OUT/softtissue) in one call, in eval mode.
    identity: ``{"body": {"id", "hash"}}`` refuses a model trained for another body."""
    folder = Path(folder)
    if not (folder / "regressor").is_dir() and (folder / SOFTTISSUE_DIR).is_dir():
        folder = folder / SOFTTISSUE_DIR
    for name in STAGES:
        if not (folder / name / "config.json").is_file():
            raise InputError(f"{folder} holds no trained SoftSMPL {name} (run `simgen train softtissue` to the end)")
    models = {name: load_model(folder / name, identity=identity, device=device) for name in STAGES}
    model = SoftSMPL(models["pose_ae"], models["soft_ae"], models["regressor"],
                     {"body": read_config(folder / "regressor").get("body", {})})
    model.folder = folder
    return model.to(device).eval()


# ------------------------------------------------------------------------------------ training
class _Run:
    """The split, the tensors on the device and the three networks."""

    def __init__(self, data: SoftTissueData, config: SoftTissueConfig, dev, body):
        from simgen.body.torch_lbs import TorchBody

        if not data.sequences:
            raise InputError("soft-tissue data holds no sequence")
        if body is None or body.hash != data.body.get("hash"):
            raise InputError(f"the body model given ({getattr(body, 'name', None)!r}) is not the data's body "
                             f"{data.body.get('id')!r} (hash {str(data.body.get('hash'))[:12]})")
        self.data, self.dev = data, dev
        self.train, self.test = data.split(*config.held_out())
        if not config.motion_transfer:
            self.train = one_shape_per_motion(self.train)
        self.identity = {"body": dict(data.body)}
        self.tb = TorchBody(body, device=dev)
        self.faces = torch.as_tensor(np.array(data.faces), device=dev)
        self.template = torch.as_tensor(data.template, device=dev)
        torch.manual_seed(config.seed)
        V = data.num_vertices
        self.nets = {
            "pose_ae": PoseAE(V, config.pose_latent, config.pose_hidden).to(dev),
            "soft_ae": SoftTissueAE(V, config.ae_latent, config.ae_hidden, config.ae_blocks,
                                    config.ae_dropout).to(dev),
            "regressor": self.new_regressor(config)}
        if config.base:
            self._take_base(config)

        def frames(d: SoftTissueData):
            if not d.sequences:
                return None
            return (torch.as_tensor(np.concatenate([s.poses for s in d.sequences]), device=dev),
                    torch.as_tensor(np.concatenate([s.displacements for s in d.sequences]), device=dev))

        # Every frame on the device for the autoencoder stages (a run on a base trains neither).
        self.frames = None if config.base else frames(self.train)
        self.test_all = _merge(self.test, data) if self.test else None   # one object: the cache keys on it
        self.test_frames = frames(self.test_all) if self.test and not config.base else None
        self._seq_cache: dict = {}
        self.items: list = []          # the regressor's training items (prepare_regressor)
        self.transfer: dict = {}       # what motion transfer added, per subject

    def new_regressor(self, config: SoftTissueConfig) -> SoftTissueRegressor:
        """An untrained regressor of this run's sizes, on its device."""
        return SoftTissueRegressor(descriptor_size(config.pose_latent if config.pose_input == "code" else 69),
                                   self.data.num_betas, config.ae_latent, config.reg_hidden, config.reg_layers,
                                   config.pose_input).to(self.dev)

    def _take_base(self, config: SoftTissueConfig) -> None:
        """Load the pose and soft-tissue autoencoders of ``config.base`` (same body, trained on none of this
        run's held-out sequences)."""
        base = _base_folder(config.base)
        for name in ("pose_ae", "soft_ae"):
            self.nets[name] = load_model(base / name, identity=self.identity, device=self.dev)
        source = read_config(base / "soft_ae").get("training", {}).get("source")
        if source is not None and source != self.data.source:
            raise InputError(f"base {config.base} was trained on {source}, this run's data is {self.data.source}")
        seen = set(_autoencoder_train(base))
        leaked = sorted(seen & {s.name for g in self.test.values() for s in g.sequences})
        if leaked:
            raise InputError(f"base {config.base} trained on {leaked[0]!r}, which this run holds out "
                             f"({len(leaked)} such sequences): its autoencoders would have seen the test data")

    def n_items(self, stage: str) -> int:
        return len(self.items) if stage == "regressor" else len(self.frames[0])

    def loss(self, stage: str, idx, config: SoftTissueConfig, test: bool = False) -> dict:
        if stage != "regressor":
            poses, disp = self.test_frames if test else self.frames
        if stage == "pose_ae":
            p = poses[idx]
            meshes = PoseAE.mesh_input(self.tb, p)
            return pose_ae_loss(self.nets["pose_ae"], meshes, p[:, 3:])
        if stage == "soft_ae":
            d = disp[idx]
            return reconstruction_loss(d, self.nets["soft_ae"](d), self.template, self.faces, config.lambda_norm)
        items = [self._encoded(self.test_all, int(i)) for i in idx] if test else [self.items[int(i)] for i in idx]
        gamma, betas, target, mask = pad_sequences(items, self.data.num_betas)
        return regression_loss(self.nets["regressor"](gamma, betas), target, mask)

    @torch.no_grad()
    def _encoded(self, d: SoftTissueData, i: int):
        """(gamma (T, F), codes (T, K), betas) of sequence i of d, cached."""
        key = (id(d), i)
        if key not in self._seq_cache:
            pose_ae, soft_ae = self.nets["pose_ae"].eval(), self.nets["soft_ae"].eval()
            s = d.sequences[i]
            p = torch.as_tensor(s.poses, device=self.dev)
            t = torch.as_tensor(s.trans, device=self.dev)
            gamma = motion_descriptor(pose_features(pose_ae, self.nets["regressor"].pose_input, p), p, t, s.fps)
            codes = soft_ae.encode(torch.as_tensor(s.displacements, device=self.dev))
            self._seq_cache[key] = (gamma, codes, torch.as_tensor(s.betas, device=self.dev))
        return self._seq_cache[key]

    def prepare_regressor(self, config: SoftTissueConfig, folder: Path) -> None:
        """The regressor's training items: the training sequences through the frozen encoders and, with
        motion transfer, each clip a subject lacks played by that subject's own regressor
        (:mod:`~simgen.learn.softtissue.transfer`, kept in folder/transfer/); the regressor's inputs
        standardised on them."""
        self.items = [self._encoded(self.train, i) for i in range(len(self.train.sequences))]
        if config.motion_transfer:
            extra, self.transfer = transferred_items(
                self.train, lambda i: self._encoded(self.train, i), lambda: self.new_regressor(config),
                epochs=config.reg_epochs, batch=config.reg_batch, lr=config.reg_lr, seed=config.seed,
                folder=folder / "transfer", identity=self.identity)
            self.items += extra
        gamma, betas, _, mask = pad_sequences(self.items, self.data.num_betas)
        self.nets["regressor"].set_standardisation(self.nets["regressor"].inputs(gamma, betas)[mask])

    @torch.no_grad()
    def val_loss(self, stage: str, config: SoftTissueConfig) -> float | None:
        if not self.test:
            return None
        self.nets[stage].eval()
        if stage == "regressor":
            n = len(self.test_all.sequences)
            return float(self.loss(stage, list(range(n)), config, test=True)["total"])
        n = len(self.test_frames[0])
        total = 0.0
        for i in range(0, n, 256):
            idx = torch.arange(i, min(n, i + 256), device=self.dev)
            total += float(self.loss(stage, idx, config, test=True)["total"]) * len(idx)
        return total / n


def _base_folder(base: str) -> Path:
    folder = Path(base)
    if not (folder / "soft_ae").is_dir() and (folder / SOFTTISSUE_DIR).is_dir():
        folder = folder / SOFTTISSUE_DIR
    for name in ("pose_ae", "soft_ae"):
        if not (folder / name / "config.json").is_file():
            raise InputError(f"base {base} holds no trained SoftSMPL {name}")
    return folder


def _autoencoder_train(folder: Path) -> list[str]:
    """The sequences a trained folder's autoencoders saw (its split.json; for a run on a base, the base's)."""
    split = json.loads((folder / "split.json").read_text())
    return split.get("autoencoder_train", split["train"])


def _with_base_sizes(config: SoftTissueConfig) -> SoftTissueConfig:
    """A run on a base takes the base's autoencoder sizes (whatever this config says about them)."""
    if not config.base:
        return config
    folder = _base_folder(config.base)
    pose, soft = (read_config(folder / n)["model"] for n in ("pose_ae", "soft_ae"))
    return replace(config, pose_latent=pose["latent"], pose_hidden=pose["hidden"], ae_latent=soft["latent"],
                   ae_hidden=soft["hidden"], ae_blocks=soft["blocks"], ae_dropout=soft["dropout"])


def _merge(groups: dict, like: SoftTissueData) -> SoftTissueData:
    seqs = [s for g in groups.values() for s in g.sequences]
    return SoftTissueData(seqs, like.body, like.faces, like.template, like.source)


def _reopen(prog: dict, config: SoftTissueConfig, folder: Path) -> None:
    """Resuming with more epochs: the regressor (the last stage) continues; an earlier, finished stage
    cannot (the later stages were trained on it), so that is refused. A run on a base trains only its
    regressor."""
    for i, stage in enumerate(STAGES[:prog["stage"]]):
        if config.base and stage != "regressor":   # the base's, not this run's
            continue
        done = prog["done"].get(stage, 0)
        if config.epochs(stage) > done and stage not in prog.get("closed", []):
            if i < len(STAGES) - 1:
                raise InputError(f"{folder} has finished its {stage} stage at {done} epochs and trained the later "
                                 f"stages on it; pass --restart to train it for {config.epochs(stage)}")
            prog.update(stage=i, epoch=done, step=0, sums={}, count=0)


def _save_state(folder: Path, run: _Run, optimizer, settings: dict, prog: dict) -> None:
    buf = io.BytesIO()
    opt = optimizer.state_dict() if isinstance(optimizer, torch.optim.Optimizer) else optimizer
    torch.save({"models": {k: v.state_dict() for k, v in run.nets.items()}, "optimizer": opt,
                "settings": json.dumps(settings), "progress": json.dumps(prog)}, buf)
    atomic_write_bytes(folder / STATE_FILE, buf.getvalue())


def train_softtissue(data: SoftTissueData, out: str | Path, *, body, config: SoftTissueConfig | None = None,
                     device: str = "cpu", time_budget: float | None = None, stage_budget: float | None = None,
                     resume: bool = True, progress=None,
                     checkpoint_every: float = 120.0) -> SoftTissueResult:
    """Train the three SoftSMPL stages on ``data`` into OUT/softtissue/ (module docstring).

    body: the :class:`~simgen.body.BodyModel` of the data (its hash must match ``data.body``);
    config: :class:`SoftTissueConfig`; device: "cpu", "cuda", "cuda:N"; time_budget [s]: stop at the
    first optimiser step after this long, everything saved; stage_budget [s]: a stage that has trained
    this long in this call ends at the epoch under way (its epochs reached are logged, and a rerun
    does not reopen it); the next stage starts; resume: continue from train_state.pt
    (more epochs continue a run; other settings are refused); False starts over; progress(done,
    total, info) after every step, done/total in epochs summed over the stages; checkpoint_every [s].
    """
    config = _with_base_sizes(config or SoftTissueConfig())
    config.check()
    dev = _device(device)
    run = _Run(data, config, dev, body)
    folder = Path(out) / SOFTTISSUE_DIR
    folder.mkdir(parents=True, exist_ok=True)
    fixed = {k: v for k, v in asdict(config).items() if k not in ("pose_epochs", "ae_epochs", "reg_epochs")}
    settings = {"config": fixed, "identity": run.identity, "source": data.source,
                "sequences": [s.name for s in data.sequences]}
    state = _load_state(folder, settings, resume, dev)
    prog = {"stage": 0, "epoch": 0, "step": 0, "sums": {}, "count": 0, "losses": {}, "done": {}}
    if config.base:   # the autoencoders come trained from the base folder, with the epochs it gave them
        base = _base_folder(config.base)
        trained = {n: read_config(base / n).get("training", {}) for n in ("pose_ae", "soft_ae")}
        prog.update(stage=STAGES.index("regressor"),
                    done={n: t.get("epochs", config.epochs(n)) for n, t in trained.items()},
                    closed=[n for n, t in trained.items() if t.get("closed_at_budget")])
    opt_state = None
    if state is not None:
        for k, net in run.nets.items():
            net.load_state_dict(state["models"][k])
        prog, opt_state = json.loads(state["progress"]), state["optimizer"]
        _reopen(prog, config, folder)
    elif not config.base:
        run.nets["soft_ae"].init_pca(pca_frames([s.displacements for s in run.train.sequences]))
    if state is None:   # a fresh run: subject regressors kept by an earlier one played its autoencoders' codes
        shutil.rmtree(folder / "transfer", ignore_errors=True)
    ae_train = _autoencoder_train(_base_folder(config.base)) if config.base else [s.name for s in run.train.sequences]
    split = {"test_motions": config.held_out()[0], "test_subjects": config.held_out()[1],
             "train": [s.name for s in run.train.sequences], "autoencoder_train": ae_train,
             "test": {k: [s.name for s in g.sequences] for k, g in run.test.items()}}
    atomic_write_bytes(folder / "split.json", (json.dumps(split, indent=2) + "\n").encode())
    log = _Logger(folder, _LOG_FIELDS, False)
    total_epochs = sum(config.epochs(s) for s in STAGES)
    t0 = last_save = time.monotonic()
    steps, stopped = 0, "epochs"
    optimizer = opt_state  # a state dict until a stage runs (a resumed, finished run saves it back)

    acc: dict = {}   # loss sums of the epoch under way, on the device

    def fold() -> None:
        """Move the device sums into prog (one host read)."""
        for k, v in acc.items():
            prog["sums"][k] = prog["sums"].get(k, 0.0) + float(v)
        acc.clear()

    def save(final_stage: int) -> None:
        _save_state(folder, run, optimizer, settings, prog)
        for k in STAGES[:final_stage]:
            save_model(run.nets[k], folder / k, identity=run.identity, training={
                "method": "SoftSMPL", "stage": k, "source": data.source, "split": split, "config": asdict(config),
                "fps": run.train.sequences[0].fps, "loss": prog["losses"].get(k), "epochs": prog["done"].get(k),
                "closed_at_budget": k in prog.get("closed", []),
                **({"motion_transfer": prog["transfer"]} if k == "regressor" and prog.get("transfer") else {})})

    try:
        while prog["stage"] < len(STAGES):
            stage = STAGES[prog["stage"]]
            net = run.nets[stage]
            lr = {"pose_ae": config.pose_lr, "soft_ae": config.ae_lr, "regressor": config.reg_lr}[stage]
            optimizer = torch.optim.Adam(net.param_groups(lr) if stage == "soft_ae" else net.parameters(), lr=lr)
            if opt_state is not None:
                if len(opt_state["param_groups"]) != len(optimizer.param_groups):
                    raise InputError(f"{folder}: its {stage} checkpoint is from a simgen whose autoencoder had one "
                                     "learning rate for all its layers; run again with --restart")
                optimizer.load_state_dict(opt_state)
                opt_state = None
            if stage == "regressor":
                run.prepare_regressor(config, folder)
                prog["transfer"] = run.transfer
            batch = {"pose_ae": config.pose_batch, "soft_ae": config.ae_batch, "regressor": config.reg_batch}[stage]
            n = run.n_items(stage)
            batches = (n + batch - 1) // batch
            done_before = sum(config.epochs(s) for s in STAGES[:prog["stage"]])
            stage_t0 = time.monotonic()
            while prog["epoch"] < config.epochs(stage):
                gen = torch.Generator().manual_seed(config.seed * 1_000_003 + prog["stage"] * 10_007 + prog["epoch"])
                perm = torch.randperm(n, generator=gen)
                while prog["step"] < batches:
                    net.train()
                    if stage == "regressor":
                        run.nets["pose_ae"].eval()
                        run.nets["soft_ae"].eval()
                    idx = perm[prog["step"] * batch:(prog["step"] + 1) * batch]
                    if stage != "regressor":
                        idx = idx.to(run.dev)
                    else:
                        idx = sorted(int(i) for i in idx)
                    terms = run.loss(stage, idx, config)
                    optimizer.zero_grad(set_to_none=True)
                    terms["total"].backward()
                    optimizer.step()
                    for k, v in terms.items():   # summed on the device: no host sync per step
                        acc[k] = acc.get(k, 0.0) + v.detach() * len(idx)
                    prog["count"] += len(idx)
                    prog["step"] += 1
                    steps += 1
                    if progress is not None:
                        progress(done_before + prog["epoch"] + prog["step"] / batches, total_epochs, {"stage": stage})
                    if time_budget is not None and time.monotonic() - t0 >= time_budget:
                        stopped = "time budget"
                        break
                    if time.monotonic() - last_save >= checkpoint_every:
                        fold()
                        save(prog["stage"])
                        last_save = time.monotonic()
                fold()
                if prog["step"] >= batches:
                    means = {k: v / max(prog["count"], 1) for k, v in prog["sums"].items()}
                    val = run.val_loss(stage, config)
                    prog["epoch"] += 1
                    prog["losses"][stage] = means.get("total")
                    log.row({"stage": stage, "epoch": prog["epoch"], "lr": lr, "loss": means.get("total"),
                             **{k: v for k, v in means.items() if k != "total"},
                             "val_loss": "" if val is None else val, "seconds": round(time.monotonic() - t0, 3)})
                    prog.update(step=0, sums={}, count=0)
                if stopped == "time budget":
                    break
                if stage_budget is not None and time.monotonic() - stage_t0 >= stage_budget \
                        and prog["epoch"] < config.epochs(stage):
                    prog.setdefault("closed", []).append(stage)
                    break
            if stopped == "time budget":
                break
            prog["done"][stage] = prog["epoch"]
            prog.update(stage=prog["stage"] + 1, epoch=0, step=0, sums={}, count=0)
            net.eval()
        save(prog["stage"])
    finally:
        log.close()
    stage = STAGES[min(prog["stage"], len(STAGES) - 1)]
    return SoftTissueResult(folder, stage if prog["stage"] < len(STAGES) else "done", prog["epoch"], steps,
                            time.monotonic() - t0, stopped, dict(prog["losses"]))


def check_model_identity(folder: str | Path, identity: dict) -> None:
    """Refuse a SoftSMPL folder trained for another body (one sentence naming both)."""
    check_identity(read_config(Path(folder) / "regressor"), identity, folder)
