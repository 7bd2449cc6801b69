"""Readers for SMPL-format model files: SMPL's official .npz and .pkl, and simgen's own .npz.

SMPL's .pkl files (versions 1.0 and 1.1) were pickled under Python 2 with chumpy objects inside
(``v_template``, ``shapedirs`` and ``posedirs`` are ``chumpy.ch.Ch``; ``J_regressor`` is a
``scipy.sparse.csc_matrix``). Pickles can run arbitrary code when loaded, and a model file is
input from outside, so they are read with :class:`_RestrictedUnpickler`: it rebuilds numpy arrays
and dtypes through numpy's own reconstructors, and turns chumpy objects and scipy sparse matrices
into inert stand-ins that only keep their pickled state (no chumpy or scipy code runs; chumpy
need not be installed). Any other global a pickle names is refused before anything is called.

.npz files are read with ``allow_pickle=False``.
"""

from __future__ import annotations

import io
import json
import pickle
import re
from pathlib import Path

import numpy as np

from simgen.body.model import NUM_JOINTS, BodyModel
from simgen.errors import InputError

__all__ = ["load_body_file"]

_SMPL_KEYS = ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "f")
_SIMGEN_KEYS = ("v_template", "shapedirs", "posedirs", "J_regressor_rows", "J_regressor_cols",
                "J_regressor_vals", "weights", "kintree_table", "f", "simgen_name", "simgen_meta")
_ZIP_MAGIC = b"PK"  # every zip archive (and so every .npz) starts with a "PK" record signature
_REASON_CHARS = 120  # error messages quote the underlying reason, clipped to stay one short sentence


def _clip(text: str) -> str:
    """One line of at most _REASON_CHARS characters (names and reasons inside messages come from the file)."""
    text = " ".join(text.split())
    return text if len(text) <= _REASON_CHARS else text[: _REASON_CHARS - 3] + "..."


def _reason(exc: BaseException) -> str:
    return _clip(f"{type(exc).__name__}: {exc}")


# ---------------------------------------------------------------------------------------------------
# Restricted unpickling
# ---------------------------------------------------------------------------------------------------
class _StandIn:
    """An inert placeholder for an object of an allowed foreign class: it only stores its pickled state.

    Subclasses are made per pickled class name (``source``, e.g. "chumpy.ch.Ch") so errors can name it.
    """

    source = "?"

    def __new__(cls, *args, **kwargs):
        obj = object.__new__(cls)
        obj.state = None
        return obj

    def __setstate__(self, state) -> None:
        self.state = state


class _ChumpyStandIn(_StandIn):
    """A chumpy object; a plain ``Ch`` keeps its value in state['x']."""


class _SparseStandIn(_StandIn):
    """A scipy sparse matrix; ``format`` is "csc", "csr" or "coo", the arrays live in the state dict."""

    format = "?"


_STAND_IN_CLASSES: dict[str, type] = {}


def _stand_in_class(base: type, module: str, name: str, **attrs) -> type:
    source = f"{module}.{name}"
    cls = _STAND_IN_CLASSES.get(source)
    if cls is None:
        cls = type(f"StandIn[{source}]", (base,), {"source": source, **attrs})
        _STAND_IN_CLASSES[source] = cls
    return cls


_SPARSE_MODULE = re.compile(r"scipy\.sparse(\.[A-Za-z_]+)?")
_SPARSE_CLASSES = {"csc_matrix", "csr_matrix", "coo_matrix", "csc_array", "csr_array", "coo_array"}


def _numpy_attr(module: str, name: str):
    """numpy's private reconstruction helpers moved from numpy.core to numpy._core in numpy 2."""
    import importlib

    for candidate in ("numpy._core." + module, "numpy.core." + module):
        try:
            return getattr(importlib.import_module(candidate), name)
        except (ImportError, AttributeError):
            continue
    raise ImportError(f"numpy has no {module}.{name}")


class _NdarrayToken:
    """What a pickle gets for 'numpy.ndarray': only usable as the subtype argument of _reconstruct,
    so a pickle cannot call the ndarray constructor on a buffer of its choosing."""


