"""Warp's console output, kept quiet: its banner and per-module load lines would break progress bars."""

from __future__ import annotations

__all__ = ["quiet_warp"]


def quiet_warp() -> None:
    """Silence Warp's banner and per-module load lines (warnings still show)."""
    import warp as wp

    wp.config.quiet = True  # warp < 1.19
    if hasattr(wp, "LOG_WARNING") and hasattr(wp.config, "log_level"):
        wp.config.log_level = wp.LOG_WARNING  # warp >= 1.19
