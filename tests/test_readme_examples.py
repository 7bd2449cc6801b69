"""Every `simgen ...` command that README.md shows runs as written.

The commands come from the README itself, parsed here, so a command added there is tested without
touching this file (a new placeholder fails its test until resolve() gives it a value):

- the fenced bash blocks (``pip install ... && simgen demo``): every ``simgen`` part;
- the command table of "The command": each line's synopsis (before the two-space gap that starts
  its description) expanded to concrete command lines. ``[...]`` groups are optional: the bare form
  and the form with every group are both checked. ``a|b`` gives one line per alternative, and
  ``list | check [NAME|all]`` means ``list`` or ``check [NAME|all]``. ``x; dataset export ...``
  is two commands;
- inline code in the prose (`simgen dataset generate thesis-tshirt --out DIR`, ...): those with
  arguments are checked like the table's, bare names (`simgen motion list`) must name a command.

Placeholders (DIR, NAME, CLIP, ...) become real paths and names in a temporary folder with its own
SIMGEN_HOME, holding a 3-frame walk clip imported as `readme_clip`, the 1k T-shirt as an OBJ and, for
the dataset commands, the `tiny` preset's store.

Each command line is then either run for real through the entry point (``simgen.cli.main``, what
the ``simgen`` script calls), which must exit 0, or, where running it is inherently long, needs a
GPU or something this machine has not, parsed by the real argument parser only: the command's click
callback is replaced by a recorder and the command line goes through ``normalize_argv`` and click
exactly as ``simgen`` would parse it (an unknown option, a missing argument or a bad value fails).
PARSE_ONLY lists which and why; the test ids say ``run`` or ``parse``. The long ones are run for
real at tiny size elsewhere: the demo in tests/test_cli.py, training in tests/test_examples.py.
"""

from __future__ import annotations

import re
import shutil
import tomllib
from dataclasses import dataclass
from itertools import product
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"

# (command path prefix, or a word of the command line) -> why it is only parsed.
PARSE_ONLY: list[tuple[tuple[str, ...] | str, str]] = [
    (("demo",), "2.5 min of simulation on a 2-core CPU (README); run for real on 0.1 s of the 1k T-shirt in "
                "tests/test_cli.py"),
    (("body", "bake"), "needs the optional 'anny' package and rewrites the bundled body (or --out) in minutes"),
    (("garment", "build"), "writes the repository's garments/ in a source checkout, minutes per template"),
    (("train",), "thesis-sized training by default (2000 epochs); trained at tiny size in tests/test_examples.py "
                 "and tests/test_snug.py"),
    (("eval", "garment"), "needs a model trained by `simgen train fit|wrinkle` (tests/test_examples.py)"),
    (("eval", "compare"), "needs trained models (`simgen train ...`)"),
    (("eval", "compare-video"), "needs an `eval compare --no-video` output (rendered in tests/test_eval_compare.py)"),
    (("eval", "softtissue"), "needs models trained by `simgen train softtissue` (tests/test_softtissue_models.py)"),
    (("export", "softtissue"), "needs a soft-tissue store (run in tests/test_softtissue_models.py on its data)"),
    (("view",), "starts a web server that runs until stopped"),
    ("thesis-tshirt", "the thesis dataset: 340 sequences, 22 min on an H100"),
    ("cuda", "needs a CUDA GPU"),
    ("--ray", "starts a Ray cluster"),
    ("--install-completion", "writes the user's shell start-up file"),
    ("SMPL_FILE", "needs an SMPL model file, which simgen does not ship (SMPL's licence)"),
]


@dataclass(frozen=True)
class Example:
    """One README command line: where it is written, the text there, and the concrete argv."""

    source: str
    text: str
    argv: tuple[str, ...]
    problem: str | None = None  # a README line this test cannot read

    @property
    def parse_only(self) -> str | None:
        for key, reason in PARSE_ONLY:
            if isinstance(key, tuple):
                if self.command_path()[:len(key)] == key:
                    return reason
            elif any(key in word for word in self.argv):
                return reason
        return None

    def command_path(self) -> tuple[str, ...]:
        return tuple(w for w in self.argv if not w.startswith("-"))[:2]

    @property
    def id(self) -> str:
        mode = "unreadable" if self.problem else "parse" if self.parse_only else "run"
        return f"{mode}: simgen {' '.join(self.argv)}" if self.argv else f"{mode}: {self.text[:60]}"


