"""Motion transfer across subjects (thesis section 3.3.2): every subject performs every clip.

A capture gives each subject only the motions that subject performed, so a regressor learns which
dynamics go with which motion *and* which subject. The thesis enriches the data by training one
regressor per subject, R_B, on that subject's sequences only, and playing with it the poses of the
clips another subject performed: subject B then "performs" motion i of subject A. This module does
that in the soft-tissue code space of the run's frozen autoencoders: for each subject B and each clip
(motion, mirrored) of the training data that B lacks, the item (gamma of A's sequence, R_B(gamma,
beta_B), beta_B) joins the regressor's training items. The pose code of gamma is deshaped by the pose
autoencoder (section 3.3.1), which is what makes A's motion B's to play.

A simulated store (``simgen dataset generate softtissue``) already has every shape perform every
clip, so nothing is missing and nothing is transferred; Dyna's subjects each performed a subset of
the motions. The subject regressors are trained with the run's regressor settings (epochs, batch,
learning rate, seed) on the run's frozen autoencoders and kept in OUT/softtissue/transfer/<subject>/:
a resumed run uses them while those settings hold, and a fresh run (or ``--restart``) starts the
folder over.
"""

from __future__ import annotations

from pathlib import Path

import torch

from simgen.learn.checkpoint import load_model, read_config, save_model
from simgen.learn.softtissue.data import SoftTissueData, SoftTissueSequence, clip_of
from simgen.learn.softtissue.models import SoftTissueRegressor, pad_sequences, regression_loss

__all__ = ["missing_clips", "fit_regressor", "transferred_items"]


def missing_clips(data: SoftTissueData) -> dict[str, list[SoftTissueSequence]]:
    """{subject: [one sequence of each clip (motion, mirrored) the subject does not perform]}, each taken
    from the first subject in sorted order that performs it; subjects that lack nothing are left out."""
    by_clip: dict[tuple, dict[str, SoftTissueSequence]] = {}
    for s in data.sequences:
        by_clip.setdefault(clip_of(s), {}).setdefault(s.subject, s)
    out: dict[str, list[SoftTissueSequence]] = {}
    for subject in data.subjects():
        lacks = [have[min(have)] for clip, have in sorted(by_clip.items()) if subject not in have]
        if lacks:
            out[subject] = lacks
    return out


def fit_regressor(regressor: SoftTissueRegressor, items: list, *, epochs: int, batch: int, lr: float,
                  seed: int) -> float | None:
    """Train ``regressor`` on items [(gamma (T, F), codes (T, K), betas (B,))] with the loss of eq. 3.10
    (Adam, sequences shuffled per epoch with ``seed``), its input standardisation set from them first;
    returns the last epoch's mean loss (None for 0 epochs)."""
    B = regressor.num_betas
    gamma, betas, _, mask = pad_sequences(items, B)
    regressor.set_standardisation(regressor.inputs(gamma, betas)[mask])
    optimizer = torch.optim.Adam(regressor.parameters(), lr=lr)
    loss = None
    regressor.train()
    for epoch in range(epochs):
        perm = torch.randperm(len(items), generator=torch.Generator().manual_seed(seed * 1_000_003 + epoch))
        total = 0.0
        for i in range(0, len(items), batch):
            g, b, c, m = pad_sequences([items[int(j)] for j in perm[i:i + batch]], B)
            terms = regression_loss(regressor(g, b), c, m)
            optimizer.zero_grad(set_to_none=True)
            terms["total"].backward()
            optimizer.step()
            total += float(terms["total"].detach()) * len(g)
        loss = total / len(items)
    regressor.eval()
    return loss


def transferred_items(train: SoftTissueData, encoded, new_regressor, *, epochs: int, batch: int, lr: float,
                      seed: int, folder: Path, identity: dict) -> tuple[list, dict]:
    """The transferred training items of ``train`` (module docstring) and a report {subject: {"clips",
    "loss"}}. encoded(i) -> (gamma, codes, betas) of train.sequences[i] (the frozen encoders);
    new_regressor() -> an untrained :class:`SoftTissueRegressor` like the run's; folder: where the
    subject regressors are kept (a rerun loads them instead of training again)."""
    missing = missing_clips(train)
    index = {s.name: i for i, s in enumerate(train.sequences)}
    items, report = [], {}
    for subject, sources in missing.items():
        names = [s.name for s in train.sequences if s.subject == subject]
        own = [encoded(index[n]) for n in names]
        where = Path(folder) / subject
        made = {"method": "SoftSMPL motion transfer (section 3.3.2)", "subject": subject, "epochs": epochs,
                "batch": batch, "lr": lr, "seed": seed, "sequences": names}
        kept = read_config(where).get("training", {}) if (where / "config.json").is_file() else {}
        if kept and {k: kept.get(k) for k in made} == made:
            regressor, loss = load_model(where, identity=identity, device=own[0][0].device), kept.get("loss")
        else:   # none yet, or one made with other settings (more epochs on a resumed run)
            torch.manual_seed(seed)
            regressor = new_regressor()
            loss = fit_regressor(regressor, own, epochs=epochs, batch=batch, lr=lr, seed=seed)
            save_model(regressor, where, identity=identity, training={**made, "loss": loss})
        betas = own[0][2]
        with torch.no_grad():
            for src in sources:
                gamma = encoded(index[src.name])[0]
                items.append((gamma, regressor(gamma[None], betas[None])[0], betas))
        report[subject] = {"clips": [f"{m}{'_mirror' if mirrored else ''}" for m, mirrored in map(clip_of, sources)],
                           "loss": loss}
    return items, report
