"""Reading SMPL-format model files: simgen's own .npz, SMPL's official .npz and chumpy .pkl, bad input.

Real SMPL files are licensed and not available here, so the tests build files with the same
layout: an .npz with SMPL's keys, and .pkl files pickled the way SMPL's were (protocol 2, Python 2
str objects and module names, chumpy ``Ch`` objects whose state dict holds 'x', a scipy
csc_matrix joint regressor), with chumpy faked only while pickling.
"""

from __future__ import annotations

import os
import pickle
import struct
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import simgen.body
from simgen.body import SMPL_PARENTS, BodyModel, load, load_body_file
from simgen.errors import InputError


def small_model(vertices_per_joint: int = 3, num_betas: int = 10, seed: int = 0, joints: int = 24) -> dict:
    """Arrays of a small SMPL-like model in SMPL's file layout (float64; 'f' uint32; kintree (2, J))."""
    rng = np.random.default_rng(seed)
    owner = np.repeat(np.arange(joints), vertices_per_joint)
    V = owner.size
    J_regressor = np.zeros((joints, V))
    J_regressor[owner, np.arange(V)] = rng.uniform(0.2, 1.0, V)
    J_regressor /= J_regressor.sum(axis=1, keepdims=True)
    weights = np.zeros((V, joints))
    weights[np.arange(V), owner] = 1.0
    parents = SMPL_PARENTS if joints == 24 else np.concatenate([SMPL_PARENTS, np.arange(joints - 24) + 20])
    kintree = np.stack([parents, np.arange(joints)]).astype(np.int64)
    kintree[0, 0] = 4294967295  # what SMPL's files store as the root's parent (uint32 -1)
    faces = np.array([[g * vertices_per_joint + i for i in range(3)] for g in range(joints)], dtype=np.uint32)
    return {
        "v_template": rng.normal(size=(V, 3)),
        "shapedirs": rng.normal(scale=0.01, size=(V, 3, num_betas)),
        "posedirs": rng.normal(scale=0.001, size=(V, 3, 9 * (joints - 1))),
        "J_regressor": J_regressor,
        "weights": weights,
        "kintree_table": kintree,
        "f": faces,
    }


def assert_model_equals_arrays(model: BodyModel, arrays: dict) -> None:
    for key in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights"):
        np.testing.assert_array_equal(getattr(model, key), arrays[key], err_msg=key)
    np.testing.assert_array_equal(model.faces, arrays["f"])
    np.testing.assert_array_equal(model.parents, SMPL_PARENTS)


# ---------------------------------------------------------------------------------------------------
# SMPL-style pickles
# ---------------------------------------------------------------------------------------------------
class FakeChumpy:
    """Context manager that installs throwaway 'chumpy' / 'chumpy.ch' modules with a Ch class pickling
    like chumpy's (object state = its __dict__ minus the weak dictionaries, 'x' holding the array)."""

    def __enter__(self):
        chumpy, ch = types.ModuleType("chumpy"), types.ModuleType("chumpy.ch")

        class Ch:
            def __init__(self, x):
                self.x = np.asarray(x, dtype=np.float64)
                self._dirty_vars = set()
                self._itr = None
                self._parents = {}
                self._cache = {"r": None}
                self._depends_on_deps = {}
                self._make_dense = False
                self._make_sparse = False

            def __getstate__(self):
                state = dict(self.__dict__)
                del state["_parents"], state["_cache"]
                return state

        Ch.__module__, Ch.__qualname__ = "chumpy.ch", "Ch"
        ch.Ch = chumpy.Ch = Ch
        chumpy.ch = ch
        sys.modules["chumpy"], sys.modules["chumpy.ch"] = chumpy, ch
        return Ch

    def __exit__(self, *exc):
        sys.modules.pop("chumpy", None)
        sys.modules.pop("chumpy.ch", None)


