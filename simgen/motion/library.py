"""The motion library: bundled clips (motions/ with library.json) and user imports (SIMGEN_HOME).

Bundled clips live in ``simgen.assets.bundled_dir("motions")`` as NAME.npz next to ``library.json``:
  {"version": 1, "clips": {NAME: {"split": "train" | "test", "description": str, "source": str,
                                   "attribution": str (optional)}}}
User clips are imported with :func:`import_motion` into ``simgen.assets.user_dir("motions", body_id)``
and shadow bundled clips of the same name. Nothing is ever written into the installed package.
"""

from __future__ import annotations

import difflib
import json
import re
import warnings
from pathlib import Path

from simgen.assets import body_asset_id, bundled_dir, search_dirs, user_dir
from simgen.body.model import BodyModel
from simgen.errors import InputError
from simgen.motion.clip import MotionClip
from simgen.motion.motion_file import load_motion_file, save_motion

__all__ = ["list_motions", "load_motion", "library_split", "import_motion", "library_index", "MOTION_NAME_PATTERN"]

MOTION_NAME_PATTERN = re.compile(r"^[A-Za-z0-9_-]+$")
_SPLITS = ("train", "test")


def library_index() -> dict[str, dict]:
    """The 'clips' table of the bundled library.json ({} when the file does not exist)."""
    path = bundled_dir("motions") / "library.json"
    if not path.is_file():
        return {}
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"motion library index {path} is not valid JSON ({exc})") from None
    clips = doc.get("clips") if isinstance(doc, dict) else None
    if not isinstance(clips, dict):
        raise InputError(f"motion library index {path} lacks the object field 'clips'")
    for name, entry in clips.items():
        if not isinstance(entry, dict) or entry.get("split") not in _SPLITS:
            raise InputError(f"motion library index {path}: clip {name!r} needs field 'split' set to 'train' or "
                             f"'test'")
    return clips


def library_split() -> dict[str, list[str]]:
    """Names of the bundled clips in each split: {"train": [...], "test": [...]}, sorted."""
    out: dict[str, list[str]] = {s: [] for s in _SPLITS}
    for name, entry in library_index().items():
        out[entry["split"]].append(name)
    return {s: sorted(v) for s, v in out.items()}


def _check_name(name: str) -> None:
    if not isinstance(name, str) or not MOTION_NAME_PATTERN.match(name):
        raise InputError(f"motion name {name!r} is invalid: use only letters, digits, '_' and '-'")


def _clip_files(body_id: str) -> list[tuple[str, str, Path]]:
    """(name, 'user' | 'bundled', path) of every clip file, user clips shadowing bundled ones."""
    seen: dict[str, tuple[str, str, Path]] = {}
    user = user_dir("motions", body_id)
    for d in search_dirs("motions", body_id):
        if not d.is_dir():
            continue
        source = "user" if d == user else "bundled"
        for p in sorted(d.glob("*.npz")):
            if MOTION_NAME_PATTERN.match(p.stem) and p.stem not in seen:
                seen[p.stem] = (p.stem, source, p)
    return sorted(seen.values())


def list_motions(body_id: str = "open") -> list[dict]:
    """The clips available for a body, sorted by name (a user clip hides a bundled one of the same name).

    Each entry: name, source ('bundled' | 'user'), path (str), fps [1/s], frames, duration [s],
    split ('train' | 'test' for bundled clips, else the clip's own meta['split'] or None) and
    description. Files that cannot be read are skipped with a warning.
    """
    index = library_index()
    out = []
    for name, source, path in _clip_files(body_id):
        try:
            clip = load_motion_file(path)
        except InputError as exc:
            warnings.warn(f"skipping motion file {path}: {exc}", stacklevel=2)
            continue
        entry = index.get(name, {}) if source == "bundled" else {}
        out.append({
            "name": name,
            "source": source,
            "path": str(path),
            "fps": clip.fps,
            "frames": clip.num_frames,
            "duration": clip.duration,
            "split": entry.get("split", clip.meta.get("split")),
            "description": entry.get("description", clip.meta.get("description", "")),
        })
    return out


def load_motion(name: str, *, body_id: str = "open") -> MotionClip:
    """Load a library clip by name: the user's imports first, then the bundled clips.

    Bundled clips get 'split', 'description', 'source' and 'attribution' from library.json in their
    meta. Raises InputError for an unknown name, listing close matches.
    """
    _check_name(name)
    files = {n: (src, p) for n, src, p in _clip_files(body_id)}
    if name not in files:
        close = difflib.get_close_matches(name, list(files), n=5, cutoff=0.5)
        hint = f"; close matches: {', '.join(close)}" if close else (
            f"; available: {', '.join(sorted(files)[:20])}" if files else "; no motions are installed")
        raise InputError(f"motion {name!r} is not in the library for body {body_id!r}{hint}")
    source, path = files[name]
    clip = load_motion_file(path, name=name)
    if source == "bundled":
        for key, value in library_index().get(name, {}).items():
            clip.meta.setdefault(key, value)
    clip.meta["library_source"] = source
    return clip


def import_motion(
    path: str | Path,
    name: str,
    *,
    body: BodyModel,
    body_id: str | None = None,
    overwrite: bool = False,
) -> Path:
    """Convert an AMASS .npz, BVH or simgen .npz file for `body` and save it in the user library.

    The clip is written as simgen .npz to user_dir("motions", body_id)/NAME.npz (body_id defaults to
    simgen.assets.body_asset_id(body): "open" for the bundled body, else its model_id) and the path
    is returned. Raises InputError, writing nothing, for a bad name (allowed:
    letters, digits, '_' and '-'), an existing clip of that name without overwrite, or a bad file.
    """
    _check_name(name)
    body_id = body_id or body_asset_id(body)
    _check_name(body_id)
    dest = user_dir("motions", body_id) / f"{name}.npz"
    if dest.exists() and not overwrite:
        raise InputError(f"motion {name!r} already exists at {dest}; pass overwrite to replace it")
    path = Path(path)
    clip = load_motion_file(path, body=body, name=name)
    clip.meta["imported_from"] = path.name
    return save_motion(clip, dest)
