"""What ``simgen eval compare`` writes: tables (Markdown + JSON), the per-frame error plot, the
side-by-side USD and the MP4 (or, with --no-video, the clips the MP4 needs), all into a staging
folder that is moved into --out only when every file is written (a failure leaves --out as it was)."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from simgen.errors import InputError

__all__ = ["staging", "publish", "write_tables", "write_results", "plot_error_per_frame", "clip_tracks",
           "write_usd_and_video", "write_clips", "read_clips", "render_clips", "REPORT_FILE", "RESULTS_FILE",
           "CLIPS_FILE", "OTHER_FILES"]

REPORT_FILE, RESULTS_FILE = "compare.md", "compare.json"
CLIPS_FILE = "compare_clips.npz"
#: Files of ``out`` besides the tables' NAME.md / NAME.json.
OTHER_FILES = (REPORT_FILE, RESULTS_FILE, "error_per_frame.png", "compare.usdc", "compare.mp4", CLIPS_FILE)


def staging(out: Path) -> Path:
    """A fresh hidden folder beside ``out`` (same file system, so publishing is a rename per file)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} is a file, not a folder")
    out.parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))


def publish(stage: Path, out: Path, owned=()) -> list[Path]:
    """Move every file of ``stage`` into ``out`` (replacing older ones of the same name); remove ``stage``.

    owned: names this command writes; those of an earlier run that this one did not write (e.g.
    compare.mp4 after --no-video) are removed, so ``out`` never mixes two runs."""
    out.mkdir(parents=True, exist_ok=True)
    fresh = {p.name for p in stage.iterdir()}
    for name in set(owned) - fresh:
        (out / name).unlink(missing_ok=True)
    moved = []
    for path in sorted(stage.iterdir()):
        os.replace(path, out / path.name)
        moved.append(out / path.name)
    shutil.rmtree(stage, ignore_errors=True)
    return moved


def write_tables(tables, results: dict, folder: Path) -> dict:
    """NAME.md and NAME.json per table and compare.md (all of them); returns {name: [files]}."""
    files = {}
    for t in tables:
        (folder / f"{t.name}.md").write_text(t.markdown(), encoding="utf-8")
        (folder / f"{t.name}.json").write_text(json.dumps(t.to_dict(), indent=1) + "\n", encoding="utf-8")
        files[t.name] = [f"{t.name}.md", f"{t.name}.json"]
    head = [f"# simgen eval compare: {results['garment']} on {results['dataset']}", "",
            f"Held-out sequences: {', '.join(f'{g} ({len(v)})' for g, v in results['split']['groups'].items())}; "
            f"split by {results['split']['by']}"
            + (f", held-out shapes {', '.join(results['split']['test_shapes'])}" if results['split']['test_shapes']
               else "") + ".", ""]
    head += [f"- {c['label']}: {c['folder'] or 'the dataset template'} ({c.get('method') or c['kind']})"
             for c in results["contestants"]]
    (folder / REPORT_FILE).write_text("\n".join(head) + "\n\n" + "\n".join(t.markdown() for t in tables),
                                      encoding="utf-8")
    files["report"] = REPORT_FILE
    return files


def write_results(results: dict, tables, folder: Path) -> Path:
    """compare.json: the results dict and every table."""
    path = folder / RESULTS_FILE
    path.write_text(json.dumps({**results, "tables": [t.to_dict() for t in tables]}, indent=1) + "\n",
                    encoding="utf-8")
    return path


