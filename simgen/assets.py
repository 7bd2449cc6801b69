"""Where simgen finds its assets: bundled (shipped in the wheel) and user ones (under SIMGEN_HOME).

Bundled motions and garments live at the repository root (``motions/``, ``garments/``) in a source
checkout and inside the installed package (``simgen/_assets/``) in a wheel. User assets go under
``$SIMGEN_HOME/<body-id>/{motions,garments}`` (SIMGEN_HOME defaults to ~/.local/share/simgen);
lookups search the user folders first, then the bundled ones. Nothing is ever written into the
installed package.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["simgen_home", "bundled_dir", "user_dir", "search_dirs", "body_asset_id"]

_PACKAGE_DIR = Path(__file__).resolve().parent


def simgen_home() -> Path:
    """The user data folder: $SIMGEN_HOME, or ~/.local/share/simgen."""
    env = os.environ.get("SIMGEN_HOME")
    return Path(env).expanduser() if env else Path.home() / ".local" / "share" / "simgen"


def bundled_dir(kind: str) -> Path:
    """Folder of the bundled assets of one kind ("motions" or "garments")."""
    if kind not in ("motions", "garments"):
        raise ValueError(f"unknown asset kind {kind!r}")
    installed = _PACKAGE_DIR / "_assets" / kind
    if installed.is_dir():
        return installed
    return _PACKAGE_DIR.parent / kind  # source checkout or editable install


def user_dir(kind: str, body_id: str = "open") -> Path:
    """Folder for user assets of one kind made for one body (not created here)."""
    return simgen_home() / body_id / kind


def search_dirs(kind: str, body_id: str = "open") -> list[Path]:
    """Folders to search for assets, user first; bundled assets only serve the bundled body."""
    dirs = [user_dir(kind, body_id)]
    if body_id == "open":
        dirs.append(bundled_dir(kind))
    return dirs


def body_asset_id(body) -> str:
    """Asset folder name for a body: "open" for the bundled default, else its model_id."""
    return "open" if getattr(body, "name", None) == "open" else body.model_id
