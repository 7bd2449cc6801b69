"""Export one stored sequence for inspection: USD (body + garment, time-sampled) and an MP4.

The body is re-posed from the sequence's stored poses, trans and betas with the store's body model
(verified by hash), so what you see is exactly the body the cloth was simulated against.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from simgen.errors import InputError

__all__ = ["export_sequence", "pack_sequences", "open_pack", "PackedSequences"]


def export_sequence(dataset, seq_id: str, out_dir, *, usd: bool = True, mp4: bool = True, body=None,
                    size: tuple[int, int] = (1280, 720), progress=None) -> dict:
    """Write OUT_DIR/<seq_id>.usdc and/or OUT_DIR/<seq_id>.mp4; returns {"usd": path|None, "mp4": path|None}.

    dataset: a :class:`simgen.dataset.Dataset`, a store path, or a pack (.npz, :func:`pack_sequences`);
    body: BodyModel or source to use instead of the store's recorded one (it must have the same hash);
    progress(done, total) while posing and rendering. The MP4 is framed by
    :func:`simgen.io.render.follow_cameras` with a legend (sequence, garment, shape, motion, frame).
    """
    from simgen.dataset.reader import Dataset, open_dataset
    from simgen.io.usd import MeshTrack

    if not (usd or mp4):
        raise InputError("nothing to export: pass --usd and/or --mp4")
    if isinstance(dataset, (Dataset, PackedSequences)):
        ds = dataset
    elif str(dataset).endswith(".npz"):
        ds = open_pack(dataset)
    else:
        ds = open_dataset(dataset)
    seq = ds.sequence(seq_id)
    bm = ds.load_body(body)
    posed = bm.forward_sequence(seq["betas"].astype(np.float64), seq["poses"], seq["trans"], progress=progress)
    faces = ds.template["faces"]
    tracks = [MeshTrack(name="body", points=posed.vertices, faces=bm.faces, role="body"),
              MeshTrack(name=_prim(ds.garment_name), points=seq["garment_vertices"], faces=faces, role="garment")]
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    fps = float(seq["attrs"].get("fps", ds.fps))
    paths = {"usd": None, "mp4": None}
    if usd:
        from simgen.io.usd import write_usd

        a = seq["attrs"]
        meta = {"dataset": str(ds.path), "sequence": seq_id, "motion": a.get("motion"), "shape_id": a.get("shape_id"),
                "betas": [float(b) for b in a.get("betas", [])], "garment": ds.garment_name,
                "body_model": ds.body_id, "split": a.get("split")}
        paths["usd"] = write_usd(out_dir / f"{seq_id}.usdc", tracks, fps=fps,
                                 metadata={k: v for k, v in meta.items() if v is not None})
    if mp4:
        from simgen.io.render import render_sequence, scene_legend

        a = seq["attrs"]
        betas = np.asarray(seq["betas"], dtype=np.float64)
        betas = betas.reshape(-1, betas.shape[-1])[-1]  # (B,), or the last frame's of (T, B)
        legend = {"sequence": seq_id, **scene_legend(garment=ds.garment_name, betas=betas, motion=a.get("motion"))}
        paths["mp4"] = render_sequence(out_dir / f"{seq_id}.mp4", tracks, fps=fps, size=size, legend=legend,
                                       progress=progress)
    return paths


def _prim(name: str) -> str:
    import re

    p = re.sub(r"[^A-Za-z0-9_]", "_", name)
    return p if p and not p[0].isdigit() else f"g_{p}"


# ------------------------------------------------------------------------------------ packs
def pack_sequences(dataset, seq_ids, out_npz) -> Path:
    """Write a few sequences of a store into one small .npz for viewing elsewhere.

    Made for the device machine, which returns files of at most 16 MiB and has no USD or renderer:
    garment positions are stored relative to the frame's root translation as float16 (~0.5 mm
    resolution within 1 m of the root), poses/trans/betas as float32, with the faces, the body's
    id, hash and source, and each sequence's attrs. ``simgen dataset export PACK.npz SEQ`` reads it.
    A 300-frame T-shirt sequence takes ~8 MB.
    """
    import json

    from simgen._fileio import temp_path_beside
    from simgen.dataset.reader import Dataset, open_dataset

    ds = dataset if isinstance(dataset, Dataset) else open_dataset(dataset)
    ids = list(seq_ids)
    if not ids:
        raise InputError("pack: name at least one sequence")
    arrays = {"faces": ds.template["faces"].astype(np.int32)}
    meta = {"kind": "simgen-dataset-pack", "source": ds.path, "garment": ds.garment_name, "body": ds.attrs["body"],
            "fps": ds.fps, "sequences": {}}
    for i, sid in enumerate(ids):
        seq = ds.sequence(sid)
        rel = seq["garment_vertices"] - seq["trans"][:, None, :]
        arrays[f"s{i}_garment_rel_f16"] = rel.astype(np.float16)
        for k in ("poses", "trans", "betas"):
            arrays[f"s{i}_{k}"] = seq[k].astype(np.float32)
        meta["sequences"][sid] = {"index": i, "attrs": seq["attrs"]}
    arrays["meta"] = np.asarray(json.dumps(meta, default=float))
    out = Path(out_npz)
    if out.suffix != ".npz":
        raise InputError(f"pack: --out {out} must end in .npz")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path_beside(out)
    try:
        np.savez_compressed(tmp, **arrays)
        tmp.replace(out)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return out


class PackedSequences:
    """A pack written by :func:`pack_sequences`, read with the Dataset methods export needs."""

    def __init__(self, path) -> None:
        import json

        self.path = str(path)
        try:
            self._z = dict(np.load(path, allow_pickle=False))
            self.meta = json.loads(str(self._z["meta"]))
        except (OSError, ValueError, KeyError) as exc:
            raise InputError(f"{path} is not a simgen dataset pack ({exc})") from None
        if self.meta.get("kind") != "simgen-dataset-pack":
            raise InputError(f"{path} is not a simgen dataset pack")
        self.attrs = {"body": self.meta["body"]}
        self.garment_name = self.meta["garment"]
        self.fps = float(self.meta["fps"])
        self.body_id = self.meta["body"]["id"]
        self.template = {"faces": self._z["faces"]}

    def sequence_ids(self, split=None) -> list[str]:
        return sorted(s for s, e in self.meta["sequences"].items() if split is None or e["attrs"].get("split") == split)

    def sequence(self, seq_id: str) -> dict:
        e = self.meta["sequences"].get(seq_id)
        if e is None:
            raise InputError(f"pack {self.path} has no sequence {seq_id!r}; it holds {', '.join(self.sequence_ids())}")
        i = e["index"]
        trans = self._z[f"s{i}_trans"]
        x = self._z[f"s{i}_garment_rel_f16"].astype(np.float32) + trans[:, None, :]
        return {"garment_vertices": x, "poses": self._z[f"s{i}_poses"], "trans": trans,
                "betas": self._z[f"s{i}_betas"], "attrs": e["attrs"]}

    def load_body(self, body=None):
        from simgen import body as body_pkg
        from simgen.body.model import BodyModel

        b = body if isinstance(body, BodyModel) else body_pkg.load(body or self.meta["body"]["source"])
        if b.hash != self.meta["body"]["hash"]:
            raise InputError(f"body model {b.name!r} is not the one the pack {self.path} was made with "
                             f"({self.body_id})")
        return b


def open_pack(path) -> PackedSequences:
    """Open a pack written by :func:`pack_sequences`."""
    if not Path(path).is_file():
        raise InputError(f"pack {path} does not exist")
    return PackedSequences(path)
