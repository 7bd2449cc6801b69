"""check_dataset(): audit a store. Every finding is a *problem* (the check fails) or a *warning*.

Problems:
- manifest and store disagree: a manifest entry whose node is missing or uncommitted, a checksum
  that does not match the node's arrays (recomputed here), a committed node the manifest lacks;
- missing frames: per-frame arrays of different lengths, fewer frames than the manifest/attrs
  say, or unwritten Zarr chunks;
- NaN or inf anywhere;
- cloth inside the body: the body is re-posed here from the stored poses, trans and betas (the
  numpy forward pass) and every checked cloth vertex more than ``max_depth`` inside it (winding-
  number sign) counts, except at body self-intersections (the closest body point moved 2 mm
  outward is still inside: armpits, crotch), which the solver cannot resolve;
- strain outliers: a triangle whose largest principal stretch exceeds 1 + ``max_strain`` against
  the cloth's rest shape (default 1.0: twice its rest length; healthy frames of the coarse
  tshirt_1k reach 40% in single triangles at the shoulders, a blown-up or tangled frame goes far
  beyond), on any frame. As for the penetration, a triangle with a vertex at a body
  self-intersection on that frame (the body is re-posed for the frames with outliers) is counted
  apart: cloth caught between two body parts that have moved into each other cannot keep its
  shape, whatever the solver does; those frames are reported as one warning with their count and
  largest strain;
- the garment off the body (:mod:`simgen.sim.placement`, on the same frames as the penetration): its
  support (the top 5 cm it hangs from: waistband, or neckline and shoulders) more than
  ``MAX_SUPPORT_DROP`` (10 cm) below its skinned (LBS) position, fewer than ``MIN_BODY_SHARE`` (a
  quarter) of its vertices within 5 cm of the body, or cloth more than 1 mm below the floor;
- fits whose stored displacement is not smooth(S_c) - T_c;
- jobs recorded as failed in the manifest.

Warnings: cloth through itself: every frame of every sequence is counted for crossing edges (a
garment edge through a garment triangle, :mod:`simgen.garment.crossings`) and the report lists every
sequence with crossings; a sequence with crossings on more than ``MAX_CROSSING_SHARE`` (0.5%) of its
frames or on more than ``MAX_CROSSING_RUN`` (3) frames in a row is named in a "self-crossing"
warning (a warning until the solver's self-collision is on by default: today's stores have such
sequences, docs/sim.md "Not yet"); planned sequences not generated yet (a problem with ``require_complete``), leftovers of an
interrupted run (removed by the next ``generate``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from simgen.dataset.quality import DEFAULT_MAX_DEPTH, DEFAULT_MAX_STRAIN
from simgen.dataset.storage import STAGING, arrays_checksum
from simgen.dataset.store import node_arrays

__all__ = ["CheckReport", "check_dataset", "DEFAULT_MAX_DEPTH", "DEFAULT_MAX_STRAIN", "MAX_CROSSING_SHARE",
           "MAX_CROSSING_RUN"]

MAX_CROSSING_SHARE = 0.005     # a sequence is named with crossing edges on more than this share of its frames ...
MAX_CROSSING_RUN = 3           # ... or on more than this many frames in a row
_POSE_CHUNK = 16
#: The per-frame arrays every sequence node holds.
_SEQUENCE_ARRAYS = ("garment_vertices", "poses", "trans", "betas")


def _posed_chunks(bm, frames, poses, trans, betas):
    """Yield (sel, out) over ``frames`` in chunks of _POSE_CHUNK: the chunk's frame numbers and
    ``bm.forward`` of their betas, poses and trans (``out.vertices`` [m] (len(sel), Vb, 3)). Chunked
    because the forward pass holds (N, Vb, 4, 4) transforms."""
    for start in range(0, len(frames), _POSE_CHUNK):
        sel = frames[start:start + _POSE_CHUNK]
        yield sel, bm.forward(betas[sel], poses[sel], trans[sel])


def _split_pinched_strain(over: dict, x, poses, trans, betas, bm, faces, **penetration_kwargs) -> tuple[dict, dict]:
    """Split the frames with strain outliers ({frame: {triangle: strain}}) into free ones (their
    outliers away from body self-intersections only) and pinched ones (every outlier triangle has a
    vertex at a self-intersection, by :func:`body_penetration` on the body re-posed here)."""
    from simgen.dataset.quality import body_penetration

    free, pinched = {}, {}
    for sel, out in _posed_chunks(bm, sorted(over), poses, trans, betas):
        for j, k in enumerate(sel):
            _, self_hit, _ = body_penetration(x[k], out.vertices[j], bm.faces, **penetration_kwargs)
            away = {f: v for f, v in over[k].items() if not np.any(self_hit[faces[f]])}
            if away:
                free[k] = away
            else:
                pinched[k] = over[k]
    return free, pinched


def _check_body(x, frames, poses, trans, betas, bm, reference, tpl, max_depth: float, **penetration_kwargs):
    """Penetration and placement of one sequence on its re-posed body, over ``frames``.

    Returns (deepest regular depth [m], its frame, the vertices deeper than max_depth there) and
    the :data:`simgen.sim.placement.PLACEMENT_KEYS` arrays over those frames (None without a
    template)."""
    from simgen.dataset.quality import body_penetration
    from simgen.garment.skinning import lbs
    from simgen.sim.placement import PLACEMENT_KEYS, placement_row

    worst, rows = (0.0, -1, 0), []
    for sel, out in _posed_chunks(bm, frames, poses, trans, betas):
        posed = out.vertices
        skinned = None
        if reference is not None:
            rest = reference.rest_vertices(tpl["garment_template"].astype(np.float64), betas[sel])
            skinned = lbs(rest, tpl["skin_weights"], out.transforms)
            up = lbs(rest + np.array([0.0, 1.0, 0.0]), tpl["skin_weights"], out.transforms) - skinned
        for j, k in enumerate(sel):
            depth, self_hit, distance = body_penetration(x[k], posed[j], bm.faces, **penetration_kwargs)
            regular = np.where(self_hit, 0.0, depth)
            d = float(regular.max(initial=0.0))
            if d > worst[0]:
                worst = (d, int(k), int(np.sum(regular > max_depth)))
            if skinned is not None:
                rows.append(placement_row(x[k], skinned[j], up[j], distance, reference.support))
    placement = {key: np.array([r[key] for r in rows]) for key in PLACEMENT_KEYS} if rows else None
    return worst, placement


@dataclass
class CheckReport:
    """Findings of :func:`check_dataset`. passed: no problem."""

    path: str
    problems: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    sequences: int = 0
    frames: int = 0
    frames_checked_body: int = 0
    max_depth: float = 0.0
    max_strain: float = 0.0
    max_strain_regular: float = 0.0
    pinched_strain_frames: int = 0
    min_body_share: float = 1.0
    max_support_drop: float = 0.0
    min_height: float = float("inf")
    crossing_frames: int = 0
    max_crossing_edges: int = 0
    crossings: dict = field(default_factory=dict)
    planned: int | None = None

    @property
    def passed(self) -> bool:
        return not self.problems

    def problem(self, node: str, check: str, message: str) -> None:
        self.problems.append({"node": node, "check": check, "message": message})

    def warn(self, node: str, check: str, message: str) -> None:
        self.warnings.append({"node": node, "check": check, "message": message})

    def absorb(self, part: CheckReport) -> None:
        """Add the findings of ``part``, a report of further sequences (a worker's share)."""
        self.problems += part.problems
        self.warnings += part.warnings
        for name in ("sequences", "frames", "frames_checked_body", "pinched_strain_frames", "crossing_frames"):
            setattr(self, name, getattr(self, name) + getattr(part, name))
        for name in ("max_depth", "max_strain", "max_strain_regular", "max_support_drop", "max_crossing_edges"):
            setattr(self, name, max(getattr(self, name), getattr(part, name)))
        self.min_body_share = min(self.min_body_share, part.min_body_share)
        self.min_height = min(self.min_height, part.min_height)
        self.crossings.update(part.crossings)

    def to_dict(self) -> dict:
        return {"path": self.path, "passed": self.passed, "problems": self.problems, "warnings": self.warnings,
                "sequences": self.sequences, "frames": self.frames, "frames_checked_body": self.frames_checked_body,
                "max_depth": self.max_depth, "max_strain": self.max_strain,
                "max_strain_regular": self.max_strain_regular, "pinched_strain_frames": self.pinched_strain_frames,
                "min_body_share": self.min_body_share, "max_support_drop": self.max_support_drop,
                "min_height": self.min_height if np.isfinite(self.min_height) else None,
                "crossing_frames": self.crossing_frames, "max_crossing_edges": self.max_crossing_edges,
                "crossings": self.crossings, "planned": self.planned}

    def format(self) -> str:
        from simgen.sim.placement import ON_BODY_DISTANCE

        lines = [f"{self.path}: {self.sequences} sequences, {self.frames} frames"
                 + (f" of {self.planned} planned sequences" if self.planned is not None else "")
                 + f"; deepest regular vertex inside the body {1e3 * self.max_depth:.2f} mm over "
                   f"{self.frames_checked_body} frames; largest strain {100 * self.max_strain_regular:.1f}% "
                   f"({100 * self.max_strain:.1f}% with body self-intersections)"
                 + (f"; on the body: at least {100 * self.min_body_share:.0f}% of the vertices within "
                    f"{100 * ON_BODY_DISTANCE:g} cm, support at most {100 * self.max_support_drop:.1f} cm below its "
                    f"skinned position, lowest vertex {1e3 * self.min_height:.1f} mm"
                    if np.isfinite(self.min_height) else "")
                 + f"; cloth through itself on {self.crossing_frames} frames of {len(self.crossings)} sequences"
                   f" (at most {self.max_crossing_edges} crossing edges)"]
        for p in self.problems:
            lines.append(f"PROBLEM {p['node']} [{p['check']}]: {p['message']}")
        for w in self.warnings:
            lines.append(f"warning {w['node']} [{w['check']}]: {w['message']}")
        lines.append("passed" if self.passed else f"FAILED: {len(self.problems)} problems")
        return "\n".join(lines)


@dataclass
class _Context:
    """What the checks of the fits and sequences share; the template's parts are None without a
    verified template.

    tpl: the template node's arrays; faces (F, 3) of the cloth; rest_inv (F, 2, 2) inverse rest
    shapes of its triangles (:func:`triangle_rest_inverse`); num_vertices: V of the cloth;
    reference: the garment's :class:`simgen.sim.placement.GarmentReference` on the body; floor [m]
    or None (stores made before the floor have none); penetration: keyword arguments of
    :func:`body_penetration` (device, home_parts (V,), part_masks (Fb,), pinch_distance [m]);
    crossings: the cloth's :class:`simgen.garment.crossings.CrossingCounter`.
    """

    tpl: dict | None
    faces: np.ndarray | None
    rest_inv: np.ndarray | None
    num_vertices: int | None
    reference: object | None
    floor: float | None
    penetration: dict
    crossings: object | None


def _verify_node(rep: CheckReport, loc, rel: str, entry: dict | None, node: str) -> bool:
    """Whether node ``rel`` of the store is committed, its commit agrees with the manifest ``entry``
    (None: not checked) and its arrays match the committed checksum; a problem of ``node`` if not."""
    commit = loc.committed(rel)
    if commit is None:
        rep.problem(node, "manifest", f"listed in the manifest but {rel} is missing or was never committed")
        return False
    if entry is not None and entry.get("checksum") != commit["checksum"]:
        rep.problem(node, "manifest", "the manifest's checksum differs from the node's commit record")
        return False
    try:
        actual = arrays_checksum(node_arrays(loc, rel))
    except Exception as exc:  # noqa: BLE001 - unreadable data is a finding, not a crash
        rep.problem(node, "manifest", f"its arrays cannot be read ({type(exc).__name__}: {exc})")
        return False
    if actual != commit["checksum"]:
        rep.problem(node, "checksum", "its arrays do not match the checksum committed with them "
                                      "(changed or damaged after writing)")
        return False
    return True


def _check_manifest(rep: CheckReport, loc, m: dict) -> bool:
    """Manifest against store: the template, nodes committed but not listed, leftovers of an
    interrupted run, failed jobs. Returns whether the template node is sound."""
    template_ok = False
    if m["template"] is not None:
        template_ok = _verify_node(rep, loc, "template", m["template"], "template")
    elif m["fits"] or m["sequences"]:
        rep.problem("template", "manifest", "fits or sequences exist but the template relaxation does not")
    for kind, folder in (("fits", "fit"), ("sequences", "sequences")):
        listed = set(m[kind])
        for name in loc.listdir(folder):
            if name == "zarr.json":
                continue
            if loc.committed(f"{folder}/{name}") is None:
                rep.warn(f"{folder}/{name}", "leftover", "an uncommitted node of an interrupted run (the next "
                                                          "generate removes it)")
            elif name not in listed:
                rep.problem(f"{folder}/{name}", "manifest", "committed in the store but missing from the manifest "
                                                            "(rerun generate to adopt it)")
    if loc.is_local and loc.listdir(STAGING):
        rep.warn(".staging", "leftover", f"{len(loc.listdir(STAGING))} half-written nodes of an interrupted run "
                                         f"(the next generate removes them)")
    for key, info in sorted(m.get("failed", {}).items()):
        rep.problem(key, "failed", f"the job failed after {info.get('attempts')} attempts: {info.get('message')}")
    return template_ok


def _context(ds, bm, template_ok: bool, device: str) -> _Context:
    """The :class:`_Context` of store ``ds`` on body ``bm``; the template's parts only when template_ok."""
    from simgen.dataset.quality import penetration_rule, triangle_rest_inverse
    from simgen.sim.placement import garment_reference

    tpl = ds.template if template_ok else None
    faces = tpl["faces"].astype(np.int64) if tpl is not None else None
    rest_inv = triangle_rest_inverse(tpl["garment_template"], faces) if tpl is not None else None
    V = len(tpl["vertices"]) if tpl is not None else None
    reference = None
    if tpl is not None:
        from simgen.garment.garment import Garment

        cloth = Garment(str((ds.attrs.get("garment") or {}).get("name", "garment")), tpl["garment_template"],
                        faces, tpl["skin_weights"])
        reference = garment_reference(cloth, bm)
    solver_config = (ds.attrs.get("solver") or {}).get("config") or {}
    floor = solver_config.get("floor")  # stores made before the floor have none
    # The solver's contact keeps cloth on its own body part where the body intersects itself: the
    # same part labels classify such cloth as at a self-intersection here.
    weights = tpl["skin_weights"] if tpl is not None else None
    penetration = dict(device=device, **penetration_rule(weights, bm, ds.attrs.get("solver")))
    crossings = None
    if tpl is not None:
        from simgen.garment.crossings import CrossingCounter

        crossings = CrossingCounter(faces, V, device)
    return _Context(tpl, faces, rest_inv, V, reference, floor, penetration, crossings)


def _check_fits(rep: CheckReport, ds, ctx: _Context) -> None:
    """Each fit: verified against the manifest, finite, and its fit_displacement [m] (V, 3) equal to
    smooth(S_c) - T_c within 1e-5 m."""
    from simgen.dataset.groundtruth import SmoothingParams, smooth_garment

    m, tpl = ds.manifest, ctx.tpl
    params = SmoothingParams.from_dict(tpl["smoothing"])
    for sid in sorted(m["fits"]):
        node = f"fit/{sid}"
        if not _verify_node(rep, ds.loc, node, m["fits"][sid], node):
            continue
        fit = ds.fit(sid)
        if not all(np.all(np.isfinite(fit[k])) for k in ("betas", "vertices", "fit_displacement")):
            rep.problem(node, "nan", "contains NaN or inf")
            continue
        expect = smooth_garment(fit["vertices"].astype(np.float64), ctx.faces, params) - tpl["smoothed"]
        err = float(np.max(np.abs(expect - fit["fit_displacement"])))
        if err > 1e-5:
            rep.problem(node, "fit", f"fit_displacement differs from smooth(S_c) - T_c by {1e3 * err:.3f} mm")


def _read_sequence(rep: CheckReport, node: str, g, entry: dict, num_vertices: int | None):
    """A sequence's arrays, checked complete and finite: garment_vertices [m] (T, V, 3), poses,
    trans [m] (T, 3) and betas, or None (and a problem of ``node``). g: its Zarr group; entry: its
    manifest entry; num_vertices: the template's V, or None. Counts the sequence and its frames."""
    attrs = g.attrs.asdict()
    rep.sequences += 1
    arrays = {k: g[k] for k in _SEQUENCE_ARRAYS if k in g}
    if len(arrays) < len(_SEQUENCE_ARRAYS):
        lacking = sorted(set(_SEQUENCE_ARRAYS) - set(arrays))
        rep.problem(node, "frames", f"lacks arrays {lacking}")
        return None
    lengths = {k: a.shape[0] for k, a in arrays.items()}
    expected = attrs.get("frames", entry.get("frames"))
    if len(set(lengths.values())) != 1 or expected not in lengths.values():
        rep.problem(node, "frames", f"frame counts disagree: {lengths}, attrs/manifest say {expected}")
        return None
    missing = [k for k, a in arrays.items() if a.nchunks_initialized < a.nchunks]
    if missing:
        rep.problem(node, "frames", f"unwritten chunks (missing frames) in {', '.join(missing)}")
        return None
    x = arrays["garment_vertices"][...]
    T = x.shape[0]
    rep.frames += T
    if num_vertices is not None and x.shape[1:] != (num_vertices, 3):
        rep.problem(node, "frames", f"garment_vertices has shape {x.shape}, the template has {num_vertices} "
                                    f"vertices")
        return None
    bad = [k for k, a in arrays.items() if not np.all(np.isfinite(a[...]))]
    if "rest_garment_vertices" in g and not np.all(np.isfinite(g["rest_garment_vertices"][...])):
        bad.append("rest_garment_vertices")
    if bad:
        first = int(np.nonzero(~np.all(np.isfinite(x.reshape(T, -1)), axis=1))[0][0]) if "garment_vertices" in bad \
            else None
        rep.problem(node, "nan", f"NaN or inf in {', '.join(bad)}" + (f" (first at frame {first})"
                                                                       if first is not None else ""))
        return None
    poses, trans, betas = (arrays[k][...] for k in ("poses", "trans", "betas"))
    return x, poses, trans, betas


def _check_sequence_body(rep: CheckReport, node: str, seq, bm, ctx: _Context, stride: int,
                         max_depth: float) -> None:
    """Penetration [m] and placement of one sequence on every stride-th frame of its re-posed body.
    seq: (garment_vertices (T, V, 3), poses, trans, betas) from :func:`_read_sequence`."""
    from simgen.sim.placement import placement_problems

    x, poses, trans, betas = seq
    frames = np.arange(0, x.shape[0], stride)
    worst, placement = _check_body(x, frames, poses, trans, betas, bm, ctx.reference, ctx.tpl, max_depth,
                                   **ctx.penetration)
    rep.frames_checked_body += len(frames)
    rep.max_depth = max(rep.max_depth, worst[0])
    if worst[0] > max_depth:
        rep.problem(node, "inside-body", f"{worst[2]} cloth vertices more than {1e3 * max_depth:g} mm inside the "
                                         f"body at frame {worst[1]} (deepest {1e3 * worst[0]:.2f} mm; "
                                         f"self-intersections excluded)")
    if placement is not None:
        rep.min_body_share = min(rep.min_body_share, float(placement["body_share"].min()))
        rep.max_support_drop = max(rep.max_support_drop, float(placement["support_drop"].max()))
        rep.min_height = min(rep.min_height, float(placement["min_height"].min()))
        for message in placement_problems(placement, ctx.floor, frames):
            rep.problem(node, "off-body", message + (f" (frames checked every {stride})" if stride > 1 else ""))


def _check_sequence_strain(rep: CheckReport, node: str, seq, bm, ctx: _Context,
                           max_strain: float) -> tuple[int, float] | None:
    """Strain outliers of one sequence on every frame (``seq`` as for :func:`_check_sequence_body`):
    a problem for those away from body self-intersections. Returns (frames, largest strain) of the
    frames whose outliers are all at self-intersections, or None when there are none."""
    from simgen.dataset.quality import triangle_strain

    x, poses, trans, betas = seq
    T = x.shape[0]
    over = {}  # frame -> {triangle: strain} of the triangles over the limit
    s = triangle_strain(x, ctx.faces, ctx.rest_inv)       # (T, F); it works a few frames at a time
    smax = float(s.max())
    below = float(s[s <= max_strain].max(initial=0.0))
    for t, f in zip(*np.nonzero(s > max_strain)):
        over.setdefault(int(t), {})[int(f)] = float(s[t, f])
    rep.max_strain = max(rep.max_strain, smax)
    free, pinched = _split_pinched_strain(over, x, poses, trans, betas, bm, ctx.faces, **ctx.penetration)
    rep.pinched_strain_frames += len(pinched)
    rep.max_strain_regular = max(rep.max_strain_regular, below, *(v for fr in free.values() for v in fr.values()))
    if free:
        k, (f, v) = max(((k, max(fr.items(), key=lambda kv: kv[1])) for k, fr in free.items()),
                        key=lambda e: e[1][1])
        rep.problem(node, "strain", f"strain outlier: triangle {f} stretched {100 * v:.0f}% at frame {k} "
                                    f"(limit {100 * max_strain:g}%; {len(free)} of {T} frames over it, "
                                    f"body self-intersections excluded)")
    if pinched:
        return len(pinched), max(max(fr.values()) for fr in pinched.values())
    return None


def _longest_run(flags: np.ndarray) -> int:
    """The most consecutive True entries of a bool array (T,)."""
    best = run = 0
    for f in flags:
        run = run + 1 if f else 0
        best = max(best, run)
    return best


def _check_sequence_crossings(rep: CheckReport, node: str, sid: str, x: np.ndarray, ctx: _Context) -> None:
    """Crossing edges of one sequence on every frame, x [m] (T, V, 3); a warning past the limits."""
    counts = ctx.crossings.count(x)
    crossed = counts > 0
    if not crossed.any():
        return
    n, run, T = int(crossed.sum()), _longest_run(crossed), len(counts)
    rep.crossing_frames += n
    rep.max_crossing_edges = max(rep.max_crossing_edges, int(counts.max()))
    rep.crossings[sid] = {"frames": n, "longest_run": run, "max_edges": int(counts.max()),
                          "first_frame": int(np.argmax(crossed))}
    if n > MAX_CROSSING_SHARE * T or run > MAX_CROSSING_RUN:
        rep.warn(node, "self-crossing", f"cloth passes through itself on {n} of {T} frames (up to "
                                           f"{int(counts.max())} crossing edges, {run} frames in a row, first at "
                                           f"frame {int(np.argmax(crossed))}; limits {100 * MAX_CROSSING_SHARE:g}% "
                                           f"of the frames, {MAX_CROSSING_RUN} in a row)")


def _check_completeness(rep: CheckReport, ds, require_complete: bool) -> None:
    """The generated sequences against the plan of the spec stored with ``ds``: missing ones are a
    warning (a problem with require_complete), ones outside the plan a warning."""
    m = ds.manifest
    spec = ds.attrs.get("spec") or {}
    planned = _planned_sequences(spec)
    if planned is not None:
        rep.planned = len(planned)
        missing = sorted(set(planned) - set(m["sequences"]))
        if missing:
            msg = (f"{len(missing)} of {len(planned)} planned sequences are not generated yet "
                   f"(e.g. {', '.join(missing[:3])}); rerun generate to continue")
            (rep.problem if require_complete else rep.warn)("sequences", "complete", msg)
        extra = sorted(set(m["sequences"]) - set(planned))
        if extra:
            rep.warn("sequences", "complete", f"{len(extra)} sequences are not in the current spec's plan "
                                              f"(e.g. {extra[0]})")


def check_dataset(path, *, body=None, stride: int = 1, max_depth: float = DEFAULT_MAX_DEPTH,
                  max_strain: float = DEFAULT_MAX_STRAIN, require_complete: bool = False, progress=None,
                  device: str = "auto", workers: int = 0) -> CheckReport:
    """Check a store (see the module doc). Returns a :class:`CheckReport`.

    stride: check the body penetration on every stride-th frame (NaN, strain, missing frames and
    checksums always cover every frame: they need no body); body: BodyModel or source to re-pose
    with (default: the store's, verified by hash); progress(done, total) per sequence; device: Warp device of the
    surface queries ("auto": CUDA when present, else the CPU); workers: processes that check the
    sequences (0: :func:`default_workers`; 1: this process alone). The report is the same for any
    number of workers.
    """
    import zarr

    from simgen._warp_log import quiet_warp
    from simgen.dataset.reader import open_dataset
    from simgen.errors import InputError

    if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
        raise InputError(f"--stride must be an integer >= 1, got {stride!r}")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
        raise InputError(f"--workers must be an integer >= 0, got {workers!r}")
    quiet_warp()
    if device == "auto":
        import warp as wp

        device = "cuda:0" if wp.get_cuda_device_count() > 0 else "cpu"
    ds = open_dataset(path)
    rep = CheckReport(path=ds.path)
    loc, m = ds.loc, ds.manifest
    bm = ds.load_body(body)
    root = zarr.open_group(loc.url(), mode="r")

    template_ok = _check_manifest(rep, loc, m)
    ctx = _context(ds, bm, template_ok, device)
    if ctx.tpl is not None:
        _check_fits(rep, ds, ctx)

    ids = sorted(m["sequences"])
    limits = (stride, max_depth, max_strain)
    workers = min(workers or default_workers(len(ids)), max(len(ids), 1))
    if workers == 1:
        pinched_seqs = _check_sequences(rep, ids, _Store(ds, bm, root, ctx), limits, progress)
    else:
        pinched_seqs = _check_in_workers(rep, ids, (path, body, device, template_ok), limits, workers, progress)

    if pinched_seqs:
        frames_total = sum(n for _, n, _ in pinched_seqs)
        worst = max(pinched_seqs, key=lambda e: e[2])
        rep.warn("sequences", "strain-pinched",
                 f"{len(pinched_seqs)} sequences have {frames_total} frames with triangles stretched past "
                 f"{100 * max_strain:g}% only where the cloth touches a body self-intersection (largest "
                 f"{100 * worst[2]:.0f}% in {worst[0]}); counted apart like the penetration")
    _check_completeness(rep, ds, require_complete)
    return rep


#: Sequences per share of a worker (:func:`check_dataset` with workers > 1).
_SHARE = 8


def default_workers(sequences: int) -> int:
    """Processes for checking ``sequences`` sequences: one per core up to 16, and one per 16 sequences
    (a worker's start, its imports and Warp, costs a few seconds)."""
    import os

    return max(1, min(os.cpu_count() or 1, 16, sequences // 16))


@dataclass
class _Store:
    """What the per-sequence checks read: the opened store ``ds``, its body ``bm``, its Zarr ``root``
    and the :class:`_Context`."""

    ds: object
    bm: object
    root: object
    ctx: _Context


def _check_sequences(rep: CheckReport, ids: list, store: _Store, limits: tuple, progress=None) -> list:
    """The checks of sequences ``ids`` into ``rep``; limits: (stride, max_depth [m], max_strain).
    Returns (sequence, frames, largest strain) of those with outliers only at body self-intersections."""
    stride, max_depth, max_strain = limits
    m, ctx = store.ds.manifest, store.ctx
    pinched_seqs = []
    for n, sid in enumerate(ids):
        node = f"sequences/{sid}"
        if progress is not None:
            progress(n, len(ids))
        if not _verify_node(rep, store.ds.loc, node, m["sequences"][sid], node):
            continue
        seq = _read_sequence(rep, node, store.root[node], m["sequences"][sid], ctx.num_vertices)
        if seq is None:
            continue
        _check_sequence_body(rep, node, seq, store.bm, ctx, stride, max_depth)
        if ctx.crossings is not None:
            _check_sequence_crossings(rep, node, sid, seq[0], ctx)
        if ctx.rest_inv is not None:
            pinched = _check_sequence_strain(rep, node, seq, store.bm, ctx, max_strain)
            if pinched is not None:
                pinched_seqs.append((sid, *pinched))
    if progress is not None:
        progress(len(ids), len(ids))
    return pinched_seqs


def _check_in_workers(rep: CheckReport, ids: list, opening: tuple, limits: tuple, workers: int, progress) -> list:
    """:func:`_check_sequences` of ``ids`` in ``workers`` processes, shares of ``_SHARE`` sequences
    handed out as workers free up and absorbed into ``rep`` in the order of ``ids``; opening: (path,
    body, device, template_ok), how each worker opens the store."""
    import multiprocessing

    shares = [ids[i:i + _SHARE] for i in range(0, len(ids), _SHARE)]
    pinched_seqs, done = [], 0
    with multiprocessing.get_context("spawn").Pool(workers, _worker_open, opening) as pool:
        if progress is not None:
            progress(0, len(ids))
        for share, (part, pinched) in zip(shares, pool.imap(functools.partial(_worker_check, limits=limits),
                                                              shares)):
            rep.absorb(part)
            pinched_seqs += pinched
            done += len(share)
            if progress is not None:
                progress(done, len(ids))
    return pinched_seqs


_WORKER: dict = {}


def _worker_open(path, body, device: str, template_ok: bool) -> None:
    """A check worker's start: open the store, its body and the checks' context once."""
    import zarr

    from simgen._warp_log import quiet_warp
    from simgen.dataset.reader import open_dataset

    quiet_warp()
    ds = open_dataset(path)
    bm = ds.load_body(body)
    _WORKER["store"] = _Store(ds, bm, zarr.open_group(ds.loc.url(), mode="r"), _context(ds, bm, template_ok, device))


def _worker_check(ids: list, limits: tuple) -> tuple[CheckReport, list]:
    part = CheckReport(path=_WORKER["store"].ds.path)
    return part, _check_sequences(part, ids, _WORKER["store"], limits)


def _planned_sequences(spec: dict) -> list[str] | None:
    """Sequence ids the stored spec plans, or None when the motions cannot be listed here."""
    from simgen.dataset.spec import DatasetSpec, ShapeSpec
    from simgen.errors import InputError

    try:
        s = DatasetSpec(name=spec["name"], garments=list(spec["garments"]))
        s.shapes_generator = "list"
        s.shape_list = tuple(ShapeSpec(x["id"], tuple(x["betas"])) for x in spec["shapes"])
        s.motion_library = tuple(spec.get("motion_library", ()))
        s.motion_files = tuple(spec.get("motion_files", ()))
        s.test_motions = tuple(spec.get("test_motions", ()))
        s.train_motions = tuple(spec.get("train_motions", ()))
        s.source = spec.get("source", "<store>")
        s.base_dir = spec.get("base_dir", ".")
        motions = s.motions()
    except (KeyError, TypeError, InputError):
        return None
    return [f"{mo.id}__{sh.id}" for mo in motions for sh in s.shapes()]
