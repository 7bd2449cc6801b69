"""Warp's console output, kept quiet: its banner and per-module load lines would break progress bars.

``simgen --verbose`` turns this off (:func:`set_verbose`): Warp then logs as it does by default.
"""

from __future__ import annotations

import os
import sys
from contextlib import contextmanager
from typing import Callable, Iterator

__all__ = ["quiet_warp", "set_verbose", "is_verbose", "init_warp", "compile_notice", "CUDA_DRIVER_WARNING"]

#: The line Warp's native library writes to stderr at initialisation when it finds no CUDA driver.
CUDA_DRIVER_WARNING = "Could not find or load the NVIDIA CUDA driver"

_verbose = False


def set_verbose(verbose: bool) -> None:
    """Let Warp print its banner, module load lines and the CUDA driver warning (``simgen --verbose``)."""
    global _verbose
    _verbose = bool(verbose)


def is_verbose() -> bool:
    return _verbose


def quiet_warp() -> None:
    """Silence Warp's banner and per-module load lines (warnings still show); nothing under --verbose."""
    if _verbose:
        return
    import warp as wp

    wp.config.quiet = True  # warp < 1.19
    if hasattr(wp, "LOG_WARNING") and hasattr(wp.config, "log_level"):
        wp.config.log_level = wp.LOG_WARNING  # warp >= 1.19


def _runtime_started() -> bool:
    for name in ("warp._src.context", "warp.context"):
        module = sys.modules.get(name)
        if module is not None and hasattr(module, "runtime"):
            return module.runtime is not None
    return False


def init_warp(device: str | None = None) -> None:
    """Quiet Warp (see :func:`quiet_warp`) and start its runtime now.

    Warp's native library prints "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver"
    straight to the process's stderr (file descriptor 2, below Python) while it starts. That
    alarms a user who runs on the CPU on purpose, so unless ``device`` names a CUDA device (or
    --verbose is on) the start runs with descriptor 2 captured, and everything captured except
    that one line is written back to stderr afterwards: real errors still show. A runtime that
    is already started is left alone.
    """
    quiet_warp()
    import warp as wp

    if _runtime_started():
        return
    if _verbose or (device is not None and str(device).startswith("cuda")):
        wp.init()
        return
    import tempfile

    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (AttributeError, ValueError, OSError):
            pass
    try:
        saved = os.dup(2)
    except OSError:  # no descriptor 2 (a detached process): nothing to filter
        wp.init()
        return
    with tempfile.TemporaryFile() as captured:
        os.dup2(captured.fileno(), 2)
        try:
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            captured.seek(0)
            text = captured.read().decode("utf-8", errors="replace")
            kept = "".join(line for line in text.splitlines(keepends=True) if CUDA_DRIVER_WARNING not in line)
            if kept:
                sys.stderr.write(kept)
                sys.stderr.flush()


@contextmanager
def compile_notice(notify: Callable[[], None]) -> Iterator[None]:
    """Call ``notify()`` once, just before Warp compiles a module that is not in its kernel cache.

    Warp compiles a module on its first launch (tens of seconds on a CPU for the solver) and
    says nothing while it does once quieted. This wraps Warp's per-module compile step for the
    duration of the block; where that step cannot be found (another Warp version) ``notify()``
    is called at once instead, which may then show on runs that find everything cached.
    """
    module_cls = None
    for name in ("warp._src.context", "warp.context"):
        try:
            module_cls = getattr(__import__(name, fromlist=["Module"]), "Module", None)
        except ImportError:
            continue
        if module_cls is not None and callable(getattr(module_cls, "_compile", None)):
            break
        module_cls = None
    if module_cls is None:
        notify()
        yield
        return
    own = "_compile" in module_cls.__dict__
    original = module_cls._compile
    fired = [False]

    def _compile(self, *args, **kwargs):
        if not fired[0]:
            try:
                # Module.load passes (device, output_dir, output_name, ...); a binary already in the
                # cache means Warp only loads it.
                output_dir = kwargs.get("output_dir", args[1] if len(args) > 1 else None)
                output_name = kwargs.get("output_name", args[2] if len(args) > 2 else None)
                cached = bool(output_dir and output_name and os.path.exists(os.path.join(output_dir, output_name)))
            except Exception:  # noqa: BLE001 - a notice must never break a compile
                cached = False
            if not cached:
                fired[0] = True
                notify()
        return original(self, *args, **kwargs)

    module_cls._compile = _compile
    try:
        yield
    finally:
        if own:
            module_cls._compile = original
        else:
            del module_cls._compile
