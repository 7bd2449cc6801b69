"""`simgen eval compare` (simgen.learn.comparison) on the CPU at tiny sizes: end to end on the `tiny`
dataset with a briefly trained SNUG (and a no-bending ablation), a briefly trained vertex-L2 GRU and a
supervised fit + wrinkle folder, every table written with its rows and columns; the mean-curvature
error is zero for identical meshes and the mean curvature of a sphere is 1/R; vertex-L2 training
lowers its loss; bad input is one sentence and leaves --out untouched."""

from __future__ import annotations

import csv
import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
import torch

from simgen.cli import main
from simgen.errors import InputError
from simgen.garment import load_garment

GARMENT = "tshirt_1k"
TABLES = ("physics", "curvature", "cost", "errors", "errors_per_clip", "inside_per_clip")


def run(argv, capsys):
    try:
        main(argv)
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """One torch thread: these tiny sizes gain nothing from more on a busy 2-core machine."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    from simgen.dataset import generate_dataset

    out = tmp_path_factory.mktemp("compare_store") / "tiny"
    generate_dataset("tiny", out=str(out))
    return out


@pytest.fixture(scope="module")
def data(store):
    from simgen.learn import load_garment_data

    return load_garment_data(store)


@pytest.fixture(scope="module")
def models(store, data, tmp_path_factory):
    """{name: folder}: SNUG, SNUG without bending, a vertex-L2 GRU (through the CLI) and a supervised
    fit + wrinkle folder, each trained for a moment."""
    from simgen.learn import FitConfig, WrinkleConfig, make_split, train_fit, train_wrinkle
    from simgen.learn.snug import SnugConfig, train_snug

    root = tmp_path_factory.mktemp("compare_models")
    tiny = SnugConfig(hidden=16, layers=2, batch_size=2, window_stride=90, val_windows=0, epochs=1)
    train_snug(GARMENT, root / "snug", motions=["walk"], config=tiny)
    train_snug(GARMENT, root / "snug_no_bending", motions=["walk"], config=replace(tiny, bending=False))
    with pytest.raises(SystemExit) as done:  # through the CLI
        main(["train", "gru-l2", "--dataset", str(store), "--out", str(root / "l2"), "--epochs", "2", "--hidden",
              "16", "--batch-size", "1"])
    assert done.value.code == 0
    split = make_split(data, "motion")
    train_fit(data, root / "supervised", split, config=FitConfig(epochs=20))
    train_wrinkle(data, root / "supervised", split, config=WrinkleConfig(hidden=16, epochs=3, window=2, val_every=0))
    return {k: root / k for k in ("snug", "snug_no_bending", "l2", "supervised")}


def _table(out, name):
    md = (out / f"{name}.md").read_text()
    table = json.loads((out / f"{name}.json").read_text())
    assert table["name"] == name and md.startswith(f"### {table['title']}")
    return table, md


def test_eval_compare_writes_every_table(store, models, tmp_path, capsys):
    out = tmp_path / "compare"
    video = _can_render()
    code, text, err = run(["eval", "compare", "--models", *map(str, models.values()), "--dataset", str(store),
                           "--out", str(out), "--timing-frames", "3", *([] if video else ["--no-video"])], capsys)
    assert code == 0, err
    assert "Physics terms per frame (thesis Table 5.1)" in text and "thesis Table 5.3: SNUG (ch. 5)" in text
    for name in TABLES:
        assert (out / f"{name}.md").is_file() and (out / f"{name}.json").is_file(), name
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".compare.partial")]  # the staging is gone
    labels = ["SNUG", "SNUG w/o bending", "vertex-L2 GRU",
              "supervised ch. 4, fit + wrinkle (supervised, 2 training sequences)", "LBS"]

    physics, _ = _table(out, "physics")
    assert [c["key"] for c in physics["columns"]] == ["method", "strain", "bending", "gravity", "inertia", "collision",
                                                      "potential"]
    rows = {r["method"]: r for r in physics["rows"]}
    assert list(rows)[:6] == ["simulation (ground truth)", *labels]
    assert "thesis Table 5.1: SNUG" in rows and "thesis Table 5.1: PBNS [BME21]" in rows
    assert all(rows[m][t] is not None and np.isfinite(rows[m][t]) for m in list(rows)[:6]
               for t in ("strain", "bending", "gravity", "inertia", "collision"))
    assert rows["simulation (ground truth)"]["gravity"] > 0

    curvature, _ = _table(out, "curvature")
    rows = {r["method"]: r for r in curvature["rows"]}
    assert list(rows)[:2] == ["SNUG w/o bending", "SNUG"]  # the thesis's order: ablations, then the full model
    assert rows["SNUG w/o bending"]["left_out"] == "bending" and rows["SNUG"]["left_out"] == "none"
    assert all(rows[m]["all"] > 0 for m in labels) and "thesis Table 5.2: SNUG full" in rows

    cost, md = _table(out, "cost")
    assert [c["key"] for c in cost["columns"]] == ["method", "data", "train", "runtime", "size"]
    rows = {r["method"]: r for r in cost["rows"]}
    thesis = rows["thesis Table 5.3: TailorNet [PLP20]"]
    assert (thesis["data"], thesis["train"], thesis["runtime"], thesis["size"]) == ("29 h", "6.5 h", 10.1, 2114.0)
    assert rows["thesis Table 5.3: ch. 4 supervised [SOC19]"]["size"] == 109.0
    assert rows["thesis Table 5.3: SNUG (ch. 5)"]["runtime"] == 2.2
    assert rows["SNUG"]["data"] == "0 (no simulated data)" and rows["SNUG"]["train"].endswith(" s")
    assert rows["vertex-L2 GRU"]["data"].endswith(" s")  # the store records its wall times
    assert all(rows[m]["runtime"] > 0 for m in labels)
    # SnugNet's parameters: 2 GRU layers of 16 here (4 of 16 for the GRU from the CLI) and the output layer.
    assert rows["SNUG"]["size"] == pytest.approx(4e-6 * (3 * 16 * (89 + 16 + 2) + 3 * 16 * (16 + 16 + 2)
                                                         + 17 * 3 * load_garment(GARMENT).num_vertices))
    assert rows["vertex-L2 GRU"]["size"] > rows["SNUG"]["size"] and rows["LBS"]["size"] == 0
    assert rows["simulation (the dataset's solver)"]["runtime"] > 0 and "(AMD Ryzen 7 2700" in md

    errors, _ = _table(out, "errors")
    assert [c["key"] for c in errors["columns"]] == ["method", "held_out_motion:error", "held_out_motion:inside"]
    rows = {r["method"]: r for r in errors["rows"]}
    assert rows["simulation (ground truth)"]["held_out_motion:error"] == 0.0
    assert all(0 < rows[m]["held_out_motion:error"] < 20 for m in labels)
    assert all(0 <= rows[m]["held_out_motion:inside"] <= 100 for m in rows)
    per_clip, _ = _table(out, "errors_per_clip")
    assert [r["clip"] for r in per_clip["rows"]] == ["walk_fast__b1p2", "walk_fast__zero"]
    inside, _ = _table(out, "inside_per_clip")
    assert [c["header"] for c in inside["columns"]][2:] == ["simulation", *labels]

    results = json.loads((out / "compare.json").read_text())
    assert results["split"]["groups"] == {"held_out_motion": ["walk_fast__b1p2", "walk_fast__zero"]}
    assert results["timing"]["frames"] == 3 and results["generation"]["seconds"] > 0
    assert (out / "error_per_frame.png").stat().st_size > 10_000
    from simgen.io.usd import read_usd_meshes

    meshes = read_usd_meshes(out / "compare.usdc")
    keys = ["ground_truth", "snug", "snug_no_bending", "gru_l2", "supervised_supervised", "lbs"]
    assert set(meshes) == {f"{k}_{w}" for k in ("body", "garment") for w in keys}
    xs = [meshes[f"garment_{k}"].points[..., 0] for k in keys]
    assert all(a.max() < b.min() for a, b in zip(xs, xs[1:]))  # side by side, in order, no overlap
    assert meshes["garment_snug"].colors is not None and meshes["garment_ground_truth"].colors is None
    if video:
        assert (out / "compare.mp4").stat().st_size > 1000
    # simgen view opens the folder: one garment track per method, side by side.
    from simgen.view.sources import open_source

    source = open_source(out)
    scene = source.load(source.select())
    assert source.kind == "eval compare" and len(scene.tracks) == len(keys)


def _can_render() -> bool:
    import importlib.util

    return importlib.util.find_spec("pyvista") is not None


def test_bad_input_is_one_sentence_and_writes_nothing(store, data, models, tmp_path, capsys):
    from simgen.learn.comparison import compare_models

    out = tmp_path / "out"
    code, _, err = run(["eval", "compare", "--models", str(tmp_path / "missing"), "--dataset", str(store), "--out",
                        str(out)], capsys)
    assert code == 2 and "missing is not a folder" in err and "Traceback" not in err and not out.exists()
    other = tmp_path / "other"
    shutil.copytree(models["snug"], other)
    cfg = json.loads((other / "snug" / "config.json").read_text())
    cfg["garment"] = {"name": "dress_1k", "hash": "0" * 64}
    (other / "snug" / "config.json").write_text(json.dumps(cfg))
    code, _, err = run(["eval", "compare", "--models", str(models["snug"]), str(other), "--dataset", str(store),
                        "--out", str(out)], capsys)
    assert code == 2 and "trained for garment 'dress_1k'" in err and not out.exists()
    code, _, err = run(["eval", "compare", "--models", str(models["snug"]), "--dataset", str(store), "--out",
                        str(out), "--test-shapes", "nope"], capsys)
    assert code == 2 and "'nope' is not in the dataset" in err and not out.exists()
    train_only = replace(data, sequences={k: replace(s, split="train") for k, s in data.sequences.items()})
    with pytest.raises(InputError, match="holds no test motions"):
        compare_models([models["snug"]], train_only, out)
    assert not out.exists() and not list(tmp_path.glob(".out.partial*"))


def test_mean_curvature_of_a_sphere_and_zero_error_for_identical_meshes():
    import trimesh

    from simgen.learn.comparison import curvature_error, mean_curvature

    for radius in (0.1, 0.4):
        s = trimesh.creation.icosphere(subdivisions=4, radius=radius)
        h = mean_curvature(s.vertices, s.faces).numpy()
        assert h.mean() == pytest.approx(1.0 / radius, rel=2e-3)
        assert np.all(np.abs(h * radius - 1.0) < 0.2)  # the 12 valence-5 vertices are the worst
        flipped = mean_curvature(s.vertices, np.ascontiguousarray(s.faces[:, ::-1])).numpy()
        assert np.allclose(flipped, -h)  # signed: inward normals, negative curvature
    x = np.stack([s.vertices, 1.5 * s.vertices])
    assert np.array_equal(curvature_error(x, x, s.faces), [0.0, 0.0])
    err = curvature_error(x[:1], 2.0 * x[:1], s.faces)  # 1/R against 1/(2R)
    assert err[0] == pytest.approx(0.5 / 0.4, rel=2e-3)
    # An open, flat sheet: zero at its interior vertices, the boundary left out.
    u, v = np.meshgrid(np.linspace(0, 1, 6), np.linspace(0, 1, 6))
    pts = np.stack([u.ravel(), v.ravel(), np.zeros(36)], axis=1)
    faces = np.array([[i * 6 + j, i * 6 + j + 1, i * 6 + j + 7] for i in range(5) for j in range(5)]
                     + [[i * 6 + j, i * 6 + j + 7, i * 6 + j + 6] for i in range(5) for j in range(5)])
    bent = pts.copy()
    bent[:, 2] = 0.3 * (pts[:, 0] - 0.5) ** 2
    assert curvature_error(bent[None], pts[None], faces)[0] > 0.1
    assert curvature_error(pts[None], pts[None] + 0.01, faces)[0] < 1e-9


def test_vertex_l2_training_lowers_its_loss_and_validates_on_the_split_s_validation(data, tmp_path):
    """The validation windows come from the split's validation sequences, never from a test group
    (the tiny store has one training motion: its b1p2 sequence stands in for a validation motion)."""
    from dataclasses import replace

    from simgen.learn import make_split
    from simgen.learn.gru_l2 import GRU_L2_METHOD, L2_TERMS, _L2Run, train_gru_l2
    from simgen.learn.snug import SnugConfig, load_snug_model

    split = make_split(data, "motion")
    held = [i for i in split.train_sequences if data.sequences[i].shape_id == "b1p2"]
    split = replace(split, train_sequences=[i for i in split.train_sequences if i not in held], validation=held)
    config = SnugConfig(hidden=16, layers=2, batch_size=1, epochs=12, lr=1e-2, lr_epochs=12, val_windows=2)
    run = _L2Run(data, split, config, torch.device("cpu"), None)
    assert held and set(run.val.names) == set(held) and not set(run.windows.names) & set(held)
    assert run.training_facts()["validation_motions"] == ["jumping_jacks"]
    assert _L2Run(data, make_split(data, "motion"), config, torch.device("cpu"), None).val is None
    result = train_gru_l2(data, tmp_path, split, config=config)
    with open(result.folder / "log.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert result.epochs == 12 and len(rows) == 12 and set(L2_TERMS) <= set(rows[0])
    assert float(rows[-1]["loss"]) < 0.8 * float(rows[0]["loss"]), (rows[0]["loss"], rows[-1]["loss"])
    assert float(rows[-1]["val_loss"]) < float(rows[0]["val_loss"])
    model = load_snug_model(tmp_path, identity=data.identity)
    assert model.net.saved_config["training"]["method"] == GRU_L2_METHOD
    assert (tmp_path / "split.json").is_file()


def test_clips_file_keeps_the_garments_and_renders_elsewhere(data, tmp_path, capsys):
    """--no-video's compare_clips.npz: every garment back within float16's 0.5 mm of the root, the
    body re-posed from the stored motion, and `simgen eval compare-video` renders it."""
    from simgen.learn.comparison.outputs import read_clips, write_clips

    clips = []
    for sid in list(data.sequences)[:2]:
        s = data.sequences[sid]
        clips.append({"id": sid, "fps": s.fps, "betas": s.betas[:3], "poses": s.poses[:3], "trans": s.trans[:3],
                      "ground_truth": s.vertices[:3], "predictions": {"lbs": s.vertices[:3] + 0.01}})
    path = write_clips(tmp_path / "compare_clips.npz", clips, ["lbs"], {"lbs": "LBS"}, data.faces,
                       {"identity": data.identity, "garment": data.garment_name})
    info, back = read_clips(path)
    assert info["order"] == ["lbs"] and [c["id"] for c in back] == [c["id"] for c in clips]
    for a, b in zip(clips, back):
        assert np.abs(b["ground_truth"] - a["ground_truth"]).max() < 5e-4
        assert np.abs(b["predictions"]["lbs"] - a["predictions"]["lbs"]).max() < 5e-4
        np.testing.assert_array_equal(b["poses"], a["poses"])
    with pytest.raises(InputError, match="is not a file"):
        read_clips(tmp_path / "missing.npz")
    (tmp_path / "text.npz").write_text("not an archive")
    with pytest.raises(InputError, match="is not a compare_clips.npz"):
        read_clips(tmp_path / "text.npz")
    if _can_render():
        code, _, err = run(["eval", "compare-video", "--clips", str(path), "--out", str(tmp_path / "c.mp4")], capsys)
        assert code == 0, err
        assert (tmp_path / "c.mp4").stat().st_size > 1000


def test_snug_trained_with_its_own_physics_is_labelled_so(data, models, tmp_path):
    """A SNUG trained with the thesis's own loss parameters (`--physics snug`) sits beside the one
    trained with the store's: its own row, named for its physics."""
    from simgen.learn.comparison.contestants import load_contestants
    from simgen.learn.snug import SnugConfig, train_snug

    tiny = SnugConfig(hidden=16, layers=2, batch_size=2, window_stride=90, val_windows=0, epochs=1, physics="snug")
    train_snug(GARMENT, tmp_path / "snug_own", motions=["walk"], config=tiny)
    rows = load_contestants([models["snug"], tmp_path / "snug_own"], data.identity)
    assert [(c.key, c.label) for c in rows] == [("snug", "SNUG"), ("snug_snug_physics", "SNUG (SNUG's physics)")]
