"""The `simgen` command: help everywhere, one-sentence errors with exit code 2 and nothing written,
and the demo / export / render paths end to end on a few frames."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from simgen.cli import app, main

REPO = Path(__file__).resolve().parents[1]


def run_main(argv: list[str], capsys) -> tuple[int, str, str]:
    """Run the CLI entry point in-process; returns (exit code, stdout, stderr)."""
    try:
        main(argv)
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    out = capsys.readouterr()
    return code, out.out, out.err


def all_command_paths() -> list[list[str]]:
    """Every command and group of the typer app, as argv prefixes."""
    import typer.main

    root = typer.main.get_command(app)
    paths: list[list[str]] = []

    def walk(cmd, prefix):
        paths.append(prefix)
        for name, sub in getattr(cmd, "commands", {}).items():
            walk(sub, prefix + [name])

    walk(root, [])
    return paths


def test_help_lists_commands(capsys):
    code, out, _ = run_main(["--help"], capsys)
    assert code == 0
    for name in ("demo", "render", "body", "motion", "export"):
        assert name in out


@pytest.mark.parametrize("path", all_command_paths(), ids=lambda p: " ".join(p) or "simgen")
def test_every_command_has_help(path, capsys):
    code, out, _ = run_main(path + ["--help"], capsys)
    assert code == 0
    assert "Usage" in out


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["demo", "--betas", "1,x"], "--betas"),
        (["demo", "--betas", ",".join(["0.5"] * 11)], "11 values"),
        (["demo", "--motion", "no_such_motion"], "no_such_motion"),
        (["demo", "--body", "missing_model.pkl"], "missing_model.pkl"),
        (["demo", "--seconds", "0"], "--seconds"),
        (["demo", "--garment", "no_such_garment"], "no_such_garment"),
        (["export", "usd", "--motion", "walk", "--out", "body.txt"], "body.txt"),
        (["motion", "list", "--split", "validation"], "--split"),
        # Values as separate words end in simgen's sentence too, not in Typer's "extra argument" box.
        (["demo", "--betas", "1", "x"], "--betas"),
        (["demo", "--betas", *["0.5"] * 11], "11 values"),
    ],
)
def test_bad_input_is_one_sentence_exit_2_nothing_written(argv, needle, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    out_dir = tmp_path / "out"
    if argv[0] in ("demo",):
        argv = argv + ["--out", str(out_dir)]
    code, _, err = run_main(argv, capsys)
    assert code == 2
    assert needle in err
    assert "Traceback" not in err
    assert len([line for line in err.strip().splitlines() if line.strip()]) <= 3  # one sentence, maybe wrapped
    assert not out_dir.exists()
    assert list(tmp_path.iterdir()) == []


def test_corrupt_smpl_file_exit_2(capsys, tmp_path):
    bad = tmp_path / "SMPL_NEUTRAL.npz"
    bad.write_bytes(b"PK\x03\x04 this is not really a zip archive")
    code, _, err = run_main(["body", "info", "--body", str(bad)], capsys)
    assert code == 2
    assert "SMPL_NEUTRAL.npz" in err


def test_body_info(capsys):
    code, out, _ = run_main(["body", "info"], capsys)
    assert code == 0
    assert "13,348" in out and "pelvis" in out


def test_demo_writes_valid_usd_mp4_png(capsys, tmp_path):
    import imageio

    from simgen.io.usd import read_usd_meshes, validate_usd

    out_dir = tmp_path / "demo"
    # The 1k-triangle T-shirt for 0.1 s of the walk (4 frames) after the start protocol.
    code, out, err = run_main(["demo", "--out", str(out_dir), "--garment", "tshirt_1k", "--seconds", "0.1"], capsys)
    assert code == 0, err
    stem = out_dir / "tshirt_1k_walk"
    usd, mp4, png, npz = (stem.with_suffix(ext) for ext in (".usdc", ".mp4", ".png", ".npz"))
    for path in (usd, mp4, png, npz):
        assert str(path) in out and path.stat().st_size > 0
    assert validate_usd(usd) == []
    meshes = read_usd_meshes(usd)
    body, cloth = meshes["body"], meshes["tshirt_1k"]
    from simgen.garment import load_garment

    assert body.points.shape[:2] == (4, 13348) and cloth.points.shape[:2] == (4, load_garment("tshirt_1k").num_vertices)
    # The body starts walking and the garment moves with it.
    assert np.abs(body.points[-1] - body.points[0]).max() > 1e-3
    assert np.abs(cloth.points[-1] - cloth.points[0]).max() > 1e-3
    assert np.all(np.isfinite(cloth.points))
    assert imageio.get_reader(mp4).count_frames() == 4


def test_export_usd_with_betas_changes_the_body(capsys, tmp_path):
    from simgen.io.usd import read_usd_meshes, validate_usd

    tall, short = tmp_path / "tall.usda", tmp_path / "short.usda"
    assert run_main(["export", "usd", "--motion", "walk", "--frames", "2", "--betas", "2", "--out", str(tall)],
                    capsys)[0] == 0
    assert run_main(["export", "usd", "--motion", "walk", "--frames", "2", "--betas", "-2", "--out", str(short)],
                    capsys)[0] == 0
    assert validate_usd(tall) == [] and validate_usd(short) == []
    h_tall = np.ptp(read_usd_meshes(tall)["body"].points[0][:, 1])
    h_short = np.ptp(read_usd_meshes(short)["body"].points[0][:, 1])
    assert h_tall > h_short + 0.2  # +beta[0] is taller, ~10 cm per unit


def test_motion_list_has_library_and_split(capsys):
    import json

    code, out, _ = run_main(["motion", "list", "--json"], capsys)
    assert code == 0
    rows = json.loads(out)
    names = {r["name"] for r in rows}
    assert {"walk", "run", "jumping_jacks"} <= names
    assert sum(r["split"] == "test" for r in rows) >= 3


def test_motion_import_goes_to_simgen_home(capsys, tmp_path, monkeypatch):
    from simgen.motion import load_motion

    home = tmp_path / "home"
    monkeypatch.setenv("SIMGEN_HOME", str(home))
    bvh = REPO.parent / "shared" / "mocap" / "cmu" / "131_03.bvh"
    if not bvh.exists():
        pytest.skip("shared CMU clips not present")
    code, out, err = run_main(["motion", "import", str(bvh), "--name", "my_hop"], capsys)
    assert code == 0, err
    saved = home / "open" / "motions" / "my_hop.npz"
    assert saved.exists()
    assert load_motion("my_hop").num_frames > 30
    # A second import of the same name is refused without --overwrite.
    code, _, err = run_main(["motion", "import", str(bvh), "--name", "my_hop"], capsys)
    assert code == 2 and "my_hop" in err


@pytest.mark.slow
def test_wheel_ships_assets_and_demo_runs_from_another_folder(tmp_path):
    """`pip install .` (not editable) then `simgen demo` elsewhere: the wheel carries body and motions."""
    import zipfile

    wheel_dir = tmp_path / "wheel"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(wheel_dir), str(REPO)],
                   check=True, capture_output=True)
    wheel = next(wheel_dir.glob("simgen-*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    assert "simgen/body/data/open.npz" in names
    assert "simgen/_assets/motions/library.json" in names
    assert "simgen/_assets/motions/walk.npz" in names
    for ext in ("obj", "json", "npz"):
        assert f"simgen/_assets/garments/tshirt/tshirt.{ext}" in names

    # Install the wheel alone into a folder that shadows the checkout, and run from elsewhere.
    site = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-index", "--target", str(site),
                    str(wheel)], check=True, capture_output=True)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = dict(os.environ, PYTHONPATH=str(site), SIMGEN_HOME=str(tmp_path / "home"))
    located = subprocess.run([sys.executable, "-c", "import simgen; print(simgen.__file__)"], cwd=elsewhere,
                             env=env, capture_output=True, text=True, check=True).stdout
    assert located.startswith(str(site))  # the installed copy runs, not the checkout
    result = subprocess.run([sys.executable, "-m", "simgen.cli", "demo", "--garment", "tshirt_1k", "--seconds", "0.05",
                             "--no-video"], cwd=elsewhere, env=env, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert (elsewhere / "simgen-demo" / "tshirt_1k_walk.usdc").exists()
    listed = subprocess.run([sys.executable, "-m", "simgen.cli", "garment", "list", "--json"], cwd=elsewhere,
                            env=env, capture_output=True, text=True, check=True).stdout
    assert '"tshirt_1k"' in listed


# ------------------------------------------------------------------------------------ garments
def test_garment_list_and_check(capsys):
    import json

    code, out, _ = run_main(["garment", "list", "--json"], capsys)
    assert code == 0
    names = {r["name"] for r in json.loads(out)}
    assert {"tshirt", "tank_top", "dress", "skirt", "pants", "shorts", "tshirt_1k"} <= names
    code, out, err = run_main(["garment", "check", "tshirt_1k"], capsys)
    assert code == 0, out + err
    assert "1 of 1 garments pass" in err


def test_garment_build_variant_into_a_folder(capsys, tmp_path):
    from simgen.garment import Garment, check_garment
    from simgen.body import load

    code, out, err = run_main(["garment", "build", "shorts", "--target-triangles", "1000", "--out", str(tmp_path)],
                              capsys)
    assert code == 0, err
    garment = Garment.load(tmp_path / "shorts_1k")
    assert 800 < garment.num_triangles < 1200
    assert check_garment(garment, load("open")).passed


def test_garment_bad_inputs(capsys, tmp_path, monkeypatch):
    monkeypatch.setenv("SIMGEN_HOME", str(tmp_path / "home"))
    code, _, err = run_main(["garment", "build", "poncho"], capsys)
    assert code == 2 and "poncho" in err
    code, _, err = run_main(["garment", "preview", "no_such_garment", "--out", str(tmp_path / "p")], capsys)
    assert code == 2 and "no_such_garment" in err
    bad = tmp_path / "broken.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n")
    code, _, err = run_main(["garment", "import", str(bad), "--name", "broken"], capsys)
    assert code == 2 and "broken.obj" in err
    assert not (tmp_path / "home").exists() or not any((tmp_path / "home").rglob("*.obj"))
    assert not (tmp_path / "p").exists()


def test_garment_preview_writes_valid_usd(capsys, tmp_path):
    from simgen.io.usd import read_usd_meshes, validate_usd

    out_dir = tmp_path / "preview"
    code, out, err = run_main(["garment", "preview", "tshirt_1k", "--motion", "walk", "--frames", "3",
                               "--no-video", "--out", str(out_dir)], capsys)
    assert code == 0, err
    usd = next(out_dir.glob("*.usdc"))
    assert validate_usd(usd) == []
    tracks = read_usd_meshes(usd)
    assert len(tracks) == 2 and all(t.num_frames == 3 for t in tracks.values())


def test_simulate_writes_npz_and_valid_usd(capsys, tmp_path):
    from simgen.io.usd import read_usd_meshes, validate_usd

    out_dir = tmp_path / "sim"
    code, out, err = run_main(["simulate", "--garment", "tshirt_1k", "--motion", "walk", "--frames", "2",
                               "--substeps", "2", "--newton-iterations", "2", "--strain-limit", "0.5",
                               "--constraint-rounds", "2", "--device", "cpu", "--no-video",
                               "--out", str(out_dir)], capsys)
    assert code == 0, err
    data = np.load(out_dir / "tshirt_1k_walk.npz")
    assert data["positions"].shape[0] == 2 and np.all(np.isfinite(data["positions"]))
    usd = out_dir / "tshirt_1k_walk.usdc"
    assert validate_usd(usd) == []
    assert set(read_usd_meshes(usd)) == {"body", "tshirt_1k"}
    solver = json.loads(str(data["metadata"]))["solver"]
    assert solver["strain_limit"] == 0.5 and solver["constraint_rounds"] == 2


@pytest.mark.parametrize("flag, value", [("--strain-limit", "-1"), ("--constraint-rounds", "0"),
                                         ("--newton-iterations", "0")])
def test_simulate_bad_solver_flag_exit_2(capsys, tmp_path, flag, value):
    code, _, err = run_main(["simulate", "--garment", "tshirt_1k", "--motion", "walk", flag, value,
                             "--out", str(tmp_path / "s")], capsys)
    assert code == 2 and flag in err
    assert not (tmp_path / "s").exists()


def test_simulate_bad_material_exit_2(capsys, tmp_path):
    code, _, err = run_main(["simulate", "--garment", "tshirt_1k", "--motion", "walk", "--material", "kevlar",
                             "--out", str(tmp_path / "s")], capsys)
    assert code == 2 and "kevlar" in err
    assert not (tmp_path / "s").exists()


# ------------------------------------------------------------------------------------ CLI conventions
@pytest.mark.parametrize(
    "argv, expected",
    [
        (["body", "info", "--betas", "1", "2", "3"], ["body", "info", "--betas", "1,2,3"]),
        (["body", "info", "--betas", "1,2,3"], ["body", "info", "--betas", "1,2,3"]),
        (["body", "info", "--betas", "-1", "0.5", "--json"], ["body", "info", "--betas", "-1,0.5", "--json"]),
        (["body", "info", "--betas", "0.5", "-1e-1", "-2"], ["body", "info", "--betas", "0.5,-1e-1,-2"]),
        (["body", "info", "--betas=1", "-2"], ["body", "info", "--betas=1,-2"]),
        # A word that is not a number still joins, so parse_betas names it in one sentence.
        (["body", "info", "--betas", "1", "x"], ["body", "info", "--betas", "1,x"]),
        # Required arguments get their words back.
        (["garment", "preview", "--betas", "1", "2", "tshirt_1k", "--frames", "2"],
         ["garment", "preview", "--betas", "1,2", "tshirt_1k", "--frames", "2"]),
        (["dataset", "generate", "--motions", "walk", "run", "tiny", "--out", "d"],
         ["dataset", "generate", "--motions", "walk,run", "tiny", "--out", "d"]),
        (["dataset", "generate", "tiny", "--motions", "walk", "run", "--shapes", "zero", "b0p2", "--dry-run"],
         ["dataset", "generate", "tiny", "--motions", "walk,run", "--shapes", "zero,b0p2", "--dry-run"]),
        (["train", "fit", "--test-shapes", "a", "b", "--dataset", "d", "--out", "o"],
         ["train", "fit", "--test-shapes", "a,b", "--dataset", "d", "--out", "o"]),
        # Values of other options are not mistaken for arguments, --verbose moves to the front,
        # and command lines Typer must reject stay as they are.
        (["dataset", "generate", "--out", "d", "--motions", "walk", "tiny"],
         ["dataset", "generate", "--out", "d", "--motions", "walk", "tiny"]),
        (["demo", "--verbose", "--seconds", "1"], ["--verbose", "demo", "--seconds", "1"]),
        (["no_such_command", "--betas", "1", "2"], ["no_such_command", "--betas", "1", "2"]),
        (["--help"], ["--help"]),
    ],
)
def test_normalize_argv(argv, expected):
    from simgen.cli import normalize_argv

    assert normalize_argv(argv) == expected


@pytest.mark.parametrize("words, joined", [(["1", "2", "3"], "1,2,3"), (["-1", "0.5"], "-1,0.5")])
def test_betas_as_words_and_comma_separated_are_the_same(words, joined, capsys):
    code, spaced, err = run_main(["body", "info", "--json", "--betas", *words], capsys)
    assert code == 0, err
    code, commas, err = run_main(["body", "info", "--json", "--betas", joined], capsys)
    assert code == 0, err
    assert json.loads(spaced) == json.loads(commas)
    assert json.loads(spaced) != json.loads(run_main(["body", "info", "--json"], capsys)[1])


def test_version(capsys):
    from simgen import __version__

    code, out, _ = run_main(["--version"], capsys)
    assert code == 0 and out == f"simgen {__version__}\n"


def test_verbose_is_a_global_option(capsys):
    from simgen import _warp_log

    try:
        for argv in (["--verbose", "motion", "list", "--json"], ["motion", "list", "--json", "--verbose"]):
            code, out, err = run_main(argv, capsys)
            assert code == 0, err
            assert json.loads(out) and _warp_log.is_verbose()
        assert run_main(["motion", "list", "--json"], capsys)[0] == 0
        assert not _warp_log.is_verbose()
    finally:
        _warp_log.set_verbose(False)


def test_completion_options_exist(capsys):
    code, out, _ = run_main(["--help"], capsys)
    assert code == 0 and "--install-completion" in out and "--show-completion" in out


def _description_widths(page: str) -> list[int]:
    """Widths of the description column in a rich help page, read off the wrapped lines of each
    panel (a line whose option columns are empty and whose description continues)."""
    widths = []
    for line in page.splitlines():
        if line.startswith("│") and line.endswith("│"):
            inner = line[1:-1]
            lead = len(inner) - len(inner.lstrip())
            if inner.strip() and lead >= 8:
                widths.append(len(inner) - lead)
    return widths


def test_simulate_help_is_readable_at_80_columns():
    env = dict(os.environ, COLUMNS="80", TERMINAL_WIDTH="80")
    page = subprocess.run([sys.executable, "-m", "simgen.cli", "simulate", "--help"], env=env, capture_output=True,
                          text=True, check=True).stdout
    assert max(len(line) for line in page.splitlines()) <= 80
    assert "<bool>" not in page and "<str>" not in page and "{" not in page
    # Solver internals in their own panel, after the everyday options.
    assert "Expert options" in page and page.index("--garment") < page.index("Expert options")
    for flag in ("--substeps", "--newton-iterations", "--strain-limit", "--constraint-rounds", "--self-contact"):
        assert page.index("Expert options") < page.index(flag)
    words = " ".join(page.replace("│", " ").split())  # help texts wrap over lines
    assert "simgen motion list" in words and "simgen garment list" in words and "simgen material list" in words
    widths = _description_widths(page)
    assert widths and min(widths) >= 38, widths  # was 20 (squeezed by the option columns)


@pytest.mark.parametrize("path", all_command_paths(), ids=lambda p: " ".join(p) or "simgen")
def test_every_help_is_readable_at_80_columns(path, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "80")
    code, page, _ = run_main(path + ["--help"], capsys)
    assert code == 0
    for noise in ("<bool>", "<str>", "{"):
        assert noise not in page
    assert all(w >= 38 for w in _description_widths(page)), page


def test_every_name_option_says_which_command_lists_the_names():
    import typer.main

    listing = {"garment": "simgen garment list", "motion": "simgen motion list", "motions": "simgen motion list",
               "material": "simgen material list", "spec": "simgen dataset presets"}
    root = typer.main.get_command(app)
    checked = []

    def walk(cmd, prefix):
        for param in getattr(cmd, "params", []):
            name = "garment" if prefix[:1] == ["garment"] and param.name == "name" and prefix[1:] in (
                ["preview"], ["check"]) else param.name
            if name in listing:
                checked.append(" ".join(prefix + [param.name]))
                assert listing[name] in (param.help or ""), (prefix, param.name)
        for sub_name, sub in getattr(cmd, "commands", {}).items():
            walk(sub, prefix + [sub_name])

    walk(root, [])
    assert "simulate garment" in checked and "demo motion" in checked and "dataset generate spec" in checked


@pytest.mark.parametrize("listing", [["material", "list", "--json"], ["dataset", "presets", "--json"]])
def test_listing_commands(listing, capsys):
    code, out, err = run_main(listing, capsys)
    assert code == 0, err
    names = {row["name"] for row in json.loads(out)}
    assert {"cotton", "silk"} <= names if listing[0] == "material" else {"tiny", "thesis-tshirt"} <= names


def test_progress_writes_a_line_per_ten_percent_when_not_a_terminal():
    import io

    from simgen.cli import _note, _progress

    stream = io.StringIO()
    progress, update = _progress("simulating", 20, stream=stream)
    with progress:
        _note(progress, "compiling kernels")
        for done in range(1, 21):
            update(done)
    lines = stream.getvalue().splitlines()
    assert lines[0] == "compiling kernels"
    assert [line.split(": ")[1].split(" ")[0] for line in lines[1:]] == [f"{p}%" for p in range(10, 101, 10)]
    assert all(line.startswith("simulating: ") for line in lines[1:])
    # A total given with the update counts; a terminal gets rich's bar instead.
    stream = io.StringIO()
    progress, update = _progress("rendering", 1, stream=stream)
    update(3, 4)
    assert stream.getvalue().startswith("rendering: 70% (3/4")

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    from rich.progress import Progress

    assert isinstance(_progress("x", 3, stream=Terminal())[0], Progress)


_FAKE_WARP_INIT = """
import os, warp
def fake_init():
    os.write(2, b"Warp CUDA warning: Could not find or load the NVIDIA CUDA driver.\\n")
    os.write(2, b"Warp CUDA error: something real\\n")
