"""The tables of ``simgen eval compare``, built from its results dict (so they can be rebuilt from
compare.json anywhere), each as Markdown and JSON.

- ``physics``: thesis Table 5.1, the physics terms [J per frame] of every method on the held-out
  sequences, beside the simulation's own;
- ``curvature``: thesis Table 5.2, the mean-curvature error [1/m] against the simulation (SNUG and
  its ablations; the other methods below them for reference);
- ``cost``: thesis Table 5.3, data generation, training, runtime per frame and model size, beside
  the thesis's rows (labelled as thesis numbers);
- ``errors``: vertex error [cm] and vertices inside the body [%] per test group;
  ``errors_per_clip`` and ``inside_per_clip``: the same per held-out clip.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from simgen.learn.comparison.contestants import ABLATION_TERMS

__all__ = ["Table", "THESIS_TABLES", "build_tables", "PHYSICS_TERMS"]

PHYSICS_TERMS = ("strain", "bending", "gravity", "inertia", "collision", "potential")

#: The thesis's numbers (ch. 5): Table 5.1 (SNUG's terms and PBNS's, SNUG's material, AMASS test
#: sequences), Table 5.2 (units not stated) and Table 5.3 (AMD Ryzen 7 2700 CPU, GTX 1080 Ti GPU).
THESIS_TABLES = {
    "physics": {"SNUG": {"strain": 0.064, "bending": 0.004, "gravity": 0.028, "inertia": 0.0034},
                "PBNS [BME21]": {"strain": 0.111, "bending": 0.007, "gravity": 0.044, "inertia": 0.0035}},
    "curvature": {"w/o bending": 17.3, "w/o strain": 19.1, "w/o gravity": 7.5, "w/o inertia": 2.8, "full": 2.7},
    "cost": [
        {"method": "TailorNet [PLP20]", "data_h": 29.0, "train_h": 6.5, "runtime_ms": 10.1, "size_mb": 2114.0},
        {"method": "ch. 4 supervised [SOC19]", "data_h": 180.0, "train_h": 17.0, "runtime_ms": 2.5, "size_mb": 109.0},
        {"method": "SNUG (ch. 5)", "data_h": 0.0, "train_h": 2.0, "runtime_ms": 2.2, "size_mb": 19.0},
    ],
    "hardware": "AMD Ryzen 7 2700 CPU, Nvidia GTX 1080 Ti GPU",
}


@dataclass
class Table:
    """A table: name (file stem), title, columns [(key, header)], rows [{key: value}] (the first
    column's value is the row label), formats {key: format spec for numbers}, notes (lines below)."""

    name: str
    title: str
    columns: list
    rows: list
    formats: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)

    def _cell(self, key: str, value) -> str:
        if value is None:
            return "n/a"
        if isinstance(value, float):
            return format(value, self.formats.get(key, ".4g"))
        return str(value)

    def markdown(self) -> str:
        head = [h for _, h in self.columns]
        lines = [f"### {self.title}", "", "| " + " | ".join(head) + " |",
                 "|" + "|".join(["---"] + ["---:"] * (len(head) - 1)) + "|"]
        for row in self.rows:
            lines.append("| " + " | ".join(self._cell(k, row.get(k)) for k, _ in self.columns) + " |")
        if self.notes:
            lines.append("")
            lines.extend(self.notes)
        return "\n".join(lines) + "\n"

    def to_dict(self) -> dict:
        return {"name": self.name, "title": self.title, "columns": [{"key": k, "header": h} for k, h in self.columns],
                "rows": self.rows, "notes": self.notes}


def _labels(results: dict) -> dict:
    return {c["key"]: c["label"] for c in results["contestants"]}


def _methods(results: dict) -> list[str]:
    """Row keys: the model folders in the order given, then LBS."""
    return [c["key"] for c in results["contestants"]]


