"""``simgen view``: a browser viewer (viser) for simulations, dataset stores and model evaluations.

    from simgen.view import open_source, Viewer, serve
    source = open_source("simgen-demo/tshirt_walk.npz")     # .npz, .usdc, a dataset store, an eval folder
    scene = source.load(source.select())                      # body (F, Vb, 3) [m], garment tracks (F, V, 3) [m]
    viewer = Viewer(source, port=8080).start()                # http://127.0.0.1:8080; viewer.stop()

Sources and the scene model: :mod:`simgen.view.sources`; colour fields and physics terms:
:mod:`simgen.view.measures`; the server: :mod:`simgen.view.app`. viser and its web client load on
first use.
"""

from __future__ import annotations

import importlib

__all__ = ["Scene", "GarmentTrack", "Source", "open_source", "register_source", "SOURCES", "Viewer", "serve"]

_LAZY = {
    "Scene": "simgen.view.sources",
    "GarmentTrack": "simgen.view.sources",
    "Source": "simgen.view.sources",
    "open_source": "simgen.view.sources",
    "register_source": "simgen.view.sources",
    "SOURCES": "simgen.view.sources",
    "Viewer": "simgen.view.app",
    "serve": "simgen.view.app",
}


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'simgen.view' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