class Py2StylePickler(pickle._Pickler):
    """Writes protocol 2 the way Python 2's pickle wrote SMPL's files: str/bytes as BINSTRING (Python 2
    str), and the module names of that era (numpy.core, scipy.sparse.csc, __builtin__, copy_reg)."""

    RENAMES = {"numpy._core.multiarray": "numpy.core.multiarray", "scipy.sparse._csc": "scipy.sparse.csc",
               "builtins": "__builtin__", "copyreg": "copy_reg"}
    dispatch = pickle._Pickler.dispatch.copy()

    def _save_py2_str(self, data: bytes, original) -> None:
        if len(data) < 256:
            self.write(pickle.SHORT_BINSTRING + bytes([len(data)]) + data)
        else:
            self.write(pickle.BINSTRING + struct.pack("<i", len(data)) + data)
        self.memoize(original)

    def save_bytes(self, obj):
        self._save_py2_str(obj, obj)

    def save_str(self, obj):
        try:
            self._save_py2_str(obj.encode("ascii"), obj)
        except UnicodeEncodeError:
            pickle._Pickler.save_str(self, obj)

    dispatch[bytes] = save_bytes
    dispatch[str] = save_str

    def save_global(self, obj, name=None):
        name = name or obj.__qualname__
        module = pickle.whichmodule(obj, name)
        module = self.RENAMES.get(module, module)
        self.write(pickle.GLOBAL + module.encode() + b"\n" + name.encode() + b"\n")
        self.memoize(obj)


def smpl_pickle_bytes(arrays: dict, style: str = "py2", protocol: int = 2) -> bytes:
    """An SMPL 1.x-layout pickle: v_template/shapedirs/posedirs as chumpy Ch, J_regressor csc, extras."""
    with FakeChumpy() as Ch:
        content = {
            "v_template": Ch(arrays["v_template"]),
            "shapedirs": Ch(arrays["shapedirs"]),
            "posedirs": Ch(arrays["posedirs"]),
            "J_regressor": scipy.sparse.csc_matrix(arrays["J_regressor"]),
            "J_regressor_prior": scipy.sparse.csc_matrix(arrays["J_regressor"]),
            "weights": arrays["weights"],
            "weights_prior": arrays["weights"],
            "kintree_table": arrays["kintree_table"],
            "f": arrays["f"],
            "J": arrays["J_regressor"] @ arrays["v_template"],
            "bs_style": "lbs",
            "bs_type": "lrotmin",
            "vert_sym_idxs": np.arange(arrays["v_template"].shape[0]),
            "pose_training_info": {"nPoses": 1786, "nSubjects": 40},
        }
        if style == "py2":
            import io

            buffer = io.BytesIO()
            Py2StylePickler(buffer, protocol=2).dump(content)
            return buffer.getvalue()
        return pickle.dumps(content, protocol=protocol)


@pytest.mark.parametrize("style,protocol", [("py2", 2), ("py3", 1), ("py3", 2), ("py3", 4), ("py3", 5)])
def test_chumpy_pickle_loads_without_chumpy(tmp_path, style, protocol):
    arrays = small_model()
    path = tmp_path / "basicmodel_f_lbs_10_207_0_v1.1.0.pkl"
    data = smpl_pickle_bytes(arrays, style, protocol)
    if style == "py2":
        assert b"chumpy.ch\nCh" in data and b"scipy.sparse.csc\ncsc_matrix" in data and b"numpy.core.multiarray" in data
    path.write_bytes(data)
    assert "chumpy" not in sys.modules
    model = load_body_file(path)
    assert "chumpy" not in sys.modules
    assert_model_equals_arrays(model, arrays)
    assert model.name == "basicmodel_f_lbs_10_207_0_v1.1.0"
    assert model.meta["gender"] == "female" and model.meta["format"] == "smpl-pkl"


def test_smpl_pickle_goes_through_simgen_body_load(tmp_path):
    arrays = small_model(seed=3)
    path = tmp_path / "basicModel_m_lbs_10_207_0_v1.0.0.pkl"
    path.write_bytes(smpl_pickle_bytes(arrays))
    model = load(str(path))
    assert_model_equals_arrays(model, arrays)
    assert model.meta["gender"] == "male"


class _RunsCode:
    def __init__(self, func, arg):
        self.func, self.arg = func, arg

    def __reduce__(self):
        return self.func, (self.arg,)