def _physics_table(results: dict) -> Table:
    labels = _labels(results)
    phys = results["overall"].get("physics") or {}
    cols = [("method", "method")] + [(t, t if t != "potential" else "total") for t in PHYSICS_TERMS]
    rows = []
    for key in ["simulation", *_methods(results)]:
        if key in phys:
            rows.append({"method": labels.get(key, "simulation (ground truth)"), **phys[key]})
    for name, terms in THESIS_TABLES["physics"].items():
        rows.append({"method": f"thesis Table 5.1: {name}", **terms})
    info = results.get("physics_info") or {}
    c = info.get("contact") or {}
    contact = (f"k = {c['stiffness']:g} J/m^3, margin {1e3 * c['margin']:g} mm, power {c['power']:g}"
               if {"stiffness", "margin", "power"} <= set(c) else "?")
    notes = [f"J per frame, mean over the {results['overall'].get('sequences', 0)} held-out sequences (each "
             f"sequence's mean over its frames; inertia from frame 2 on). Material {info.get('material', '?')}, "
             f"contact {contact}: the dataset's own simulation parameters; total: the five summed per frame "
             "(frames 2 on). Predictions without collision post-process.",
             "Thesis rows: SNUG's cotton material and its own garment, motions and body; compare orders of "
             "magnitude and rankings, not values. The simulation minimises the sum of these terms frame by frame, "
             "so a method reproduces its physics the closer each of its terms is to the simulation's row."]
    return Table("physics", "Physics terms per frame (thesis Table 5.1)", cols, rows,
                 formats={t: ".4g" for t in PHYSICS_TERMS}, notes=notes)


def _curvature_table(results: dict) -> Table:
    labels = _labels(results)
    groups = list(results["groups"])
    cols = [("method", "method"), ("left_out", "loss terms left out"), ("all", "mean-curvature error [1/m]")]
    cols += [(g, g.replace("_", " ") + " [1/m]") for g in groups]
    contestants = {c["key"]: c for c in results["contestants"]}

    def order(key: str):  # as the thesis: the ablations, the full model, then the other methods
        c = contestants[key]
        if c["kind"] != "snug":
            return (2, 0)
        return (1, 0) if not c["ablation"] else (0, min(ABLATION_TERMS.index(t) for t in c["ablation"]))

    rows = []
    for key in sorted(_methods(results), key=order):
        c = contestants[key]
        row = {"method": labels[key], "left_out": ", ".join(c["ablation"]) or ("none" if c["kind"] == "snug" else "-"),
               "all": results["overall"]["curvature_error"].get(key)}
        row.update({g: results["groups"][g]["curvature_error"].get(key) for g in groups})
        rows.append(row)
    for name, value in THESIS_TABLES["curvature"].items():
        rows.append({"method": f"thesis Table 5.2: SNUG {name}", "left_out": name[4:] if name != "full" else "none",
                     "all": value})
    sim = results["overall"].get("mean_abs_curvature")
    notes = ["Mean over held-out frames and interior garment vertices of |H_model - H_sim|, H the signed discrete "
             "mean curvature (cotangent Laplacian over barycentric areas; docs/learn.md). For scale: the simulated "
             f"garment's mean |H| is {sim:.3g} 1/m." if sim is not None else "",
             "Thesis rows: units not stated, another garment and mesh resolution; compare rankings only."]
    crit = results.get("criterion")
    if crit:
        notes.append(f"Fig. 5.6 criterion (SNUG's mean-curvature error below the vertex-L2 GRU's): {crit}.")
    return Table("curvature", "Mean-curvature error against the simulation (thesis Table 5.2)", cols, rows,
                 formats={"all": ".3f", **{g: ".3f" for g in groups}}, notes=[n for n in notes if n])


def _hours(seconds) -> str | None:
    if seconds is None:
        return None
    return f"{seconds:.1f} s" if seconds < 600 else f"{seconds / 3600:.2f} h"


