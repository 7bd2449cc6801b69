"""Dataset specs: a TOML file (or a bundled preset name) that says what to simulate and how.

A spec names the garment(s), the material, the body model, the shapes (an explicit list or a
generator), the motions (library names or glob patterns, and globs of AMASS/BVH/simgen .npz files),
the train/test split, the solver settings, the start protocol's frame counts, the smoothing of the
ground truth and where the store goes. Every field is validated when the spec is read; a bad one
raises :class:`simgen.errors.InputError` with one sentence naming the file and the field
("spec tiny.toml: field 'solver.substeps' must be an integer >= 1, got '10'").

Layout (every table and field optional except ``garment.names``)::

    name = "thesis-tshirt"                   # default: the file stem
    description = "..."

    [garment]
    names = ["tshirt"]                        # one store per garment
    material = "interlock"                    # preset name; default: each garment's default material
    material_overrides = { area_density = 0.2 }

    [body]
    model = "open"                            # or a path to an SMPL model file (relative to the spec)

    [shapes]
    generator = "axes"                        # "axes" | "list"
    components = 4                            # axes: the first N shape components ...
    values = [-2.0, -1.0, 1.0, 2.0]           # ... each set to these values, the others 0
    include_zero = true                       # axes: add the all-zero shape
    list = [{ id = "zero", betas = [] }]      # list: explicit shapes (id: letters, digits, _ . -)

    [motions]
    library = ["*"]                           # library clip names or glob patterns over them
    files = []                                # globs of motion files, relative to the spec file
    test = []                                 # clips put in the test split besides the library's
    train = []                                # library clips moved into the train split
    start_frame = 0                           # first frame used of every clip
    max_frames = 0                            # frames kept per clip (0: all)

    [solver]
    device = "auto"                           # "auto" | "cpu" | "cuda" | "cuda:N"
    fps = 30.0                                # output frames per second (clips are resampled to it)
    substeps = 10                             # solver steps per frame (SimulationConfig.substeps)
    cg_iterations = 50                        # e.g.: any other simgen.sim.SolverConfig field, with its
    strain_limit = 0.5                        # name, bounds and default (solver_settings(); SolverConfig's
                                              # docstring lists them; TOML has no None: unset is the default)
    friction = true                           # false: no cloth-body friction (or a [solver.friction] table)
    self_contact = false                      # true: cloth-cloth repulsion (or a [solver.self_contact] table)

    [solver.contact]                          # e.g.: a parameter class of SolverConfig (contact, gravity,
    stiffness = 1.0e5                         # friction, self_contact) as a table of its fields (simgen.params)

    [protocol]                                # thesis section 4.3.1 (see simgen.sim.driver)
    relax_frames = 15                         # these three: simgen.sim.SimulationConfig's fields
    ramp_frames = 30
    rest_frames = 15
    store_rest_frames = true                  # keep the rest-phase frames of every sequence and fit

    [smoothing]                               # the operator rho of eq. 4.4 (simgen.dataset.groundtruth)
    method = "taubin"                         # "taubin" | "laplacian" | "none"
    iterations = 10
    lambda = 0.5
    mu = -0.53
    boundary = "boundary"                     # "boundary" (along the loops) | "free" | "fixed"

    [execution]
    batch_size = 0                            # slots of the simulation pool (jobs simulated at once);
                                              # 0: from the GPU's free memory, at most 128 (4 on a CPU)
    max_attempts = 3                          # tries per job; each retry halves the substep
    chunk_frames = 32                         # frames per Zarr chunk
    overlap_writes = true                     # write each finished job in the background while the pool steps
    retry_strain_outliers = true              # a sequence with a triangle past the check's strain limit is
                                              # simulated again with the substep halved (max_attempts)
    retry_depth_outliers = true               # the same for a cloth vertex past the check's depth limit

    [output]
    path = "datasets/thesis-tshirt"           # default of --out (relative to the working folder)
"""

from __future__ import annotations

import copy
import difflib
import fnmatch
import functools
import glob
import hashlib
import json
import math
import re
import tomllib
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

from simgen.errors import InputError
from simgen.settings import Setting, settings_of

__all__ = [
    "DatasetSpec", "ShapeSpec", "MotionEntry", "load_spec", "parse_spec", "list_presets", "preset_path",
    "PRESETS_DIR", "ID_PATTERN", "solver_settings", "simulation_settings",
]

PRESETS_DIR = Path(__file__).resolve().parent / "presets"
ID_PATTERN = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")