class _RestrictedUnpickler(pickle.Unpickler):
    """Unpickler that resolves only the globals an SMPL model file needs; see the module docstring."""

    def __init__(self, file, path: Path):
        super().__init__(file, encoding="latin1")
        self._path = path
        reconstruct = _numpy_attr("multiarray", "_reconstruct")

        def safe_reconstruct(subtype, shape, dtype):
            if subtype is not _NdarrayToken:
                raise InputError(f"{path}: the pickle asks numpy to rebuild {_clip(repr(subtype))}, which no SMPL "
                                 f"model file holds; refusing to load it")
            return reconstruct(np.ndarray, shape, dtype)

        def safe_reconstructor(cls, base, state):
            # copy_reg._reconstructor is how protocols 0 and 1 rebuild plain objects (chumpy Ch, sparse).
            if not (isinstance(cls, type) and issubclass(cls, _StandIn) and base is object and state is None):
                raise InputError(f"{path}: the pickle asks copy_reg._reconstructor to build {_clip(repr(cls))}, "
                                 f"which no SMPL model file holds; refusing to load it")
            return cls.__new__(cls)

        def latin1_encode(text, encoding="utf-8", errors="strict"):
            # Python 3 writes bytes under protocol 2 as _codecs.encode(str, 'latin1'); nothing else is allowed.
            if encoding not in ("latin1", "latin-1") or not isinstance(text, str):
                raise InputError(f"{path}: the pickle asks _codecs.encode for {_clip(repr(encoding))}, which no "
                                 f"SMPL model file holds; refusing to load it")
            return text.encode("latin1")

        self._allowed = {
            ("numpy.core.multiarray", "_reconstruct"): safe_reconstruct,
            ("numpy._core.multiarray", "_reconstruct"): safe_reconstruct,
            ("numpy", "ndarray"): _NdarrayToken,
            ("numpy", "dtype"): np.dtype,
            ("numpy.core.multiarray", "scalar"): _numpy_attr("multiarray", "scalar"),
            ("numpy._core.multiarray", "scalar"): _numpy_attr("multiarray", "scalar"),
            ("numpy.core.numeric", "_frombuffer"): _numpy_attr("numeric", "_frombuffer"),
            ("numpy._core.numeric", "_frombuffer"): _numpy_attr("numeric", "_frombuffer"),
            ("copy_reg", "_reconstructor"): safe_reconstructor,
            ("copyreg", "_reconstructor"): safe_reconstructor,
            ("__builtin__", "object"): object,
            ("builtins", "object"): object,
            # chumpy's pickled state holds its dirty-variable set.
            ("__builtin__", "set"): set,
            ("builtins", "set"): set,
            ("__builtin__", "frozenset"): frozenset,
            ("builtins", "frozenset"): frozenset,
            ("_codecs", "encode"): latin1_encode,
        }

    def find_class(self, module: str, name: str):
        allowed = self._allowed.get((module, name))
        if allowed is not None:
            return allowed
        if module == "chumpy" or module.startswith("chumpy."):
            return _stand_in_class(_ChumpyStandIn, module, name)
        if _SPARSE_MODULE.fullmatch(module) and name in _SPARSE_CLASSES:
            return _stand_in_class(_SparseStandIn, module, name, format=name[:3])
        raise InputError(f"{self._path}: the pickle asks for {_clip(f'{module}.{name}')!r}, which no SMPL model "
                         f"file holds; refusing to load it")

    def persistent_load(self, pid):
        raise InputError(f"{self._path}: the pickle refers to a persistent object, which no SMPL model file holds; "
                         f"refusing to load it")


# ---------------------------------------------------------------------------------------------------
# Field conversion
# ---------------------------------------------------------------------------------------------------
def _plain_value(path: Path, field: str, value, sparse_shape: tuple[int, int] | None = None, depth: int = 0):
    """Turn chumpy and sparse stand-ins into numpy arrays; other values are returned unchanged.

    sparse_shape: the shape a sparse matrix in this field must declare (checked before densifying).
    """
    if isinstance(value, _ChumpyStandIn):
        state = value.state
        if isinstance(state, dict) and "x" in state and depth < 4:
            return _plain_value(path, field, state["x"], sparse_shape, depth + 1)
        raise InputError(f"{path}: field {field!r} is a chumpy expression ({value.source}) rather than a stored "
                         f"array; re-save the model with plain arrays")
    if isinstance(value, _SparseStandIn):
        return _densify_sparse(path, field, value, sparse_shape)
    return value