@pytest.mark.parametrize("attack", ["os.system", "builtins.eval", "text-protocol"])
def test_pickle_that_runs_code_is_refused_and_nothing_runs(tmp_path, attack):
    marker = tmp_path / "pwned"
    command = f"touch {marker}"
    path = tmp_path / "SMPL_NEUTRAL.pkl"
    arrays = small_model()
    if attack == "os.system":
        payload = pickle.dumps({**arrays, "bs_style": _RunsCode(os.system, command)}, protocol=2)
    elif attack == "builtins.eval":
        payload = pickle.dumps({"v_template": _RunsCode(eval, f"__import__('os').system({command!r})")}, protocol=2)
    else:  # protocol 0, as hand-written exploits are
        payload = b"cos\nsystem\n(S'" + command.encode() + b"'\ntR."
    path.write_bytes(payload)
    with pytest.raises(InputError, match="refusing to load it") as info:
        load_body_file(path)
    assert str(path) in str(info.value)
    expected = {"os.system": "system'", "builtins.eval": "eval'", "text-protocol": "'os.system'"}[attack]
    assert expected in str(info.value)
    assert not marker.exists()


def test_allowed_reconstructor_cannot_build_other_classes(tmp_path):
    path = tmp_path / "model.pkl"
    path.write_bytes(b"ccopy_reg\n_reconstructor\n(c__builtin__\nset\nc__builtin__\nobject\nNtR.")
    with pytest.raises(InputError, match="_reconstructor"):
        load_body_file(path)


# ---------------------------------------------------------------------------------------------------
# .npz layouts
# ---------------------------------------------------------------------------------------------------
def test_simgen_npz_round_trip_is_exact_to_float32(tmp_path):
    arrays = small_model(seed=1)
    source = BodyModel(arrays["v_template"], arrays["shapedirs"], arrays["posedirs"], arrays["J_regressor"],
                       arrays["weights"], SMPL_PARENTS, arrays["f"], name="tester", meta={"source": "unit test"})
    loaded = load_body_file(source.save(tmp_path / "tester.npz"))
    for key in ("v_template", "shapedirs", "posedirs", "weights"):
        np.testing.assert_array_equal(getattr(loaded, key), getattr(source, key).astype(np.float32), err_msg=key)
    np.testing.assert_array_equal(loaded.J_regressor, source.J_regressor)  # stored as float64 values
    np.testing.assert_array_equal(loaded.parents, source.parents)
    np.testing.assert_array_equal(loaded.faces, source.faces)
    assert loaded.name == "tester" and loaded.meta == {"source": "unit test"}


def test_official_layout_npz(tmp_path):
    arrays = small_model(seed=2)
    path = tmp_path / "SMPL_FEMALE.npz"
    np.savez(path, **arrays, J=arrays["J_regressor"] @ arrays["v_template"], bs_style=np.array("lbs"))
    model = load_body_file(path)
    assert_model_equals_arrays(model, arrays)
    assert model.name == "SMPL_FEMALE" and model.meta["gender"] == "female" and model.meta["format"] == "smpl-npz"


# ---------------------------------------------------------------------------------------------------
# Bad files
# ---------------------------------------------------------------------------------------------------
def _write_npz(path: Path, arrays: dict) -> Path:
    np.savez(path, **arrays)
    return path


@pytest.mark.parametrize("case,expected", [
    ("missing key npz", "'weights' is missing"),
    ("missing key pkl", "'posedirs' is missing"),
    ("wrong shape", "'shapedirs' must have shape"),
    ("52 joints", "52 joints"),
    ("55 joints pkl", "55 joints"),
    ("nonexistent", "no such file"),
    ("directory", "is a directory"),
    ("empty", "is empty"),
    ("text as pkl", "not a readable SMPL model pickle"),
    ("text as npz", "not a readable .npz"),
    ("not a dict", "not the dict"),
    ("nan", "NaN"),
    ("faces out of range", "'f' indexes"),
    ("dual-quaternion skinning", "'bs_style' is 'dqbs'"),
])
def test_bad_files_raise_one_clear_input_error(tmp_path, case, expected):
    arrays = small_model()
    path = tmp_path / "model.npz"
    if case == "missing key npz":
        _write_npz(path, {k: v for k, v in arrays.items() if k != "weights"})
    elif case == "missing key pkl":
        path = tmp_path / "model.pkl"
        path.write_bytes(pickle.dumps({k: v for k, v in arrays.items() if k != "posedirs"}, protocol=2))
    elif case == "wrong shape":
        _write_npz(path, {**arrays, "shapedirs": arrays["shapedirs"][:, :2]})
    elif case == "52 joints":
        _write_npz(path, small_model(joints=52))
    elif case == "55 joints pkl":
        path = tmp_path / "SMPLX_NEUTRAL.pkl"
        path.write_bytes(smpl_pickle_bytes(small_model(joints=55)))
    elif case == "nonexistent":
        path = tmp_path / "absent.pkl"
    elif case == "directory":
        path = tmp_path / "folder.pkl"
        path.mkdir()
    elif case == "empty":
        path.write_bytes(b"")
    elif case == "text as pkl":
        path = tmp_path / "model.pkl"
        path.write_text("this is not a model\n")
    elif case == "text as npz":
        path.write_text("this is not a model\n")
    elif case == "not a dict":
        path = tmp_path / "model.pkl"
        path.write_bytes(pickle.dumps([1, 2, 3], protocol=2))
    elif case == "nan":
        bad = arrays["weights"].copy()
        bad[0, 0] = np.nan
        _write_npz(path, {**arrays, "weights": bad})
    elif case == "faces out of range":
        _write_npz(path, {**arrays, "f": arrays["f"] + 1000})
    elif case == "dual-quaternion skinning":
        _write_npz(path, {**arrays, "bs_style": np.array("dqbs")})
    with pytest.raises(InputError, match=expected) as info:
        load_body_file(path)
    assert str(path) in str(info.value)
    assert "\n" not in str(info.value)


