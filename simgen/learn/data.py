"""Training data for the garment models: one dataset store in memory, its ground truth, its splits.

:func:`load_garment_data` reads a store (``simgen.dataset.open_dataset``) and computes the ground
truth of thesis section 4.2 with ``simgen.dataset.groundtruth``: per frame the body's skinning
transforms A(beta, theta) and the wrinkle displacements Delta_L (eq. 4.5) against the stored fit
displacements Delta_G (eq. 4.4) of the sequence's shape. :class:`GarmentData` can also be built
from arrays (tests); :func:`attach_ground_truth` then computes the same quantities in torch.

Everything is held in memory as float32 (a thesis-size T-shirt, 4.4k vertices, takes ~53 kB per
frame and field: ~1,000 frames per 100 MB for positions plus wrinkles).

Splits (:func:`make_split`):

- ``"motion"`` (the thesis): train on the sequences of the motions marked "train" in the store,
  test on the held-out motions (the motion library's test clips), all body shapes in both; the
  fit MLP sees every shape.
- ``"shape"`` (ours): additionally hold out body shapes (by default the most extreme ones, i.e.
  extrapolation beyond the training range); the fit MLP and the GRU never see them.

Either split may keep whole training motions out of training as a validation set
(``validation_motions``): their sequences at the training shapes pick the wrinkle GRU's weights and
tell it when to stop (:class:`simgen.learn.train.WrinkleConfig`), so that neither looks at the
held-out motions the model is tested on.

Sequences whose betas change over time (shape sweeps, thesis Fig. 4.6) are never trained on; they
form their own test group.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from simgen.errors import InputError

__all__ = ["SequenceData", "GarmentData", "Split", "SPLIT_MODES", "load_garment_data", "attach_ground_truth",
           "make_split", "pick_validation_motions", "stack_sequences", "SequenceBatch", "body_for_identity",
           "garment_shape_directions"]

SPLIT_MODES = ("motion", "shape")


@dataclass(eq=False)
class SequenceData:
    """One simulated sequence and its ground truth (float32 arrays).

    betas, shape (T, B); poses axis-angle [rad], shape (T, 24, 3); trans [m], shape (T, 3);
    vertices: simulated garment S_c(beta, theta) [m], shape (T, V, 3); transforms: body skinning
    transforms, shape (T, 24, 4, 4); wrinkle: Delta_L [m], shape (T, V, 3) (None when the shape has
    no fit ground truth, e.g. a shape sweep). split: "train" or "test" (the motion's split).
    """

    id: str
    motion: str
    shape_id: str | None
    split: str
    fps: float
    betas: np.ndarray
    poses: np.ndarray
    trans: np.ndarray
    vertices: np.ndarray
    transforms: np.ndarray | None = None
    wrinkle: np.ndarray | None = None

    @property
    def num_frames(self) -> int:
        return int(len(self.poses))

    @property
    def shape_sweep(self) -> bool:
        """True when the body shape changes during the sequence."""
        return bool(np.ptp(self.betas, axis=0).max() > 1e-6) if len(self.betas) > 1 else False


@dataclass(eq=False)
class GarmentData:
    """A garment's dataset in memory.

    identity: {"garment": {"name", "hash"}, "body": {"id", "hash"}}; template [m] (V, 3): T_r;
    template_smoothed [m] (V, 3): T_c; faces (F, 3); skin_weights (V, 24);
    shapes: shape id -> {"betas": (B,), "fit": Delta_G [m] (V, 3), "vertices": S_c(beta, 0) [m] (V, 3), the
    simulated rest-pose garment (optional)}; sequences: id -> SequenceData. Optional, for the physics
    terms: rest_template [m] (V, 3), the garment template the solver used as rest shape, and
    material (a :class:`simgen.sim.Material`); attrs: the store's root attributes.
    """

    identity: dict
    template: np.ndarray
    template_smoothed: np.ndarray
    faces: np.ndarray
    skin_weights: np.ndarray
    shapes: dict[str, dict]
    sequences: dict[str, SequenceData]
    source: str | None = None
    attrs: dict = field(default_factory=dict)
    rest_template: np.ndarray | None = None
    material: object | None = None

    def __post_init__(self) -> None:
        v = len(self.template_smoothed)
        if self.template.shape != (v, 3) or self.skin_weights.shape != (v, 24):
            raise InputError(f"garment data: template {self.template.shape}, smoothed template "
                             f"{self.template_smoothed.shape} and skin weights {self.skin_weights.shape} disagree")

    @property
    def num_vertices(self) -> int:
        return int(len(self.template_smoothed))

    @property
    def num_betas(self) -> int:
        for s in self.sequences.values():
            return int(s.betas.shape[1])
        for s in self.shapes.values():
            return int(len(s["betas"]))
        raise InputError("garment data has neither sequences nor shapes")

    @property
    def garment_name(self) -> str:
        return str(self.identity.get("garment", {}).get("name", "?"))

    def shape_fit(self, shape_id: str | None) -> np.ndarray | None:
        entry = self.shapes.get(shape_id) if shape_id is not None else None
        return None if entry is None else entry["fit"]


# ------------------------------------------------------------------------------------ body and shapes
def body_for_identity(identity: dict, body=None):
    """The body model a dataset or model was made with: ``body`` if given, else the bundled "open"
    body; refused (InputError) when its hash is not the recorded one."""
    from simgen.body import load

    want = identity.get("body") or {}
    model = body if body is not None else load("open")
    if want.get("hash") and model.hash != want["hash"]:
        raise InputError(f"the data was made with body {want.get('id', '?')!r} (hash {str(want['hash'])[:12]}) "
                         f"but the body given is {model.model_id!r}; pass the matching body model")
    return model


def garment_shape_directions(template, body) -> np.ndarray:
    """The body's shape blendshapes carried to garment vertices (diffused, thesis eq. 6.5).

    template [m] (V, 3) on the template body -> directions [m], shape (V, 3, B): the LBS baseline
    dresses a shaped body with T_r + directions . beta. Linear in beta, so one call with the
    identity matrix gives all directions.
    """
    from simgen.garment.skinning import shape_offsets

    nb = body.num_betas
    offsets = shape_offsets(np.asarray(template, dtype=np.float64), body, np.eye(nb))  # (B, V, 3)
    return np.ascontiguousarray(np.transpose(offsets, (1, 2, 0)), dtype=np.float32)


# ------------------------------------------------------------------------------------ store
def load_garment_data(path: str | Path, *, body=None, sequence_ids=None, max_frames: int | None = None,
                      device=None, progress=None) -> GarmentData:
    """Read a dataset store and compute its ground truth.

    path: the store (``simgen dataset generate ... --out``); body: the BodyModel it was made with
    (default: the bundled body, checked against the store's body hash); sequence_ids: only these
    sequences (default: all); max_frames: cut every sequence to its first N frames; device: None
    computes the ground truth with ``simgen.dataset.groundtruth`` (numpy, the reference), a torch
    device computes the same quantities there with :func:`attach_ground_truth` (float64; much
    faster on a GPU for large stores); progress(done, total): called after each sequence.
    """
    from simgen.dataset import groundtruth, open_dataset

    ds = open_dataset(path)
    attrs = dict(ds.attrs)
    identity = {"garment": dict(attrs.get("garment") or {}), "body": dict(attrs.get("body") or {})}
    model = body_for_identity(identity, body)
    tpl = ds.template
    skin = np.asarray(tpl["skin_weights"], dtype=np.float32)
    smoothed = np.asarray(tpl["smoothed"], dtype=np.float32)
    shapes = {}
    for sid in ds.shape_ids():
        fit = ds.fit(sid)
        shapes[sid] = {"betas": np.asarray(fit["betas"], dtype=np.float32),
                       "fit": np.asarray(fit["fit_displacement"], dtype=np.float32),
                       "vertices": np.asarray(fit["vertices"], dtype=np.float32)}
    ids = list(ds.sequence_ids()) if sequence_ids is None else list(sequence_ids)
    known = set(ds.sequence_ids())
    missing = [i for i in ids if i not in known]
    if missing:
        raise InputError(f"dataset {path} has no sequence {missing[0]!r}")
    sequences = {}
    for k, sid in enumerate(ids):
        seq = ds.sequence(sid)
        a = dict(seq.get("attrs") or {})
        cut = slice(None, max_frames)
        betas = np.asarray(seq["betas"], dtype=np.float32)[cut]
        poses = np.asarray(seq["poses"], dtype=np.float32)[cut]
        trans = np.asarray(seq["trans"], dtype=np.float32)[cut]
        verts = np.asarray(seq["garment_vertices"], dtype=np.float32)[cut]
        shape_id = a.get("shape_id")
        s = SequenceData(id=sid, motion=str(a.get("motion", sid)), shape_id=shape_id,
                         split=str(a.get("split", "train")), fps=float(a.get("fps", 30.0)), betas=betas,
                         poses=poses, trans=trans, vertices=verts)
        fit = shapes.get(shape_id, {}).get("fit") if shape_id is not None else None
        if device is None:
            transforms = groundtruth.skinning_transforms(model, betas, poses, trans)
            s.transforms = np.asarray(transforms, dtype=np.float32)
        if device is None and fit is not None and not s.shape_sweep:
            s.wrinkle = np.asarray(groundtruth.wrinkle_displacements(verts, transforms, skin, smoothed, fit),
                                   dtype=np.float32)
        sequences[sid] = s
        if progress is not None:
            progress(k + 1, len(ids))
    data = GarmentData(identity=identity, template=np.asarray(tpl["vertices"], dtype=np.float32),
                       template_smoothed=smoothed, faces=np.asarray(tpl["faces"], dtype=np.int64),
                       skin_weights=skin, shapes=shapes, sequences=sequences, source=str(path), attrs=attrs,
                       rest_template=(np.asarray(tpl["garment_template"], dtype=np.float32)
                                      if "garment_template" in tpl else None),
                       material=ds.material)
    return data if device is None else attach_ground_truth(data, model, device=device)


@torch.no_grad()
def attach_ground_truth(data: GarmentData, body, *, device="cpu") -> GarmentData:
    """Fill in transforms and wrinkle displacements of sequences that lack them (torch, float64).

    The same quantities as ``simgen.dataset.groundtruth`` (eq. 4.5: W^-1(S_c) - T_c - Delta_G),
    for data built from arrays. Returns ``data`` (modified in place).
    """
    from simgen.body.torch_lbs import TorchBody
    from simgen.learn.skinning import inverse_lbs_torch

    tb = TorchBody(body, dtype=torch.float64, device=device)
    w = torch.as_tensor(data.skin_weights, dtype=torch.float64, device=device)
    tc = torch.as_tensor(data.template_smoothed, dtype=torch.float64, device=device)
    for s in data.sequences.values():
        if s.transforms is None:
            _, _, a = tb(s.betas, s.poses, s.trans)
            s.transforms = a.cpu().numpy().astype(np.float32)
        fit = data.shape_fit(s.shape_id)
        if s.wrinkle is None and fit is not None and not s.shape_sweep:
            a = torch.as_tensor(s.transforms, dtype=torch.float64, device=device)
            rest = inverse_lbs_torch(torch.as_tensor(s.vertices, dtype=torch.float64, device=device), w, a)
            fit_t = torch.as_tensor(fit, dtype=torch.float64, device=device)
            s.wrinkle = (rest - tc - fit_t).cpu().numpy().astype(np.float32)
    return data


# ------------------------------------------------------------------------------------ splits
@dataclass
class Split:
    """Which sequences and shapes train and test.

    by: "motion" or "shape"; train_sequences; test: group name -> sequence ids, groups
    "held_out_motion", "held_out_shape", "held_out_both", "shape_sweep" (empty ones dropped);
    train_shapes / test_shapes: shape ids for the fit MLP; validation: sequence ids of training
    motions kept out of training (the validation motions at the training shapes; may be empty).
    """

    by: str
    train_sequences: list[str]
    test: dict[str, list[str]]
    train_shapes: list[str]
    test_shapes: list[str]
    validation: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        d = {"by": self.by, "train_sequences": self.train_sequences, "test": self.test,
             "train_shapes": self.train_shapes, "test_shapes": self.test_shapes}
        if self.validation:   # a split without one reads as the files written before it existed
            d["validation"] = self.validation
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "Split":
        return cls(by=d["by"], train_sequences=list(d["train_sequences"]),
                   test={k: list(v) for k, v in d["test"].items()}, train_shapes=list(d["train_shapes"]),
                   test_shapes=list(d["test_shapes"]), validation=list(d.get("validation", [])))


def extreme_shapes(data: GarmentData) -> list[str]:
    """Shape ids whose largest |beta| equals the largest over all shapes (the range's ends)."""
    if not data.shapes:
        return []
    reach = {sid: float(np.abs(s["betas"]).max()) for sid, s in data.shapes.items()}
    top = max(reach.values())
    return sorted(sid for sid, r in reach.items() if top > 0 and r >= top - 1e-6)


def make_split(data: GarmentData, by: str = "motion", *, test_shapes=None, validation_motions=None,
               require_train: bool = True) -> Split:
    """Split sequences by held-out motion (thesis) or by held-out motion and shape (ours); see the
    module docstring. test_shapes: shape ids to hold out with by="shape" (default: the extremes);
    validation_motions: training motions whose sequences go to ``Split.validation`` instead of
    training, as names, or as a number of them, taken in the order of their names' CRC-32 (a fixed
    choice that nobody made; None or 0: none); require_train: refuse a split without training
    sequences (False: data holding only the sequences to test, as ``simgen eval compare`` reads them)."""
    if by not in SPLIT_MODES:
        raise InputError(f"split {by!r} is not one of {', '.join(SPLIT_MODES)}")
    all_shapes = sorted(data.shapes)
    if by == "motion":
        held = set()
    else:
        held = set(extreme_shapes(data) if test_shapes is None else test_shapes)
        unknown = held - set(all_shapes)
        if unknown:
            raise InputError(f"held-out shape {sorted(unknown)[0]!r} is not in the dataset (shapes: "
                             f"{', '.join(all_shapes)})")
        if not held or held == set(all_shapes):
            raise InputError("a shape split needs at least one held-out shape and one training shape")
    groups: dict[str, list[str]] = {"held_out_motion": [], "held_out_shape": [], "held_out_both": [],
                                    "shape_sweep": []}
    train = []
    for sid in sorted(data.sequences):
        s = data.sequences[sid]
        if s.shape_sweep or s.shape_id not in data.shapes:
            groups["shape_sweep" if s.shape_sweep else "held_out_shape"].append(sid)
            continue
        test_motion, test_shape = s.split == "test", s.shape_id in held
        if test_motion and test_shape:
            groups["held_out_both"].append(sid)
        elif test_motion:
            groups["held_out_motion"].append(sid)
        elif test_shape:
            groups["held_out_shape"].append(sid)
        else:
            train.append(sid)
    validation = _validation(data, train, validation_motions)
    kept_out = set(validation)
    train = [sid for sid in train if sid not in kept_out]
    if not train and require_train:
        raise InputError("the split leaves no training sequence (need sequences of 'train' motions with a "
                         "training shape)")
    return Split(by=by, train_sequences=train, test={k: v for k, v in groups.items() if v},
                 train_shapes=[s for s in all_shapes if s not in held], test_shapes=sorted(held),
                 validation=validation)


def pick_validation_motions(motions, count: int) -> list[str]:
    """The ``count`` motions (names) of ``motions`` kept out of training for validation: the first in
    the order of their names' CRC-32, a fixed order that does not follow the names' alphabet or the
    library's listing (so every model trained on the same motions validates on the same ones)."""
    import zlib

    return sorted(set(motions), key=lambda m: zlib.crc32(m.encode()))[:count]


def _validation(data: GarmentData, train: list[str], motions) -> list[str]:
    """The sequences of ``train`` whose motion is a validation motion (:func:`make_split`)."""
    available = sorted({data.sequences[sid].motion for sid in train})
    if motions is None or isinstance(motions, int):
        count = int(motions or 0)
        if not 0 <= count < max(len(available), 1):
            raise InputError(f"{count} validation motions asked for, but the split has {len(available)} training "
                             f"motions and needs at least one left to train on")
        chosen = set(pick_validation_motions(available, count))
    else:
        chosen = {motions} if isinstance(motions, str) else set(motions)
        unknown = sorted(chosen - set(available))
        if unknown:
            raise InputError(f"validation motion {unknown[0]!r} is not a training motion of the dataset (training "
                             f"motions: {', '.join(available)})")
        if chosen == set(available):
            raise InputError("the validation motions are every training motion; leave at least one to train on")
    return [sid for sid in train if data.sequences[sid].motion in chosen]


# ------------------------------------------------------------------------------------ tensors
@dataclass
class SequenceBatch:
    """Sequences stacked and zero-padded to the longest (tensors on one device).

    betas (N, T, B); features (N, T, F); targets [m] (N, T, V, 3) or None; mask bool (N, T)
    (True on real frames); lengths list[int]; ids list[str].
    """

    ids: list[str]
    betas: torch.Tensor
    features: torch.Tensor
    targets: torch.Tensor | None
    mask: torch.Tensor
    lengths: list[int]


def stack_sequences(data: GarmentData, ids, *, feature_mode: str, target: str | None = "wrinkle",
                    device="cpu") -> SequenceBatch:
    """Stack sequences for training or evaluation.

    target: "wrinkle" (Delta_L, eq. 4.5), "unposed" (Delta_G + Delta_L: what the linear baselines
    regress) or None. Raises InputError when a requested target is missing (a sequence without fit
    ground truth).
    """
    from simgen.learn.features import motion_features

    ids = list(ids)
    if not ids:
        raise InputError("no sequences to stack")
    seqs = [data.sequences[i] for i in ids]
    t_max = max(s.num_frames for s in seqs)
    n, b, v = len(seqs), seqs[0].betas.shape[1], data.num_vertices
    betas = torch.zeros((n, t_max, b))
    feats = None
    targets = torch.zeros((n, t_max, v, 3)) if target is not None else None
    mask = torch.zeros((n, t_max), dtype=torch.bool)
    for i, s in enumerate(seqs):
        t = s.num_frames
        betas[i, :t] = torch.from_numpy(s.betas)
        f = motion_features(torch.from_numpy(s.poses).double(), torch.from_numpy(s.trans).double(), s.fps,
                            feature_mode).float()
        if feats is None:
            feats = torch.zeros((n, t_max, f.shape[-1]))
        feats[i, :t] = f
        mask[i, :t] = True
        if target is not None:
            if s.wrinkle is None:
                raise InputError(f"sequence {s.id!r} has no wrinkle ground truth (no fit for shape {s.shape_id!r})")
            y = s.wrinkle if target == "wrinkle" else s.wrinkle + data.shape_fit(s.shape_id)[None]
            targets[i, :t] = torch.from_numpy(np.asarray(y, dtype=np.float32))
    to = (lambda x: None if x is None else x.to(device))
    return SequenceBatch(ids=ids, betas=to(betas), features=to(feats), targets=to(targets), mask=to(mask),
                         lengths=[s.num_frames for s in seqs])