def plot_error_per_frame(results: dict, path: Path, *, max_panels: int = 6) -> Path | None:
    """Vertex error [cm] per frame, one panel per held-out clip (up to ``max_panels``), a line per method."""
    from simgen.learn.plots import _pyplot, _save

    seqs = results["sequences"]
    if not seqs:
        return None
    labels = {c["key"]: c["label"] for c in results["contestants"]}
    chosen = list(seqs)[:max_panels]
    plt = _pyplot()
    fig, axes = plt.subplots(len(chosen), 1, figsize=(8, 1.6 + 2.4 * len(chosen)), squeeze=False,
                             layout="constrained")
    for ax, sid in zip(axes[:, 0], chosen):
        row = seqs[sid]
        fps = float(row.get("fps", 30.0))
        for key, e in row["error_cm_per_frame"].items():
            ax.plot(np.arange(len(e)) / fps, e, label=f"{labels.get(key, key)} ({row['error_cm'][key]:.2f})",
                    lw=1.4 if key != "lbs" else 1.0, ls="-" if key != "lbs" else "--")
        ax.set_title(f"{sid} ({row['group'].replace('_', ' ')})", fontsize=10)
        ax.set_ylabel("vertex error [cm]")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper left")
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle("Mean vertex error against the simulation, per frame (no post-process)", fontsize=11)
    _save(fig, Path(path))
    plt.close(fig)
    return Path(path)


def clip_tracks(clips: list[dict], body_faces, garment_faces, order: list[str]):
    """Side-by-side tracks of each clip (the simulation, then ``order``), at one spacing for all.

    clips: [{"id", "fps", "body" (T, Vb, 3), "ground_truth" (T, V, 3), "predictions" {key: (T, V, 3)}}].
    Returns [(tracks, meta)] per clip.
    """
    from simgen.learn.compare import side_by_side_tracks

    width = max(float(np.ptp(np.concatenate([c["body"].reshape(-1, 3), c["ground_truth"].reshape(-1, 3)])[:, 0]))
                for c in clips)
    spacing = max(1.0, 1.15 * width)
    return [side_by_side_tracks(c["body"], body_faces, garment_faces, c["ground_truth"],
                                {k: c["predictions"][k] for k in order}, spacing=spacing) for c in clips]


def _concatenated(per_clip: list) -> list:
    """One track set playing the clips one after the other (same names, vertex counts and roles)."""
    from simgen.io.usd import MeshTrack

    first = per_clip[0][0]
    out = []
    for k, track in enumerate(first):
        parts = [tracks[k] for tracks, _ in per_clip]
        colors = None
        if track.colors is not None:
            colors = np.concatenate([np.broadcast_to(p.colors, p.points.shape) for p in parts])
        out.append(MeshTrack(name=track.name, points=np.concatenate([p.points for p in parts]), faces=track.faces,
                             colors=colors, role=track.role))
    return out


def write_usd_and_video(clips: list[dict], body_faces, garment_faces, order: list[str], labels: dict,
                        folder: Path, *, video: bool, meta: dict, video_order: list[str] | None = None,
                        identity: dict | None = None, progress=None) -> dict:
    """compare.usdc (the first clip, every method side by side) and either compare.mp4 (``video``:
    the clips one after the other, the methods of ``video_order``, default ``order``) or, without
    video, compare_clips.npz (what the MP4 needs, :func:`write_clips`, for :func:`render_clips` on a
    machine that can render). Returns {"usd": file name, "video" or "clips": file name}."""
    from simgen.io.usd import write_usd

    per_clip = clip_tracks(clips, body_faces, garment_faces, order)
    tracks, m = per_clip[0]
    names = ["simulation"] + [labels[k] for k in order]
    write_usd(folder / "compare.usdc", tracks, fps=clips[0]["fps"],
              metadata={**meta, **m, "sequence": clips[0]["id"], "labels": names})
    files = {"usd": "compare.usdc"}
    shown = list(video_order or order)
    if video:
        _render_video(folder / "compare.mp4", clips, body_faces, garment_faces, shown, labels, progress)
        files["video"] = "compare.mp4"
    else:
        write_clips(folder / CLIPS_FILE, clips, shown, labels, garment_faces, {**meta, "identity": identity or {}})
        files["clips"] = CLIPS_FILE
    return files


def _render_video(path: Path, clips: list[dict], body_faces, garment_faces, order: list[str], labels: dict,
                  progress=None) -> None:
    from simgen.io.render import follow_cameras, render_sequence

    per_clip = clip_tracks(clips, body_faces, garment_faces, order)
    names = ["simulation"] + [labels[k] for k in order]
    title = " | ".join(names) + "   clips: " + ", ".join(c["id"] for c in clips)
    tracks, size = _concatenated(per_clip), (min(1920, 384 * len(names)), 480)
    # From the front, so that every copy in the row is drawn at the same size.
    cameras = follow_cameras(tracks, aspect=size[0] / size[1], fps=clips[0]["fps"], azimuth=0.0, elevation=5.0)
    render_sequence(path, tracks, fps=clips[0]["fps"], size=size, camera=cameras, title=title, progress=progress)


