"""The methods ``simgen eval compare`` puts side by side: model folders, LBS, and how each is labelled.

A model folder is one of

- a SNUG-type folder (``snug/``: ``simgen train snug`` or ``simgen train gru-l2``): a
  :class:`~simgen.learn.snug.SnugModel`; its config.json's ``training.method`` tells SNUG from the
  vertex-L2 GRU, ``training.config`` which loss terms a SNUG ablation left out;
- a supervised folder (``template/`` + ``fit/`` [+ ``wrinkle/``]: ``simgen train fit|wrinkle``):
  a :class:`~simgen.learn.garment_model.GarmentModel`, labelled with its folder name (thesis ch. 4).

Every prediction is the raw model output (no collision post-process: SNUG has none).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from simgen.errors import InputError

__all__ = ["Contestant", "load_contestants", "lbs_contestant", "ABLATION_TERMS", "SIMULATION", "LBS"]

#: Keys of the two rows that are not model folders.
SIMULATION, LBS = "simulation", "lbs"
#: SNUG's loss terms that ``simgen train snug --no-TERM`` leaves out (thesis Table 5.2), in the thesis's order.
ABLATION_TERMS = ("bending", "strain", "gravity", "inertia", "collision")


@dataclass(eq=False)
class Contestant:
    """One compared method.

    key: identifier-safe name (USD prims, JSON); label: the table's row name; kind: "snug",
    "gru_l2", "supervised" or "lbs"; folder: the model folder (None for LBS); model: what predicts
    (SnugModel, GarmentModel, or the LBS stepper); ablation: the SNUG loss terms left out (tuple);
    facts: the training facts of its config.json(s); logs: its log.csv files; split: the Split it
    was trained on (split.json), if any; size_mb: float32 parameters [MB]; uses_data: trained on
    simulated data.
    """

    key: str
    label: str
    kind: str
    folder: Path | None
    model: object
    ablation: tuple = ()
    facts: dict = field(default_factory=dict)
    logs: list = field(default_factory=list)
    split: object | None = None
    size_mb: float = 0.0
    uses_data: bool = False

    @torch.no_grad()
    def predict(self, betas: torch.Tensor, poses: torch.Tensor, trans: torch.Tensor, fps: float,
                transforms: torch.Tensor) -> torch.Tensor:
        """Garment [m] (T, V, 3) of one sequence: betas (T, B), poses (T, 24, 3) [rad], trans (T, 3) [m],
        transforms (T, 24, 4, 4) (the body's, for LBS), on the model's device; no post-process."""
        if self.kind == LBS:
            from simgen.learn.garment_model import lbs_baseline

            return lbs_baseline(self.model.template, betas, transforms)
        return self.model.predict(betas, poses, trans, fps, postprocess=False).raw

    def stepper(self):
        """The object :func:`simgen.learn.evaluate.time_inference` times (``to`` and ``step``)."""
        from simgen.learn.comparison.metrics import SnugStepper

        return SnugStepper(self.model) if self.kind in ("snug", "gru_l2") else self.model

    def to_dict(self) -> dict:
        return {"key": self.key, "label": self.label, "kind": self.kind,
                "folder": None if self.folder is None else str(self.folder), "ablation": list(self.ablation),
                "method": self.facts.get("method"), "size_mb": self.size_mb, "uses_data": self.uses_data}


def _slug(text: str) -> str:
    s = re.sub(r"[^A-Za-z0-9]+", "_", text).strip("_").lower()
    return s if s and not s[0].isdigit() else f"m_{s}"


def _snug_contestant(folder: Path, identity: dict, body, device) -> Contestant:
    from simgen.learn.checkpoint import model_size_mb
    from simgen.learn.garment_model import load_split
    from simgen.learn.gru_l2 import GRU_L2_METHOD
    from simgen.learn.snug import SNUG_DIR, load_snug_model

    model = load_snug_model(folder, identity=identity, body=body, device=device)
    facts = dict(model.net.saved_config.get("training") or {})
    sub = folder / SNUG_DIR if (folder / SNUG_DIR).is_dir() else folder
    if facts.get("method") == GRU_L2_METHOD:
        return Contestant("gru_l2", "vertex-L2 GRU", "gru_l2", folder, model, facts=facts, logs=[sub / "log.csv"],
                          split=load_split(folder), size_mb=model_size_mb(model.net), uses_data=True)
    config = facts.get("config") or {}
    off = tuple(t for t in ABLATION_TERMS if config.get(t) is False)
    label = "SNUG" if not off else "SNUG w/o " + ", ".join(off)
    key = "snug" if not off else "snug_no_" + "_".join(off)
    if (facts.get("physics") or {}).get("source") == "snug":  # the thesis's own loss parameters
        label, key = label + " (SNUG's physics)", key + "_snug_physics"
    return Contestant(key, label, "snug", folder, model, ablation=off, facts=facts, logs=[sub / "log.csv"],
                      size_mb=model_size_mb(model.net))


def _supervised_contestant(folder: Path, identity: dict, body, device) -> Contestant:
    from simgen.learn.checkpoint import model_size_mb, read_config
    from simgen.learn.garment_model import FIT_DIR, WRINKLE_DIR, load_garment_model, load_split

    model = load_garment_model(folder, identity=identity, body=body, device=device)
    parts = "fit + wrinkle" if model.wrinkle is not None else "fit only"
    facts = {name: read_config(folder / sub).get("training", {}) for name, sub in (("fit", FIT_DIR),
                                                                                  ("wrinkle", WRINKLE_DIR))
             if (folder / sub / "config.json").is_file()}
    size = model_size_mb(model.fit) + (model_size_mb(model.wrinkle) if model.wrinkle is not None else 0.0)
    split = load_split(folder)
    # How much data it saw is part of its name: a model of a store subset must not pass for the full one.
    seen = f", {len(split.train_sequences)} training sequences" if split is not None else ""
    return Contestant(_slug(f"supervised_{folder.name}"), f"supervised ch. 4, {parts} ({folder.name}{seen})",
                      "supervised", folder, model, facts={"method": f"ch. 4 supervised ({parts})", **facts},
                      logs=[folder / FIT_DIR / "log.csv", folder / WRINKLE_DIR / "log.csv"],
                      split=split, size_mb=size, uses_data=True)


def load_contestants(folders, identity: dict, *, body=None, device="cpu") -> list[Contestant]:
    """One :class:`Contestant` per model folder, in the order given (labels made unique with the folder name).

    identity: the dataset's garment and body; a folder trained for another garment or body, a
    missing folder or one holding no model is refused (InputError) before anything is computed.
    """
    from simgen.learn.garment_model import FIT_DIR, TEMPLATE_DIR
    from simgen.learn.snug import SNUG_DIR

    if not folders:
        raise InputError("--models needs at least one model folder")
    out = []
    for folder in (Path(f) for f in folders):
        if not folder.is_dir():
            raise InputError(f"--models {folder} is not a folder")
        if (folder / SNUG_DIR / "config.json").is_file() or ((folder / "config.json").is_file()
                                                               and (folder / "model.pt").is_file()):
            c = _snug_contestant(folder, identity, body, device)
        elif (folder / TEMPLATE_DIR).is_dir() and (folder / FIT_DIR).is_dir():
            c = _supervised_contestant(folder, identity, body, device)
        else:
            raise InputError(f"--models {folder} holds no trained model (expected {SNUG_DIR}/ from `simgen train "
                             f"snug|gru-l2` or {TEMPLATE_DIR}/ + {FIT_DIR}/ from `simgen train fit`)")
        out.append(c)
    keys = [c.key for c in out]
    labels = [c.label for c in out]
    for c in out:
        if keys.count(c.key) > 1 or c.key in (SIMULATION, LBS):
            c.key = _slug(f"{c.key}_{c.folder.name}")
        if labels.count(c.label) > 1:
            c.label = f"{c.label} [{c.folder.name}]"
    if len({c.key for c in out}) < len(out):
        raise InputError("--models names the same model folder twice")
    return out


def lbs_contestant(data, body, device="cpu") -> Contestant:
    """LBS of the dataset's relaxed template T_r, carried to the shaped body with the body's shape
    blendshapes and skinned (the ch. 4 baseline; :func:`~simgen.learn.garment_model.lbs_baseline`)."""
    from simgen.body.torch_lbs import TorchBody
    from simgen.learn.comparison.metrics import LbsStepper
    from simgen.learn.data import garment_shape_directions
    from simgen.learn.models import GarmentTemplate

    tpl = GarmentTemplate.from_arrays(data.template, data.template_smoothed, data.faces, data.skin_weights,
                                      garment_shape_directions(np.asarray(data.template), body)).to(device)
    return Contestant(LBS, "LBS", LBS, None, LbsStepper(tpl, TorchBody(body, device=device)),
                      facts={"method": "LBS of the template"})