def _cost_table(results: dict) -> Table:
    labels = _labels(results)
    timing = results.get("timing") or {}
    graphed = timing.get("methods_cuda_graph") or {}
    cols = [("method", "method"), ("data", "data generation"), ("train", "training"),
            ("runtime", "runtime [ms/frame]"), *([("runtime_graph", "CUDA graph [ms/frame]")] if graphed else []),
            ("size", "model size [MB]")]
    rows = [{"method": f"thesis Table 5.3: {r['method']}", "data": f"{r['data_h']:g} h", "train": f"{r['train_h']:g} h",
             "runtime": r["runtime_ms"], "size": r["size_mb"]} for r in THESIS_TABLES["cost"]]
    gen = results.get("generation") or {}
    data_time = _hours(gen.get("seconds")) if gen.get("seconds") is not None else "n/a (not recorded in the store)"
    for c in results["contestants"]:
        key = c["key"]
        t = (timing.get("methods") or {}).get(key) or {}
        rows.append({"method": labels[key], "data": data_time if c["uses_data"] else "0 (no simulated data)",
                     "train": ("0 (no training)" if c["kind"] == "lbs" else
                               _hours(c.get("train_seconds")) or "n/a (no log.csv)"),
                     "runtime": t.get("mean_ms"), "size": c["size_mb"],
                     **({"runtime_graph": (graphed.get(key) or {}).get("mean_ms")} if graphed else {})})
    sim_ms = gen.get("ms_per_frame")
    rows.append({"method": "simulation (the dataset's solver)", "data": "-", "train": "-",
                 "runtime": sim_ms, "size": None})
    notes = [f"Ours: runtime measured frame by frame (one garment, GRU state carried, no post-process) on "
             f"{timing.get('device', '?')} ({timing.get('device_name', '?')}"
             + (f", {timing['threads']} torch threads" if str(timing.get("device")) == "cpu" else "")
             + f"), {timing.get('frames', '?')} frames "
             f"after {timing.get('warmup', '?')} warm-up frames; training time from each folder's log.csv; data "
             "generation from the store's metadata (the wall time of every fit and sequence, all of the store, "
             "whichever part a model trained on); model size: float32 parameters, 1 MB = 1e6 bytes."
             + (" CUDA graph: the same frames replayed from one recorded frame (simgen.learn.streaming), the "
                "inputs' copy included." if graphed else ""),
             "Simulation runtime: the store's wall time per stored frame (start protocol included)"
             + ("" if sim_ms is not None else f": {gen.get('reason', 'not recorded')}") + ".",
             f"Thesis rows: thesis Table 5.3 ({THESIS_TABLES['hardware']}), not measured here."]
    return Table("cost", "Data generation, training, runtime and size (thesis Table 5.3)", cols, rows,
                 formats={"runtime": ".3g", "runtime_graph": ".3g", "size": ".4g"}, notes=notes)


def _error_tables(results: dict) -> list[Table]:
    labels = _labels(results)
    groups = list(results["groups"])
    cols = [("method", "method")]
    for g in groups:
        name = g.replace("_", " ")
        cols += [(f"{g}:error", f"{name}: vertex error [cm]"), (f"{g}:inside", f"{name}: inside body [%]")]
    rows = []
    for key in ["simulation", *_methods(results)]:
        row = {"method": labels.get(key, "simulation (ground truth)")}
        for g in groups:
            res = results["groups"][g]
            row[f"{g}:error"] = 0.0 if key == "simulation" else res["error_cm"].get(key)
            row[f"{g}:inside"] = res["inside_percent"].get(key)
        rows.append(row)
    notes = ["Vertex error: mean over vertices and frames of the distance to the simulated garment. Inside: share "
             "of garment vertices inside the posed body (winding number), not counting vertices at body "
             "self-intersections, as `simgen dataset check` counts its regular vertices; "
             + ("every frame" if results.get("inside_stride", 1) == 1 else
                f"every {results['inside_stride']}th frame") + ". No collision post-process on any method."]
    notes += results.get("warnings", [])
    summary = Table("errors", "Vertex error and vertices inside the body, per test group", cols, rows,
                    formats={k: ".3f" for k, _ in cols[1:]}, notes=notes)
    keys = ["simulation", *_methods(results)]
    error_cols = [("clip", "held-out clip"), ("group", "group")] + [(k, labels[k]) for k in keys[1:]]
    inside_cols = [("clip", "held-out clip"), ("group", "group")] + [(k, labels.get(k, "simulation"))
                                                                     for k in keys]
    error_rows, inside_rows = [], []
    for sid, row in results["sequences"].items():
        error_rows.append({"clip": sid, "group": row["group"], **{k: row["error_cm"].get(k) for k in keys[1:]}})
        inside_rows.append({"clip": sid, "group": row["group"], **{k: row["inside_percent"].get(k) for k in keys}})
    per_clip = Table("errors_per_clip", "Vertex error [cm] per held-out clip", error_cols, error_rows,
                     formats={k: ".3f" for k in keys})
    inside_clip = Table("inside_per_clip", "Vertices inside the body [%] per held-out clip (no post-process)",
                        inside_cols, inside_rows, formats={k: ".3f" for k in keys})
    return [summary, per_clip, inside_clip]


def build_tables(results: dict) -> list[Table]:
    """The tables of a compare results dict (see :func:`simgen.learn.comparison.compare_models`)."""
    return [_physics_table(results), _curvature_table(results), _cost_table(results), *_error_tables(results)]