# ------------------------------------------------------------------------------------ clips for later rendering
def write_clips(path: Path, clips: list[dict], order: list[str], labels: dict, garment_faces, meta: dict) -> Path:
    """compare_clips.npz: each clip's id, fps, body motion (betas (T, B), poses (T, 24, 3) [rad], trans
    (T, 3) [m]) and the garment [m] (T, V, 3) of the simulation and of each method in ``order``,
    stored as float16 offsets from the root translation (resolution <= 0.5 mm within 1 m of it); the
    posed body is not stored (:func:`render_clips` poses it again with the store's body)."""
    arrays = {"faces": np.asarray(garment_faces, dtype=np.int32)}
    for k, c in enumerate(clips):
        root = np.asarray(c["trans"], dtype=np.float32)[:, None]
        arrays.update({f"c{k}_betas": c["betas"], f"c{k}_poses": c["poses"], f"c{k}_trans": c["trans"],
                       f"c{k}_simulation": (c["ground_truth"] - root).astype(np.float16)})
        for key in order:
            arrays[f"c{k}_{key}"] = (c["predictions"][key] - root).astype(np.float16)
    info = {"format": "simgen-compare-clips", "version": 1, "order": order,
            "labels": {k: labels[k] for k in order}, "clips": [{"id": c["id"], "fps": c["fps"]} for c in clips],
            **meta}
    np.savez_compressed(path, meta=np.array(json.dumps(info)), **arrays)
    return path


def read_clips(clips_file) -> tuple[dict, list[dict]]:
    """(info, clips) of a compare_clips.npz (:func:`write_clips`): info holds "order", "labels",
    "identity", ...; each clip {"id", "fps", "betas", "poses", "trans", "faces", "ground_truth" [m]
    (T, V, 3), "predictions" {key: [m] (T, V, 3)}} in float32, without the posed body."""
    path = Path(clips_file)
    if not path.is_file():
        raise InputError(f"--clips {path} is not a file")
    import zipfile

    not_clips = InputError(f"{path} is not a compare_clips.npz of `simgen eval compare --no-video`")
    try:
        with np.load(path) as z:
            if "meta" not in z.files:
                raise not_clips
            info = json.loads(str(z["meta"]))
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile):  # not an npz archive at all
        raise not_clips from None
    clips = []
    for k, c in enumerate(info["clips"]):
        root = arrays[f"c{k}_trans"].astype(np.float32)[:, None]
        clips.append({**c, **{n: arrays[f"c{k}_{n}"] for n in ("betas", "poses", "trans")}, "faces": arrays["faces"],
                      "ground_truth": arrays[f"c{k}_simulation"].astype(np.float32) + root,
                      "predictions": {key: arrays[f"c{k}_{key}"].astype(np.float32) + root for key in info["order"]}})
    return info, clips


def render_clips(clips_file, out_mp4, *, body=None, progress=None) -> Path:
    """compare.mp4 from a compare_clips.npz (:func:`write_clips`): the body re-posed with ``body``
    (default: the bundled body; its hash must be the store's), the methods side by side, coloured
    by their error against the simulation, the clips one after the other."""
    import torch

    from simgen.body.torch_lbs import TorchBody
    from simgen.learn.data import body_for_identity

    info, clips = read_clips(clips_file)
    model = body_for_identity(info.get("identity") or {}, body)
    tb = TorchBody(model)
    for c in clips:
        with torch.no_grad():
            motion = (torch.as_tensor(c[n], dtype=torch.float32) for n in ("betas", "poses", "trans"))
            c["body"] = tb(*motion)[0].numpy()
    out = Path(out_mp4)
    out.parent.mkdir(parents=True, exist_ok=True)
    _render_video(out, clips, np.asarray(model.faces), clips[0]["faces"], info["order"], info["labels"], progress)
    return out
