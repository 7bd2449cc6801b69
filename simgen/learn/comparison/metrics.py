"""Metrics of ``simgen eval compare``: mean curvature, vertices inside the body, costs.

- :func:`mean_curvature` / :func:`curvature_error`: the discrete mean curvature per vertex
  (cotangent Laplacian over the barycentric area) and the thesis Table 5.2 error against the
  simulation;
- :class:`InsideCounter`: garment vertices inside the posed body, counted as ``simgen dataset
  check`` counts its regular vertices (:func:`simgen.dataset.quality.body_penetration` with the
  solver's body-part rule; vertices at body self-intersections are not counted);
- :func:`training_seconds` (from model folders' log.csv) and :func:`generation_seconds` (from the
  store's per-node wall times);
- :class:`SnugStepper` and :class:`LbsStepper`: frame-by-frame inference of a SNUG-type model and
  of LBS with the ``step`` interface of :class:`~simgen.learn.garment_model.GarmentModel`, so
  :func:`simgen.learn.evaluate.time_inference` times every method the same way.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import torch

from simgen.errors import InputError

__all__ = ["boundary_vertices", "mean_curvature", "curvature_error", "InsideCounter", "training_seconds",
           "generation_seconds", "SnugStepper", "LbsStepper"]


# ------------------------------------------------------------------------------------ curvature
def boundary_vertices(faces, num_vertices: int) -> np.ndarray:
    """Vertices on the mesh boundary (an edge with one triangle): bool (V,). faces (F, 3)."""
    f = np.asarray(faces, dtype=np.int64)
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    out = np.zeros(num_vertices, dtype=bool)
    out[uniq[counts == 1].ravel()] = True
    return out


def mean_curvature(vertices, faces) -> torch.Tensor:
    """Signed discrete mean curvature H [1/m] per vertex (Meyer et al. 2003, barycentric areas).

    vertices [m] (..., V, 3) (numpy or torch), faces (F, 3) -> H (..., V), float64:

        K_i = 1 / (2 A_i) * sum_j (cot a_ij + cot b_ij) (x_i - x_j)      (= 2 H_i n_i)
        H_i = |K_i| / 2 * sign(K_i . n_i)

    a_ij, b_ij: the angles opposite edge ij; A_i: a third of the area of the triangles around i;
    n_i: the area-weighted vertex normal (H > 0 where the surface bends away from its normal, e.g.
    a sphere with outward normals: H = 1/R). Boundary vertices get the formula too but it does not
    measure curvature there (see :func:`boundary_vertices`).
    """
    x = torch.as_tensor(np.asarray(vertices) if not isinstance(vertices, torch.Tensor) else vertices)
    x = x.to(torch.float64)
    f = torch.as_tensor(np.ascontiguousarray(faces, dtype=np.int64), device=x.device)
    x0, x1, x2 = x[..., f[:, 0], :], x[..., f[:, 1], :], x[..., f[:, 2], :]
    n = torch.cross(x1 - x0, x2 - x0, dim=-1)
    twice_area = n.norm(dim=-1).clamp_min(1e-300)

    def cot(a, b):  # cotangent of the angle between edge vectors a and b
        return (a * b).sum(-1) / twice_area

    cots = (cot(x1 - x0, x2 - x0), cot(x2 - x1, x0 - x1), cot(x0 - x2, x1 - x2))  # at vertices 0, 1, 2
    acc = torch.zeros_like(x)
    normal = torch.zeros_like(x)
    area = torch.zeros(x.shape[:-1], dtype=x.dtype, device=x.device)
    corners = (x0, x1, x2)
    for k in range(3):  # the angle at corner k weights the opposite edge (i, j)
        i, j = (k + 1) % 3, (k + 2) % 3
        w = cots[k][..., None] * (corners[i] - corners[j])
        acc.index_add_(-2, f[:, i], w)
        acc.index_add_(-2, f[:, j], -w)
        area.index_add_(-1, f[:, k], twice_area / 6.0)
        normal.index_add_(-2, f[:, k], n)
    K = acc / (2.0 * area.clamp_min(1e-300))[..., None]
    sign = torch.where((K * normal).sum(-1) < 0, -1.0, 1.0).to(x.dtype)
    return 0.5 * K.norm(dim=-1) * sign


def curvature_error(prediction, reference, faces, mask=None, *, reference_curvature=None) -> np.ndarray:
    """Mean-curvature error [1/m] per frame: mean over vertices of |H(prediction) - H(reference)|.

    prediction, reference [m] (T, V, 3) (numpy, or torch on any device: computed there); faces
    (F, 3); mask bool (V,): the vertices that count (default: all but the boundary,
    :func:`boundary_vertices`); reference_curvature: H(reference) (T, V) if already computed.
    Returns (T,) float64.
    """
    v = prediction.shape[-2]
    keep = ~boundary_vertices(faces, v) if mask is None else np.asarray(mask, dtype=bool)
    h_ref = mean_curvature(reference, faces) if reference_curvature is None else reference_curvature
    diff = (mean_curvature(prediction, faces) - h_ref).abs()
    return diff[..., torch.as_tensor(keep, device=diff.device)].mean(-1).cpu().numpy()


# ------------------------------------------------------------------------------------ inside the body
class InsideCounter:
    """Share of garment vertices inside the posed body, as ``simgen dataset check`` counts them.

    body: the BodyModel; skin_weights (V, 24): the garment's (each vertex's home body part);
    solver: the store's ``attrs["solver"]`` (its contact pinch distance); device: Warp's.
    A vertex is inside when :func:`simgen.dataset.quality.body_penetration` gives it a depth > 0
    (winding number) and it is not at a body self-intersection (armpits, crotch; the check's
    "regular" vertices).
    """

    def __init__(self, body, skin_weights, solver: dict | None = None, device: str = "cpu"):
        from simgen.dataset.quality import penetration_rule

        if skin_weights is None:
            raise InputError("InsideCounter needs the garment's skinning weights (each vertex's body part)")
        self.faces = np.asarray(body.faces)
        self.rule = penetration_rule(skin_weights, body, solver)
        self.device = device

    def fractions(self, sets: dict, body_vertices) -> dict[str, float]:
        """{name: garment (V, 3) [m]} on one posed body (Vb, 3) [m] -> {name: share inside [-]} (one query)."""
        from simgen.dataset.quality import body_penetration

        names = list(sets)
        points = np.concatenate([np.asarray(sets[n], dtype=np.float32) for n in names])
        rule = {**self.rule, "home_parts": np.tile(self.rule["home_parts"], len(names))}
        depth, self_hit, _ = body_penetration(points, body_vertices, self.faces, device=self.device, **rule)
        regular = (depth > 0.0) & ~self_hit
        v = len(self.rule["home_parts"])
        return {n: float(regular[k * v:(k + 1) * v].mean()) for k, n in enumerate(names)}


# ------------------------------------------------------------------------------------ costs
def training_seconds(logs) -> float | None:
    """Training time [s] from log.csv files (their "seconds" column: of the call, at each epoch's end).

    Each call (a resume starts a new one) counts up to its last logged epoch: the sum over calls
    of their last "seconds"; a call is recognised by its seconds falling below the previous row's.
    Time after a call's last completed epoch (a time-budget stop) is not counted. None when no
    log has a seconds column."""
    total, found = 0.0, False
    for path in logs:
        path = Path(path)
        if not path.is_file():
            continue
        with open(path, newline="", encoding="utf-8") as fh:
            values = [float(r["seconds"]) for r in csv.DictReader(fh) if r.get("seconds") not in (None, "")]
        if not values:
            continue
        found = True
        last = 0.0
        for s in values:
            if s < last:
                total += last
            last = s
        total += last
    return total if found else None


def generation_seconds(store) -> dict:
    """Data-generation time of a store from its metadata: every fit's and sequence's ``stats.wall_time``
    [s] (its share of the batch's simulation wall time, protocol frames included).

    Returns {"seconds", "frames" (stored sequence frames), "ms_per_frame" (seconds / frames, the
    protocol's cost included), "nodes"} or {"seconds": None, "reason"} when the store lacks them.
    """
    from simgen.dataset import open_dataset

    try:
        ds = open_dataset(store)
    except Exception as exc:  # noqa: BLE001 - data built from arrays, an unreadable store: no metadata
        return {"seconds": None, "reason": f"no dataset store to read ({exc})"}
    total, frames, nodes, missing = 0.0, 0, 0, 0
    for sid in ds.shape_ids():
        wall = (ds.fit(sid)["attrs"].get("stats") or {}).get("wall_time")
        if wall is None:
            missing += 1
        else:
            total, nodes = total + float(wall), nodes + 1
    for sid in ds.sequence_ids():
        attrs = ds.sequence(sid, frames=slice(0, 1))["attrs"]
        wall = (attrs.get("stats") or {}).get("wall_time", attrs.get("wall_time"))
        if wall is None:
            missing += 1
        else:
            total, nodes = total + float(wall), nodes + 1
            frames += int(attrs.get("frames") or 0)
    if nodes == 0 or missing:
        return {"seconds": None, "reason": f"the store records no wall time for {missing} of its nodes"}
    return {"seconds": total, "frames": frames, "nodes": nodes,
            "ms_per_frame": 1e3 * total / frames if frames else None}


# ------------------------------------------------------------------------------------ timing adapters
class SnugStepper:
    """Frame-by-frame inference of a SnugModel (SNUG, vertex-L2 GRU): one GRU step, LBS; no post-process.

    ``step(state, betas (N, B), pose (N, 24, 3), trans (N, 3), fps)`` -> vertices [m] (N, V, 3),
    the :class:`~simgen.learn.garment_model.StreamState` updated in place."""

    def __init__(self, model):
        self.model = model

    def to(self, device):
        self.model.to(device)
        return self

    @torch.no_grad()
    def step(self, state, betas, pose, trans, fps: float, *, postprocess: bool = False) -> torch.Tensor:
        from simgen.learn.features import motion_features
        from simgen.learn.garment_model import joint_transforms

        net = self.model.net
        features = motion_features(pose[:, None], trans[:, None], fps, net.feature_mode, previous=state.previous)
        unposed, state.hidden = net(betas[:, None], features, state.hidden)
        state.previous = (pose, trans)
        return net.posed(unposed[:, 0], joint_transforms(self.model.body, betas, pose, trans))


class LbsStepper:
    """Frame-by-frame LBS of a template (:class:`~simgen.learn.models.GarmentTemplate`, T_r carried to
    the shaped body) on a TorchBody: joint transforms and skinning, no learning."""

    def __init__(self, template, body):
        self.template, self.body = template, body

    def to(self, device):
        self.template.to(device)
        self.body.to(device)
        return self

    @torch.no_grad()
    def step(self, state, betas, pose, trans, fps: float, *, postprocess: bool = False) -> torch.Tensor:
        from simgen.learn.garment_model import joint_transforms, lbs_baseline

        return lbs_baseline(self.template, betas, joint_transforms(self.body, betas, pose, trans))


def finite_mean(values) -> float | None:
    """Mean of the finite values, None when there are none."""
    v = [float(x) for x in values if x is not None and math.isfinite(float(x))]
    return float(np.mean(v)) if v else None