# The [solver] keys that are the spec's own (not SolverConfig's or SimulationConfig's).
_SPEC_SOLVER = ("device", "fps")
# SimulationConfig fields a spec sets, by table (name, bounds and default from their declarations).
_SIMULATION_FIELDS = {"solver": ("substeps",), "protocol": ("relax_frames", "ramp_frames", "rest_frames")}


def _declared(name: str):
    """The default of a DatasetSpec field that a config declares: SimulationConfig's substeps and
    protocol frames; whether SolverConfig's friction / self_contact is on by default."""
    if name in ("friction", "self_contact"):
        return solver_settings()[name].default is not None
    return simulation_settings()[name].default


@functools.cache
def solver_settings() -> dict[str, Setting]:
    """The [solver] keys that set :class:`simgen.sim.SolverConfig` fields: every field, with the
    declaration's type, bounds and default. A nested parameter class (contact, gravity, friction,
    self_contact) is the sub-table [solver.NAME] of its own fields; an optional one (friction,
    self_contact) may instead be true or false, kept in the DatasetSpec field of that name.
    """
    from simgen.sim.config import SolverConfig

    return dict(settings_of(SolverConfig))


@functools.cache
def simulation_settings() -> dict[str, Setting]:
    """The :class:`simgen.sim.SimulationConfig` fields a spec sets ([solver] substeps, [protocol] frames)."""
    from simgen.sim.config import SimulationConfig

    every = settings_of(SimulationConfig)
    return {k: every[k] for keys in _SIMULATION_FIELDS.values() for k in keys}


def _switches() -> tuple[str, ...]:
    """SolverConfig's optional parameter classes (friction, self_contact): on/off DatasetSpec fields."""
    return tuple(k for k, s in solver_settings().items() if s.nested and s.optional)


def _flat_key(table: str, key: str) -> str:
    """The one-level name of a sub-table field in the content key (contact.stiffness -> contact_stiffness,
    the name the field had when specs were flat: the stores made then keep their key)."""
    return f"{table}_{key}"


_TOP = ("name", "description", "garment", "body", "shapes", "motions", "solver", "protocol", "smoothing",
        "execution", "output")
_SECTIONS = {
    "garment": ("names", "material", "material_overrides"),
    "body": ("model",),
    "shapes": ("generator", "components", "values", "include_zero", "list"),
    "motions": ("library", "files", "test", "train", "start_frame", "max_frames"),
    "solver": _SPEC_SOLVER + _SIMULATION_FIELDS["solver"],          # + solver_settings()
    "protocol": _SIMULATION_FIELDS["protocol"] + ("store_rest_frames",),
    "smoothing": ("method", "iterations", "lambda", "mu", "boundary"),
    "execution": ("batch_size", "max_attempts", "chunk_frames", "overlap_writes", "retry_strain_outliers",
                  "retry_depth_outliers"),
    "output": ("path",),
}


@dataclass(frozen=True)
class ShapeSpec:
    """One body shape: id (letters, digits, _ . -) and betas (B',), missing components zero."""

    id: str
    betas: tuple[float, ...]


@dataclass(frozen=True)
class MotionEntry:
    """One motion of the plan: id (the clip name), source ("library" or a file path), split."""

    id: str
    source: str
    split: str


