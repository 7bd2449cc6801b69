"""The vertex-L2 GRU: SNUG's network trained on simulated data (thesis section 5.3.3, Fig. 5.6 "supervised").

The thesis retrains SNUG's network "in a per-vertex supervised manner" on the ground-truth
simulations, with the same motions and the same architecture, to show that vertex supervision
smooths the wrinkles away. Here everything but the data and the loss is SNUG's
(:mod:`simgen.learn.snug`), shared rather than copied:

- the model: :class:`~simgen.learn.snug.SnugNet` (T + S(beta) + R, R a 4 x 256 GRU stack and a
  linear layer, skinned with the garment's weights), saved the same way (OUT/snug/, kind "snug";
  config.json's ``training.method`` tells the two apart), so :func:`~simgen.learn.snug.load_snug_model`,
  ``simgen export usd --compare`` and ``simgen eval compare`` read it;
- the training loop (:func:`simgen.learn.snug._train_loop`): 3-frame windows, stride 3, each GRU
  layer's initial state drawn from N(0, 0.1) per window, batch 16, Adam 1e-3 for 10 epochs then
  1e-4, the same convergence criterion, checkpoints, resume and time budget.

What differs:

- **windows** are cut from the training sequences of a dataset store (the split of ``simgen train
  fit``: the store's "train" motions, minus held-out shapes with ``--split shape``), each with the
  body shape it was simulated with (SNUG draws a fresh shape per window and epoch);
- **loss**: the mean over vertices and frames of the squared distance between the posed prediction
  and the simulated garment, in cm^2 (log columns ``l2_cm2`` and ``error_cm``, the mean distance
  [cm]); the convergence criterion's ``min_improvement`` is then in cm^2;
- **validation**: windows of the split's validation sequences (training motions kept out of
  training, ``make_split(..., validation_motions=...)``; none: no convergence test).
"""

from __future__ import annotations

from dataclasses import asdict, replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

from simgen.errors import InputError
from simgen.learn.snug import SnugConfig, SnugPhysics, SnugResult, SnugWindows, _Run, _start

__all__ = ["GRU_L2_METHOD", "L2_TERMS", "train_gru_l2"]

#: config.json's training.method of a vertex-L2 GRU (SNUG's is "SNUG (thesis ch. 5)").
GRU_L2_METHOD = "vertex-L2 GRU (thesis Fig. 5.6, supervised)"
#: The log's loss columns: mean squared vertex distance [cm^2] (the loss) and mean distance [cm].
L2_TERMS = ("l2_cm2", "error_cm")


