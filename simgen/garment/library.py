"""The garment library: bundled templates and user garments, found by name.

Garments live in folders NAME/ holding NAME.obj, NAME.json and NAME.npz (see
:class:`simgen.garment.Garment`). For a body with asset id B (``simgen.assets.body_asset_id``), the
search order is ``$SIMGEN_HOME/B/garments/`` (imports and garments built for that body), then the
bundled ``garments/`` (only for the bundled body "open"). A user garment shadows a bundled one of
the same name.

A garment records the body it was made on (metadata "body": {"id", "name", "hash"}); loading it
for another body is refused, because its vertices and skinning weights belong to that body's rest
template.
"""

from __future__ import annotations

import difflib
import json
import warnings
from pathlib import Path

from simgen.errors import InputError

__all__ = ["list_garments", "load_garment", "find_garment", "garment_body", "check_garment_body"]


def garment_body(metadata: dict) -> dict:
    """The body a garment was made for, from its metadata: {"id", "name", "hash"} (None if unknown).

    Reads the "body" mapping written by simgen (and, for robustness, "body_id"/"body_hash" keys or
    a plain "body" string naming the body id).
    """
    body = metadata.get("body")
    info = {"id": None, "name": None, "hash": None}
    if isinstance(body, dict):
        info.update({k: body.get(k) for k in info})
        info["id"] = info["id"] or body.get("model_id") or body.get("asset_id")
    elif isinstance(body, str):
        info["id"] = body
    info["id"] = info["id"] or metadata.get("body_id")
    info["hash"] = info["hash"] or metadata.get("body_hash")
    return info


def check_garment_body(garment, body) -> None:
    """Raise InputError when ``garment`` was made for another body than ``body`` (hash mismatch).

    A garment without a recorded body hash is accepted.
    """
    from simgen.assets import body_asset_id

    info = garment_body(garment.metadata)
    if info["hash"] and info["hash"] != body.hash:
        made_for = info["id"] or info["name"] or "another body"
        body_id = body_asset_id(body)
        spec = "open" if body_id == "open" else "PATH"
        raise InputError(
            f"garment {garment.name!r} was made for body {made_for!r} (hash {str(info['hash'])[:12]}), not for "
            f"body {body_id!r} (hash {body.hash[:12]}); rebuild it for this body with `simgen garment build "
            f"{garment.name} --body {spec}` (templates) or re-import its OBJ with `simgen garment import FILE "
            f"--name {garment.name} --body {spec}`")


def _garment_folders(body_id: str) -> dict[str, tuple[str, Path]]:
    """name -> ('user' | 'bundled', folder), user garments shadowing bundled ones."""
    from simgen.assets import search_dirs, user_dir
    from simgen.garment.obj_import import GARMENT_NAME_PATTERN

    found: dict[str, tuple[str, Path]] = {}
    user = user_dir("garments", body_id)
    for d in search_dirs("garments", body_id):
        if not d.is_dir():
            continue
        source = "user" if d == user else "bundled"
        for sub in sorted(d.iterdir()):
            name = sub.name
            if (GARMENT_NAME_PATTERN.match(name) and name not in found and sub.is_dir()
                    and (sub / f"{name}.json").is_file()):
                found[name] = (source, sub)
    return found


def list_garments(body_id: str = "open") -> list[dict]:
    """The garments available for a body, sorted by name (user garments shadow bundled ones).

    Each entry: name, source ('user' | 'bundled'), path (str, the garment folder), vertices,
    triangles, openings (number of boundary loops), default_material, skinning (method),
    body_id and body_hash (of the body the garment was made for). Read from NAME.json only;
    folders whose JSON cannot be read are skipped with a warning.
    """
    out = []
    for name, (source, folder) in sorted(_garment_folders(body_id).items()):
        path = folder / f"{name}.json"
        try:
            meta = json.loads(path.read_text(encoding="utf-8"))
            if not isinstance(meta, dict):
                raise ValueError("not a JSON object")
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            warnings.warn(f"skipping garment {folder}: {path.name} is unreadable ({exc})", stacklevel=2)
            continue
        body = garment_body(meta)
        openings = meta.get("openings")
        if isinstance(openings, (list, dict)):
            openings = len(openings)
        skinning = meta.get("skinning")
        out.append({
            "name": name,
            "source": source,
            "path": str(folder),
            "vertices": meta.get("num_vertices"),
            "triangles": meta.get("num_triangles"),
            "openings": openings,
            "default_material": meta.get("default_material"),
            "skinning": skinning.get("method") if isinstance(skinning, dict) else skinning,
            "body_id": body["id"],
            "body_hash": body["hash"],
        })
    return out


def find_garment(name: str, body_id: str = "open") -> Path:
    """The folder of garment ``name`` for a body (user folder first); InputError when unknown."""
    from simgen.garment.obj_import import GARMENT_NAME_PATTERN

    if not isinstance(name, str) or not GARMENT_NAME_PATTERN.match(name):
        raise InputError(f"garment name {name!r} is invalid: use only letters, digits, '_' and '-'")
    folders = _garment_folders(body_id)
    if name not in folders:
        close = difflib.get_close_matches(name, list(folders), n=3, cutoff=0.6)
        if folders:
            hint = f"; available: {', '.join(sorted(folders))}"
            if close:
                hint = f"; did you mean {' or '.join(close)}? Available: {', '.join(sorted(folders))}"
        else:
            hint = ("; no garments are installed for this body (build the templates with `simgen garment "
                    "build all` or import one with `simgen garment import`)")
        raise InputError(f"garment {name!r} is not in the library for body {body_id!r}{hint}")
    return folders[name][1]


def load_garment(name: str, *, body=None):
    """Load a garment by name: the user's garments for the body first, then the bundled ones.

    Args:
        name: garment name (``list_garments`` shows them).
        body: the :class:`~simgen.body.BodyModel` it will be used with (default: the bundled
            body's library, without a body check). When given, its asset id picks the folders and
            a garment made for another body (a different hash) is refused with InputError saying
            how to rebuild it.

    Returns:
        The :class:`~simgen.garment.Garment`.
    """
    from simgen.assets import body_asset_id
    from simgen.garment.garment import Garment

    body_id = "open" if body is None else body_asset_id(body)
    garment = Garment.load(find_garment(name, body_id))
    if body is not None:
        check_garment_body(garment, body)
    return garment