# --------------------------------------------------------------------------------- reading the README
def fenced_blocks(text: str) -> list[tuple[str, str]]:
    """(language, body) of every fenced code block."""
    return [(m.group(1), m.group(2)) for m in re.finditer(r"^```(\w*)\n(.*?)^```", text, flags=re.S | re.M)]


def without_blocks(text: str) -> str:
    return re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)


def bash_commands(text: str) -> list[str]:
    """The `simgen ...` parts of the fenced bash blocks' lines."""
    out = []
    for lang, body in fenced_blocks(text):
        if lang not in ("bash", "sh", "shell", "console"):
            continue
        for line in body.splitlines():
            out += [part.strip() for part in re.split(r"&&|;|\|\|", line) if part.strip().startswith("simgen")]
    return out


def table_synopses(text: str) -> list[tuple[str, str | None]]:
    """(synopsis, problem) of every line of the command table (continuation lines joined to
    theirs); problem: why the line cannot be read (then the synopsis is the whole line)."""
    block = next(body for lang, body in fenced_blocks(text.split("## The command", 1)[1]) if not lang)
    entries: list[tuple[str, str | None]] = []
    for line in block.splitlines():
        if not line.strip():
            continue
        if line.startswith("simgen"):
            gap = re.search(r"\S( {2,})\S", line)
            if gap is None:
                entries.append((line, "no two-space gap between the command and its description"))
            else:
                entries.append((line[:gap.start(1)].strip(), None))
        else:  # a continuation: options of the line above, in the synopsis column
            entries[-1] = (entries[-1][0] + " " + line.strip(), entries[-1][1])
    return entries


def inline_commands(text: str) -> list[str]:
    return re.findall(r"`(simgen(?: [^`]*)?)`", without_blocks(text))


def split_alternatives(synopsis: str) -> list[str]:
    """`simgen a b; c d` -> two commands; `simgen g list | check X` -> `simgen g list`, `simgen g check X`."""
    out = []
    for k, part in enumerate(synopsis.split(";")):
        part = part.strip()
        if k and not part.startswith("simgen"):
            part = "simgen " + part
        if " | " in part:
            left, right = part.split(" | ", 1)
            out += [left, " ".join(left.split()[:-1] + [right])]
        else:
            out.append(part)
    return out


def tokens(synopsis: str) -> list[str]:
    """Words and whole [...] groups."""
    return re.findall(r"\[[^\]]*\]|\S+", synopsis)


def variants(synopsis: str) -> list[list[str]]:
    """Word lists of a synopsis: without its optional groups and with all of them, every
    alternative a|b taken once (the first alternative elsewhere)."""
    words = tokens(synopsis)
    forms = {"bare": [w for w in words if not w.startswith("[")],
             "full": [x for w in words for x in (w[1:-1].split() if w.startswith("[") else [w])]}
    out: list[list[str]] = []
    for form in forms.values():
        choices = [w.split("|") if "|" in w else [w] for w in form]
        # Every alternative of each choice, not the full product: the others stay at their first.
        runs = [[c[0] for c in choices]]
        for i, c in enumerate(choices):
            for alt in c[1:]:
                runs.append([alt if j == i else cc[0] for j, cc in enumerate(choices)])
        for run in runs:
            if run not in out:
                out.append(run)
    return out