def _densify_sparse(path: Path, field: str, matrix: _SparseStandIn,
                    expected_shape: tuple[int, int] | None) -> np.ndarray:
    import scipy.sparse

    state = matrix.state
    if not isinstance(state, dict):
        raise InputError(f"{path}: field {field!r} is a sparse matrix without its arrays")
    shape = state.get("_shape", state.get("shape"))
    try:
        rows, cols = (int(s) for s in shape)
    except (TypeError, ValueError):
        raise InputError(f"{path}: field {field!r} is a sparse matrix with an unreadable shape "
                         f"{_clip(repr(shape))}") from None
    # Check the declared shape before allocating the dense matrix (a corrupt file may declare any size).
    if expected_shape is not None and (rows, cols) != tuple(expected_shape):
        raise InputError(f"{path}: field {field!r} must have shape {tuple(expected_shape)}, got ({rows}, {cols})")
    if not (0 < rows <= 1024 and 0 < cols <= 10_000_000):
        raise InputError(f"{path}: field {field!r} is a sparse matrix of implausible shape ({rows}, {cols})")
    try:
        data = np.asarray(state["data"], dtype=np.float64)
        if matrix.format == "coo":
            built = scipy.sparse.coo_matrix((data, (np.asarray(state["row"]), np.asarray(state["col"]))),
                                            shape=(rows, cols))
        else:
            make = scipy.sparse.csc_matrix if matrix.format == "csc" else scipy.sparse.csr_matrix
            built = make((data, np.asarray(state["indices"]), np.asarray(state["indptr"])), shape=(rows, cols))
            built.check_format(full_check=True)
        return built.toarray()
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"{path}: field {field!r} is a corrupt sparse matrix ({_reason(exc)})") from None


def _numeric(path: Path, field: str, value, *, integer: bool = False,
             sparse_shape: tuple[int, int] | None = None) -> np.ndarray:
    """A field as a numeric numpy array (float64, or int64 when integer=True); see _plain_value for sparse_shape."""
    value = _plain_value(path, field, value, sparse_shape)
    try:
        array = np.asarray(value)
    except Exception as exc:
        raise InputError(f"{path}: field {field!r} is not an array ({_reason(exc)})") from None
    if array.dtype.kind not in "biuf":
        raise InputError(f"{path}: field {field!r} must hold numbers, got {array.dtype} values")
    if integer:
        if array.dtype.kind == "f" and not np.all(np.isfinite(array) & (array == np.round(array))):
            raise InputError(f"{path}: field {field!r} must hold integers")
        if array.size and (array.max() > np.iinfo(np.int64).max or array.min() < np.iinfo(np.int64).min):
            raise InputError(f"{path}: field {field!r} holds integers out of range")
        return array.astype(np.int64)
    return array.astype(np.float64)


def _parents_from_kintree(path: Path, kintree: np.ndarray) -> np.ndarray:
    """SMPL's kintree_table (2, J): row 0 the parent id of each joint (root's is ignored), row 1 its id."""
    if kintree.ndim != 2 or kintree.shape[0] != 2:
        raise InputError(f"{path}: field 'kintree_table' must have shape (2, 24), got {kintree.shape}")
    num_joints = kintree.shape[1]
    if num_joints != NUM_JOINTS:
        raise InputError(
            f"{path}: the model has {num_joints} joints (kintree_table) but simgen needs SMPL's 24-joint skeleton "
            f"(SMPL-H has 52 and SMPL-X 55 joints); use a plain SMPL model file")
    column_of_id = {int(joint_id): column for column, joint_id in enumerate(kintree[1])}
    parents = np.full(NUM_JOINTS, -1, dtype=np.int64)
    for j in range(1, NUM_JOINTS):
        parent_id = int(kintree[0, j])
        if parent_id not in column_of_id:
            raise InputError(f"{path}: field 'kintree_table' names parent {parent_id} for joint {j}, which is no joint")
        parents[j] = column_of_id[parent_id]
    return parents


def _gender_from_stem(stem: str) -> str | None:
    """'basicmodel_f_lbs_10_207_0_v1.1.0' -> 'female', 'SMPL_MALE' -> 'male', 'SMPL_NEUTRAL' -> 'neutral'."""
    lower = stem.lower()
    tokens = set(re.split(r"[^a-z0-9]+", lower))
    if "female" in lower or "f" in tokens:
        return "female"
    if "male" in lower or "m" in tokens:
        return "male"
    if "neutral" in lower:
        return "neutral"
    return None


def _check_style(path: Path, fields: dict) -> None:
    """SMPL pkl files name their skinning and pose-blendshape type; simgen implements SMPL's own pair."""
    for key, expected, meaning in (("bs_style", "lbs", "linear blend skinning"),
                                   ("bs_type", "lrotmin", "R - I pose-corrective features")):
        value = fields.get(key)
        if isinstance(value, bytes):
            value = value.decode("latin1")
        if isinstance(value, str) and value != expected:
            raise InputError(f"{path}: field {key!r} is {value!r} but simgen implements {expected!r} ({meaning})")