# ---------------------------------------------------------------------------------------------------
# The public loader
# ---------------------------------------------------------------------------------------------------
def test_load_open_is_cached_read_only_and_explains_a_missing_bake(tmp_path, monkeypatch):
    monkeypatch.setattr(simgen.body, "_open_cache", None)
    monkeypatch.setattr(simgen.body, "OPEN_BODY_PATH", tmp_path / "open.npz")
    with pytest.raises(InputError, match="simgen body bake"):
        load("open")
    arrays = small_model(seed=4)
    BodyModel(arrays["v_template"], arrays["shapedirs"], arrays["posedirs"], arrays["J_regressor"],
              arrays["weights"], SMPL_PARENTS, arrays["f"], name="open").save(tmp_path / "open.npz")
    first = load()
    assert load("open") is first and first.name == "open"
    with pytest.raises(ValueError):
        first.v_template[0, 0] = 1.0


def test_import_simgen_body_loads_neither_warp_nor_torch():
    code = ("import sys, simgen.body as b; assert 'warp' not in sys.modules and 'torch' not in sys.modules; "
            "b.WarpBody; assert 'warp' in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


# ---------------------------------------------------------------------------------------------------
# Fuzz: truncated and garbled files load or raise InputError, nothing else
# ---------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def valid_files(tmp_path_factory) -> dict:
    folder = tmp_path_factory.mktemp("fuzz")
    arrays = small_model(vertices_per_joint=3, num_betas=4)
    model = BodyModel(arrays["v_template"], arrays["shapedirs"], arrays["posedirs"], arrays["J_regressor"],
                      arrays["weights"], SMPL_PARENTS, arrays["f"])
    official = _write_npz(folder / "official.npz", arrays)
    return {"folder": folder, "simgen.npz": model.save(folder / "simgen.npz").read_bytes(),
            "official.npz": official.read_bytes(), "smpl.pkl": smpl_pickle_bytes(arrays)}


def _loads_or_input_error(path: Path) -> None:
    try:
        model = load_body_file(path)
    except InputError as exc:
        assert str(path) in str(exc)
        return
    assert isinstance(model, BodyModel)


_FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@pytest.mark.parametrize("kind", ["simgen.npz", "official.npz", "smpl.pkl"])
@_FUZZ
@given(data=st.data())
def test_fuzz_truncated_files(valid_files, kind, data):
    original = valid_files[kind]
    cut = data.draw(st.integers(0, len(original) - 1))
    path = valid_files["folder"] / f"truncated.{kind.split('.')[-1]}"
    path.write_bytes(original[:cut])
    _loads_or_input_error(path)


@pytest.mark.parametrize("kind", ["simgen.npz", "official.npz", "smpl.pkl"])
@_FUZZ
@given(data=st.data())
def test_fuzz_garbled_files(valid_files, kind, data):
    garbled = bytearray(valid_files[kind])
    edits = data.draw(st.lists(st.tuples(st.integers(0, len(garbled) - 1), st.integers(0, 255)), min_size=1,
                               max_size=8))
    for position, value in edits:
        garbled[position] = value
    path = valid_files["folder"] / f"garbled.{kind.split('.')[-1]}"
    path.write_bytes(bytes(garbled))
    _loads_or_input_error(path)