warp.init = fake_init
from simgen._warp_log import init_warp, set_verbose
set_verbose({verbose})
init_warp({device!r})
"""


@pytest.mark.parametrize("device, verbose, shown", [("cpu", False, False), (None, False, False),
                                                    ("cuda", False, True), ("cpu", True, True)])
def test_init_warp_drops_only_the_cuda_driver_warning(device, verbose, shown):
    code = _FAKE_WARP_INIT.format(device=device, verbose=verbose)
    err = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stderr
    assert "something real" in err
    assert ("Could not find or load the NVIDIA CUDA driver" in err) == shown


def test_init_warp_is_quiet():
    """The real Warp: no banner on stdout, no CUDA driver warning on stderr."""
    result = subprocess.run([sys.executable, "-c", "from simgen._warp_log import init_warp; init_warp('cpu')"],
                            capture_output=True, text=True, check=True)
    assert "Warp" not in result.stdout
    assert "NVIDIA CUDA driver" not in result.stderr


def test_library_calls_that_start_warp_are_quiet():
    """A script that uses the library without the CLI (make_motion_library's workers query the body's
    surface) gets no Warp banner on stdout: the library starts Warp through init_warp."""
    code = ("from simgen.body import load\nfrom simgen.body.surface import SurfaceMesh\n"
            "b = load('open')\nSurfaceMesh(b.v_template, b.faces)\nprint('END')\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout == "END\n"
    assert "NVIDIA CUDA driver" not in result.stderr


def test_compile_notice_only_when_warp_compiles(tmp_path):
    script = tmp_path / "tiny_kernel.py"
    script.write_text(
        "import warp as wp\n"
        "from simgen._warp_log import compile_notice, init_warp\n"
        "init_warp('cpu')\n"
        "@wp.kernel\n"
        "def double(a: wp.array(dtype=float)):\n"
        "    i = wp.tid()\n"
        "    a[i] = 2.0 * a[i]\n"
        "with compile_notice(lambda: print('NOTICE', flush=True)):\n"
        "    wp.launch(double, dim=3, inputs=[wp.ones(3, dtype=float, device='cpu')], device='cpu')\n"
        "    wp.launch(double, dim=3, inputs=[wp.ones(3, dtype=float, device='cpu')], device='cpu')\n")
    env = dict(os.environ, WARP_CACHE_PATH=str(tmp_path / "cache"))
    first = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, check=True).stdout
    again = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, check=True).stdout
    assert first.count("NOTICE") == 1  # once, though the module loads on both launches
    assert "NOTICE" not in again  # cached


def test_the_plain_dataset_entry_takes_names_as_words_or_comma_separated(capsys):
    # `python -m simgen.dataset` (argparse, for the device machine) plans the same subset either way.
    from simgen.dataset._cli import main as plain_main

    plans = []
    for extra in (["--motions", "walk", "run", "--shapes", "zero", "b1p2"],
                  ["--motions", "walk,run", "--shapes", "zero,b1p2"]):
        assert plain_main(["generate", "tiny", "--dry-run", *extra]) == 0
        plans.append(capsys.readouterr().out)
    assert plans[0] == plans[1] and json.loads(plans[0])[0]["motions"] == 2
    assert plain_main(["generate", "tiny", "--dry-run", "--motions", "no_such_clip"]) == 2