@dataclass
class DatasetSpec:
    """A validated dataset spec (see the module doc for the TOML layout and defaults).

    ``source`` is the file it came from (or "<dict>"); relative paths in it resolve against
    ``base_dir``. :meth:`to_dict` gives the normalised spec stored in the dataset's root attrs.
    """

    name: str
    garments: list[str]
    description: str = ""
    material: str | None = None
    material_overrides: dict = field(default_factory=dict)
    body: str = "open"
    shapes_generator: str = "axes"
    shape_components: int = 4
    shape_values: tuple[float, ...] = (-2.0, -1.0, 1.0, 2.0)
    include_zero: bool = True
    shape_list: tuple[ShapeSpec, ...] = ()
    motion_library: tuple[str, ...] = ("*",)
    motion_files: tuple[str, ...] = ()
    test_motions: tuple[str, ...] = ()
    train_motions: tuple[str, ...] = ()
    start_frame: int = 0
    max_frames: int = 0
    device: str = "auto"
    fps: float = 30.0
    # Defaults from the declarations of SimulationConfig (substeps, the protocol's frames) and
    # SolverConfig (friction, self_contact: on unless its default is None).
    substeps: int = field(default_factory=lambda: _declared("substeps"))
    friction: bool = field(default_factory=lambda: _declared("friction"))
    self_contact: bool = field(default_factory=lambda: _declared("self_contact"))
    solver: dict = field(default_factory=dict)     # the SolverConfig fields set; a sub-table as a dict
    relax_frames: int = field(default_factory=lambda: _declared("relax_frames"))
    ramp_frames: int = field(default_factory=lambda: _declared("ramp_frames"))
    rest_frames: int = field(default_factory=lambda: _declared("rest_frames"))
    store_rest_frames: bool = True
    smoothing: dict = field(default_factory=lambda: {"method": "taubin", "iterations": 10, "lambda": 0.5,
                                                     "mu": -0.53, "boundary": "boundary"})
    batch_size: int = 0
    max_attempts: int = 3
    chunk_frames: int = 32
    overlap_writes: bool = True
    retry_strain_outliers: bool = True
    retry_depth_outliers: bool = True
    output: str | None = None
    source: str = "<dict>"
    base_dir: str = "."

    # ------------------------------------------------------------------ derived
    def shapes(self) -> list[ShapeSpec]:
        """The shapes of the plan, in order (axes: zero first, then component by component)."""
        if self.shapes_generator == "list":
            return list(self.shape_list)
        out = [ShapeSpec("zero", ())] if self.include_zero else []
        for c in range(self.shape_components):
            for v in self.shape_values:
                betas = [0.0] * c + [float(v)]
                out.append(ShapeSpec(f"b{c}{'m' if v < 0 else 'p'}{_num(abs(v))}", tuple(betas)))
        return out

    def motions(self) -> list[MotionEntry]:
        """The motions of the plan: library clips matching ``motion_library`` then the files of
        ``motion_files`` (sorted), each with its split. Raises InputError for unknown names,
        patterns that match nothing, missing files and duplicate clip names."""
        from simgen.motion.library import library_index, list_motions

        where = f"spec {self.source}"
        index = library_index()
        available = {r["name"]: r for r in list_motions()}
        names: list[str] = []
        for pattern in self.motion_library:
            if any(ch in pattern for ch in "*?["):
                hits = sorted(n for n in available if fnmatch.fnmatchcase(n, pattern))
                if not hits:
                    raise InputError(f"{where}: field 'motions.library' pattern {pattern!r} matches no library motion")
            else:
                if pattern not in available:
                    close = difflib.get_close_matches(pattern, list(available), n=3, cutoff=0.5)
                    hint = f" (close: {', '.join(close)})" if close else ""
                    raise InputError(f"{where}: field 'motions.library' names unknown motion {pattern!r}{hint}")
                hits = [pattern]
            names += [h for h in hits if h not in names]
        entries: list[MotionEntry] = []
        for n in names:
            split = index.get(n, {}).get("split") or available[n].get("split") or "train"
            entries.append(MotionEntry(n, "library", split))
        seen = {e.id for e in entries}
        base = Path(self.base_dir)
        for pattern in self.motion_files:
            p = Path(pattern).expanduser()
            full = p if p.is_absolute() else base / p
            hits = sorted(glob.glob(str(full), recursive=True))
            if not hits:
                kind = "pattern" if any(ch in pattern for ch in "*?[") else "file"
                raise InputError(f"{where}: field 'motions.files' {kind} {pattern!r} matches no file "
                                 f"(looked for {full})")
            for h in hits:
                stem = re.sub(r"[^A-Za-z0-9_-]", "_", Path(h).stem)
                if stem in seen:
                    raise InputError(f"{where}: field 'motions.files': clip name {stem!r} (from {h}) is used twice")
                seen.add(stem)
                entries.append(MotionEntry(stem, str(Path(h).resolve()), "train"))
        ids = {e.id for e in entries}
        for label, names_, split in (("test", self.test_motions, "test"), ("train", self.train_motions, "train")):
            for n in names_:
                if n not in ids:
                    raise InputError(f"{where}: field 'motions.{label}' names {n!r}, which is not among the "
                                     f"spec's motions")
            entries = [MotionEntry(e.id, e.source, split) if e.id in names_ else e for e in entries]
        if not entries:
            raise InputError(f"{where}: the spec selects no motion (fields 'motions.library' and 'motions.files')")
        return entries

    def solver_config(self, *, substeps_factor: int = 1):
        """The :class:`simgen.sim.SimulationConfig` of every job (substeps multiplied on a retry)."""
        from simgen.sim import SimulationConfig

        return SimulationConfig(
            fps=self.fps, substeps=self.substeps * substeps_factor, solver=self.solver_options(),
            material=self.material, material_overrides=dict(self.material_overrides), relax_frames=self.relax_frames,
            ramp_frames=self.ramp_frames, rest_frames=self.rest_frames, device=self.resolved_device())

    def solver_options(self):
        """The :class:`simgen.sim.SolverConfig` of the spec: its [solver] fields and sub-tables over the
        declared defaults; friction / self_contact off (None) or on (the sub-table's fields, else the
        class's defaults)."""
        from simgen.sim.config import SolverConfig

        settings = solver_settings()
        kwargs = {k: settings[k].nested(**v) if settings[k].nested else v for k, v in self.solver.items()}
        for key in _switches():
            if not getattr(self, key):
                kwargs[key] = None
            elif key not in kwargs and settings[key].default is None:
                kwargs[key] = settings[key].nested()
        return SolverConfig(**kwargs)

    def resolved_device(self) -> str:
        """The Warp device: "auto" becomes cuda:0 when a CUDA device exists, else cpu."""
        if self.device != "auto":
            return "cuda:0" if self.device == "cuda" else self.device
        import warp as wp

        from simgen._warp_log import init_warp

        init_warp()
        return "cuda:0" if wp.get_cuda_device_count() > 0 else "cpu"

    def smoothing_params(self):
        """The :class:`simgen.dataset.groundtruth.SmoothingParams` of the spec."""
        from simgen.dataset.groundtruth import SmoothingParams

        s = self.smoothing
        return SmoothingParams(method=s["method"], iterations=s["iterations"], lam=s["lambda"], mu=s["mu"],
                               boundary=s.get("boundary", "boundary"))

    def protocol_frames(self) -> int:
        """Frames simulated before the first output frame of every job (relax + ramp + rest)."""
        return self.relax_frames + self.ramp_frames + self.rest_frames

    def output_path(self, garment: str, out: str | None = None) -> str:
        """Where the store of ``garment`` goes: OUT (or the spec's output.path, or datasets/NAME),
        with one sub-folder per garment when the spec names several."""
        root = out if out is not None else (self.output or f"datasets/{self.name}")
        if len(self.garments) == 1:
            return root
        return root.rstrip("/") + "/" + garment

    def to_dict(self) -> dict:
        """The normalised spec as plain JSON types (stored in the root attrs of every store)."""
        d = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "shape_list":
                v = [{"id": s.id, "betas": list(s.betas)} for s in v]
            elif isinstance(v, tuple):
                v = list(v)
            d[f.name] = copy.deepcopy(v)
        d["shapes"] = [{"id": s.id, "betas": list(s.betas)} for s in self.shapes()]
        return d

    def content_key(self, garment: str) -> dict:
        """The fields that decide what is stored for ``garment`` (a store made with a different key
        cannot be resumed): garment, material, fps, solver, protocol, smoothing and frame range (the
        body enters by its hash, see :func:`simgen.dataset.generate.root_attrs`, so a moved model file
        still resumes). Shapes and motions may grow between runs; execution settings are free."""
        solver = {}
        for key, value in self.solver.items():
            if isinstance(value, dict):   # a sub-table: one level, as when specs were flat
                solver.update({_flat_key(key, k): v for k, v in value.items()})
            else:
                solver[key] = value
        return {
            "garment": garment, "material": self.material, "material_overrides": self.material_overrides,
            "fps": self.fps, "substeps": self.substeps, "friction": self.friction,
            "solver": solver, "relax_frames": self.relax_frames, "ramp_frames": self.ramp_frames,
            "rest_frames": self.rest_frames, "store_rest_frames": self.store_rest_frames,
            "smoothing": self.smoothing, "start_frame": self.start_frame, "max_frames": self.max_frames,
            # The floor came with the waistbands: stores simulated without it cannot be resumed.
            "floor": self.solver.get("floor", solver_settings()["floor"].default),
            # Only when on, so stores made before the option existed keep their key.
            **({"self_contact": True} if self.self_contact else {}),
        }

    def content_hash(self, garment: str) -> str:
        return hashlib.sha256(json.dumps(self.content_key(garment), sort_keys=True).encode()).hexdigest()

    def with_overrides(self, **overrides) -> DatasetSpec:
        """A copy with CLI overrides applied and validated (None values are ignored).

        Keys: device, batch_size, substeps, max_frames, motions (list of library names/patterns),
        shapes (list of shape ids to keep), material, output, overlap_writes, retry_strain_outliers,
        retry_depth_outliers.
        """
        d = copy.copy(self)
        d.solver = copy.deepcopy(self.solver)
        for key, value in overrides.items():
            if value is None:
                continue
            if key == "motions":
                d.motion_library = tuple(value)
                d.motion_files = ()
                d.test_motions = tuple(m for m in self.test_motions if m in value)
                d.train_motions = tuple(m for m in self.train_motions if m in value)
            elif key == "shapes":
                known = {s.id: s for s in self.shapes()}
                bad = [s for s in value if s not in known]
                if bad:
                    raise InputError(f"--shapes: unknown shape id {bad[0]!r}; the spec's shapes are "
                                     f"{', '.join(known)}")
                d.shapes_generator = "list"
                d.shape_list = tuple(known[s] for s in value)
            elif key in ("device", "batch_size", "substeps", "max_frames", "material", "output", "overlap_writes",
                         "retry_strain_outliers", "retry_depth_outliers"):
                setattr(d, key, value)
            else:
                raise InputError(f"unknown spec override {key!r}")
        _validate_scalars(d, f"command line (spec {self.source})")
        return d