# --------------------------------------------------------------------------------- placeholders
@dataclass
class World:
    """The files and names the placeholders stand for (see the module docstring)."""

    root: Path
    home: Path
    motion_file: Path
    obj: Path
    clip: str = "readme_clip"
    store: Path | None = None
    sequence: str | None = None

    def fresh(self, name: str) -> str:
        """A path under out/ that no command line got before (NAME, NAME1, ...; suffix kept)."""
        stem, dot, suffix = name.partition(".")
        path, k = self.root / "out" / name, 0
        while path.exists() or str(path) in self._given:
            k += 1
            path = self.root / "out" / f"{stem}{k}{dot}{suffix}"
        self._given.add(str(path))
        return str(path)

    def __post_init__(self):
        self._given: set[str] = set()


def resolve(word: str, prev: str, path: tuple[str, ...], world: World) -> str:
    """The concrete value of a README word (itself when it is no placeholder)."""
    name = word.rstrip(".") if word.endswith("...") and word != "..." else word
    if word == "...":  # the values of --betas
        return "1.5,-0.5"
    if name == "DIR":
        if prev == "--dataset" or (path[0] == "dataset" and prev != "--out") or path[:2] == ("eval", "physics"):
            return str(world.store or world.root / "store")  # no store: only parsed
        if prev in ("--model", "--models"):
            return str(world.root / "no-model")
        return world.fresh("dir")
    if name in ("FILE", "FILE.usdc", "FILE.obj", "PATH", "SOURCE", "SEQ", "SPEC", "CLIP", "M", "NAME", "N", "S",
                "ADDR", "SMPL_FILE", "COMMAND", "MP4"):
        table = {
            "FILE.obj": str(world.obj),
            "FILE.usdc": world.fresh("body.usdc"),
            "PATH": str(world.root / "no-such-simulation.npz"),
            "SOURCE": str(world.store or world.root / "store"),
            "SEQ": world.sequence or "walk__zero",
            "SPEC": "tiny",
            "CLIP": world.clip,
            "M": world.clip,
            "ADDR": "127.0.0.1:6379",
            "SMPL_FILE": str(world.root / "SMPL_FILE.npz"),
            "COMMAND": "motion list",
            "MP4": world.fresh("compare.mp4"),
        }
        if name == "FILE":
            return str(world.motion_file) if path[:2] == ("motion", "import") else world.fresh("open.npz")
        if name == "NAME":
            if prev == "--name":
                return "readme_shirt" if path[0] == "garment" else "readme_motion"
            return world.clip if prev == "--motion" else "tshirt_1k"
        if name == "N":
            return "8080" if prev == "--port" else "1000"
        if name == "S":
            return "zero" if prev == "--shape" else "1"
        return table[name]
    if re.fullmatch(r"[A-Z][A-Z0-9_.]*", name) and name not in ("SNUG",):
        raise AssertionError(f"README placeholder {word!r} has no value: add it to resolve() in {Path(__file__).name}")
    return word


def concrete(words: list[str], world: World) -> tuple[str, ...]:
    assert words[0] == "simgen", words
    words = words[1:]
    path = tuple(w for w in words if not w.startswith("-"))[:2] or ("",)
    argv: list[str] = []
    prev = ""
    for w in words:
        value = resolve(w, prev, path, world)
        argv += value.split() if w == "COMMAND" else [value]
        prev = w
    return tuple(argv)


def readme_examples(world: World | None = None) -> list[Example]:
    """Every README command line, concrete (placeholders filled from ``world``; without a world,
    stand-in paths, which is enough for the test ids)."""
    text = README.read_text()
    world = world or World(Path("readme"), Path("readme/home"), Path("readme/clip.npz"),
                           Path("readme/shirt.obj"), store=Path(STAND_IN_STORE), sequence="SEQ")
    found: list[tuple[str, str]] = [("bash block", c) for c in bash_commands(text)]
    examples = []
    for synopsis, problem in table_synopses(text):
        if problem:
            examples.append(Example("command table", synopsis, (), problem))
        else:
            found += [("command table", c) for c in split_alternatives(synopsis)]
    found += [("inline", c) for c in inline_commands(text) if len(c.split()) > 1 and not _bare_name(c)]
    for source, synopsis in found:
        for words in variants(synopsis):
            try:
                ex = Example(source, synopsis, concrete(words, world))
            except AssertionError as exc:
                ex = Example(source, synopsis, (), str(exc))
            if not any(ex.argv == e.argv and (ex.argv or ex.text == e.text) for e in examples):
                examples.append(ex)
    return examples


