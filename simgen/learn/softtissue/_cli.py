"""`simgen train softtissue`: the command's body, kept out of simgen/cli.py."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from simgen.errors import InputError

__all__ = ["run_train_softtissue", "run_eval_softtissue", "load_softtissue_source"]


def load_softtissue_source(data: str, body_file: str | None, *, max_frames: int | None = None, device: str = "cpu",
                           mirror: bool = True, progress=None):
    """(SoftTissueData, BodyModel) of a ``--data`` value: "synthetic" (the bundled open body and the
    synthetic test signal of :func:`~simgen.learn.softtissue.data.synthetic_softtissue_data`), a
    soft-tissue store (``simgen dataset generate softtissue``, :func:`~simgen.dataset.softtissue.read_softtissue_store`)
    or a Dyna .h5 file, read with the SMPL body file ``body_file`` (:func:`~simgen.learn.softtissue.dyna.read_dyna`)
    and, with ``mirror``, each of its sequences mirrored as in the thesis (section 3.4.1; a simulated store
    simulates its mirror images instead)."""
    from simgen.body import load
    from simgen.dataset.softtissue import is_softtissue_store, read_softtissue_store, store_body

    if data == "synthetic":
        from simgen.learn.softtissue.data import synthetic_softtissue_data

        body = load(body_file) if body_file else load("open")
        return synthetic_softtissue_data(body, frames=max_frames or 60), body
    if is_softtissue_store(data):
        body = store_body(data, body_file)
        return read_softtissue_store(data, body=body, max_frames=max_frames), body
    path = Path(data)
    if path.suffix.lower() not in (".h5", ".hdf5"):
        raise InputError(f"--data must be 'synthetic', a soft-tissue store or a Dyna .h5 file, got {data!r}")
    if not path.is_file():
        raise InputError(f"--data {data} does not exist")
    if not body_file:
        raise InputError("--data with a Dyna file needs --body SMPL_FILE (your SMPL .pkl or .npz: Dyna's meshes are "
                         "in SMPL topology)")
    from simgen.learn.softtissue.dyna import read_dyna

    body = load(body_file)
    return read_dyna(path, body, max_frames=max_frames, device=device, mirror=mirror, progress=progress), body


def run_train_softtissue(*, data: str, body: str | None, out: Path, device: str, time_budget: float | None,
                         restart: bool, max_frames: int | None, test_motions: str | None, test_subjects: str | None,
                         pose_epochs: int | None, ae_epochs: int | None, reg_epochs: int | None,
                         ae_latent: int | None, seed: int | None, pose_input: str | None = None,
                         motion_transfer: bool | None = None, base: str | None = None,
                         stage_budget: float | None = None, mirror: bool = True, echo,
                         progress_factory) -> None:
    from simgen.learn.softtissue.train import SoftTissueConfig, train_softtissue

    for flag, v in (("--time-budget", time_budget), ("--stage-budget", stage_budget)):
        if v is not None and not v > 0:
            raise InputError(f"{flag} must be positive seconds, got {v}")
    if max_frames is not None and max_frames < 1:
        raise InputError(f"--max-frames must be at least 1, got {max_frames}")
    progress, update = progress_factory(f"reading {data}", 1)
    with progress:
        dataset, model_body = load_softtissue_source(data, body, max_frames=max_frames, device=device, mirror=mirror,
                                                     progress=lambda done, total: update(done, total))
    if test_motions is None:
        # A store's own split (its spec's test_motions, else the library's test clips) by default.
        test_motions = ",".join(sorted({s.motion for s in dataset.sequences if s.meta.get("split") == "test"})) or None
    given = {"pose_epochs": pose_epochs, "ae_epochs": ae_epochs, "reg_epochs": reg_epochs, "ae_latent": ae_latent,
             "test_motions": test_motions, "test_subjects": test_subjects, "seed": seed, "pose_input": pose_input,
             "motion_transfer": motion_transfer, "base": base}
    config = replace(SoftTissueConfig(), **{k: v for k, v in given.items() if v is not None})
    config.check()
    total = config.pose_epochs + config.ae_epochs + config.reg_epochs
    progress, update = progress_factory("training SoftSMPL", max(total, 1))
    with progress:
        result = train_softtissue(dataset, out, body=model_body, config=config, device=device,
                                  time_budget=time_budget, stage_budget=stage_budget, resume=not restart,
                                  progress=lambda done, total, info: update(int(done), total))
    losses = ", ".join(f"{k} {v:.4g}" for k, v in result.losses.items() if v is not None)
    echo(f"SoftSMPL: reached {result.stage}, stopped: {result.stopped}; last training losses: {losses or '-'}")
    echo(f"model: {result.folder}")


def run_eval_softtissue(*, models: str, data: str, body: str | None, out: Path, device: str,
                        max_frames: int | None, timing_frames: int, echo, progress_factory) -> None:
    from simgen.learn.softtissue.evaluate import evaluate_softtissue

    folders = [m for part in models.replace(",", " ").split() for m in [part] if m]
    progress, update = progress_factory(f"reading {data}", 1)
    with progress:
        dataset, model_body = load_softtissue_source(data, body, max_frames=max_frames, device=device,
                                                     progress=lambda done, total: update(done, total))
    report = evaluate_softtissue(folders, dataset, out, body=model_body, device=device, timing_frames=timing_frames)
    for m in report["models"]:
        if not m["sequences"]:
            echo(f"{m['folder']}: AE {m['ae_latent']} " + ", ".join(f"{g} {v:.2f} mm" for g, v in m["ae_mm"].items())
                 + " (autoencoder only: its regressor was not trained)")
            continue
        errs = [s["error_mm"] for s in m["sequences"]]
        base = [s["no_soft_tissue_mm"] for s in m["sequences"]]
        echo(f"{m['folder']}: AE {m['ae_latent']} "
             + ", ".join(f"{g} {v:.2f} mm" for g, v in m["ae_mm"].items())
             + f"; regressor {np.mean(errs):.2f} mm (no soft tissue {np.mean(base):.2f} mm) over {len(errs)} "
               f"held-out sequences; {m['timing']['ms_per_frame']:.2f} ms per frame")
    echo(f"tables: {Path(out) / 'softtissue_eval.md'}; plot: {Path(out) / 'speed_vs_mass.png'}")