def _num(v: float) -> str:
    return f"{v:g}".replace("-", "m")


# ------------------------------------------------------------------------------------ parsing
class _Reader:
    """Typed access to one table of the TOML document, with errors naming the file and field."""

    def __init__(self, source: str, table: dict, prefix: str) -> None:
        self.source, self.table, self.prefix = source, table, prefix

    def err(self, key: str, what: str) -> InputError:
        return InputError(f"spec {self.source}: field '{self.prefix}{key}' {what}")

    def _got(self, value) -> str:
        return f"got {value!r} ({type(value).__name__})"

    def get(self, key, default, kind, *, low=None, high=None, inclusive=True, choices=None, finite=True):
        if key not in self.table:
            return default
        v = self.table[key]
        bound = _bound(low, high, inclusive)
        if kind is bool:
            if not isinstance(v, bool):
                raise self.err(key, f"must be true or false, {self._got(v)}")
            return v
        if kind is int:
            if isinstance(v, bool) or not isinstance(v, int):
                raise self.err(key, f"must be an integer{bound}, {self._got(v)}")
        elif kind is float:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or math.isnan(v) or (finite and math.isinf(v)):
                raise self.err(key, f"must be a {'finite ' if finite else ''}number{bound}, {self._got(v)}")
            v = float(v)
        elif kind is str:
            if not isinstance(v, str) or not v:
                raise self.err(key, f"must be a non-empty string, {self._got(v)}")
            if choices is not None and v not in choices:
                raise self.err(key, f"must be one of {', '.join(map(repr, choices))}, got {v!r}")
            return v
        if (low is not None and (v < low if inclusive else v <= low)) or \
                (high is not None and (v > high if inclusive else v >= high)):
            raise self.err(key, f"must be{bound}, got {v!r}")
        return v

    def setting(self, key, s: Setting):
        """The value of a declared setting (its type and bounds), or its default when absent."""
        if key not in self.table:
            return s.default
        if s.kind is tuple:
            values = self.numbers(key, ())
            if len(values) != s.length:
                raise self.err(key, f"must be a list of {s.length} finite numbers, {self._got(self.table[key])}")
            return list(values)
        if s.kind not in (bool, int, float, str):
            raise self.err(key, "cannot be set in a spec")
        # The declaration checks its own values (the same rule and message as the config's).
        return replace(s, optional=False).check(self.table[key], f"spec {self.source}: field '{self.prefix}{key}'")

    def strings(self, key, default) -> tuple[str, ...]:
        if key not in self.table:
            return tuple(default)
        v = self.table[key]
        if isinstance(v, str):
            v = [v]
        if not isinstance(v, list) or not all(isinstance(x, str) and x for x in v):
            raise self.err(key, f"must be a list of non-empty strings, {self._got(v)}")
        return tuple(v)

    def numbers(self, key, default) -> tuple[float, ...]:
        if key not in self.table:
            return tuple(default)
        v = self.table[key]
        if not isinstance(v, list) or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                              and math.isfinite(x) for x in v):
            raise self.err(key, f"must be a list of finite numbers, {self._got(v)}")
        return tuple(float(x) for x in v)


