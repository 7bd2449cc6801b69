"""The three examples in examples/, run in-process at tiny sizes on the CPU and chained: the store
that generate_dataset.py writes is what train_and_evaluate.py trains on. Each test checks that the
outputs are real: a USD stage with time-sampled meshes, a store that passes the dataset check, and
metrics with finite values. About a minute on a 2-core CPU, the dataset being most of it."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def _tshirt_1k_vertices() -> int:
    from simgen.garment import load_garment

    return load_garment("tshirt_1k").num_vertices


def load_example(name: str):
    spec = importlib.util.spec_from_file_location(f"simgen_example_{name}", EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def printed_path(out: str, label: str) -> Path:
    """The path the example printed as 'label: PATH'."""
    lines = [ln for ln in out.splitlines() if ln.startswith(f"{label}: ")]
    assert lines, f"no '{label}:' line in the output:\n{out}"
    return Path(lines[-1][len(label) + 2:])


def numbers(tree, where=""):
    """(path, value) of every number in a JSON tree."""
    if isinstance(tree, dict):
        for k, v in tree.items():
            yield from numbers(v, f"{where}/{k}")
    elif isinstance(tree, list):
        for i, v in enumerate(tree):
            yield from numbers(v, f"{where}/{i}")
    elif isinstance(tree, (int, float)) and not isinstance(tree, bool):
        yield where, tree


@pytest.mark.parametrize("name", ["simulate_garment", "generate_dataset", "train_and_evaluate"])
def test_example_is_documented_and_has_options(name, capsys):
    module = load_example(name)
    assert "Full size" in module.__doc__
    with pytest.raises(SystemExit) as exc:
        module.main(["--help"])
    assert exc.value.code == 0
    assert "--device" in capsys.readouterr().out


def test_simulate_garment_writes_an_animated_usd(tmp_path, capsys):
    from pxr import Usd, UsdGeom

    frames = 2
    code = load_example("simulate_garment").main([
        "--garment", "tshirt_1k", "--motion", "walk", "--frames", str(frames), "--substeps", "2",
        "--relax-frames", "1", "--ramp-frames", "2", "--rest-frames", "1", "--device", "cpu",
        "--out", str(tmp_path / "sim")])
    out = capsys.readouterr().out
    assert code == 0, out
    usd, npz = printed_path(out, "usd"), printed_path(out, "npz")
    assert usd == tmp_path / "sim" / "tshirt_1k_walk.usdc" and npz.is_file()
    stage = Usd.Stage.Open(str(usd))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    meshes = {p.GetName(): UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)}
    assert set(meshes) == {"body", "tshirt_1k"}
    for name, mesh in meshes.items():
        attr = mesh.GetPointsAttr()
        assert attr.GetNumTimeSamples() == frames, name
        times = attr.GetTimeSamples()
        first, last = attr.Get(times[0]), attr.Get(times[-1])
        assert len(first) == len(last) > 500 and all(math.isfinite(c) for p in last for c in p), name
    assert len(meshes["tshirt_1k"].GetPointsAttr().Get(0)) == _tshirt_1k_vertices()


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """examples/generate_dataset.py on the tiny preset (2 shapes x 2 clips) cut to 3 frames per clip."""
    out = tmp_path_factory.mktemp("example_dataset") / "tiny"
    code = load_example("generate_dataset").main(["--spec", "tiny", "--max-frames", "3", "--device", "cpu",
                                                  "--out", str(out)])
    return code, out


def test_generate_dataset_writes_a_store_that_passes_the_check(store, capsys):
    from simgen.dataset import check_dataset, open_dataset

    code, out = store
    assert code == 0
    ds = open_dataset(out)
    assert len(ds.sequence_ids("train")) == 2 and len(ds.sequence_ids("test")) == 2
    assert ds.shape_ids() == ["zero", "b1p2"]
    assert ds.sequence(ds.sequence_ids()[0])["garment_vertices"].shape == (3, _tshirt_1k_vertices(), 3)
    report = check_dataset(out, stride=3)
    assert report.passed, report.format()


def test_train_and_evaluate_writes_finite_metrics(store, tmp_path, capsys):
    code, dataset = store
    assert code == 0
    capsys.readouterr()
    code = load_example("train_and_evaluate").main([
        "--dataset", str(dataset), "--out", str(tmp_path / "model"), "--device", "cpu", "--fit-epochs", "30",
        "--epochs", "3", "--hidden", "16", "--window", "2", "--batch-size", "4", "--timing-frames", "2",
        "--inside-stride", "3", "--physics-sequences", "1", "--no-plots"])
    out = capsys.readouterr().out
    assert code == 0, out
    path = printed_path(out, "metrics")
    assert path == tmp_path / "model" / "eval" / "metrics.json"
    metrics = json.loads(path.read_text())
    for sub in ("fit", "wrinkle", "lr_pose", "lr_shape_pose"):
        assert (tmp_path / "model" / sub / "model.pt").is_file(), sub
    assert set(metrics["groups"]) == {"held_out_motion", "train"}
    held = metrics["groups"]["held_out_motion"]
    assert held["sequences"] == 2 and held["frames"] == 6
    assert all(0.0 < v < 50.0 for v in held["error_cm"].values()), held["error_cm"]
    assert metrics["physics"] and metrics["timing"]["cpu"]["with_postprocess"]["mean_ms"] > 0
    values = list(numbers(metrics))
    assert len(values) > 100
    bad = [(k, v) for k, v in values if not math.isfinite(v)]
    assert not bad, bad[:5]
