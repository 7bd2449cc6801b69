"""What ``simgen view`` shows, loaded into one in-memory model: a :class:`Scene`.

A scene is one posed body over F frames with one or more garment tracks on it (a simulation; or
ground truth, model and LBS side by side), plus what the colourings and the physics plot need: the
garment's stress-free shape, its material and the collision term's parameters. All numpy, SI units.

Every kind of input is a :class:`Source`. A source names the choices its GUI offers (``keys``:
dropdowns such as garment, shape, motion), lists the options of each for the current selection
(:meth:`Source.choices`) and loads the scene of one selection (:meth:`Source.load`):

- :class:`SimulationSource`: an .npz of ``simgen simulate`` / ``simgen demo``, read by
  :func:`simgen.physics.load_simulation` (the body re-posed from its motion unless stored).
- :class:`UsdSource`: a .usd/.usdc/.usda written by simgen (:func:`simgen.io.usd.read_usd_meshes`),
  side by side when it is an ``export usd --compare`` file.
- :class:`DatasetSource`: a dataset store, or a folder of stores (one per garment), read with
  :func:`simgen.dataset.open_dataset`; dropdowns garment, shape, motion.
- :class:`EvalGarmentSource`: an ``simgen eval garment`` output folder (its metrics.json names the
  model folder and the dataset); ground truth, model and LBS come from
  :func:`simgen.learn.compare.compare_tracks`; dropdowns motion, shape.
- :class:`EvalCompareSource`: an ``simgen eval compare`` output folder: its compare.usdc, every
  model beside the simulation and LBS.

:func:`open_source` takes the first class in :data:`SOURCES` whose ``accepts(path)`` is true. A new
kind of input is one more Source subclass whose ``load`` returns a Scene with one track per model,
added with :func:`register_source`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from simgen.errors import InputError

__all__ = ["GarmentTrack", "Scene", "Source", "SimulationSource", "UsdSource", "DatasetSource",
           "EvalGarmentSource", "EvalCompareSource", "SOURCES", "register_source", "open_source", "scene_from_mesh_tracks"]

USD_SUFFIXES = (".usd", ".usdc", ".usda")


@dataclass
class GarmentTrack:
    """One garment over the scene's frames.

    label: its name in the GUI ("simulation", "ground_truth", "ours", "lbs", ...); positions [m]
    (F, V, 3) float32 on the scene's body (without the display offset); offset [m] (3,): where this
    track's copy of the body and garment is drawn (side by side along +X; zero for a single track).
    """

    label: str
    positions: np.ndarray
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3, dtype=np.float32))


@dataclass
class Scene:
    """Everything the viewer draws and measures for one selection.

    title: one line for the GUI; fps [1/s]; body_vertices [m] (F, Vb, 3) float32; body_faces (Fb, 3);
    garment_faces (Fg, 3); tracks: the garments, all (F, V, 3); reference: label of the track the
    others' per-vertex error is measured against (None: no error colouring); rest [m] (V, 3): the
    garment's stress-free shape (None: no strain or physics terms); material: a
    :class:`simgen.materials.Material` (None: no physics terms); contact: the
    :class:`simgen.params.ContactParams` of the collision term; meta: free-form facts for the GUI.
    """

    title: str
    fps: float
    body_vertices: np.ndarray
    body_faces: np.ndarray
    garment_faces: np.ndarray
    tracks: list[GarmentTrack]
    reference: str | None = None
    rest: np.ndarray | None = None
    material: object | None = None
    contact: object | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        F = self.body_vertices.shape[0]
        for t in self.tracks:
            if t.positions.ndim != 3 or t.positions.shape[0] != F:
                raise InputError(f"{self.title}: garment {t.label!r} has shape {t.positions.shape}, "
                                 f"the body {F} frames")
        if self.reference is not None and self.reference not in self.labels:
            raise InputError(f"{self.title}: reference track {self.reference!r} is not one of {self.labels}")
        if self.rest is not None and self.rest.shape != self.tracks[0].positions.shape[1:]:
            self.rest = None  # a rest shape of another mesh: no strain, no terms

    @property
    def num_frames(self) -> int:
        return int(self.body_vertices.shape[0])

    @property
    def labels(self) -> list[str]:
        return [t.label for t in self.tracks]

    def track(self, label: str) -> GarmentTrack:
        return next(t for t in self.tracks if t.label == label)


class Source:
    """One input of the viewer (module doc). Subclasses set ``kind`` and ``keys`` and implement
    ``accepts``, ``choices`` and ``load``; ``path`` is what the user passed."""

    kind = "input"
    keys: tuple[str, ...] = ()

    def __init__(self, path) -> None:
        self.path = Path(path)

    @classmethod
    def accepts(cls, path: Path) -> bool:
        raise NotImplementedError

    def choices(self, selection: dict) -> dict[str, list[str]]:
        """The options of every key given the selection so far (the first option is the default)."""
        return {}

    def load(self, selection: dict) -> Scene:
        raise NotImplementedError

    def select(self, wanted: dict | None = None) -> dict:
        """A full selection from the wanted values (None: the default), each checked against its
        options; InputError naming the value and the options otherwise."""
        extra = [k for k, v in (wanted or {}).items() if v is not None and k not in self.keys]
        if extra:
            offers = f"; it offers {', '.join('--' + k for k in self.keys)}" if self.keys else ""
            raise InputError(f"--{extra[0]} does not apply to {self.path} (a {self.kind}{offers})")
        selection: dict = {}
        for key in self.keys:
            options = self.choices(selection)[key]
            value = (wanted or {}).get(key)
            if not options:
                raise InputError(f"{self.path} holds no {key} to show")
            if value is not None and value not in options:
                raise InputError(f"--{key} {value!r} is not in {self.path} (it has: {', '.join(options)})")
            selection[key] = value if value is not None else options[0]
        return selection


# ------------------------------------------------------------------------------------ simulations
class SimulationSource(Source):
    """An .npz of ``simgen simulate`` / ``simgen demo`` (:meth:`simgen.sim.SimulationResult.save_npz`)."""

    kind = "simulation"

    @classmethod
    def accepts(cls, path: Path) -> bool:
        return path.suffix == ".npz"

    def load(self, selection: dict) -> Scene:
        import zipfile

        from simgen.physics import load_simulation

        try:
            seq = load_simulation(self.path)
        except zipfile.BadZipFile:  # load_simulation turns OSError and ValueError into InputError, not this
            raise InputError(f"{self.path} is not a readable .npz file (not a zip archive)") from None
        return Scene(title=f"{seq.meta['garment']} on {seq.meta['motion']} ({self.path.name})", fps=seq.fps,
                     body_vertices=np.asarray(seq.body_vertices, dtype=np.float32),
                     body_faces=np.asarray(seq.body.faces), garment_faces=np.asarray(seq.garment.faces),
                     tracks=[GarmentTrack("simulation", seq.positions)], rest=np.asarray(seq.garment.vertices),
                     material=seq.material, contact=seq.contact, meta={"source": str(self.path)})


# ------------------------------------------------------------------------------------ USD files
def _suffix(name: str, role: str) -> str:
    return name[len(role) + 1:] if name.startswith(role + "_") else name


def _animated(points: np.ndarray, frames: int) -> np.ndarray:
    return np.broadcast_to(points, (frames,) + points.shape[-2:]) if points.ndim == 2 else points


def scene_from_mesh_tracks(tracks, fps: float, title: str, **scene_fields) -> Scene:
    """A Scene from :class:`simgen.io.usd.MeshTrack` objects: the first body is the scene's body,
    every garment becomes a track, offset by where its body (``body_X`` for ``garment_X``, else the
    first) sits relative to the first; labels drop the ``garment_`` prefix. "ground_truth", when
    present beside other tracks, is the error reference."""
    bodies = [t for t in tracks if t.role == "body"]
    garments = [t for t in tracks if t.role == "garment"]
    if not bodies or not garments:
        raise InputError(f"{title} holds no body and garment meshes (simgen:role 'body' and 'garment')")
    frames = max(t.num_frames for t in tracks)
    base = _animated(bodies[0].points, frames)
    by_suffix = {_suffix(b.name, "body"): _animated(b.points, frames) for b in bodies}
    out = []
    for g in garments:
        label = _suffix(g.name, "garment")
        body = by_suffix.get(label, base)
        offset = (body[0] - base[0]).mean(axis=0).astype(np.float32)
        out.append(GarmentTrack(label, np.ascontiguousarray(_animated(g.points, frames) - offset), offset))
    labels = [t.label for t in out]
    reference = "ground_truth" if "ground_truth" in labels and len(out) > 1 else None
    return Scene(title=title, fps=float(fps), body_vertices=np.ascontiguousarray(base),
                 body_faces=bodies[0].faces, garment_faces=garments[0].faces, tracks=out, reference=reference,
                 **scene_fields)


def _garment_rest(name) -> tuple[np.ndarray | None, object | None]:
    """(rest shape [m] (V, 3), default material) of a named garment, (None, None) if unknown."""
    from simgen.garment import load_garment
    from simgen.materials import get_material

    if not isinstance(name, str):
        return None, None
    try:
        g = load_garment(name)
        return np.asarray(g.vertices), get_material((g.metadata or {}).get("default_material") or "cotton")
    except InputError:
        return None, None


class UsdSource(Source):
    """A USD file written by simgen (``simgen simulate``, ``export usd [--compare]``, ``garment preview``)."""

    kind = "usd"

    @classmethod
    def accepts(cls, path: Path) -> bool:
        return path.suffix in USD_SUFFIXES

    def load(self, selection: dict) -> Scene:
        from simgen.io.usd import read_usd_info, read_usd_meshes

        meshes = read_usd_meshes(self.path)
        info = read_usd_info(self.path)
        meta = info.get("metadata") or {}
        rest, material = _garment_rest(meta.get("garment"))
        return scene_from_mesh_tracks(list(meshes.values()), info["time_codes_per_second"] or 30.0,
                                      f"{self.path.name}", rest=rest, material=material,
                                      meta={"source": str(self.path), **meta})


# ------------------------------------------------------------------------------------ dataset stores
def _is_store(path: Path) -> bool:
    return (path / "zarr.json").is_file()


class DatasetSource(Source):
    """A dataset store or a folder of stores (one per garment); dropdowns garment, shape, motion."""

    kind = "dataset"
    keys = ("garment", "shape", "motion")

    @classmethod
    def accepts(cls, path: Path) -> bool:
        return path.is_dir() and (_is_store(path) or any(_is_store(p) for p in path.iterdir() if p.is_dir()))

    def __init__(self, path) -> None:
        from simgen.dataset import open_dataset

        super().__init__(path)
        folders = [self.path] if _is_store(self.path) else sorted(p for p in self.path.iterdir() if _is_store(p))
        self.stores = {}
        for folder in folders:
            ds = open_dataset(folder)
            name = ds.garment_name if ds.garment_name not in self.stores else f"{ds.garment_name}/{folder.name}"
            self.stores[name] = ds

    def choices(self, selection: dict) -> dict[str, list[str]]:
        garments = list(self.stores)
        ds = self.stores.get(selection.get("garment"), self.stores[garments[0]])
        infos = [ds.sequence_info(i) for i in ds.sequence_ids()]
        shapes = [s for s in ds.shape_ids() if any(i.get("shape_id") == s for i in infos)]
        shape = selection.get("shape") or (shapes[0] if shapes else None)
        motions = sorted({i["motion"] for i in infos if i.get("shape_id") == shape})
        return {"garment": garments, "shape": shapes, "motion": motions}

    def load(self, selection: dict) -> Scene:
        from simgen.physics.sources import contact_params_from

        ds = self.stores[selection["garment"]]
        seq_id = f"{selection['motion']}__{selection['shape']}"
        seq = ds.sequence(seq_id)
        body = ds.load_body()
        posed = body.forward_sequence(seq["betas"], seq["poses"], seq["trans"])
        tpl = ds.template
        solver = ds.attrs.get("solver", {})
        return Scene(title=f"{ds.garment_name}: {seq_id}", fps=float(seq["attrs"].get("fps") or ds.fps),
                     body_vertices=posed.vertices, body_faces=np.asarray(body.faces), garment_faces=tpl["faces"],
                     tracks=[GarmentTrack("simulation", np.asarray(seq["garment_vertices"], dtype=np.float32))],
                     rest=np.asarray(tpl["garment_template"]), material=ds.material,
                     contact=contact_params_from(solver.get("config", solver)),
                     meta={"source": str(ds.path), "sequence": seq_id, "split": seq["attrs"].get("split")})


# ------------------------------------------------------------------------------------ eval folders
def _read_metrics(path: Path) -> dict | None:
    try:
        metrics = json.loads((path / "metrics.json").read_text())
    except (OSError, ValueError):
        return None
    return metrics if isinstance(metrics, dict) else None


class EvalGarmentSource(Source):
    """An ``simgen eval garment --out`` folder: ground truth, model and LBS of one evaluated sequence."""

    kind = "eval garment"
    keys = ("motion", "shape")

    @classmethod
    def accepts(cls, path: Path) -> bool:
        m = _read_metrics(path) if path.is_dir() else None
        return bool(m) and {"model_dir", "dataset", "sequences"} <= set(m)

    def __init__(self, path) -> None:
        super().__init__(path)
        self.metrics = _read_metrics(self.path)
        for key, what in (("model_dir", "model folder"), ("dataset", "dataset store")):
            if not Path(self.metrics[key]).exists():
                raise InputError(f"{self.path / 'metrics.json'}: its {what} {self.metrics[key]!r} ({key}) "
                                 "does not exist")
        held = [s for s, v in self.metrics["sequences"].items() if v.get("group") == "held_out_motion"]
        self.order = held + [s for s in self.metrics["sequences"] if s not in held]

    def choices(self, selection: dict) -> dict[str, list[str]]:
        seqs = self.metrics["sequences"]
        motions = list(dict.fromkeys(seqs[s]["motion"] for s in self.order))
        motion = selection.get("motion", motions[0] if motions else None)
        shapes = [str(seqs[s]["shape_id"]) for s in self.order if seqs[s]["motion"] == motion]
        return {"motion": motions, "shape": shapes}

    def load(self, selection: dict) -> Scene:
        from simgen.learn.compare import compare_tracks
        from simgen.learn.data import load_garment_data
        from simgen.physics.sources import contact_params_from

        seq_id = f"{selection['motion']}__{selection['shape']}"
        data = load_garment_data(self.metrics["dataset"], sequence_ids=[seq_id])
        tracks, meta, fps = compare_tracks(self._model(data), data, seq_id)
        solver = data.attrs.get("solver", {})
        rest = data.rest_template if data.rest_template is not None else data.template
        return scene_from_mesh_tracks(tracks, fps, f"{data.garment_name}: {seq_id} (ground truth | ours | LBS)",
                                      rest=np.asarray(rest), material=data.material,
                                      contact=contact_params_from(solver.get("config", solver)),
                                      meta={"source": str(self.path), **meta})

    def _model(self, data):
        """The evaluated model (supervised, or SNUG for a folder with snug/ and no fit/), checked
        against the data's garment and body."""
        from simgen.learn.data import body_for_identity
        from simgen.learn.garment_model import FIT_DIR, load_garment_model
        from simgen.learn.snug import SNUG_DIR, load_snug_model

        folder = Path(self.metrics["model_dir"])
        snug = (folder / SNUG_DIR).is_dir() and not (folder / FIT_DIR).is_dir()
        loader = load_snug_model if snug else load_garment_model
        return loader(folder, identity=data.identity, body=body_for_identity(data.identity))