def _bound(low, high=None, inclusive=True) -> str:
    parts = []
    if low is not None:
        parts.append(f"{'>=' if inclusive else '>'} {low:g}")
    if high is not None:
        parts.append(f"{'<=' if inclusive else '<'} {high:g}")
    return (" " + " and ".join(parts)) if parts else ""


def _check_keys(source: str, table: dict, allowed, prefix: str, moved: dict | None = None) -> None:
    """InputError for a key not in ``allowed``: a key of ``moved`` (old name -> where it is now) says
    where it went, another the closest allowed name or the list."""
    for key in table:
        if key not in allowed:
            if moved and key in moved:
                raise InputError(f"spec {source}: unknown field '{prefix}{key}' (it is now {moved[key]})")
            close = difflib.get_close_matches(key, list(allowed), n=1, cutoff=0.6)
            hint = f" (did you mean '{prefix}{close[0]}'?)" if close else f"; allowed: {', '.join(allowed)}"
            raise InputError(f"spec {source}: unknown field '{prefix}{key}'{hint}")


def _table(source: str, doc: dict, name: str) -> dict:
    t = doc.get(name, {})
    if not isinstance(t, dict):
        raise InputError(f"spec {source}: field '{name}' must be a table ([{name}]), got {type(t).__name__}")
    allowed, moved = _SECTIONS[name], None
    if name == "solver":
        allowed = allowed + tuple(solver_settings())
        # A sub-table's field under its one-level name (solver.contact_stiffness) says where it is now.
        moved = {_flat_key(k, f): f"'solver.{k}.{f}': {f} in a [solver.{k}] table"
                 for k, s in solver_settings().items() if s.nested for f in settings_of(s.nested)}
    _check_keys(source, t, allowed, f"{name}.", moved)
    return t