def _assemble(path: Path, fields: dict, J_regressor_reader, name: str, meta: dict) -> BodyModel:
    """Validate the raw fields of either layout and build the BodyModel; every error names the file and field."""
    kintree = _numeric(path, "kintree_table", fields["kintree_table"], integer=True)
    parents = _parents_from_kintree(path, kintree)
    v_template = _numeric(path, "v_template", fields["v_template"])
    if v_template.ndim != 2 or v_template.shape[1] != 3 or v_template.shape[0] < 4:
        raise InputError(f"{path}: field 'v_template' must have shape (V, 3), got {v_template.shape}")
    V = v_template.shape[0]
    weights = _numeric(path, "weights", fields["weights"])
    if weights.ndim == 2 and weights.shape[0] == V and weights.shape[1] != NUM_JOINTS:
        raise InputError(f"{path}: the model has {weights.shape[1]} joints (weights) but simgen needs SMPL's "
                         f"24-joint skeleton (SMPL-H has 52 and SMPL-X 55 joints); use a plain SMPL model file")
    if weights.shape != (V, NUM_JOINTS):
        raise InputError(f"{path}: field 'weights' must have shape ({V}, 24), got {weights.shape}")
    shapedirs = _numeric(path, "shapedirs", fields["shapedirs"])
    if shapedirs.ndim != 3 or shapedirs.shape[:2] != (V, 3):
        raise InputError(f"{path}: field 'shapedirs' must have shape ({V}, 3, B), got {shapedirs.shape}")
    posedirs = _numeric(path, "posedirs", fields["posedirs"])
    if posedirs.ndim != 3 or posedirs.shape[:2] != (V, 3) or posedirs.shape[2] not in (0, 9 * (NUM_JOINTS - 1)):
        raise InputError(f"{path}: field 'posedirs' must have shape ({V}, 3, 207) or ({V}, 3, 0), "
                         f"got {posedirs.shape}")
    J_regressor = J_regressor_reader(V)
    faces = _numeric(path, "f", fields["f"], integer=True)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] < 1:
        raise InputError(f"{path}: field 'f' must have shape (F, 3), got {faces.shape}")
    if faces.min() < 0 or faces.max() >= V:
        raise InputError(f"{path}: field 'f' indexes vertices outside 0..{V - 1}")
    try:
        return BodyModel(v_template=v_template, shapedirs=shapedirs, posedirs=posedirs, J_regressor=J_regressor,
                         weights=weights, parents=parents, faces=faces, name=name, meta=meta)
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None


def _smpl_meta(path: Path, file_format: str) -> dict:
    meta = {"source": path.name, "format": file_format,
            "licence": "SMPL model licence (the user's own copy of the model file)"}
    gender = _gender_from_stem(path.stem)
    if gender is not None:
        meta["gender"] = gender
    return meta


