"""Import of a user's garment from a Wavefront OBJ file: validation, safe repairs, skinning, saving.

What is read: ``v`` (the first three coordinates; a w or vertex colours after them are ignored) and
``f`` (any of ``i``, ``i/t``, ``i//n``, ``i/t/n``; negative indices count back from the last vertex
read so far; polygons are split into triangle fans). ``vt``, ``vn``, ``vp``, groups, objects,
smoothing groups, materials, lines and points are ignored (the report counts them); a backslash at
the end of a line continues it. Unknown statements are ignored with a warning.

What refuses a file (every problem found is listed, with its count and examples): unreadable,
empty, binary or not an OBJ; malformed statements or face indices out of range; NaN or inf
coordinates; more than :data:`MAX_TRIANGLES` triangles; an absurd scale or units (the garment's
bounding box against the body's: a file in centimetres, millimetres, inches or decimetres is
recognised and the ``scale=`` to use is named) or a garment that is not placed on the body (a
Z-up file is recognised); non-convex polygons (their triangle fan would fold over); degenerate or
zero-area triangles; duplicated triangles; non-manifold edges or vertices; a non-orientable
surface; vertices inside the template body (negative signed distance).

What is repaired, and only that (the report says what was done): duplicate vertices (equal or
within :data:`MERGE_TOLERANCE` metres) are merged, unreferenced vertices dropped, and triangles
are re-oriented consistently with normals facing away from the body (no vertex moves).

Warnings that do not refuse a file: vertices within 2 mm of the body, several connected pieces,
very thin triangles, unknown statements.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from simgen.errors import InputError

__all__ = [
    "ImportReport",
    "ReportItem",
    "GarmentImportError",
    "import_garment_obj",
    "validate_obj",
    "GARMENT_NAME_PATTERN",
    "MAX_TRIANGLES",
    "MERGE_TOLERANCE",
    "MIN_CLEARANCE",
    "DIFFUSED_DISTANCE",
]

GARMENT_NAME_PATTERN = re.compile(r"^[A-Za-z0-9_-]+$")
MAX_TRIANGLES = 200_000
MERGE_TOLERANCE = 1e-7  # [m] vertices closer than this are one vertex
MIN_CLEARANCE = 2e-3  # [m] the templates' clearance to the body; closer vertices are reported
#: Skinning chosen by default: "diffused" when the 90th percentile of the vertices' distance to the
#: body exceeds this [m] (loose garments: skirts, dresses, coats), else "closest".
DIFFUSED_DISTANCE = 0.03
DEFAULT_MATERIAL = "cotton"
MAX_FILE_BYTES = 512 * 1024 * 1024
# Zero area: below 1e-10 m^2 (a triangle ~15 um across) or a height below 1 um (collinear corners).
_MIN_AREA = 1e-10
_MIN_HEIGHT = 1e-6
_THIN_ANGLE = 1.0  # [deg] thinner triangles are warned about (they slow down and stiffen the solver)
_MAX_EXAMPLES = 5
# Length units a file may have been written in: metres per file unit.
_UNITS = (("centimetres", 0.01), ("millimetres", 0.001), ("inches", 0.0254), ("decimetres", 0.1))
# The statements of the OBJ format that carry nothing a garment needs.
_IGNORED = {"vt", "vn", "vp", "g", "o", "s", "usemtl", "mtllib", "l", "p", "cstype", "deg", "bmat", "step",
            "curv", "curv2", "surf", "parm", "trim", "hole", "scrv", "sp", "end", "con", "mg", "bevel",
            "c_interp", "d_interp", "lod", "shadow_obj", "trace_obj", "ctech", "stech", "maplib", "usemap"}


# --------------------------------------------------------------------------- report
@dataclass
class ReportItem:
    """One finding of an import.

    kind: "problem" (refuses the file), "repair" (done), "warning" (accepted) or "note" (facts).
    code: short identifier ("non_manifold_edges", "merged_vertices", ...). message: one sentence.
    count: how many elements are concerned. examples: up to 5 of them (line numbers, indices, values).
    """

    kind: str
    code: str
    message: str
    count: int = 0
    examples: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"kind": self.kind, "code": self.code, "message": self.message, "count": int(self.count),
                "examples": _plain(self.examples)}


@dataclass
class ImportReport:
    """Everything the validation of one OBJ file found, and what was repaired.

    path: the file. items: :class:`ReportItem` in the order found. stats: numbers of the mesh read
    and of the repaired mesh (vertices, triangles, bounding box [m], distance to the body [m], edge
    lengths [m], smallest angle [deg], openings, skinning).
    """

    path: str
    items: list[ReportItem] = field(default_factory=list)
    stats: dict = field(default_factory=dict)

    def add(self, kind: str, code: str, message: str, count: int = 0, examples=()) -> ReportItem:
        item = ReportItem(kind, code, message, int(count), list(examples)[:_MAX_EXAMPLES])
        self.items.append(item)
        return item

    def _of(self, kind: str) -> list[ReportItem]:
        return [i for i in self.items if i.kind == kind]

    @property
    def problems(self) -> list[ReportItem]:
        return self._of("problem")

    @property
    def repairs(self) -> list[ReportItem]:
        return self._of("repair")

    @property
    def warnings(self) -> list[ReportItem]:
        return self._of("warning")

    @property
    def notes(self) -> list[ReportItem]:
        return self._of("note")

    @property
    def passed(self) -> bool:
        """True when nothing refuses the file."""
        return not self.problems

    def format(self) -> str:
        """A human-readable multi-line report."""
        verdict = "OK" if self.passed else f"REFUSED ({len(self.problems)} problem(s))"
        lines = [f"OBJ import check of {self.path}: {verdict}"]
        for title, kind in (("Problems", "problem"), ("Repairs", "repair"), ("Warnings", "warning"),
                            ("Notes", "note")):
            items = self._of(kind)
            if not items:
                continue
            lines.append(f"{title}:")
            for it in items:
                ex = f" e.g. {', '.join(str(e) for e in it.examples)}" if it.examples else ""
                lines.append(f"  - [{it.code}] {it.message}{ex}")
        if self.stats:
            lines.append("Stats:")
            for k, v in self.stats.items():
                lines.append(f"  {k}: {_plain(v)}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {"path": self.path, "passed": self.passed, "items": [i.to_dict() for i in self.items],
                "stats": _plain(self.stats)}


class GarmentImportError(InputError):
    """An OBJ import refused; ``report`` holds every problem found (an :class:`ImportReport`)."""

    def __init__(self, message: str, report: ImportReport):
        super().__init__(message)
        self.report = report


def _plain(value):
    """JSON-friendly copy (numpy scalars and arrays to Python)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float):
        return round(value, 9)
    return value