class EvalCompareSource(Source):
    """An ``simgen eval compare --out`` folder: its compare.usdc (the simulation, every model and LBS
    side by side, coloured by error) titled from compare.json."""

    kind = "eval compare"

    @classmethod
    def accepts(cls, path: Path) -> bool:
        return path.is_dir() and (path / "compare.json").is_file() and (path / "compare.usdc").is_file()

    def load(self, selection: dict) -> Scene:
        scene = UsdSource(self.path / "compare.usdc").load({})
        scene.title = f"{self.path.name}: {' | '.join(t.label for t in scene.tracks)}"
        return scene


# ------------------------------------------------------------------------------------ dispatch
SOURCES: list[type[Source]] = [SimulationSource, UsdSource, EvalGarmentSource, EvalCompareSource, DatasetSource]


def register_source(cls: type[Source], *, first: bool = True) -> type[Source]:
    """Add a kind of input (checked before the built-in ones unless ``first=False``); usable as a
    class decorator."""
    SOURCES.insert(0, cls) if first else SOURCES.append(cls)
    return cls


def open_source(path) -> Source:
    """The Source for PATH: the first of :data:`SOURCES` that accepts it; InputError otherwise."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p} does not exist")
    for cls in SOURCES:
        if cls.accepts(p):
            return cls(p)
    raise InputError(f"{p} is not something simgen view opens (a simulation .npz, a simgen USD file, a dataset "
                     "store, an `eval garment` or an `eval compare` folder)")
