"""Read-only view of a dataset store: ``open_dataset(path)``.

Only committed nodes listed in the manifest are visible, so a reader never sees a half-written
sequence, also while a generator is still writing to the store.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np

from simgen.dataset.storage import Location
from simgen.dataset.store import read_manifest
from simgen.errors import InputError

__all__ = ["Dataset", "open_dataset"]


def open_dataset(path) -> Dataset:
    """Open a store (local folder or fsspec URL) read-only. InputError if it is not a simgen dataset."""
    loc = Location(path)
    attrs = loc.node_attrs("")
    if attrs is None:
        raise InputError(f"{loc.root} is not a dataset store (no zarr.json; make one with `simgen dataset generate`)")
    if attrs.get("format_version") is None:
        raise InputError(f"{loc.root} is a Zarr group but not a simgen dataset store")
    manifest = read_manifest(loc)
    if manifest is None:
        raise InputError(f"dataset store {loc.root} has no manifest.json (its creation did not finish)")
    return Dataset(loc, attrs, manifest)


class Dataset:
    """A dataset store (one garment + material). See :func:`open_dataset`.

    attrs: root attrs (format_version, simgen_version, spec, body {id, hash, source}, garment {name,
    hash}, material, solver); manifest: the parsed manifest.json.
    """

    def __init__(self, loc: Location, attrs: dict, manifest: dict) -> None:
        self.loc, self.attrs, self.manifest = loc, attrs, manifest

    def __repr__(self) -> str:
        return (f"Dataset({self.loc.root!r}, garment={self.garment_name!r}, sequences={len(self.sequence_ids())}, "
                f"shapes={len(self.shape_ids())})")

    @cached_property
    def _root(self):
        import zarr

        return zarr.open_group(self.loc.url(), mode="r")

    @property
    def path(self) -> str:
        return self.loc.root

    @property
    def garment_name(self) -> str:
        return self.attrs["garment"]["name"]

    @property
    def body_id(self) -> str:
        return self.attrs["body"]["id"]

    @property
    def material(self):
        """The :class:`simgen.sim.Material` every sequence was simulated with."""
        from simgen.materials import Material

        return Material.from_dict(self.attrs["material"])

    @property
    def fps(self) -> float:
        return float(self.attrs["solver"]["fps"])

    def load_body(self, body=None):
        """The body model of the store (its recorded source, checked against the recorded hash).

        body: a BodyModel or source ("open", a path) to use instead of the recorded source.
        """
        from simgen import body as body_pkg
        from simgen.body.model import BodyModel

        b = body if isinstance(body, BodyModel) else body_pkg.load(body or self.attrs["body"]["source"])
        if b.hash != self.attrs["body"]["hash"]:
            raise InputError(f"body model {b.name!r} (hash {b.hash[:12]}) is not the one the dataset {self.path} was "
                             f"made with ({self.attrs['body']['id']})")
        return b

    # ------------------------------------------------------------------ template and fits
    @cached_property
    def template(self) -> dict:
        """vertices (V,3) f4 T_r, smoothed (V,3) f4 T_c, faces (F,3) i4, skin_weights (V,24) f4,
        garment_template (V,3) f4 (the cloth's rest shape), smoothing (dict), stats (dict)."""
        if self.manifest["template"] is None:
            raise InputError(f"dataset {self.path} has no template yet (generation has not finished its first batch)")
        g = self._root["template"]
        out = {k: g[k][...] for k in ("vertices", "smoothed", "faces", "skin_weights", "garment_template")}
        out["smoothing"] = dict(g.attrs["smoothing"])
        out["stats"] = dict(g.attrs.get("stats", {}))
        return out

    def shape_ids(self) -> list[str]:
        """Shapes whose fit is in the store, in plan order."""
        order = [s["id"] for s in self.attrs.get("spec", {}).get("shapes", [])]
        have = set(self.manifest["fits"])
        return [s for s in order if s in have] + sorted(have - set(order))

    def fit(self, shape_id: str) -> dict:
        """betas (B,) f4, vertices (V,3) f4 = S_c(beta, 0) (rest pose, no trans), fit_displacement (V,3)
        f4 = smooth(S_c(beta, 0)) - T_c, rest_vertices (R,V,3) f4 (the fit's rest frames, if stored), attrs."""
        if shape_id not in self.manifest["fits"]:
            raise InputError(f"dataset {self.path} has no fit for shape {shape_id!r}; shapes: "
                             f"{', '.join(self.shape_ids()) or 'none yet'}")
        g = self._root[f"fit/{shape_id}"]
        out = {k: g[k][...] for k in ("betas", "vertices", "fit_displacement")}
        if "rest_vertices" in g:
            out["rest_vertices"] = g["rest_vertices"][...]
        out["attrs"] = g.attrs.asdict()
        return out

    # ------------------------------------------------------------------ sequences
    def sequence_ids(self, split: str | None = None) -> list[str]:
        """Completed sequences, sorted; split "train" | "test" (held-out motions) | None (all)."""
        if split not in (None, "train", "test"):
            raise InputError(f"split must be 'train', 'test' or None, got {split!r}")
        seqs = self.manifest["sequences"]
        return sorted(i for i, e in seqs.items() if split is None or e.get("split") == split)

    def sequence_info(self, seq_id: str) -> dict:
        """The manifest entry of a sequence (checksum, frames, motion, shape_id, split)."""
        self._check_seq(seq_id)
        return dict(self.manifest["sequences"][seq_id])

    def _check_seq(self, seq_id: str) -> None:
        if seq_id not in self.manifest["sequences"]:
            ids = self.sequence_ids()
            import difflib

            close = difflib.get_close_matches(seq_id, ids, n=3, cutoff=0.5)
            raise InputError(f"dataset {self.path} has no sequence {seq_id!r}"
                             + (f"; close: {', '.join(close)}" if close else f" ({len(ids)} sequences)"))

    def sequence(self, seq_id: str, frames: slice | None = None) -> dict:
        """garment_vertices (T,V,3) f4, poses (T,24,3) f4, trans (T,3) f4, betas (T,B) f4,
        rest_garment_vertices (R,V,3) f4 (cloth over the protocol's rest phase, body at frame 0's
        pose, if stored), frame_stats {key: (T,)}, attrs (motion, fps, split, shape_id, frames, stats ...).
        frames: optional slice of frames to read (the per-frame arrays only)."""
        self._check_seq(seq_id)
        g = self._root[f"sequences/{seq_id}"]
        sl = frames if frames is not None else slice(None)
        out = {k: g[k][sl] for k in ("garment_vertices", "poses", "trans", "betas")}
        if "rest_garment_vertices" in g:
            out["rest_garment_vertices"] = g["rest_garment_vertices"][...]
        out["frame_stats"] = {name: a[sl] for name, a in g["stats"].arrays()} if "stats" in g else {}
        out["attrs"] = g.attrs.asdict()
        return out

    # ------------------------------------------------------------------ ground truth
    def groundtruth(self, seq_id: str, body=None) -> dict:
        """Eqs. 4.4/4.5 for one sequence: transforms (T,24,4,4), fit_displacement (V,3) and
        wrinkle (T,V,3), all float64 (see :mod:`simgen.dataset.groundtruth`)."""
        from simgen.dataset.groundtruth import skinning_transforms, wrinkle_displacements

        seq = self.sequence(seq_id)
        b = self.load_body(body)
        fit = self.fit(seq["attrs"]["shape_id"])
        tpl = self.template
        A = skinning_transforms(b, seq["betas"], seq["poses"], seq["trans"])
        wr = wrinkle_displacements(seq["garment_vertices"], A, tpl["skin_weights"], tpl["smoothed"],
                                   fit["fit_displacement"])
        return {"transforms": A, "fit_displacement": fit["fit_displacement"].astype(np.float64), "wrinkle": wr}
