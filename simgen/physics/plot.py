"""Plots of physics reports (matplotlib, Agg backend; imported only when a figure is made).

:func:`plot_terms`: one panel per term over time, one line per sequence (thesis Fig. 5.4 shows
strain, bending and inertia of SNUG vs PBNS over a test sequence). :func:`plot_potentials`: the
per-frame incremental potential of a simulated sequence and of a candidate (LBS) with the same
history, and their difference.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from simgen._fileio import temp_path_beside
from simgen.errors import InputError

__all__ = ["plot_terms", "plot_potentials", "have_matplotlib", "PANELS"]

PANELS = (("strain", "strain"), ("bending", "bending"), ("gravity", "gravity"), ("inertia", "inertia"),
          ("collision", "collision"), ("inside_share", "vertices inside the body"))
MAX_LINES = 8


def have_matplotlib() -> bool:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def _pyplot():
    try:
        import matplotlib
    except ImportError:
        raise InputError("plots need matplotlib (pip install matplotlib)") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path_beside(path)
    try:
        fig.savefig(tmp, dpi=110)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def plot_terms(reports, path, *, title: str | None = None) -> Path:
    """Per-frame terms of up to 8 :class:`~simgen.physics.evaluate.PhysicsReport` (one line each) as a PNG."""
    plt = _pyplot()
    reports = list(reports)
    if not reports:
        raise InputError("plot_terms needs at least one report")
    shown = reports[:MAX_LINES]
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5), sharex=True)
    # An LBS baseline is drawn dashed in the colour of the sequence it belongs to.
    bases = []
    for rep in shown:
        base = rep.name.removesuffix(" (LBS)")
        if base not in bases:
            bases.append(base)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, (key, label) in zip(axes.ravel(), PANELS):
        for rep in shown:
            v = np.asarray(rep.values[key], dtype=np.float64)
            t = np.arange(len(v)) / rep.fps
            lbs = rep.meta.get("kind") == "lbs" or rep.name.endswith(" (LBS)")
            colour = colours[bases.index(rep.name.removesuffix(" (LBS)")) % len(colours)]
            ax.plot(t, 100 * v if key == "inside_share" else v, lw=1.2, label=rep.name, color=colour,
                    ls="--" if lbs else "-")
        unit = "%" if key == "inside_share" else shown[0].unit
        ax.set_title(f"{label} [{unit}]", fontsize=10)
        ax.grid(alpha=0.3)
    for ax in axes[1]:
        ax.set_xlabel("time [s]")
    axes[0, 0].legend(fontsize=8, loc="best")
    head = title or "physics terms per frame"
    if len(reports) > len(shown):
        head += f" (first {len(shown)} of {len(reports)} sequences)"
    fig.suptitle(head, fontsize=11)
    fig.tight_layout()
    out = _save(fig, path)
    plt.close(fig)
    return out


def plot_potentials(comparison: dict, path, *, fps: float, names=("simulated", "LBS"),
                    title: str | None = None) -> Path:
    """The incremental potential per frame of reference and candidate (from
    :func:`~simgen.physics.evaluate.compare_potentials`) and their difference, as a PNG."""
    plt = _pyplot()
    t = np.asarray(comparison["frames"]) / fps
    ref, cand = np.asarray(comparison["reference"]), np.asarray(comparison["candidate"])
    fig, axes = plt.subplots(1, 2, figsize=(12, 4))
    axes[0].plot(t, ref, lw=1.2, label=names[0])
    axes[0].plot(t, cand, lw=1.2, label=names[1])
    axes[0].set_title("incremental potential (eq. 5.4) [J]", fontsize=10)
    axes[0].legend(fontsize=8)
    axes[1].plot(t, cand - ref, lw=1.2, color="tab:red")
    axes[1].axhline(0.0, color="k", lw=0.8)
    axes[1].set_yscale("symlog", linthresh=1e-4)
    axes[1].set_title(f"{names[1]} - {names[0]} [J]  ({names[0]} lower on "
                      f"{100 * comparison['lower_share']:.1f}% of frames)", fontsize=10)
    for ax in axes:
        ax.set_xlabel("time [s]")
        ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    out = _save(fig, path)
    plt.close(fig)
    return out