def _read_solver(spec: DatasetSpec, sv: _Reader) -> dict:
    """The [solver] fields that set SolverConfig ones, sub-tables as dicts; friction / self_contact
    given as true/false (or as a table: on) set the DatasetSpec field of that name."""
    settings = solver_settings()
    solver = {}
    for key, s in settings.items():
        if key not in sv.table:
            continue
        if s.nested is None:
            solver[key] = sv.setting(key, s)
            continue
        value = sv.table[key]
        if s.optional and isinstance(value, bool):
            setattr(spec, key, value)
            continue
        if not isinstance(value, dict):
            either = " or true / false" if s.optional else ""
            raise sv.err(key, f"must be a table ([solver.{key}]){either}, {sv._got(value)}")
        fields_ = settings_of(s.nested)
        _check_keys(sv.source, value, tuple(fields_), f"solver.{key}.")
        sub = _Reader(sv.source, value, f"solver.{key}.")
        table = {k: sub.setting(k, fields_[k]) for k in fields_ if k in value}
        if s.optional:
            setattr(spec, key, True)
        if table:
            try:
                s.nested(**table)   # the class's own checks across fields (e.g. pinch_distance > margin)
            except InputError as exc:
                raise InputError(f"spec {sv.source}: table 'solver.{key}': {exc}") from None
            solver[key] = table
    return solver