def _bare_name(command: str) -> bool:
    """`simgen motion list`, `simgen train fit|wrinkle`: a command named in prose, no arguments."""
    words = command.split()[1:]
    return all(re.fullmatch(r"[a-z][a-z0-9-]*(\|[a-z][a-z0-9-]*)*", w) for w in words)


# --------------------------------------------------------------------------------- running
def run_main(argv) -> tuple[int, str]:
    from simgen.cli import main

    try:
        main(list(argv))
        return 0, ""
    except SystemExit as exc:
        return (exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)), str(exc)


def parse_only(argv) -> tuple[tuple[str, ...], dict]:
    """Parse a command line as `simgen` does and return (command path, its parameters), running
    nothing: the commands' callbacks are replaced by a recorder."""
    import typer.main

    from simgen.cli import app, normalize_argv

    root = typer.main.get_command(app)  # a fresh click tree: patching it changes nothing else
    calls: list[tuple[tuple[str, ...], dict]] = []

    def patch(cmd, path):
        if getattr(cmd, "commands", None) is not None:  # a group (Typer may bring its own click)
            for name, sub in cmd.commands.items():
                patch(sub, path + (name,))
        else:
            cmd.callback = lambda **kw: calls.append((path, kw))

    patch(root, ())
    argv = list(argv)
    if "--install-completion" in argv:  # an eager option that would act while parsing
        assert any("--install-completion" in p.opts for p in root.params)
        argv.remove("--install-completion")
        if not argv:
            return (), {}
    root.main(args=normalize_argv(argv), prog_name="simgen", standalone_mode=False)
    assert len(calls) == 1, f"simgen {' '.join(argv)} ran {len(calls)} commands"
    return calls[0]


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """The temporary folder the placeholders point into, with SIMGEN_HOME, the clip and the OBJ."""
    from simgen.body import load as load_body
    from simgen.garment import load_garment
    from simgen.motion import import_motion, load_motion, save_motion, trim

    root = tmp_path_factory.mktemp("readme")
    home = root / "home"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SIMGEN_HOME", str(home))
        walk = load_motion("walk")
        short = trim(walk, 40 / walk.fps, 42.5 / walk.fps)  # 3 frames in stride
        save_motion(short, root / "clip.npz")
        import_motion(root / "clip.npz", "readme_clip", body=load_body("open"))
    shirt = load_garment("tshirt_1k")
    obj = root / "shirt.obj"
    with obj.open("w") as f:
        f.writelines(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in shirt.vertices)
        f.writelines(f"f {a} {b} {c}\n" for a, b, c in shirt.faces + 1)
    return World(root, home, root / "clip.npz", obj)


@pytest.fixture(scope="module")
def store(world):
    """The `tiny` preset's store (12 s on one CPU core)."""
    from simgen.dataset import open_dataset

    path = world.root / "store"
    code, _ = run_main(["dataset", "generate", "tiny", "--out", str(path)])
    assert code == 0
    return path, open_dataset(path).sequence_ids()[0]


STAND_IN_STORE = "readme/store"
EXAMPLES = readme_examples()


def test_the_readme_has_commands_to_check():
    assert len(EXAMPLES) > 30
    sources = {e.source for e in EXAMPLES}
    assert sources == {"bash block", "command table", "inline"}


