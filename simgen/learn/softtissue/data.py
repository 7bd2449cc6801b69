"""The in-memory training format of the soft-tissue models (SoftSMPL, thesis ch. 3).

One :class:`SoftTissueSequence` per captured (or synthesised) motion of one subject, with the body
parameters that explain it and the soft-tissue displacements left over (thesis eqs. 3.2, 3.3):

    x_t = W(T + B_s(beta) + B_p(theta_t) + Delta_t, beta, theta_t, W) + trans_t

- W: the body's linear blend skinning; T: its template; B_s, B_p: shape and pose blendshapes.
- Delta_t [m], shape (V, 3): per-vertex displacements in the **unposed (rest-pose) frame**, so they
  are independent of the pose and of where the body is.

:class:`SoftTissueData` holds the sequences of one body model (its ``{id, hash}`` identity, faces
and template), with split helpers: held-out motions and held-out subjects (shapes).

:func:`synthetic_softtissue_data` makes a small dataset from the bundled open body and library
motions whose displacements come from a known closed-form field. It is a **synthetic test
signal**, learnable by construction, not soft tissue and never ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from simgen.errors import InputError

__all__ = ["SoftTissueSequence", "SoftTissueData", "synthetic_softtissue_data", "synthetic_displacements",
           "soft_region_weights", "root_local_acceleration", "one_shape_per_motion", "clip_of", "with_mirrored",
           "mirror_vertex_map"]

MIRROR_TOLERANCE = 2e-3   # [m] largest distance of a reflected template vertex from its mirror vertex


@dataclass
class SoftTissueSequence:
    """One motion of one subject.

    name: unique id ("<subject>_<motion>"); subject: subject / shape id (sequences of one subject share
    betas); motion: the motion's name (the unit of the held-out-motion split); betas (B,) float32:
    shape coefficients of the body model; poses (T, 72) float32: SMPL axis-angle joint rotations
    [rad], the first 3 the root's global orientation; trans (T, 3) float32: root translation [m]
    (SMPL's meaning); fps [1/s]; displacements (T, V, 3) float32: Delta [m] in the unposed frame
    (module docstring); meta: provenance (JSON-serialisable).
    """

    name: str
    subject: str
    motion: str
    betas: np.ndarray
    poses: np.ndarray
    trans: np.ndarray
    fps: float
    displacements: np.ndarray
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        where = f"soft-tissue sequence {self.name!r}"
        self.betas = np.asarray(self.betas, dtype=np.float32).reshape(-1)
        self.poses = np.asarray(self.poses, dtype=np.float32)
        if self.poses.ndim == 3:
            self.poses = self.poses.reshape(len(self.poses), -1)
        self.trans = np.asarray(self.trans, dtype=np.float32)
        self.displacements = np.asarray(self.displacements, dtype=np.float32)
        T = len(self.poses)
        if self.poses.shape != (T, 72) or T < 1:
            raise InputError(f"{where}: poses must have shape (T, 72) with T >= 1, got {self.poses.shape}")
        if self.trans.shape != (T, 3):
            raise InputError(f"{where}: trans must have shape ({T}, 3), got {self.trans.shape}")
        if self.displacements.ndim != 3 or self.displacements.shape[0] != T or self.displacements.shape[2] != 3:
            raise InputError(f"{where}: displacements must have shape ({T}, V, 3), got {self.displacements.shape}")
        if not (self.fps > 0):
            raise InputError(f"{where}: fps must be positive, got {self.fps}")

    @property
    def num_frames(self) -> int:
        return len(self.poses)

    @classmethod
    def from_result(cls, result) -> "SoftTissueSequence":
        """The sequence of a simulated :class:`simgen.softtissue.simulate.SoftTissueResult`."""
        return cls(name=result.name, subject=result.subject, motion=result.motion, betas=result.betas,
                   poses=result.poses, trans=result.trans, fps=result.fps, displacements=result.displacements,
                   meta=dict(result.meta))


@dataclass
class SoftTissueData:
    """The sequences of one body model.

    sequences: list of :class:`SoftTissueSequence` (all with V = the body's vertex count);
    body: ``{"id", "hash"}`` of the body model the parameters belong to (what a trained model is
    checked against); faces (F, 3) int64: the body's triangles; template (V, 3) float32 [m]: the
    body's rest template (the mesh whose face normals the autoencoder's normal term compares);
    source: where the data came from ("synthetic", a Dyna file, ...).
    """

    sequences: list
    body: dict
    faces: np.ndarray
    template: np.ndarray
    source: str = ""

    def __post_init__(self) -> None:
        self.faces = np.asarray(self.faces, dtype=np.int64)
        self.template = np.asarray(self.template, dtype=np.float32)
        V = len(self.template)
        names = set()
        for s in self.sequences:
            if s.displacements.shape[1] != V:
                raise InputError(f"soft-tissue sequence {s.name!r} has {s.displacements.shape[1]} vertices, the "
                                 f"body has {V}")
            if s.name in names:
                raise InputError(f"soft-tissue data holds two sequences named {s.name!r}")
            names.add(s.name)

    @property
    def num_vertices(self) -> int:
        return len(self.template)

    @property
    def num_betas(self) -> int:
        return max((len(s.betas) for s in self.sequences), default=0)

    @property
    def num_frames(self) -> int:
        return sum(s.num_frames for s in self.sequences)

    def subjects(self) -> list[str]:
        return sorted({s.subject for s in self.sequences})

    def motions(self) -> list[str]:
        return sorted({s.motion for s in self.sequences})

    def subset(self, keep) -> "SoftTissueData":
        """The sequences for which ``keep(sequence)`` is true, same body."""
        return SoftTissueData([s for s in self.sequences if keep(s)], self.body, self.faces, self.template,
                              self.source)

    def split(self, test_motions=(), test_subjects=()) -> tuple["SoftTissueData", dict[str, "SoftTissueData"]]:
        """(train, test groups): training sequences are those of neither a held-out motion nor a held-out
        subject; test groups ``held_out_motion`` (training subjects), ``held_out_shape`` (training
        motions) and ``held_out_both``, each present only when non-empty. Unknown names are refused."""
        test_motions, test_subjects = set(test_motions), set(test_subjects)
        for label, given, known in (("motion", test_motions, self.motions()), ("subject", test_subjects,
                                                                               self.subjects())):
            unknown = sorted(given - set(known))
            if unknown:
                raise InputError(f"held-out {label} {', '.join(map(repr, unknown))} is not in the data "
                                 f"({', '.join(known)})")
        train = self.subset(lambda s: s.motion not in test_motions and s.subject not in test_subjects)
        if not train.sequences:
            raise InputError("the split leaves no training sequence")
        groups = {
            "held_out_motion": self.subset(lambda s: s.motion in test_motions and s.subject not in test_subjects),
            "held_out_shape": self.subset(lambda s: s.motion not in test_motions and s.subject in test_subjects),
            "held_out_both": self.subset(lambda s: s.motion in test_motions and s.subject in test_subjects),
        }
        return train, {k: v for k, v in groups.items() if v.sequences}


def clip_of(s: SoftTissueSequence) -> tuple[str, bool]:
    """The clip a sequence plays, (motion, mirrored): what subjects share or lack."""
    return s.motion, bool(s.meta.get("mirrored", False))


def one_shape_per_motion(data: "SoftTissueData") -> "SoftTissueData":
    """The sequences a capture without motion transfer would have (thesis section 3.3.2's ablation): each
    clip, a (motion, mirrored) pair, performed by one subject only, the i-th clip in sorted order by the
    (i mod S)-th of the S subjects in sorted order, so that every subject keeps about 1/S of the clips.
    Where the chosen subject lacks the clip, the next subject in order that has it."""
    subjects = data.subjects()
    have: dict[tuple, dict] = {}
    for s in data.sequences:
        have.setdefault(clip_of(s), {})[s.subject] = s.name
    keep = set()
    for i, clip in enumerate(sorted(have)):
        order = subjects[i % len(subjects):] + subjects[:i % len(subjects)]
        keep.add(have[clip][next(sub for sub in order if sub in have[clip])])
    return data.subset(lambda s: s.name in keep)


def mirror_vertex_map(template) -> np.ndarray:
    """(V,) int64: the vertex each template vertex [m], (V, 3), lands on when reflected across the
    sagittal plane (x -> -x in SMPL's frame). Refuses a template that is not left-right symmetric
    within MIRROR_TOLERANCE or whose map is not its own inverse."""
    from scipy.spatial import cKDTree

    v = np.asarray(template, dtype=np.float64)
    dist, idx = cKDTree(v).query(v * np.array([-1.0, 1.0, 1.0]))
    if dist.max() > MIRROR_TOLERANCE or not np.array_equal(idx[idx], np.arange(len(v))):
        raise InputError(f"the body's template is not left-right symmetric (a reflected vertex lies "
                         f"{1000 * dist.max():.1f} mm from the nearest vertex, tolerance "
                         f"{1000 * MIRROR_TOLERANCE:.0f} mm): its sequences cannot be mirrored (train with "
                         f"--no-mirror)")
    return idx.astype(np.int64)


def with_mirrored(data: "SoftTissueData") -> "SoftTissueData":
    """``data`` and the mirror image of each of its sequences (thesis section 3.4.1): joints swapped and
    reflected (:func:`simgen.motion.ops.mirror`), and Delta [m] of vertex v taken from its mirror vertex
    with x negated, so that the mirrored body is the reflection of the original in the unposed frame.
    A mirrored sequence keeps its subject and betas (the shape space is taken as symmetric), is named
    ``<name>_mirror`` and has ``meta["mirrored"]``; a mirrored sequence, or one whose mirror image is
    there already, is not mirrored again."""
    from simgen.motion.clip import MotionClip
    from simgen.motion.ops import mirror

    vmap = mirror_vertex_map(data.template)
    flip = np.array([-1.0, 1.0, 1.0], dtype=np.float32)
    out = list(data.sequences)
    names = {s.name for s in data.sequences}
    for s in data.sequences:
        if s.meta.get("mirrored") or f"{s.name}_mirror" in names:
            continue
        m = mirror(MotionClip(s.motion, s.fps, s.poses.reshape(len(s.poses), -1, 3), s.trans))
        out.append(SoftTissueSequence(f"{s.name}_mirror", s.subject, s.motion, s.betas,
                                      m.poses.reshape(len(s.poses), -1), m.trans, s.fps,
                                      s.displacements[:, vmap] * flip, meta={**s.meta, "mirrored": True}))
    return SoftTissueData(out, data.body, data.faces, data.template, data.source)


# ------------------------------------------------------------------------------------ synthetic test signal
def soft_region_weights(body) -> np.ndarray:
    """(V,) float32 in [0, 1]: a smooth weight on the front of the torso (belly and chest) of a body.

    Torso vertices (:func:`simgen.body.parts.vertex_parts`) in front of the torso's centre, weighted
    by a Gaussian in height around the middle of the torso (sigma: a quarter of its height) and by
    how far forward (+z, SMPL's facing direction) they are."""
    from simgen.body.parts import BODY_PARTS, vertex_parts

    v = np.asarray(body.v_template, dtype=np.float64)
    torso = vertex_parts(body.weights) == BODY_PARTS.index("torso")
    tv = v[torso]
    lo, hi = np.percentile(tv[:, 1], [10, 70])
    yc, sigma = 0.5 * (lo + hi), 0.25 * (hi - lo) + 1e-9
    zc, zmax = np.median(tv[:, 2]), tv[:, 2].max()
    front = np.clip((v[:, 2] - zc) / max(zmax - zc, 1e-9), 0.0, 1.0)
    w = np.exp(-0.5 * ((v[:, 1] - yc) / sigma) ** 2) * front * torso
    return (w / max(w.max(), 1e-12)).astype(np.float32)


def root_local_acceleration(poses: np.ndarray, trans: np.ndarray, fps: float) -> np.ndarray:
    """(T, 3) root acceleration [m/s^2] in the root's local frame: R_root(t)^T d^2 trans/dt^2 (backward
    differences; the first two frames are at rest)."""
    from simgen.rotations import axis_angle_to_matrix

    trans = np.asarray(trans, dtype=np.float64)
    acc = np.zeros_like(trans)
    if len(trans) >= 3:
        acc[2:] = (trans[2:] - 2 * trans[1:-1] + trans[:-2]) * fps ** 2
    R = axis_angle_to_matrix(np.asarray(poses, dtype=np.float64).reshape(len(trans), -1)[:, :3])
    return np.einsum("tji,tj->ti", R, acc)


def synthetic_displacements(weights: np.ndarray, poses, trans, fps: float, *, softness: float = 1.0,
                            frequency: float = 3.0, damping: float = 0.3, max_amplitude: float = 0.02) -> np.ndarray:
    """The synthetic test signal, (T, V, 3) float32 [m]: a damped oscillator driven by the root.

    x'' + 2 zeta w x' + w^2 x = -a(t), with a(t) the root acceleration in the root's frame
    (:func:`root_local_acceleration`), w = 2 pi ``frequency`` / sqrt(softness), zeta = ``damping``,
    integrated exactly per frame for a piecewise-constant drive (starting at rest, x = x' = 0), then
    squashed as max_amplitude * tanh(x / max_amplitude) and laid on the vertices as
    Delta_v(t) = weights_v * x(t) (all three coordinates of the unposed frame). A softer subject
    (``softness`` > 1) oscillates slower and further. Not a model of soft tissue: a known, smooth,
    history-dependent field that a recurrent regressor can learn.
    """
    a = root_local_acceleration(poses, trans, fps)
    dt = 1.0 / fps
    w = 2 * np.pi * frequency / np.sqrt(softness)
    # Exact discretisation of the linear ODE (matrix exponential of the 2x2 system, drive held per step).
    A = np.array([[0.0, 1.0], [-w * w, -2 * damping * w]])
    vals, vecs = np.linalg.eig(A)
    Ad = np.real(vecs @ np.diag(np.exp(vals * dt)) @ np.linalg.inv(vecs))
    Bd = np.linalg.solve(A, (Ad - np.eye(2)) @ np.array([0.0, 1.0]))
    state = np.zeros((2, 3))
    x = np.zeros((len(a), 3))
    for t in range(len(a)):
        state = Ad @ state + np.outer(Bd, -a[t])
        x[t] = state[0]
    x = max_amplitude * np.tanh(x / max_amplitude)
    return (np.asarray(weights, dtype=np.float64)[None, :, None] * x[:, None, :]).astype(np.float32)


def synthetic_softtissue_data(body=None, *, motions=("jump", "walk"), subjects: int = 2, frames: int | None = 24,
                              seed: int = 0) -> SoftTissueData:
    """A small :class:`SoftTissueData` for tests and smoke runs: the body (default: the bundled open
    body) with ``subjects`` random shapes (betas ~ N(0, 0.5^2) on the first two components; a
    subject's ``softness`` grows as beta_1 falls, like fat subjects in the thesis) playing library
    ``motions`` (their first ``frames`` frames; None: all), with :func:`synthetic_displacements` on
    :func:`soft_region_weights`. A synthetic test signal, not ground truth.
    """
    from simgen.body import load
    from simgen.motion import load_motion

    body = body if body is not None else load("open")
    rng = np.random.default_rng(seed)
    region = soft_region_weights(body)
    seqs = []
    for k in range(subjects):
        betas = np.zeros(body.num_betas, dtype=np.float32)
        betas[:min(2, body.num_betas)] = rng.normal(0.0, 0.5, size=min(2, body.num_betas))
        softness = float(np.exp(-0.5 * betas[1])) if body.num_betas > 1 else 1.0
        subject = f"s{k}"
        for m in motions:
            clip = load_motion(m)
            n = len(clip.poses) if frames is None else min(frames, len(clip.poses))
            poses, trans = clip.poses[:n].reshape(n, 72), clip.trans[:n]
            disp = synthetic_displacements(region, poses, trans, clip.fps, softness=softness)
            seqs.append(SoftTissueSequence(f"{subject}_{m}", subject, m, betas, poses, trans, clip.fps, disp,
                                           meta={"signal": "synthetic damped oscillator (test signal)",
                                                 "softness": softness}))
    return SoftTissueData(seqs, {"id": body.name, "hash": body.hash}, body.faces, body.v_template, "synthetic")
