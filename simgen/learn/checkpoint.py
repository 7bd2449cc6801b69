"""Saving and loading learned models: weights + a JSON config, one call each way.

A model folder holds ``model.pt`` (the state_dict, read back with ``torch.load(...,
weights_only=True)``: no pickled code runs on load) and ``config.json``:

    {"format_version": 1, "kind": "garment_fit" | "garment_wrinkle" | "garment_linear" | "garment_template",
     "simgen_version": ..., "model": {constructor arguments},
     "garment": {"name", "hash"}, "body": {"id", "hash"},   # what the model was trained for
     "training": {...}}                                    # dataset, split, epochs, losses, ...

Loading with an ``identity`` (the garment and body of a dataset or of another model) refuses a
model trained for a different garment or body with one sentence naming both.
"""

from __future__ import annotations

import inspect
import io
import json
from pathlib import Path
from typing import Any

import torch

from simgen._fileio import atomic_write_bytes
from simgen.errors import InputError

__all__ = ["FORMAT_VERSION", "MODEL_FILE", "CONFIG_FILE", "save_model", "load_model", "read_config",
           "check_identity", "model_size_mb"]

FORMAT_VERSION = 1
MODEL_FILE = "model.pt"
CONFIG_FILE = "config.json"


def _simgen_version() -> str:
    from simgen import __version__

    return __version__


def _torch_bytes(obj: Any) -> bytes:
    buf = io.BytesIO()
    torch.save(obj, buf)
    return buf.getvalue()


def save_model(model: torch.nn.Module, folder: str | Path, *, identity: dict, training: dict | None = None) -> Path:
    """Write FOLDER/model.pt and FOLDER/config.json (each atomically, the JSON last); returns FOLDER.

    identity: {"garment": {"name", "hash"}, "body": {"id", "hash"}}; training: JSON-serialisable
    facts about how the model was made.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    atomic_write_bytes(folder / MODEL_FILE, _torch_bytes(state))
    config = {"format_version": FORMAT_VERSION, "kind": model.kind, "simgen_version": _simgen_version(),
              "model": model.config(), "garment": dict(identity.get("garment", {})),
              "body": dict(identity.get("body", {})), "training": training or {}}
    atomic_write_bytes(folder / CONFIG_FILE, (json.dumps(config, indent=2, default=_json_default) + "\n").encode())
    return folder


def _json_default(value):
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"not JSON-serialisable: {type(value).__name__}")


def read_config(folder: str | Path) -> dict:
    """The config.json of a model folder (InputError when missing or not a simgen model)."""
    folder = Path(folder)
    path = folder / CONFIG_FILE
    if not path.is_file():
        raise InputError(f"{folder} is not a simgen model folder (no {CONFIG_FILE})")
    try:
        config = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"{path} is not valid JSON ({exc})") from None
    if not isinstance(config, dict) or "kind" not in config or "model" not in config:
        raise InputError(f"{path} lacks the fields 'kind' and 'model' of a simgen model config")
    if config.get("format_version") != FORMAT_VERSION:
        raise InputError(f"{path} has format_version {config.get('format_version')!r}; this simgen reads "
                         f"{FORMAT_VERSION}")
    return config


def _describe(side: dict, key: str) -> str:
    h = str(side.get("hash") or "?")[:12]
    return f"{side.get(key, '?')!r} (hash {h})"


def check_identity(config: dict, identity: dict, where: str | Path) -> None:
    """Refuse a model whose garment or body differs from ``identity`` (same layout as the config's)."""
    for part, key in (("garment", "name"), ("body", "id")):
        want, have = identity.get(part) or {}, config.get(part) or {}
        if not want:
            continue
        same = want.get(key) == have.get(key) and (not want.get("hash") or not have.get("hash")
                                                   or want.get("hash") == have.get("hash"))
        if not same:
            raise InputError(f"model {where} was trained for {part} {_describe(have, key)}, not for "
                             f"{_describe(want, key)}; train a model for this {part} or pick the matching model")


def load_model(folder: str | Path, *, identity: dict | None = None, kind: str | None = None,
               device: str | torch.device = "cpu") -> torch.nn.Module:
    """Load a saved model in one call (eval mode, on ``device``).

    identity: refuse a model trained for another garment or body (see :func:`check_identity`);
    kind: refuse a model of another kind (e.g. "garment_fit"). The model's ``saved_config``
    attribute holds its config.json.
    """
    from simgen.learn.models import MODEL_KINDS

    folder = Path(folder)
    config = read_config(folder)
    if kind is not None and config["kind"] != kind:
        raise InputError(f"model {folder} is a {config['kind']!r} model, expected {kind!r}")
    if identity is not None:
        check_identity(config, identity, folder)
    cls = MODEL_KINDS.get(config["kind"])
    if cls is None:
        raise InputError(f"model {folder} has unknown kind {config['kind']!r}")
    args = dict(config["model"])
    positional = []
    for prm in list(inspect.signature(cls.__init__).parameters.values())[1:]:
        if prm.kind not in (prm.POSITIONAL_ONLY, prm.POSITIONAL_OR_KEYWORD):
            continue
        if prm.name in args:
            positional.append(args.pop(prm.name))
        elif prm.default is not prm.empty:     # a setting added since the model was saved
            positional.append(prm.default)
        else:
            raise InputError(f"model {folder}: its config.json lacks the model setting {prm.name!r}")
    try:
        model = cls(*positional, **args)
        state = torch.load(folder / MODEL_FILE, map_location="cpu", weights_only=True)
        model.load_state_dict(state)
    except FileNotFoundError:
        raise InputError(f"model {folder} has a config but no {MODEL_FILE}") from None
    except (RuntimeError, TypeError, KeyError) as exc:
        raise InputError(f"model {folder}: the weights in {MODEL_FILE} do not match its config ({exc})") from None
    model.saved_config = config
    return model.to(device).eval()


def model_size_mb(model: torch.nn.Module, *, parameters_only: bool = True) -> float:
    """Memory of a model's float32 weights in MB (1e6 bytes), as thesis Table 4.1 counts it."""
    tensors = list(model.parameters()) if parameters_only else list(model.state_dict().values())
    return sum(t.numel() * t.element_size() for t in tensors) / 1e6