# Measured on the shared 2-core machine, no command takes 30 s (slowest: `garment check`
# of every garment, 18 s; `dataset check`, 17 s with the tiny store's generation): none is marked slow.
@pytest.mark.parametrize("index", range(len(EXAMPLES)), ids=[e.id for e in EXAMPLES])
def test_readme_command(index, world, tmp_path, monkeypatch, capsys, request):
    stand_in = EXAMPLES[index]
    if not stand_in.parse_only and any(STAND_IN_STORE in word or word == "SEQ" for word in stand_in.argv):
        world.store, world.sequence = request.getfixturevalue("store")
    example = readme_examples(world)[index]
    assert example.problem is None, f"README {example.source}: {example.text!r}: {example.problem}"
    assert example.id.split(":")[0] == EXAMPLES[index].id.split(":")[0]
    monkeypatch.chdir(tmp_path)  # commands' default output folders land here
    home = tmp_path / "home"
    shutil.copytree(world.home, home)  # each command its own SIMGEN_HOME, with the clip
    monkeypatch.setenv("SIMGEN_HOME", str(home))
    if example.parse_only:
        parse_only(example.argv)
        return
    code, _ = run_main(example.argv)
    out = capsys.readouterr()
    assert code == 0, f"simgen {' '.join(example.argv)} (README: {example.text!r}) exited {code}:\n{out.err[-2000:]}"
    assert "Traceback" not in out.err


@pytest.mark.parametrize("command", sorted({c for c in inline_commands(README.read_text()) if _bare_name(c)}))
def test_commands_named_in_the_prose_exist(command):
    """`simgen motion list`, `simgen train fit|wrinkle`: each names a command or group."""
    import typer.main

    from simgen.cli import app

    words = command.split()[1:]
    for choice in product(*[w.split("|") for w in words]):
        cmd = typer.main.get_command(app)
        for w in choice:
            assert w in getattr(cmd, "commands", {}), f"README names `simgen {' '.join(choice)}`: no such command"
            cmd = cmd.commands[w]


def test_betas_as_words_and_comma_separated_parse_the_same():
    """The README: `--betas 1.5,-0.5` and `--betas 1.5 -0.5` are the same."""
    comma = parse_only(["body", "info", "--betas", "1.5,-0.5"])
    words = parse_only(["body", "info", "--betas", "1.5", "-0.5"])
    assert comma == words and comma[1]["betas"] == "1.5,-0.5"


def test_the_parse_only_check_catches_a_wrong_command():
    """What makes the parse-only commands a test: a wrong option or a missing argument fails."""
    import typer

    usage_error = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "UsageError")  # click's
    with pytest.raises(usage_error, match="no-such-option"):
        parse_only(["demo", "--no-such-option"])
    with pytest.raises(usage_error, match="out"):
        parse_only(["train", "fit", "--dataset", "d"])  # --out missing
    with pytest.raises(usage_error, match="number"):
        parse_only(["demo", "--seconds", "three"])
    assert parse_only(["demo", "--seconds", "3"])[0] == ("demo",)


def test_the_install_lines_name_what_exists():
    """The pip lines' extras, the scripts and files the README tells to run exist (pip itself and the
    test suite are not run here: they need the network and are this suite)."""
    text = README.read_text()
    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    for extra in re.findall(r"simgen\[(\w+)\]|\.\[(\w+)\]", text):
        name = extra[0] or extra[1]
        assert name in extras, f"README installs the extra [{name}], which pyproject.toml does not declare"
    for script in re.findall(r"python (scripts/\S+\.py)", text) + re.findall(r"`(\.ci/\S+\.sh)`", text):
        assert (REPO / script).exists(), script
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["simgen"] == "simgen.cli:main"  # the entry point these tests call


def test_synopsis_expansion():
    assert split_alternatives("simgen garment list | check [NAME|all]") == [
        "simgen garment list", "simgen garment check [NAME|all]"]
    assert split_alternatives("simgen dataset check|info DIR; dataset export DIR SEQ") == [
        "simgen dataset check|info DIR", "simgen dataset export DIR SEQ"]
    assert variants("simgen motion list [--split train|test]") == [
        ["simgen", "motion", "list"], ["simgen", "motion", "list", "--split", "train"],
        ["simgen", "motion", "list", "--split", "test"]]
    assert np.array_equal(variants("simgen train fit|wrinkle --out DIR")[1], ["simgen", "train", "wrinkle", "--out",
                                                                              "DIR"])