# --------------------------------------------------------------------------- parsing
@dataclass
class _Parsed:
    vertices: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3) zero-based
    face_lines: np.ndarray  # (F,) OBJ line number of each triangle
    polygons: int  # faces with more than 3 corners
    polygon_examples: list
    ignored: dict  # keyword -> count
    unknown: list  # (line, keyword)
    errors: list  # "line N: ..." messages
    statements: int


def _parse_obj(text: str) -> _Parsed:
    verts: list[list[float]] = []
    faces: list[tuple[int, int, int]] = []
    face_lines: list[int] = []
    polygons, polygon_examples = 0, []
    ignored: dict[str, int] = {}
    unknown: list = []
    errors: list[str] = []
    statements = 0
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        lineno = i + 1
        line = lines[i]
        i += 1
        # A trailing backslash continues the statement on the next line.
        while line.endswith("\\") and i < len(lines):
            line = line[:-1] + " " + lines[i]
            i += 1
        hash_at = line.find("#")
        if hash_at >= 0:
            line = line[:hash_at]
        tokens = line.split()
        if not tokens:
            continue
        statements += 1
        key = tokens[0]
        if key == "v":
            if len(tokens) < 4:
                errors.append(f"line {lineno}: vertex has {len(tokens) - 1} coordinate(s), needs 3")
                continue
            try:
                verts.append([float(tokens[1]), float(tokens[2]), float(tokens[3])])
            except ValueError:
                errors.append(f"line {lineno}: vertex coordinates {' '.join(tokens[1:4])!r} are not numbers")
        elif key == "f":
            corners = tokens[1:]
            if len(corners) < 3:
                errors.append(f"line {lineno}: face has {len(corners)} corner(s), needs at least 3")
                continue
            idx = []
            for c in corners:
                head = c.split("/", 1)[0]
                try:
                    k = int(head)
                except ValueError:
                    errors.append(f"line {lineno}: face corner {c!r} is not a vertex index")
                    idx = None
                    break
                if k == 0:
                    errors.append(f"line {lineno}: face corner {c!r}: OBJ indices start at 1")
                    idx = None
                    break
                if k < 0:
                    k = len(verts) + k  # relative to the vertices read so far
                    if k < 0:
                        errors.append(f"line {lineno}: face corner {c!r} points before the first vertex")
                        idx = None
                        break
                else:
                    k -= 1
                idx.append(k)
            if idx is None:
                continue
            if len(idx) > 3:
                polygons += 1
                if len(polygon_examples) < _MAX_EXAMPLES:
                    polygon_examples.append(f"line {lineno} ({len(idx)} corners)")
            for k in range(1, len(idx) - 1):  # triangle fan around the first corner
                faces.append((idx[0], idx[k], idx[k + 1]))
                face_lines.append(lineno)
        elif key in _IGNORED:
            ignored[key] = ignored.get(key, 0) + 1
        else:
            unknown.append((lineno, key[:20]))
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    v = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
    if len(f) and (f.max() >= len(v)):
        bad = np.flatnonzero((f >= len(v)).any(axis=1))
        for t in bad[:_MAX_EXAMPLES]:
            errors.append(f"line {face_lines[t]}: face uses vertex {int(f[t].max()) + 1} but the file has "
                          f"{len(v)} vertices")
        if len(bad) > _MAX_EXAMPLES:
            errors.append(f"{len(bad) - _MAX_EXAMPLES} more faces use vertices the file does not have")
    return _Parsed(v, f, np.asarray(face_lines, dtype=np.int64), polygons, polygon_examples, ignored, unknown,
                   errors, statements)


