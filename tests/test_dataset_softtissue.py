"""Soft-tissue stores (simgen.dataset.softtissue): the simulation's results stored as committed nodes,
read back for training, checked, and resumed after SIGKILL (CPU, the bundled flesh mesh, clips of a
tenth of a second)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from simgen.dataset.softtissue import (check_softtissue_store, generate_softtissue, is_softtissue_spec,
                                       list_softtissue_presets, load_softtissue_spec, read_softtissue_store)
from simgen.dataset.storage import Location
from simgen.errors import InputError

SPEC = {"kind": "softtissue", "name": "st-test", "motions": ["jump", "run"], "test_motions": ["run"],
        "clip_start": 1.0, "max_seconds": 0.05,
        "device": "cpu", "shapes": [{"id": "light", "betas": [0.0, -2.0]}, {"id": "heavy", "betas": [0.0, 2.0]}]}
IDS = {f"{m}{r}__{s}" for m in ("jump", "run") for r in ("", "_mirror") for s in ("light", "heavy")}


def _write_spec(path: Path, doc: dict) -> Path:
    lines = []
    for k, v in doc.items():
        if k != "shapes":
            lines.append(f"{k} = {json.dumps(v)}")
    for s in doc["shapes"]:
        lines += ["[[shapes]]", f"id = {json.dumps(s['id'])}", f"betas = {json.dumps(s['betas'])}"]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A run of SPEC killed by SIGKILL after its first simulation was written, then resumed, and a
    clean run of the same spec."""
    root = tmp_path_factory.mktemp("softtissue")
    spec_file = _write_spec(root / "st.toml", SPEC)
    out = root / "killed"
    proc = subprocess.Popen([sys.executable, "-m", "simgen.cli", "dataset", "generate", str(spec_file), "--out",
                             str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            env=dict(os.environ, SIMGEN_DATASET_WRITE_DELAY="0.5"))
    at_kill = None
    deadline = time.time() + 300
    try:
        while time.time() < deadline and proc.poll() is None:
            loc = Location(out)
            committed = [n for n in loc.listdir("sequences") if n != "zarr.json" and loc.committed(f"sequences/{n}")]
            if committed:
                os.kill(proc.pid, signal.SIGKILL)
                at_kill = {"committed": set(committed), "staging": sorted(os.listdir(out / ".staging"))}
                break
            time.sleep(0.02)
    finally:
        if proc.poll() is None and at_kill is None:
            proc.kill()
        proc.wait()
    assert at_kill is not None, f"the run ended before it was killed: {proc.stderr.read().decode()[-2000:]}"
    resumed = generate_softtissue(spec_file, str(out))
    clean = generate_softtissue(SPEC, str(root / "clean"))
    return {"root": root, "out": out, "at_kill": at_kill, "resumed": resumed, "clean": clean, "spec": spec_file}


def test_a_killed_run_resumes_to_the_clean_runs_data(store):
    r, at_kill = store["resumed"], store["at_kill"]
    # The simulation under way at the kill was writing its nodes: at least one committed, maybe one staged.
    assert r.reconcile["staging_removed"] == len(at_kill["staging"])
    # What was committed before the kill (listed in the manifest or adopted from the store) stays.
    assert r.pending == 0 and r.done_before >= len(at_kill["committed"]) and r.done_before + r.written == len(IDS)
    killed = json.loads((store["out"] / "manifest.json").read_text())["sequences"]
    clean = json.loads((store["root"] / "clean" / "manifest.json").read_text())["sequences"]
    assert set(killed) == set(clean) == IDS
    # The resumed store holds what a clean run writes: the same where the batch was the same, and to
    # the solver's tolerance where a shape was simulated without its batch mate (each PCG iterates on
    # until the batch's last instance converges).
    a, b = read_softtissue_store(store["out"]), read_softtissue_store(store["root"] / "clean")
    for sa, sb in zip(a.sequences, b.sequences):
        assert sa.name == sb.name and np.allclose(sa.displacements, sb.displacements, rtol=0, atol=2e-6), sa.name
    assert sum(killed[k]["checksum"] == clean[k]["checksum"] for k in IDS) >= len(IDS) - 2
    again = generate_softtissue(store["spec"], str(store["out"]))
    assert again.written == 0 and again.frames == 0


def test_the_store_holds_what_the_simulation_returns(store):
    from simgen import body as body_pkg
    from simgen.motion.library import load_motion
    from simgen.motion.ops import mirror, trim
    from simgen.softtissue.simulate import simulate_softtissue

    data = read_softtissue_store(store["out"])
    assert {s.name for s in data.sequences} == IDS
    assert {s.subject for s in data.sequences} == {"light", "heavy"} and {s.motion for s in data.sequences} == {"jump",
                                                                                                              "run"}
    body = body_pkg.load("open")
    spec = load_softtissue_spec(SPEC)
    clip = mirror(trim(load_motion("run"), 1.0, 1.05))
    (ref,) = simulate_softtissue(body, clip, np.array([[0.0, 2.0] + [0.0] * (body.num_betas - 2)]), spec.flesh,
                                 device="cpu")
    got = next(s for s in data.sequences if s.name == "run_mirror__heavy")
    assert got.displacements.shape == ref.displacements.shape == (3, body.num_vertices, 3)   # 1.0-1.033 s of the 30 fps clip at 60 fps
    assert np.allclose(got.displacements, ref.displacements, atol=1e-7)
    assert np.allclose(got.poses, ref.poses.reshape(len(ref.poses), -1), atol=1e-6)
    assert got.meta["mirrored"] is True and got.meta["split"] == "test"
    # The flesh sags under gravity from the first frame; the heavy body more than the light one.
    peak = {s.name: np.abs(s.displacements).max() for s in data.sequences}
    assert 0 < peak["run__light"] < peak["run__heavy"] < 0.05


def test_check_passes_and_catches_damage(store, tmp_path):
    import shutil

    import zarr

    rep = check_softtissue_store(store["out"], require_complete=True)
    assert rep["passed"], rep["problems"]
    assert rep["sequences"] == len(IDS) and rep["frames"] == 3 * len(IDS) and 0 < rep["min_det"] <= 1
    bad = tmp_path / "bad"
    shutil.copytree(store["out"], bad)
    z = zarr.open_group(str(bad / "sequences" / "jump__light"), mode="r+")
    d = z["displacements"][...]
    d[2, 10] += 0.3
    z["displacements"][...] = d
    rep = check_softtissue_store(bad)
    assert not rep["passed"] and any("jump__light" in p and "checksum" in p for p in rep["problems"])
    # A limit the data exceeds is reported per sequence.
    rep = check_softtissue_store(store["out"], max_peak=1e-4)
    assert not rep["passed"] and sum("moves" in p for p in rep["problems"]) == len(IDS)


def test_the_cli_checks_and_describes_a_soft_tissue_store(store):
    env = dict(os.environ)
    for cmd in (["check", str(store["out"]), "--require-complete", "--json"], ["info", str(store["out"]), "--json"]):
        p = subprocess.run([sys.executable, "-m", "simgen.cli", "dataset", *cmd], capture_output=True, text=True,
                           env=env, timeout=300)
        assert p.returncode == 0, p.stderr[-2000:]
        doc = json.loads(p.stdout)
        if cmd[0] == "check":
            assert doc["passed"] and doc["sequences"] == len(IDS)
        else:
            assert doc["dataset"]["sequences"] == len(IDS) and {r["id"] for r in doc["sequences"]} == IDS


def test_training_reads_a_store_and_holds_out_its_test_motions(store, tmp_path):
    from contextlib import nullcontext

    from simgen.learn.softtissue._cli import load_softtissue_source, run_train_softtissue

    data, body = load_softtissue_source(str(store["out"]), None, max_frames=2)
    assert body.name == "open" and len(data.sequences) == len(IDS)
    assert all(len(s.poses) == 2 for s in data.sequences)
    train, tests = data.split(test_motions=["run"])
    assert {s.motion for s in train.sequences} == {"jump"}   # a held-out motion holds out its mirror too
    run_train_softtissue(data=str(store["out"]), body=None, out=tmp_path / "m", device="cpu", time_budget=None,
                         restart=False, max_frames=2, test_motions=None, test_subjects=None, pose_epochs=1,
                         ae_epochs=1, reg_epochs=1, ae_latent=4, seed=None, echo=lambda msg: None,
                         progress_factory=lambda label, total: (nullcontext(), lambda *a: None))
    split = json.loads((tmp_path / "m" / "softtissue" / "split.json").read_text())
    assert split["test_motions"] == ["run"]                  # the store's split, not "nothing held out"
    assert set(split["test"]["held_out_motion"]) == {n for n in IDS if n.startswith("run")}


def test_a_store_refuses_another_spec(store):
    other = dict(SPEC, max_seconds=0.1)
    with pytest.raises(InputError, match="different spec"):
        generate_softtissue(other, str(store["out"]))


def test_the_preset_and_spec_errors():
    assert "softtissue" in list_softtissue_presets() and is_softtissue_spec("softtissue")
    spec = load_softtissue_spec("softtissue")
    assert len(spec.shapes) == 5 and len(spec.motions) == 20 and spec.mirror and spec.flesh.fps == 60
    assert spec.split("walk_fast") == "test" and spec.split("run") == "train"
    for change, field in ((dict(colour="red"), "colour"), (dict(shapes=[{"id": "a__b", "betas": []}]), "shapes"),
                          (dict(test_motions=["walk"]), "test_motions"),
                          (dict(mirror="yes"), "mirror"), (dict(max_seconds=0), "max_seconds"),
                          (dict(motions=[]), "motions"), (dict(flesh={"poisson": 0.6}), "poisson")):
        with pytest.raises(InputError, match=field):
            load_softtissue_spec({**SPEC, **change})


def test_a_failed_simulation_is_not_written_and_bad_shapes_write_nothing(tmp_path, monkeypatch):
    import simgen.softtissue.simulate as sim

    real = sim.simulate_softtissue_jobs

    def diverging(*args, **kw):
        out = real(*args, **kw)
        out[0].displacements[1, 5, 0] = np.nan
        return out

    monkeypatch.setattr(sim, "simulate_softtissue_jobs", diverging)
    spec = {**SPEC, "motions": ["jump"], "test_motions": None, "mirror": False}
    spec.pop("test_motions")
    r = generate_softtissue(spec, str(tmp_path / "nan"))
    assert list(r.failed) == ["jump__light"] and r.written == 1 and r.pending == 1
    rep = check_softtissue_store(tmp_path / "nan")
    assert not rep["passed"] and any("jump__light" in p and "failed" in p for p in rep["problems"])
    monkeypatch.setattr(sim, "simulate_softtissue_jobs", real)
    r = generate_softtissue(spec, str(tmp_path / "nan"))         # the rerun simulates it again
    assert r.written == 1 and not r.failed and check_softtissue_store(tmp_path / "nan", require_complete=True)["passed"]
    # A shape the body cannot take is refused before the store exists.
    bad = {**spec, "shapes": [{"id": "ok", "betas": [0.0]}, {"id": "long", "betas": [0.0] * 500}]}
    with pytest.raises(InputError, match="shape 'long'"):
        generate_softtissue(bad, str(tmp_path / "bad"))
    assert not (tmp_path / "bad").exists()
    # A partial store fails --require-complete, naming what is missing.
    generate_softtissue({**spec, "shapes": SPEC["shapes"]}, str(tmp_path / "part"), max_sequences=1)
    rep = check_softtissue_store(tmp_path / "part", require_complete=True)
    assert not rep["passed"] and any("1 planned sequences missing" in p for p in rep["problems"])


def test_the_thesis_script_trains_ablations_and_folds_and_reports(store, tmp_path):
    # scripts/softtissue_thesis.py at a tiny size: budgets of seconds stop every run, which is then
    # closed at the epochs it reached; a second call finds everything finished and only reports.
    root = Path(__file__).resolve().parents[1]
    cmd = [sys.executable, str(root / "scripts" / "softtissue_thesis.py"), "--data", str(store["root"] / "clean"),
           "--work", str(tmp_path / "work"), "--out", str(tmp_path / "out"), "--device", "cpu", "--ae-sizes", "8",
           "--ae-budget", "2", "--reg-budget", "2", "--reg-jobs", "2", "--timing-frames", "2"]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert set(s["regressors"]["runs"]) == {"full", "no_static", "no_dynamic", "neither", "lomo_run"}
    assert all(r["epochs"].get("regressor", 0) >= 1 for r in s["regressors"]["runs"].values())
    lomo = s["eval"]["leave_one_motion_out"]
    assert [r["motion"] for r in lomo] == ["run"] and lomo[0]["sequences"] == 4 and np.isfinite(lomo[0]["error_mm"])
    md = (tmp_path / "out" / "summary.md").read_text()
    assert "| no_dynamic | code | no |" in md and "Leave one motion out" in md
    again = subprocess.run(cmd[:-2] + ["--phases", "ae,reg"], capture_output=True, text=True, timeout=600)
    assert again.returncode == 0 and "started" not in again.stdout