class _L2Run(_Run):
    """A SNUG run whose windows are a dataset's training sequences and whose loss is vertex L2."""

    method = GRU_L2_METHOD
    terms = L2_TERMS

    def __init__(self, data, split, config: SnugConfig, dev: torch.device, body):
        from simgen.garment.garment import Garment
        from simgen.learn.data import body_for_identity

        self.data, self.split = data, split
        rest = data.rest_template if data.rest_template is not None else data.template
        material = getattr(data.material, "name", None)
        garment = Garment(data.garment_name, rest, data.faces, data.skin_weights,
                          metadata={"default_material": material} if material else {})
        super().__init__(garment, None, config, dev, body_for_identity(data.identity, body))
        self.identity = {"garment": dict(data.identity.get("garment", {})),
                         "body": dict(data.identity.get("body", {}))}

    def _resolve_physics(self, config: SnugConfig, garment) -> SnugPhysics:
        """The store's own simulation parameters (recorded in config.json; the loss does not use them)."""
        from simgen.materials import get_material
        from simgen.params import GravityParams
        from simgen.physics.sources import contact_params_from

        rates = sorted({round(float(s.fps), 6) for s in self.data.sequences.values()})
        if len(rates) != 1:
            raise InputError(f"dataset {self.data.source} mixes frame rates {rates}; the GRU needs one")
        solver = dict(self.data.attrs.get("solver") or {})
        material = self.data.material if self.data.material is not None else get_material("cotton")
        return SnugPhysics(material, contact_params_from(solver.get("config", solver)), GravityParams(), "template",
                           rates[0], f"dataset {self.data.source}")

    def _windows(self, ids: list[str], config: SnugConfig, stride: int, dev) -> SnugWindows:
        """SnugWindows of dataset sequences (names: sequence ids), with ``betas`` (N, B) of each window."""
        seqs = [self.data.sequences[i] for i in ids]
        clips = [SimpleNamespace(name=s.id, poses=s.poses, trans=s.trans, num_frames=s.num_frames) for s in seqs]
        w = SnugWindows(clips, self.physics.fps, config.feature_mode, window=config.window, stride=stride,
                        device=dev)
        return self._with_betas(w)

    def _with_betas(self, w: SnugWindows) -> SnugWindows:
        seqs = self.data.sequences
        w.betas = torch.from_numpy(np.stack([seqs[n].betas[s] for n, s in zip(w.names, w.starts)])).float()
        return w

    def _load_windows(self, motions, config: SnugConfig, dev) -> None:
        train = [i for i in self.split.train_sequences if i in self.data.sequences]
        if not train:
            raise InputError(f"dataset {self.data.source} holds none of the split's training sequences")
        self.motions = sorted({self.data.sequences[i].motion for i in train})
        self.train_ids = train
        self.windows = self._windows(train, config, config.window_stride, dev)
        val = [i for i in self.split.validation if i in self.data.sequences]
        self.val = None
        if val and config.val_windows:
            self.val = self._with_betas(self._windows(val, config, config.window, dev).subset(config.val_windows))

    def plan(self, n: int, config: SnugConfig, generator: torch.Generator, windows: SnugWindows | None = None):
        """The epoch's order, the windows' own shapes (n, B), GRU initial states (n, layers, hidden)."""
        w = windows if windows is not None else self.windows
        perm = torch.randperm(n, generator=generator)
        h0 = torch.randn((n, config.layers, config.hidden), generator=generator) * config.hidden_init_std
        return perm, w.betas, h0

    def batch_loss(self, windows: SnugWindows, idx, betas, h0, config: SnugConfig) -> dict[str, torch.Tensor]:
        """Vertex L2 of windows[idx]: mean squared distance [cm^2] of the posed prediction (n, W, V, 3)
        to the simulated garment, over windows, frames and vertices."""
        from simgen.learn.garment_model import joint_transforms

        dev = windows.poses.device
        idx_d, betas, h0 = idx.to(dev), betas.to(dev), h0.to(dev)
        poses, trans, feats = windows.poses[idx_d], windows.trans[idx_d], windows.features[idx_d]
        n, w = poses.shape[:2]
        b_seq = betas[:, None].expand(n, w, -1)
        unposed, _ = self.net(b_seq, feats, h0.transpose(0, 1).contiguous())
        a = joint_transforms(self.torch_body, b_seq.reshape(n * w, -1), poses.reshape(n * w, 24, 3),
                             trans.reshape(n * w, 3))
        x = self.net.posed(unposed, a.reshape(n, w, 24, 4, 4))
        seqs = self.data.sequences
        target = torch.from_numpy(np.stack([seqs[windows.names[i]].vertices[windows.starts[i]:windows.starts[i] + w]
                                            for i in idx.tolist()])).to(dev)
        d2 = (x - target).pow(2).sum(-1)  # (n, W, V) [m^2]
        l2 = d2.mean() * 1e4
        return {"total": l2, "l2_cm2": l2.detach(), "error_cm": d2.detach().sqrt().mean() * 100.0}

    def training_facts(self) -> dict:
        return {"dataset": self.data.source, "split": self.split.by, "test_shapes": list(self.split.test_shapes),
                "train_sequences": len(self.train_ids),
                "validation_motions": sorted({self.data.sequences[i].motion for i in self.split.validation
                                             if i in self.data.sequences}),
                "loss": "mean squared vertex distance to the simulation [cm^2] (posed, no post-process)"}


def train_gru_l2(data, out: str | Path, split, *, config: SnugConfig | None = None, device: str = "cpu",
                 time_budget: float | None = None, resume: bool = True, body=None, progress=None,
                 checkpoint_every: float = 120.0) -> SnugResult:
    """Train SNUG's network with vertex L2 on a dataset's training sequences; write OUT/snug/ and OUT/split.json.

    data: :class:`~simgen.learn.data.GarmentData` (a store read by ``load_garment_data``); split:
    :class:`~simgen.learn.data.Split` (``make_split``: which sequences train, which validate);
    config: :class:`~simgen.learn.snug.SnugConfig` (network, windows, schedule; its physics and
    term switches are not used); device, time_budget [s], resume, body, progress(epochs_done,
    epochs, info), checkpoint_every [s]: as :func:`~simgen.learn.snug.train_snug`. Returns a
    :class:`~simgen.learn.snug.SnugResult` (losses in cm^2).
    """
    from simgen.learn.train import _device, write_split

    config = config or SnugConfig()
    config.check()
    # The split, not val_motions, picks the validation: config.json records how many it holds.
    config = replace(config, val_motions=len({data.sequences[i].motion for i in split.validation
                                              if i in data.sequences}))
    dev = _device(device)
    run = _L2Run(data, split, config, dev, body)  # checks data and split: nothing written yet
    out = Path(out)
    write_split(split, out)
    settings = {"method": GRU_L2_METHOD, "config": asdict(config), "split": split.to_dict(),
                "identity": run.identity}
    return _start(run, out, config, dev, resume=resume, time_budget=time_budget, progress=progress,
                  checkpoint_every=checkpoint_every, settings=settings)
