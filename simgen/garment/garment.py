"""Garment: a triangle mesh dressed on the template body in rest pose, with skinning weights.

On disk a garment is a folder NAME/ holding NAME.obj (geometry), NAME.json (metadata: body model
id and hash, counts, openings, default material, how it was made, quality report) and NAME.npz
(skinning weights as sparse top-k joint indices and weights). Bundled garments live under
``garments/``; garments built for another body or imported by a user live under
``$SIMGEN_HOME/<body-id>/garments/`` (see ``simgen.assets``).
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from simgen._fileio import atomic_write_bytes
from simgen.errors import InputError

__all__ = ["Garment", "SKIN_TOP_K", "FORMAT_VERSION"]

FORMAT_VERSION = 1
SKIN_TOP_K = 8  # joints kept per vertex on disk; diffused weights rarely need more than 6


@dataclass(eq=False)
class Garment:
    """A garment template.

    name: identifier (folder and file stem).
    vertices [m], shape (V, 3): on the template body in rest pose (Y-up).
    faces, int shape (F, 3): triangles, counter-clockwise seen from outside (normals point away
      from the body).
    skin_weights, shape (V, 24): linear blend skinning weights over SMPL's joints, rows >= 0
      summing to 1.
    metadata: JSON-serialisable dict (body, openings, default_material, made_by, skinning, quality).
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    skin_weights: np.ndarray
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int64)
        self.skin_weights = np.ascontiguousarray(self.skin_weights, dtype=np.float64)
        where = f"garment {self.name!r}"
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise InputError(f"{where}: vertices must have shape (V, 3), got {self.vertices.shape}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or len(self.faces) == 0:
            raise InputError(f"{where}: faces must have shape (F, 3), got {self.faces.shape}")
        if self.faces.min() < 0 or self.faces.max() >= len(self.vertices):
            raise InputError(f"{where}: faces index vertex {int(self.faces.max())} of {len(self.vertices)}")
        if self.skin_weights.shape != (len(self.vertices), 24):
            raise InputError(f"{where}: skin_weights must have shape ({len(self.vertices)}, 24), "
                             f"got {self.skin_weights.shape}")
        if not np.all(np.isfinite(self.vertices)):
            raise InputError(f"{where}: vertices contain NaN or inf")

    @property
    def num_vertices(self) -> int:
        return int(len(self.vertices))

    @property
    def num_triangles(self) -> int:
        return int(len(self.faces))

    def __repr__(self) -> str:
        return f"Garment({self.name!r}, vertices={self.num_vertices}, triangles={self.num_triangles})"

    # ------------------------------------------------------------------ persistence
    def save(self, folder: str | Path) -> Path:
        """Write FOLDER/NAME/{NAME.obj, NAME.json, NAME.npz}; returns the garment folder.

        Each file is written to a temporary name and renamed, the JSON last, so a reader never
        sees a JSON that describes files not yet complete.
        """
        out = Path(folder) / self.name
        out.mkdir(parents=True, exist_ok=True)
        lines = [f"# simgen garment {self.name}: {self.num_vertices} vertices, {self.num_triangles} triangles, metres, Y-up"]
        lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in self.vertices]
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in self.faces]
        atomic_write_bytes(out / f"{self.name}.obj", ("\n".join(lines) + "\n").encode())

        k = min(SKIN_TOP_K, 24)
        order = np.argsort(-self.skin_weights, axis=1, kind="stable")[:, :k]
        top = np.take_along_axis(self.skin_weights, order, axis=1)
        top = top / np.maximum(top.sum(axis=1, keepdims=True), 1e-12)
        buf = io.BytesIO()
        np.savez_compressed(buf, skin_joint_indices=order.astype(np.int16), skin_joint_weights=top.astype(np.float32))
        atomic_write_bytes(out / f"{self.name}.npz", buf.getvalue())

        meta = dict(self.metadata)
        meta.update(format_version=FORMAT_VERSION, name=self.name, num_vertices=self.num_vertices,
                    num_triangles=self.num_triangles, skin_top_k=k)
        atomic_write_bytes(out / f"{self.name}.json", (json.dumps(meta, indent=2) + "\n").encode())
        return out

    @classmethod
    def load(cls, folder: str | Path) -> "Garment":
        """Read a garment folder written by :meth:`save` (FOLDER is the NAME/ folder itself)."""
        folder = Path(folder)
        name = folder.name
        paths = {ext: folder / f"{name}.{ext}" for ext in ("obj", "json", "npz")}
        for ext, p in paths.items():
            if not p.is_file():
                raise InputError(f"garment folder {folder}: missing {p.name}")
        try:
            meta = json.loads(paths["json"].read_text())
        except (OSError, ValueError) as exc:
            raise InputError(f"{paths['json']}: not valid JSON ({exc})") from None
        vertices, faces = [], []
        try:
            for line in paths["obj"].read_text().splitlines():
                if line.startswith("v "):
                    vertices.append([float(t) for t in line.split()[1:4]])
                elif line.startswith("f "):
                    faces.append([int(t.split("/")[0]) - 1 for t in line.split()[1:4]])
        except (OSError, ValueError, UnicodeDecodeError) as exc:
            raise InputError(f"{paths['obj']}: unreadable OBJ ({exc})") from None
        try:
            with np.load(paths["npz"], allow_pickle=False) as z:
                idx = z["skin_joint_indices"].astype(np.int64)
                w = z["skin_joint_weights"].astype(np.float64)
        except (OSError, ValueError, KeyError) as exc:
            raise InputError(f"{paths['npz']}: unreadable skinning weights ({exc})") from None
        if len(vertices) == 0 or idx.shape != w.shape or idx.shape[0] != len(vertices) or idx.max() >= 24:
            raise InputError(f"garment folder {folder}: {paths['npz'].name} does not match {paths['obj'].name} "
                             f"({idx.shape[0]} weight rows, {len(vertices)} vertices)")
        weights = np.zeros((len(vertices), 24))
        np.put_along_axis(weights, idx, w, axis=1)
        return cls(name=name, vertices=np.asarray(vertices), faces=np.asarray(faces, dtype=np.int64),
                   skin_weights=weights, metadata=meta)
