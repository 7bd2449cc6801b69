"""The work behind ``simgen eval physics`` (kept out of cli.py so the command stays a thin parser)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from simgen.errors import InputError

__all__ = ["eval_physics", "CONTACT_CHOICES"]

CONTACT_CHOICES = ("solver", "snug")


def _is_dataset(path: Path) -> bool:
    return path.is_dir() or path.suffix == ".zarr" or "://" in str(path)


def _load_sources(sources, *, split, material, body, frames, lbs, max_sequences):
    """GarmentSequence list (simulations, their LBS baselines when asked, dataset sequences)."""
    from simgen.physics.sources import load_dataset_sequences, load_simulation

    out = []  # (sequence, reference sequence for the IP comparison or None)
    for src in sources:
        path = Path(src)
        if _is_dataset(path):
            seqs = load_dataset_sequences(path, split=split, body=body, material=material, limit=max_sequences)
        elif path.suffix == ".npz":
            seqs = [load_simulation(path, body=body, material=material)]
        else:
            raise InputError(f"{path}: not a simulated sequence (.npz) or a dataset store (folder)")
        for seq in seqs:
            if frames is not None:
                seq = _first_frames(seq, frames)
            out.append((seq, None))
            if lbs:
                out.append((seq.lbs(), seq))
    return out


def _first_frames(seq, n: int):
    from dataclasses import replace

    sl = slice(0, int(n))
    b = np.asarray(seq.betas)
    return replace(seq, positions=seq.positions[sl], body_vertices=seq.body_vertices[sl], root=seq.root[sl],
                   transforms=seq.transforms[sl], betas=b[sl] if b.ndim == 2 else b)


def eval_physics(sources, *, out: Path, lbs: bool = False, split: str | None = None, material: str | None = None,
                 contact: str = "solver", normalisation: str = "frame", body="open", frames: int | None = None,
                 max_sequences: int | None = None, device: str | None = None, plot: bool = True,
                 bending_rest: str = "template", progress_factory=None, console=None) -> dict:
    """Evaluate every source, write OUT/physics.csv (per frame), OUT/physics_summary.json (means, and the
    incremental-potential comparison of each simulation with its LBS baseline when ``lbs``),
    OUT/physics.png (+ OUT/potential_<name>.png with ``lbs``). Returns the summary dict."""
    import torch

    from simgen._fileio import atomic_write_bytes
    from simgen.physics.surface_query import BodySurface
    from simgen.physics.evaluate import NORMALISATIONS, compare_potentials, evaluate_sequence, write_csv
    from simgen.physics.plot import have_matplotlib, plot_potentials, plot_terms
    from simgen.params import ContactParams

    if not sources:
        raise InputError("give at least one SOURCE (a simulated .npz or a dataset store)")
    if contact not in CONTACT_CHOICES:
        raise InputError(f"--contact must be one of {', '.join(CONTACT_CHOICES)}, got {contact!r}")
    if normalisation not in NORMALISATIONS:
        raise InputError(f"--normalisation must be one of {', '.join(NORMALISATIONS)}, got {normalisation!r}")
    if bending_rest not in ("template", "flat"):
        raise InputError(f"--bending-rest must be template or flat, got {bending_rest!r}")
    if split not in (None, "train", "test"):
        raise InputError(f"--split must be train or test, got {split!r}")
    if frames is not None and frames < 3:
        raise InputError(f"--frames must be at least 3 (inertia needs two previous frames), got {frames}")
    if max_sequences is not None and max_sequences < 1:
        raise InputError(f"--max-sequences must be at least 1, got {max_sequences}")
    if material is not None:
        from simgen.materials import get_material

        get_material(material)
    dev = torch.device("cuda" if device == "cuda" else (device or "cpu"))
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: torch sees no CUDA device")
    if isinstance(body, str):
        from simgen import body as body_pkg

        body = body_pkg.load(body)

    pairs = _load_sources(sources, split=split, material=material, body=body, frames=frames, lbs=lbs,
                          max_sequences=max_sequences)
    surfaces = {}
    reports, comparisons = [], []
    for seq, reference in pairs:
        key = id(seq.body)
        if key not in surfaces:
            surfaces[key] = BodySurface.from_body(seq.body, device=dev)
        surface = surfaces[key]
        params = ContactParams.snug() if contact == "snug" else seq.contact
        rest = seq.rest(device=dev, bending_rest=bending_rest)
        if progress_factory is not None:
            bar, update = progress_factory(f"physics: {seq.name}", seq.num_frames)
        else:
            bar, update = None, None
        with (bar if bar is not None else _nullcontext()):
            rep = evaluate_sequence(seq.positions, seq.body_vertices, rest, surface, seq.fps, contact_params=params,
                                    root=seq.root, normalisation=normalisation, name=seq.name, device=dev,
                                    meta=dict(seq.meta), progress=update)
            reports.append(rep)
            if reference is not None:
                cmp = compare_potentials(reference.positions, seq.positions, seq.body_vertices, rest, surface, seq.fps,
                                         contact_params=params, device=dev)
                comparisons.append((reference.name, seq.name, seq.fps, cmp))

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = {"csv": atomic_write_bytes(out / "physics.csv", write_csv(reports))}
    summary = {
        "normalisation": normalisation, "unit": reports[0].unit, "contact": contact, "bending_rest": bending_rest,
        "sequences": [{"name": r.name, "frames": r.num_frames, "fps": r.fps, "means": r.means(), "meta": r.meta}
                      for r in reports],
        "potential_comparisons": [
            {"reference": ref, "candidate": cand, "frames": int(len(c["frames"])),
             "reference_lower_share": c["lower_share"],
             "reference_mean": float(np.mean(c["reference"])), "candidate_mean": float(np.mean(c["candidate"]))}
            for ref, cand, _, c in comparisons],
    }
    if plot:
        if have_matplotlib():
            files["png"] = plot_terms(reports, out / "physics.png",
                                      title=f"physics terms per frame ({reports[0].unit}, contact: {contact})")
            for ref, cand, fps, c in comparisons:
                stem = "".join(ch if ch.isalnum() or ch in "_-" else "_" for ch in ref)
                files[f"potential {ref}"] = plot_potentials(c, out / f"potential_{stem}.png", fps=fps,
                                                            names=("simulated", "LBS"), title=ref)
        else:
            summary["plot"] = "skipped: matplotlib is not installed"
    summary["files"] = {k: str(v) for k, v in files.items()}
    files["json"] = atomic_write_bytes(out / "physics_summary.json",
                                       (json.dumps(summary, indent=2, default=float) + "\n").encode("utf-8"))
    summary["files"]["json"] = str(files["json"])
    if console is not None:
        _print_table(console, reports, summary)
    return summary


class _nullcontext:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def _print_table(console, reports, summary) -> None:
    from rich import box
    from rich.table import Table

    unit = reports[0].unit
    cols = ("strain", "bending", "gravity", "inertia", "collision")
    table = Table(title=f"physics terms, mean over frames [{unit} per frame]", box=box.SIMPLE_HEAD)
    table.add_column("sequence (frames)", overflow="fold", min_width=14)
    for col in cols:
        table.add_column(col, justify="right", no_wrap=True)
    table.add_column("inside %", justify="right", no_wrap=True)
    table.add_column("frames with crossings", justify="right", no_wrap=True)
    for rep in reports:
        m = rep.means()
        crossing = rep.values["crossing_edges"]
        table.add_row(f"{rep.name} ({rep.num_frames})", *(f"{m[c]:.3g}" for c in cols),
                      f"{100 * m['inside_share']:.2f}", f"{int((crossing > 0).sum())} (max {int(crossing.max())})")
    if len(reports) > 1:
        means = {k: float(np.nanmean([r.means()[k] for r in reports])) for k in (*cols, "inside_share")}
        table.add_row(f"[bold]mean of {len(reports)}[/]", *(f"{means[c]:.3g}" for c in cols),
                      f"{100 * means['inside_share']:.2f}", "")
    console.print(table)
    for c in summary["potential_comparisons"]:
        console.print(f"{c['reference']}: incremental potential of the simulated frame below the LBS frame on "
                      f"{100 * c['reference_lower_share']:.1f}% of {c['frames']} frames "
                      f"(means {c['reference_mean']:.4g} J vs {c['candidate_mean']:.4g} J)")
