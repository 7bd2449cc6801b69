"""What every benchmark script records beside its numbers: the commit it ran at."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path


def commit() -> str:
    """``SIMGEN_COMMIT`` (the device machine gets the tree without .git), else ``git rev-parse
    --short HEAD`` of this repository, else "unknown"."""
    env = os.environ.get("SIMGEN_COMMIT")
    if env:
        return env
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).resolve().parent, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