# --------------------------------------------------------------------------- mesh helpers
def _merge_duplicates(v: np.ndarray, tol: float) -> np.ndarray:
    """Representative (smallest index) of each vertex's cluster of points within tol, shape (V,)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    pairs = cKDTree(v).query_pairs(tol, output_type="ndarray")
    if len(pairs) == 0:
        return np.arange(len(v))
    g = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(v), len(v)))
    _, labels = connected_components(g, directed=False)
    rep = np.full(labels.max() + 1, len(v))
    np.minimum.at(rep, labels, np.arange(len(v)))
    return rep[labels]


def _orientation_flips(faces: np.ndarray) -> np.ndarray | None:
    """Which triangles to flip so that every interior edge is walked once each way, shape (F,) bool;
    None when the surface is not orientable. Needs a mesh without non-manifold edges."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import breadth_first_order, connected_components

    F = len(faces)
    d = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    fid = np.tile(np.arange(F), 3)
    key = np.sort(d, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    ks = key[order]
    same = np.all(ks[1:] == ks[:-1], axis=1)
    h1, h2 = order[:-1][same], order[1:][same]
    f1, f2 = fid[h1], fid[h2]
    # Two triangles walking their shared edge the same way need opposite flips (parity 1).
    parity = (d[h1, 0] == d[h2, 0]).astype(np.int64)
    g = sp.coo_matrix((np.r_[parity, parity] + 1, (np.r_[f1, f2], np.r_[f2, f1])), shape=(F, F)).tocsr()
    ncomp, labels = connected_components(g, directed=False)
    flip = np.zeros(F, dtype=np.int64)
    for c in range(ncomp):
        root = int(np.flatnonzero(labels == c)[0])
        bfs, pred = breadth_first_order(g, root, directed=False, return_predecessors=True)
        if len(bfs) < 2:
            continue
        rest = bfs[1:]
        edge_parity = np.asarray(g[pred[rest], rest]).ravel() - 1
        fl = flip.tolist()
        pl = pred.tolist()
        for f, p in zip(rest.tolist(), edge_parity.tolist()):
            fl[f] = fl[pl[f]] ^ p
        flip = np.asarray(fl, dtype=np.int64)
    if np.any((flip[f1] ^ flip[f2]) != parity):
        return None
    return flip.astype(bool)


def _bbox_text(ext: np.ndarray) -> str:
    """Box dimensions as "0.4 x 1.2 x 0.3"."""
    return " x ".join(f"{e:.3g}" for e in ext)


def _point_text(p: np.ndarray) -> str:
    """A position as "(0.09, 0.55, 0)"."""
    return "(" + ", ".join(f"{e:.3g}" for e in p) + ")"


def _guess_unit(points: np.ndarray, body, ratio: float) -> tuple[str, float] | None:
    """The length unit a garment was most likely written in, from (name, metres per unit) in
    _UNITS: among the units that give it a plausible size (8 % to 150 % of the body's) and leave
    at most 5 % of its vertices inside the body, the one that puts it closest to the body (median
    distance of up to 2000 of its vertices, below 10 cm). None when no unit fits."""
    from simgen.garment.skinning import closest_body_points

    sample = points[np.linspace(0, len(points) - 1, min(len(points), 2000)).astype(np.int64)]
    best, best_d = None, 0.1
    for name, s in _UNITS:
        if not 0.08 <= ratio * s <= 1.5:
            continue
        dist = closest_body_points(sample * s, body).distance
        d = float(np.median(np.abs(dist)))
        if np.mean(dist < 0) <= 0.05 and d < best_d:
            best, best_d = (name, s), d
    return best


# --------------------------------------------------------------------------- validation
@dataclass
class _Checked:
    report: ImportReport
    vertices: np.ndarray | None = None
    faces: np.ndarray | None = None
    distance: np.ndarray | None = None


def _read(path: Path, report: ImportReport) -> str | None:
    if not path.exists():
        report.add("problem", "missing", f"the file {path} does not exist")
        return None
    if not path.is_file():
        report.add("problem", "unreadable", f"{path} is not a file")
        return None
    try:
        size = path.stat().st_size
        if size > MAX_FILE_BYTES:
            report.add("problem", "too_large", f"the file is {size / 2**20:.0f} MiB, more than an OBJ of "
                       f"{MAX_TRIANGLES} triangles needs ({MAX_FILE_BYTES // 2**20} MiB at most)", 1)
            return None
        data = path.read_bytes()
    except OSError as exc:
        report.add("problem", "unreadable", f"the file cannot be read ({exc.strerror or exc})")
        return None
    if not data.strip():
        report.add("problem", "empty", "the file is empty")
        return None
    if b"\x00" in data[: 1 << 20]:
        report.add("problem", "not_obj", "the file holds binary data, not the text of a Wavefront OBJ")
        return None
    # Names and comments in other encodings must not stop an import: undecodable bytes become U+FFFD.
    return data.decode("utf-8", errors="replace")


def _check(path, body, scale) -> _Checked:
    """Validate and repair one OBJ garment for ``body``; nothing is written.

    Every finding goes to the returned report. When nothing refuses the file, the result also
    holds the repaired mesh: vertices [m] (V, 3), faces (F, 3) facing away from the body, and
    each vertex's signed distance to the body [m] (V,). Only a bad ``body`` or ``scale`` raises.
    """
    from simgen.body.model import BodyModel

    if not isinstance(body, BodyModel):
        raise InputError(f"body must be a simgen BodyModel, got {type(body).__name__}")
    path = Path(path)
    report = ImportReport(path=str(path))
    out = _Checked(report)
    if scale is not None:
        ok = isinstance(scale, (int, float, np.integer, np.floating)) and not isinstance(scale, bool)
        if not (ok and np.isfinite(scale) and scale > 0):
            raise InputError(f"scale must be a positive number (metres per file unit), got {scale!r}")
    text = _read(path, report)
    if text is None:
        return out
    p = _parse_obj(text)
    if not _check_statements(p, report):
        return out
    v = p.vertices * (1.0 if scale is None else float(scale))
    if not _check_size_and_placement(v, p.faces, body, scale, report):
        return out
    if p.polygons:
        _check_polygons_convex(v, p.faces, p.face_lines, report)
    v, f = _merge_and_drop_vertices(v, p.faces, report)
    collapsed = _check_triangles(v, f, p.face_lines, report)
    _check_topology(v, f[~collapsed], report)
    near = _check_body_distance(v, body, report)
    if report.problems:
        return out
    f = _orient_outward(v, f, p.face_lines, body, near, report)
    if f is None:
        return out
    _record_openings(f, report)
    out.vertices, out.faces, out.distance = v, f, near.distance
    return out


def _check_statements(p: _Parsed, report: ImportReport) -> bool:
    """Report what the parse found (syntax errors, ignored and unknown statements, polygons, point
    clouds, too many triangles, NaN/inf vertices); True when the mesh checks can go on."""
    st = report.stats
    st["file_vertices"], st["file_triangles"] = len(p.vertices), len(p.faces)
    if p.statements == 0:
        report.add("problem", "empty", "the file has no statements (only blank lines and comments)")
        return False
    unknown_examples = [f"line {ln}: {k!r}" for ln, k in p.unknown]
    if len(p.vertices) == 0 and len(p.faces) == 0 and not p.errors:
        report.add("problem", "not_obj", f"none of the file's {p.statements} statement(s) is an OBJ vertex "
                   f"('v') or face ('f'): it is not a Wavefront OBJ garment", len(p.unknown), unknown_examples)
        return False
    if p.errors:
        report.add("problem", "syntax", f"{len(p.errors)} malformed statement(s): {p.errors[0]}", len(p.errors),
                   p.errors)
    if p.unknown:
        report.add("warning", "unknown_statements", f"{len(p.unknown)} line(s) with statements OBJ does not "
                   f"define were ignored", len(p.unknown), unknown_examples)
    if p.ignored:
        counts = ", ".join(f"{n} {k}" for k, n in sorted(p.ignored.items()))
        report.add("note", "ignored", f"ignored statements: {counts}", sum(p.ignored.values()))
    if p.polygons:
        report.add("note", "triangulated", f"{p.polygons} polygon(s) with more than 3 corners were split into "
                   f"triangle fans around their first corner", p.polygons, p.polygon_examples)
    if len(p.faces) == 0 and not p.errors:
        report.add("problem", "no_faces", f"the file has {len(p.vertices)} vertices but no faces: "
                   f"a point cloud, not a garment surface")
    if len(p.faces) > MAX_TRIANGLES:
        report.add("problem", "too_many_triangles", f"{len(p.faces)} triangles, more than the {MAX_TRIANGLES} "
                   f"simgen accepts (decimate the garment first); the other checks were skipped", len(p.faces))
        return False
    bad = ~np.all(np.isfinite(p.vertices), axis=1)
    if np.any(bad):
        report.add("problem", "non_finite", f"{int(bad.sum())} vertex(es) have NaN or infinite coordinates",
                   int(bad.sum()), [f"vertex {int(k) + 1}" for k in np.flatnonzero(bad)])
    return not report.problems


def _check_size_and_placement(v: np.ndarray, f: np.ndarray, body, scale, report: ImportReport) -> bool:
    """Size and placement of the garment against the body's rest template, before any tolerance in
    metres applies: v [m] (V, 3) after ``scale``, f (F, 3). A size more than 2x or under 1% of the
    body's is refused (naming the likely unit), as is a bounding box that misses the body's by more
    than 10 cm (naming a Z-up file). Records the bounding box [m]; True when the garment fits."""
    used = np.unique(f)
    lo, hi = v[used].min(axis=0), v[used].max(axis=0)
    body_lo, body_hi = body.v_template.min(axis=0), body.v_template.max(axis=0)
    body_size = float(np.max(body_hi - body_lo))
    size = float(np.max(hi - lo))
    report.stats["bounding_box_min"], report.stats["bounding_box_max"] = lo, hi
    ratio = size / body_size
    unit = "" if scale is None else f" (after scale={scale:g})"

    def overlap(a_lo, a_hi, margin=0.1):
        return bool(np.all(a_lo <= body_hi + margin) and np.all(a_hi >= body_lo - margin))

    if ratio > 2.0 or ratio < 0.01:
        guess = _guess_unit(v[used], body, ratio) if ratio > 2.0 else None
        if guess is not None:
            name, s = guess
            hint = f": the file looks like {name}; import it with scale={s:g} (`--scale {s:g}`)"
        elif ratio > 2.0:
            hint = ": is it in other units than metres, or not a garment of this body?"
        else:
            hint = ": too small for a garment of this body (is it in kilometres, or a fragment?)"
        report.add("problem", "scale", f"the garment's bounding box{unit} ({_bbox_text(hi - lo)}) is {ratio:.3g} "
                   f"times the body's size ({body_size:.2f} m){hint}", 1)
        return False
    if not overlap(lo, hi):
        turned = np.stack([v[used][:, 0], v[used][:, 2], -v[used][:, 1]], axis=1)
        zup = overlap(turned.min(axis=0), turned.max(axis=0))
        hint = " (it looks Z-up: simgen is Y-up)" if zup else ""
        report.add("problem", "placement", f"the garment's bounding box{unit} {_point_text(lo)} .. {_point_text(hi)} "
                   f"does not meet the body's {_point_text(body_lo)} .. {_point_text(body_hi)}{hint}: garments "
                   f"must be modelled on the template body in rest pose, Y-up, in metres", 1)
        return False
    return True


def _check_polygons_convex(v: np.ndarray, f: np.ndarray, face_lines: np.ndarray, report: ImportReport) -> None:
    """Refuse polygons whose triangle fan folds over itself (non-convex: the triangles would
    overlap). v [m] (V, 3); f (F, 3) the fans' triangles; face_lines (F,) their OBJ lines."""
    line_ids, group = np.unique(face_lines, return_inverse=True)
    sizes = np.bincount(group)
    area_vec = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    total = np.zeros((len(line_ids), 3))
    np.add.at(total, group, area_vec)
    folded = (sizes[group] > 1) & (np.einsum("ij,ij->i", area_vec, total[group]) < 0)
    if np.any(folded):
        lines = np.unique(face_lines[folded])
        report.add("problem", "non_convex_polygons", f"{len(lines)} polygon(s) are not convex: their fan "
                   f"triangulation folds over itself (triangulate them in your modelling tool)", len(lines),
                   [f"line {int(ln)}" for ln in lines])


def _merge_and_drop_vertices(v: np.ndarray, f: np.ndarray, report: ImportReport) -> tuple[np.ndarray, np.ndarray]:
    """The safe repairs: merge duplicate vertices (within MERGE_TOLERANCE [m]) and drop unreferenced
    ones. v [m] (V, 3), f (F, 3) -> the kept vertices [m] (V', 3) and f re-indexed (F, 3), rows in
    the same order; records the counts in the report's stats."""
    rep = _merge_duplicates(v, MERGE_TOLERANCE)
    merged = int(np.sum(rep != np.arange(len(v))))
    if merged:
        dup = np.flatnonzero(rep != np.arange(len(v)))
        report.add("repair", "merged_vertices", f"merged {merged} duplicate vertex(es) (equal or within "
                   f"{MERGE_TOLERANCE:g} m of another)", merged,
                   [f"vertex {int(k) + 1} -> {int(rep[k]) + 1}" for k in dup])
    f = rep[f]
    used = np.unique(f)
    unref = len(v) - merged - len(used)
    if unref:
        isolated = np.setdiff1d(np.flatnonzero(rep == np.arange(len(v))), used)
        report.add("repair", "unreferenced_vertices", f"dropped {unref} vertex(es) no face uses", unref,
                   [f"vertex {int(k) + 1}" for k in isolated])
    new_index = np.full(len(v), -1, dtype=np.int64)
    new_index[used] = np.arange(len(used))
    v, f = v[used], new_index[f]
    report.stats["vertices"], report.stats["triangles"] = len(v), len(f)
    return v, f


def _check_triangles(v: np.ndarray, f: np.ndarray, face_lines: np.ndarray, report: ImportReport) -> np.ndarray:
    """Refuse degenerate and duplicated triangles; warn about thin ones; record the smallest angles
    [deg] and edge lengths [m]. v [m] (V, 3), f (F, 3), face_lines (F,) their OBJ lines.
    Returns which triangles repeat a corner, shape (F,) bool."""
    from simgen.garment import mesh as m

    st = report.stats
    collapsed = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    area = m.triangle_areas(v, f)
    longest = np.max(np.stack([np.linalg.norm(v[f[:, a]] - v[f[:, b]], axis=1)
                               for a, b in ((0, 1), (1, 2), (2, 0))]), axis=0)
    height = 2.0 * area / np.maximum(longest, 1e-300)
    degenerate = collapsed | (area < _MIN_AREA) | (height < _MIN_HEIGHT)
    if np.any(degenerate):
        k = np.flatnonzero(degenerate)
        report.add("problem", "degenerate_triangles", f"{len(k)} degenerate triangle(s) (zero area, collinear or "
                   f"repeated corners)", len(k),
                   [f"line {face_lines[t]} (area {area[t]:.2g} m^2)" for t in k])
    sorted_f = np.sort(f, axis=1)
    _, first, counts = np.unique(sorted_f, axis=0, return_index=True, return_counts=True)
    if np.any(counts > 1):
        dupes = first[counts > 1]
        report.add("problem", "duplicate_triangles", f"{int(np.sum(counts - 1))} triangle(s) repeat another "
                   f"triangle's corners", int(np.sum(counts - 1)), [f"line {face_lines[t]}" for t in dupes])
    good = ~degenerate
    if np.any(good):
        angles = m.triangle_angles(v, f[good])
        min_angle = np.nanmin(angles, axis=1)
        st["min_angle_deg"] = float(np.nanmin(min_angle))
        st["min_angle_deg_p5"] = float(np.nanpercentile(min_angle, 5))
        thin = int(np.sum(min_angle < _THIN_ANGLE))
        if thin:
            report.add("warning", "thin_triangles", f"{thin} triangle(s) have an angle below {_THIN_ANGLE:g} deg "
                       f"(they stiffen and slow down the simulation; consider remeshing)", thin)
        e = m.unique_edges(f[good])
        lengths = m.edge_lengths(v, e)
        st["edge_length_min"], st["edge_length_median"], st["edge_length_max"] = (
            float(lengths.min()), float(np.median(lengths)), float(lengths.max()))
    return collapsed


def _check_topology(v: np.ndarray, proper: np.ndarray, report: ImportReport) -> None:
    """Refuse non-manifold edges and vertices; warn about several pieces. v [m] (V, 3); proper (F', 3)
    the triangles with three distinct corners (collapsed ones are reported as degenerate)."""
    from simgen.garment import mesh as m

    nm_edges = m.non_manifold_edges(proper)
    if len(nm_edges):
        report.add("problem", "non_manifold_edges", f"{len(nm_edges)} edge(s) are shared by more than two "
                   f"triangles", len(nm_edges),
                   [f"vertices {int(a) + 1}-{int(b) + 1} at {_point_text(v[a])}" for a, b in nm_edges])
    nm_verts = m.non_manifold_vertices(proper)
    if len(nm_verts):
        report.add("problem", "non_manifold_vertices", f"{len(nm_verts)} vertex(es) join surface pieces that "
                   f"share no edge there (bow-tie vertices)", len(nm_verts),
                   [f"vertex at {_point_text(v[k])}" for k in nm_verts])
    ncomp, _ = m.connected_components(proper, len(v))
    report.stats["connected_components"] = ncomp
    if ncomp > 1:
        report.add("warning", "several_pieces", f"the garment has {ncomp} separate pieces", ncomp)


def _check_body_distance(v: np.ndarray, body, report: ImportReport):
    """Refuse vertices inside the body; warn about those within MIN_CLEARANCE of it; record the
    distance statistics [m]. v [m] (V, 3). Returns the closest body points of the vertices (their
    ``distance`` [m] (V,), negative inside; ``face`` and ``bary`` on the body's template)."""
    from simgen.garment.skinning import closest_body_points

    near = closest_body_points(v, body)
    dist = near.distance
    inside = dist < 0
    if np.any(inside):
        k = np.flatnonzero(inside)
        k = k[np.argsort(dist[k])]
        report.add("problem", "inside_body", f"{len(k)} vertex(es) lie inside the body (deepest "
                   f"{-dist[k[0]] * 1000:.1f} mm)", len(k),
                   [f"vertex at {_point_text(v[t])} ({dist[t] * 1000:.1f} mm)" for t in k])
    close = (~inside) & (dist < MIN_CLEARANCE)
    if np.any(close):
        report.add("warning", "close_to_body", f"{int(close.sum())} vertex(es) are within "
                   f"{MIN_CLEARANCE * 1000:g} mm of the body (the templates keep {MIN_CLEARANCE * 1000:g} mm)",
                   int(close.sum()), [f"vertex at {_point_text(v[t])} ({dist[t] * 1000:.2f} mm)"
                                      for t in np.flatnonzero(close)])
    st = report.stats
    st["distance_to_body_min"] = float(dist.min())
    st["distance_to_body_median"] = float(np.median(dist))
    st["distance_to_body_p90"] = float(np.percentile(dist, 90))
    st["distance_to_body_max"] = float(dist.max())
    return near


def _orient_outward(v: np.ndarray, f: np.ndarray, face_lines: np.ndarray, body, near,
                    report: ImportReport) -> np.ndarray | None:
    """Re-orient a clean manifold's triangles consistently, then each connected piece so that its
    normals face away from the body (an area-weighted vote). v [m] (V, 3), f (F, 3), face_lines (F,);
    near: the vertices' closest body points. Returns the re-oriented faces (F, 3), or None (and a
    problem) when the surface is not orientable."""
    from simgen.garment import mesh as m

    flips = _orientation_flips(f)
    if flips is None:
        report.add("problem", "non_orientable", "the surface is not orientable (a Moebius-like twist): its "
                   "triangles cannot all face one side", 1)
        return None
    if np.any(flips):
        f = np.where(flips[:, None], f[:, ::-1], f)
        report.add("repair", "reoriented", f"re-oriented {int(flips.sum())} triangle(s) to agree with their "
                   f"neighbours", int(flips.sum()), [f"line {face_lines[t]}" for t in np.flatnonzero(flips)])
    closest = np.einsum("pc,pcd->pd", near.bary, body.v_template[body.faces[near.face]])
    away = v - closest
    away /= np.maximum(np.linalg.norm(away, axis=1, keepdims=True), 1e-12)
    normal = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    vote = np.einsum("fd,fd->f", normal, away[f].mean(axis=1))
    _, labels = m.connected_components(f, len(v))
    face_label = labels[f[:, 0]]
    score = np.bincount(face_label, weights=vote, minlength=labels.max() + 1)
    inward = score[face_label] < 0
    if np.any(inward):
        f = np.where(inward[:, None], f[:, ::-1], f)
        report.add("repair", "flipped_outward", f"flipped {int(inward.sum())} triangle(s) so that their normals "
                   f"face away from the body", int(inward.sum()))
    return f


def _record_openings(f: np.ndarray, report: ImportReport) -> None:
    """Record the number of openings (boundary loops) of f (F, 3) and their sizes [vertices]; a
    warning when they cannot be traced."""
    from simgen.garment import mesh as m

    try:
        loops = m.boundary_loops(f)
        report.stats["openings"] = len(loops)
        report.stats["opening_sizes"] = sorted((len(lp) for lp in loops), reverse=True)
    except ValueError as exc:
        report.add("warning", "openings", f"openings could not be traced ({exc})")


def validate_obj(path, body, *, scale: float | None = None) -> ImportReport:
    """Check an OBJ garment for import without writing anything.

    Args:
        path: the .obj file.
        body: the :class:`~simgen.body.BodyModel` the garment is dressed on (its rest template).
        scale: metres per file unit (e.g. 0.01 for a file in centimetres); None: metres.

    Returns:
        The :class:`ImportReport` (``.passed`` False when the file would be refused). Only a bad
        ``body`` or ``scale`` argument raises (InputError); every problem of the file is reported.
    """
    return _check(path, body, scale).report


def _refusal(path: Path, report: ImportReport) -> GarmentImportError:
    first = report.problems[0]
    more = len(report.problems) - 1
    tail = f" (and {more} more problem(s): see the report)" if more else ""
    return GarmentImportError(f"{path}: garment import refused: {first.message}{tail}", report)


def import_garment_obj(path, name: str, body, *, overwrite: bool = False, skinning: str | None = None,
                       out_dir=None, scale: float | None = None, skinning_options: dict | None = None):
    """Import an OBJ garment for a body: validate, repair what is safe, compute skinning weights, save.

    Args:
        path: the .obj file (metres, Y-up, dressed on the body's template in rest pose).
        name: garment name, letters, digits, '_' and '-' only; the folder and file stem.
        body: the :class:`~simgen.body.BodyModel`.
        overwrite: replace an existing garment of that name in the target folder.
        skinning: "closest" or "diffused" (see :func:`simgen.garment.compute_skin_weights`);
            None picks "diffused" when the 90th percentile of the distance to the body exceeds
            :data:`DIFFUSED_DISTANCE` (a loose garment such as a skirt), else "closest".
        out_dir: folder to save into (the garment goes to OUT_DIR/NAME/); default
            ``simgen.assets.user_dir("garments", body_asset_id(body))``. Never inside the package.
        scale: metres per file unit, e.g. 0.01 for a file in centimetres.
        skinning_options: extra keyword arguments of compute_skin_weights (num_samples, sigma,
            smoothing_iterations, seed).

    Returns:
        (Garment, ImportReport). The garment's metadata records the body (id, name, hash), the
        openings, the default material, the source file and its SHA-256, the skinning and the report.

    Raises:
        GarmentImportError (an InputError): the file is refused; its sentence names the file and the
        first problem, ``.report`` lists them all. Nothing is written then.
        InputError: a bad name, an existing garment without ``overwrite``, a bad argument.
    """
    from simgen.assets import body_asset_id, user_dir
    from simgen.garment.garment import Garment
    from simgen.garment.skinning import SKINNING_METHODS, compute_skin_weights

    path = Path(path)
    if not isinstance(name, str) or not GARMENT_NAME_PATTERN.match(name):
        raise InputError(f"garment name {name!r} is invalid: use only letters, digits, '_' and '-'")
    if skinning is not None and skinning not in SKINNING_METHODS:
        raise InputError(f"skinning {skinning!r} is not one of {', '.join(SKINNING_METHODS)}")
    options = dict(skinning_options or {})
    unknown = set(options) - {"num_samples", "sigma", "smoothing_iterations", "seed"}
    if unknown:
        raise InputError(f"skinning_options: unknown option(s) {', '.join(sorted(unknown))}")
    folder = Path(out_dir) if out_dir is not None else user_dir("garments", body_asset_id(body))
    package = Path(__file__).resolve().parents[1]
    if folder.resolve() == package or package in folder.resolve().parents:
        raise InputError(f"out_dir {folder} is inside the installed simgen package; imported garments go "
                         f"under SIMGEN_HOME or a folder of yours")
    target = folder / name
    if target.exists() and not overwrite:
        raise InputError(f"garment {name!r} already exists in {folder}; choose another name or overwrite it "
                         f"(--overwrite)")

    checked = _check(path, body, scale)
    report = checked.report
    if not report.passed:
        raise _refusal(path, report)

    v, f, dist = checked.vertices, checked.faces, checked.distance
    method = skinning or ("diffused" if float(np.percentile(dist, 90)) > DIFFUSED_DISTANCE else "closest")
    weights = compute_skin_weights(v, body, method=method, faces=f, **options)
    skin_meta = {"method": method}
    if method == "diffused":
        from simgen.garment import skinning as sk

        skin_meta.update(num_samples=options.get("num_samples", sk.DEFAULT_NUM_SAMPLES),
                         sigma=options.get("sigma", sk.DEFAULT_SIGMA),
                         smoothing_iterations=options.get("smoothing_iterations", sk.DEFAULT_SMOOTHING_ITERATIONS),
                         seed=options.get("seed", 0))
    report.stats["skinning"] = method
    report.add("note", "skinning", f"skinning weights: {method}" + (
        "" if skinning else f" (chosen: 90% of the vertices are within {np.percentile(dist, 90) * 100:.1f} cm "
        f"of the body; 'diffused' above {DIFFUSED_DISTANCE * 100:g} cm)"))

    loops = []
    from simgen.garment.mesh import boundary_loops

    try:
        loops = boundary_loops(f)
    except ValueError:
        pass
    metadata = {
        "body": {"id": body_asset_id(body), "name": body.name, "hash": body.hash},
        "openings": len(loops),
        "opening_sizes": sorted((len(lp) for lp in loops), reverse=True),
        "default_material": DEFAULT_MATERIAL,
        "made_by": {"how": "imported", "source": str(path.resolve()), "sha256": _sha256(path),
                    "scale": 1.0 if scale is None else float(scale)},
        "skinning": skin_meta,
        "import_report": report.to_dict(),
    }
    garment = Garment(name=name, vertices=v, faces=f, skin_weights=weights, metadata=metadata)
    _save_atomically(garment, folder, overwrite)
    return garment, report


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _save_atomically(garment, folder: Path, overwrite: bool) -> Path:
    """Write the garment to FOLDER/NAME/ through a temporary folder renamed into place, so a
    failure leaves no half-written garment (and an overwrite keeps the old one until the end)."""
    folder.mkdir(parents=True, exist_ok=True)
    tag = uuid.uuid4().hex[:12]
    staging = folder / f".{garment.name}.import-{tag}"
    target = folder / garment.name
    old = folder / f".{garment.name}.old-{tag}"
    try:
        garment.save(staging)
        if target.exists():
            if not overwrite:
                raise InputError(f"garment {garment.name!r} appeared in {folder} during the import")
            os.replace(target, old)
        os.replace(staging / garment.name, target)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        shutil.rmtree(old, ignore_errors=True)
    return target