def parse_spec(doc: dict, *, source: str = "<dict>", base_dir: str | Path = ".", default_name: str = "dataset"
               ) -> DatasetSpec:
    """Validate a parsed TOML document (a dict) and return the :class:`DatasetSpec`."""
    if not isinstance(doc, dict):
        raise InputError(f"spec {source} must be a TOML table at the top level")
    _check_keys(source, doc, _TOP, "")
    top = _Reader(source, doc, "")
    spec = DatasetSpec(name=top.get("name", default_name, str), garments=[], source=source,
                       base_dir=str(base_dir))
    if not ID_PATTERN.match(spec.name):
        raise InputError(f"spec {source}: field 'name' may hold only letters, digits, '_', '.' and '-', "
                         f"got {spec.name!r}")
    if "description" in doc and not isinstance(doc["description"], str):
        raise top.err("description", f"must be a string, got {type(doc['description']).__name__}")
    spec.description = doc.get("description", "")

    g = _Reader(source, _table(source, doc, "garment"), "garment.")
    if "names" not in g.table:
        raise InputError(f"spec {source}: field 'garment.names' is missing (for example names = [\"tshirt\"])")
    spec.garments = list(g.strings("names", ()))
    if not spec.garments:
        raise g.err("names", "must name at least one garment")
    if len(set(spec.garments)) != len(spec.garments):
        raise g.err("names", "names a garment twice")
    spec.material = g.get("material", None, str)
    mo = g.table.get("material_overrides", {})
    if not isinstance(mo, dict):
        raise g.err("material_overrides", f"must be a table of Material fields, got {type(mo).__name__}")
    spec.material_overrides = dict(mo)

    b = _Reader(source, _table(source, doc, "body"), "body.")
    model = b.get("model", "open", str)
    if model != "open":
        p = Path(model).expanduser()
        model = str(p if p.is_absolute() else (Path(base_dir) / p).resolve())
    spec.body = model

    s = _Reader(source, _table(source, doc, "shapes"), "shapes.")
    spec.shapes_generator = s.get("generator", "axes" if "list" not in s.table else "list", str,
                                  choices=("axes", "list"))
    spec.shape_components = s.get("components", 4, int, low=0)
    spec.shape_values = s.numbers("values", (-2.0, -1.0, 1.0, 2.0))
    spec.include_zero = s.get("include_zero", True, bool)
    if "list" in s.table:
        if spec.shapes_generator != "list":
            raise s.err("list", "is only read with generator = \"list\"")
        items = s.table["list"]
        if not isinstance(items, list) or not items:
            raise s.err("list", "must be a non-empty array of tables {id = \"...\", betas = [...]}")
        shapes = []
        for i, item in enumerate(items):
            r = _Reader(source, item if isinstance(item, dict) else {}, f"shapes.list[{i}].")
            if not isinstance(item, dict):
                raise s.err("list", f"entry {i} must be a table {{id = \"...\", betas = [...]}}")
            _check_keys(source, item, ("id", "betas"), f"shapes.list[{i}].")
            if "id" not in item:
                raise r.err("id", "is missing")
            sid = r.get("id", None, str)
            if not ID_PATTERN.match(sid):
                raise r.err("id", f"may hold only letters, digits, '_', '.' and '-', got {sid!r}")
            shapes.append(ShapeSpec(sid, r.numbers("betas", ())))
        spec.shape_list = tuple(shapes)
    elif spec.shapes_generator == "list":
        raise s.err("list", "is missing (generator = \"list\" needs explicit shapes)")
    ids = [sh.id for sh in spec.shapes()]
    if not ids:
        raise InputError(f"spec {source}: the spec selects no shape (table 'shapes')")
    if len(set(ids)) != len(ids):
        dup = next(i for i in ids if ids.count(i) > 1)
        raise InputError(f"spec {source}: field 'shapes' gives shape id {dup!r} twice")

    m = _Reader(source, _table(source, doc, "motions"), "motions.")
    spec.motion_library = m.strings("library", ("*",) if "files" not in m.table else ())
    spec.motion_files = m.strings("files", ())
    spec.test_motions = m.strings("test", ())
    spec.train_motions = m.strings("train", ())
    both = set(spec.test_motions) & set(spec.train_motions)
    if both:
        raise m.err("test", f"and 'motions.train' both name {sorted(both)[0]!r}")
    spec.start_frame = m.get("start_frame", 0, int, low=0)
    spec.max_frames = m.get("max_frames", 0, int, low=0)

    simulation = simulation_settings()
    sv = _Reader(source, _table(source, doc, "solver"), "solver.")
    spec.device = sv.get("device", "auto", str)
    spec.fps = sv.get("fps", 30.0, float, low=0.0, inclusive=False)
    spec.substeps = sv.setting("substeps", simulation["substeps"])
    for key in _switches():   # on unless SolverConfig's default is None
        setattr(spec, key, solver_settings()[key].default is not None)
    spec.solver = _read_solver(spec, sv)

    p = _Reader(source, _table(source, doc, "protocol"), "protocol.")
    for key in _SIMULATION_FIELDS["protocol"]:
        setattr(spec, key, p.setting(key, simulation[key]))
    spec.store_rest_frames = p.get("store_rest_frames", True, bool)

    sm = _Reader(source, _table(source, doc, "smoothing"), "smoothing.")
    spec.smoothing = {
        "method": sm.get("method", "taubin", str, choices=("taubin", "laplacian", "none")),
        "iterations": sm.get("iterations", 10, int, low=0),
        "lambda": sm.get("lambda", 0.5, float, low=0.0, inclusive=False),
        "mu": sm.get("mu", -0.53, float),
        "boundary": sm.get("boundary", "boundary", str, choices=("boundary", "free", "fixed")),
    }
    if spec.smoothing["lambda"] > 1.0:
        raise sm.err("lambda", f"must be <= 1, got {spec.smoothing['lambda']!r}")
    if spec.smoothing["method"] == "taubin" and not spec.smoothing["mu"] < -spec.smoothing["lambda"]:
        raise sm.err("mu", f"must be below -lambda for Taubin smoothing (no shrinkage), got {spec.smoothing['mu']!r}")

    e = _Reader(source, _table(source, doc, "execution"), "execution.")
    spec.batch_size = e.get("batch_size", 0, int, low=0)
    spec.max_attempts = e.get("max_attempts", 3, int, low=1)
    spec.chunk_frames = e.get("chunk_frames", 32, int, low=1)
    spec.overlap_writes = e.get("overlap_writes", True, bool)
    spec.retry_strain_outliers = e.get("retry_strain_outliers", True, bool)
    spec.retry_depth_outliers = e.get("retry_depth_outliers", True, bool)

    o = _Reader(source, _table(source, doc, "output"), "output.")
    spec.output = o.get("path", None, str)

    _validate_scalars(spec, f"spec {source}")
    try:
        spec.solver_options()   # the checks across fields and classes
    except InputError as exc:
        raise InputError(f"spec {source}: table 'solver': {exc}") from None
    return spec