# ---------------------------------------------------------------------------------------------------
# Formats
# ---------------------------------------------------------------------------------------------------
def _read_npz(path: Path, data: bytes) -> BodyModel:
    try:
        archive = np.load(io.BytesIO(data), allow_pickle=False)
        keys = set(archive.files)
    except Exception as exc:
        raise InputError(f"{path}: not a readable .npz archive ({_reason(exc)})") from None

    with archive:
        simgen_layout = "simgen_name" in keys
        required = _SIMGEN_KEYS if simgen_layout else _SMPL_KEYS
        missing = [k for k in required if k not in keys]
        if missing:
            raise InputError(f"{path}: field {missing[0]!r} is missing (an SMPL-format .npz holds "
                             f"{', '.join(required)})")

        cache: dict[str, np.ndarray] = {}

        def read(key: str) -> np.ndarray:
            if key not in cache:
                try:
                    cache[key] = archive[key]
                except Exception as exc:
                    raise InputError(f"{path}: field {key!r} cannot be read ({_reason(exc)})") from None
            return cache[key]

        fields = {k: read(k) for k in ("v_template", "shapedirs", "posedirs", "weights", "kintree_table", "f")}

        if simgen_layout:
            def regressor(V: int) -> np.ndarray:
                rows = _numeric(path, "J_regressor_rows", read("J_regressor_rows"), integer=True)
                cols = _numeric(path, "J_regressor_cols", read("J_regressor_cols"), integer=True)
                vals = _numeric(path, "J_regressor_vals", read("J_regressor_vals"))
                if not (rows.ndim == cols.ndim == vals.ndim == 1 and rows.shape == cols.shape == vals.shape):
                    raise InputError(f"{path}: fields 'J_regressor_rows/cols/vals' must be 1-d arrays of one length, "
                                     f"got {rows.shape}, {cols.shape}, {vals.shape}")
                if rows.size and (rows.min() < 0 or rows.max() >= NUM_JOINTS or cols.min() < 0 or cols.max() >= V):
                    raise InputError(f"{path}: field 'J_regressor_rows/cols' indexes outside (24, {V})")
                dense = np.zeros((NUM_JOINTS, V))
                dense[rows, cols] = vals
                return dense

            try:
                name = str(read("simgen_name").item())
                meta = json.loads(str(read("simgen_meta").item()))
            except InputError:
                raise
            except Exception as exc:
                raise InputError(f"{path}: field 'simgen_name' or 'simgen_meta' is unreadable "
                                 f"({_reason(exc)})") from None
            if not isinstance(meta, dict):
                raise InputError(f"{path}: field 'simgen_meta' must be a JSON object")
        else:
            def regressor(V: int) -> np.ndarray:
                dense = _numeric(path, "J_regressor", read("J_regressor"))
                if dense.shape != (NUM_JOINTS, V):
                    raise InputError(f"{path}: field 'J_regressor' must have shape (24, {V}), got {dense.shape}")
                return dense

            style = {}
            for key in ("bs_style", "bs_type"):
                try:
                    value = read(key) if key in keys else None
                except InputError:  # e.g. stored as a pickled object; the model does not need it
                    value = None
                if value is not None and value.ndim == 0 and value.dtype.kind in "US":
                    style[key] = value.item()
            _check_style(path, style)
            name, meta = path.stem, _smpl_meta(path, "smpl-npz")
        return _assemble(path, fields, regressor, name, meta)


def _read_pickle(path: Path, data: bytes) -> BodyModel:
    try:
        content = _RestrictedUnpickler(io.BytesIO(data), path).load()
    except InputError:
        raise
    except Exception as exc:  # truncated or garbled: any failure inside the unpickler
        raise InputError(f"{path}: not a readable SMPL model pickle ({_reason(exc)})") from None
    if not isinstance(content, dict):
        raise InputError(f"{path}: the pickle holds a {type(content).__name__}, not the dict of an SMPL model")
    fields = {k.decode("latin1") if isinstance(k, bytes) else k: v for k, v in content.items()}
    missing = [k for k in _SMPL_KEYS if k not in fields]
    if missing:
        raise InputError(f"{path}: field {missing[0]!r} is missing (an SMPL model pickle holds "
                         f"{', '.join(_SMPL_KEYS)})")
    _check_style(path, fields)

    def regressor(V: int) -> np.ndarray:
        dense = _numeric(path, "J_regressor", fields["J_regressor"], sparse_shape=(NUM_JOINTS, V))
        if dense.shape != (NUM_JOINTS, V):
            raise InputError(f"{path}: field 'J_regressor' must have shape (24, {V}), got {dense.shape}")
        return dense

    return _assemble(path, fields, regressor, path.stem, _smpl_meta(path, "smpl-pkl"))


def load_body_file(path: str | Path) -> BodyModel:
    """Read an SMPL-format body model file.

    Accepts SMPL's official .npz (dense ``J_regressor``) and .pkl (chumpy-pickled, read without chumpy
    by a restricted unpickler), and simgen's own .npz written by :meth:`BodyModel.save`. The format
    is recognised from the content (a zip archive is an .npz), not the suffix.
    The model is named after the file stem (simgen's own files keep their saved name and meta);
    meta['gender'] is set from names such as ``*_f_*``, ``*female*``, ``*_m_*``, ``*neutral*``.
    Every problem (missing, unreadable, truncated, wrong layout, a pickle asking for anything but
    numpy/scipy-sparse/chumpy data, a joint count other than SMPL's 24) raises InputError naming the
    file and the field.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file")
    if path.is_dir():
        raise InputError(f"{path}: is a directory, not an SMPL model file")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot be read ({_reason(exc)})") from None
    if not data:
        raise InputError(f"{path}: the file is empty")
    if data.startswith(_ZIP_MAGIC):
        return _read_npz(path, data)
    if path.suffix.lower() == ".npz":
        raise InputError(f"{path}: not a readable .npz archive (no zip header)")
    return _read_pickle(path, data)