def _validate_scalars(spec: DatasetSpec, where: str) -> None:
    """Checks shared by the file and the command-line overrides."""
    from simgen.materials import MATERIALS, Material

    dev = spec.device
    if not (dev in ("auto", "cpu", "cuda") or re.fullmatch(r"cuda:\d+", dev or "")):
        raise InputError(f"{where}: field 'solver.device' must be auto, cpu, cuda or cuda:N, got {dev!r}")
    for name, low in (("batch_size", 0), ("max_frames", 0)):
        v = getattr(spec, name)
        if isinstance(v, bool) or not isinstance(v, int) or v < low:
            raise InputError(f"{where}: field '{name}' must be an integer >= {low}, got {v!r}")
    simulation_settings()["substeps"].check(spec.substeps, f"{where}: field 'solver.substeps'")
    for name in ("overlap_writes", "retry_strain_outliers", "retry_depth_outliers"):
        if not isinstance(getattr(spec, name), bool):
            raise InputError(f"{where}: field 'execution.{name}' must be true or false, "
                             f"got {getattr(spec, name)!r}")
    if spec.material is not None and spec.material not in MATERIALS:
        raise InputError(f"{where}: field 'garment.material' is {spec.material!r}, not one of the presets "
                         f"{', '.join(MATERIALS)}")
    known = {f.name for f in fields(Material)} - {"name", "source"}
    for key, value in spec.material_overrides.items():
        if key not in known:
            raise InputError(f"{where}: field 'garment.material_overrides.{key}' is not a Material field; "
                             f"fields are {', '.join(sorted(known))}")
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(f"{where}: field 'garment.material_overrides.{key}' must be a number, got {value!r}")


# ------------------------------------------------------------------------------------ loading
def list_presets() -> list[str]:
    """Names of the bundled garment presets (simgen/dataset/presets/*.toml; the soft-tissue ones,
    ``kind = "softtissue"``, are :func:`simgen.dataset.softtissue.list_softtissue_presets`)."""
    from simgen.dataset.softtissue import is_softtissue_spec

    return sorted(p.stem for p in PRESETS_DIR.glob("*.toml") if not is_softtissue_spec(p))


def preset_path(name: str) -> Path:
    """Path of a bundled preset; InputError for an unknown name."""
    p = PRESETS_DIR / f"{name}.toml"
    if not p.is_file():
        from simgen.dataset.softtissue import list_softtissue_presets

        raise InputError(f"unknown dataset preset {name!r}; presets: "
                         f"{', '.join(sorted(list_presets() + list_softtissue_presets()))} (or give the path of a "
                         f".toml spec)")
    return p


def load_spec(spec: str | Path | dict) -> DatasetSpec:
    """Read a spec: a TOML path, a bundled preset name (``tiny``, ``thesis-tshirt``, ...) or a dict.

    Raises InputError for a missing file, invalid TOML, unknown or mistyped fields.
    """
    if isinstance(spec, DatasetSpec):
        return spec
    if isinstance(spec, dict):
        return parse_spec(spec)
    text = str(spec)
    path = Path(text).expanduser()
    if path.suffix != ".toml" and "/" not in text and not path.exists():
        path = preset_path(text)
    if not path.is_file():
        raise InputError(f"spec file {path} does not exist")
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise InputError(f"spec {path} is not UTF-8 text") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"spec {path} is not valid TOML ({exc})") from None
    source = path.name if path.parent == PRESETS_DIR else str(path)
    return parse_spec(doc, source=source, base_dir=path.resolve().parent, default_name=path.stem)
