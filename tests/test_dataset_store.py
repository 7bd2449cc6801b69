"""Dataset generation and the store: kill -9 and resume, write failures, retries of diverged jobs,
the reader API, `simgen dataset check|info|export`, and `--ray local`.

The `tiny` preset (tshirt_1k, 2 shapes x 2 clips x 5 frames, 7 protocol frames) is generated once
for the module by a subprocess that is killed with SIGKILL while it writes a sequence, then resumed.
Other tests use smaller overrides of it (one clip, two frames). About a minute on 2 CPU cores.
"""

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from simgen.dataset import check_dataset, generate_dataset, load_spec, open_dataset
from simgen.dataset.storage import Location, arrays_checksum
from simgen.dataset.store import node_arrays
from simgen.errors import InputError
from simgen.sim import SimulationFailure

TINY_IDS = {f"{m}__{s}" for m in ("jumping_jacks", "walk_fast") for s in ("zero", "b1p2")}


def micro(library=("walk_fast",), solver: dict | None = None, **over):
    """tiny with one clip (``library``: its motions) of one frame and a 4-frame protocol: for tests
    of the driver's logic; ``solver``: sub-tables of [solver] to set."""
    from simgen.dataset import parse_spec
    from simgen.dataset.spec import preset_path

    import tomllib

    doc = tomllib.loads(preset_path("tiny").read_text())
    doc["name"] = "micro"
    doc["protocol"] = {"relax_frames": 0, "ramp_frames": 3, "rest_frames": 1}
    doc["motions"].update(library=list(library), max_frames=1)
    for table, values in (solver or {}).items():
        doc.setdefault("solver", {}).setdefault(table, {}).update(values)
    return parse_spec(doc, source="micro.toml").with_overrides(**over)


def _committed_sequences(out: Path) -> set:
    loc = Location(out)
    return {n for n in loc.listdir("sequences") if n != "zarr.json" and loc.committed(f"sequences/{n}")}


def _half_written_sequence(out: Path) -> str | None:
    """A sequence node in .staging with some arrays but no commit marker yet."""
    staging = out / ".staging"
    if not staging.is_dir():
        return None
    for d in list(staging.iterdir()):
        if not d.name.startswith("sequences-"):
            continue
        try:  # the writer may rename the folder away while we look
            attrs = json.loads((d / "zarr.json").read_text()).get("attributes", {})
            arrays = [c for c in d.iterdir() if (c / "zarr.json").exists()]
        except (ValueError, OSError):
            continue
        if "commit" not in attrs and arrays:
            return d.name
    return None


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """`simgen dataset generate tiny` killed by SIGKILL mid-write of its 2nd sequence, then resumed."""
    out = tmp_path_factory.mktemp("tiny") / "store"
    env = dict(os.environ, SIMGEN_DATASET_WRITE_DELAY="1.5")
    proc = subprocess.Popen([sys.executable, "-m", "simgen.cli", "dataset", "generate", "tiny", "--out", str(out)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    killed_at = None
    deadline = time.time() + 240
    try:
        while time.time() < deadline and proc.poll() is None:
            half = _half_written_sequence(out)
            if half and _committed_sequences(out):
                committed = _committed_sequences(out)
                os.kill(proc.pid, signal.SIGKILL)
                killed_at = {"half": half, "committed": committed,
                             "manifest": json.loads((out / "manifest.json").read_text())}
                break
            time.sleep(0.02)
    finally:
        if proc.poll() is None and killed_at is None:
            proc.kill()
        proc.wait()
    assert killed_at is not None, f"the run ended before it could be killed: {proc.stderr.read().decode()[-2000:]}"
    assert proc.returncode == -signal.SIGKILL
    state = {"out": out, "killed": killed_at}
    # What the killed run left: a half-written node in .staging, nothing half-written under sequences/.
    state["after_kill_committed"] = _committed_sequences(out)
    loc = Location(out)
    state["after_kill_nodes"] = ({"template"} if loc.committed("template") else set()) | \
        {f"fit/{f}" for f in loc.listdir("fit") if f != "zarr.json" and loc.committed(f"fit/{f}")} | \
        {f"sequences/{q}" for q in state["after_kill_committed"]}
    state["after_kill_dirs"] = sorted(n for n in os.listdir(out / "sequences") if n != "zarr.json")
    state["after_kill_staging"] = sorted(os.listdir(out / ".staging"))
    state["checksums_at_kill"] = {n: Location(out).committed(f"sequences/{n}")["checksum"]
                                  for n in state["after_kill_committed"]}
    state["reader_at_kill"] = open_dataset(out).sequence_ids()
    state["resume"] = generate_dataset("tiny", out=str(out))
    return state


def _injected(job):
    return SimulationFailure(job.key, "diverged (injected)", "animate", 1)


def assert_complete_tiny_store(out: Path) -> None:
    """``out`` holds the whole `tiny` plan once: every sequence, nothing staged, no lock, and a
    manifest listing every node with the checksum of its arrays."""
    assert sorted(os.listdir(out / "sequences")) == sorted(TINY_IDS | {"zarr.json"})
    assert not (out / ".staging").exists() or os.listdir(out / ".staging") == []
    assert not (out / ".lock").exists()
    m = json.loads((out / "manifest.json").read_text())
    assert set(m["sequences"]) == TINY_IDS and set(m["fits"]) == {"zero", "b1p2"} and m["template"]
    assert m["failed"] == {}
    for sid, entry in m["sequences"].items():
        assert arrays_checksum(node_arrays(Location(out), f"sequences/{sid}")) == entry["checksum"], sid


def test_kill_leaves_no_half_sequence(tiny):
    k = tiny["killed"]
    half_id = k["half"].split("-", 1)[1].rsplit("-", 1)[0]
    assert half_id in TINY_IDS
    # The half-written node stayed in .staging (with the node another writer thread had begun, if
    # any: none of them committed); under sequences/ every folder is a committed sequence.
    assert k["half"] in tiny["after_kill_staging"]
    staged = {d.split("-", 1)[1].rsplit("-", 1)[0] for d in tiny["after_kill_staging"]}
    assert not staged & tiny["after_kill_committed"]
    assert set(tiny["after_kill_dirs"]) == tiny["after_kill_committed"]
    assert half_id not in tiny["after_kill_committed"]
    # The reader only sees what the manifest lists, which is a subset of the committed nodes.
    assert set(tiny["reader_at_kill"]) <= tiny["after_kill_committed"]


def test_resume_completes_without_loss_or_duplicates(tiny):
    out = tiny["out"]
    (rep,) = tiny["resume"]
    # Committed-but-unlisted sequences were adopted, not simulated again; the staged one was redone.
    assert rep.reconcile["staging_removed"] == len(tiny["after_kill_staging"])
    # (The manifest is rewritten every few seconds, so the template and fits may be among them.)
    m = tiny["killed"]["manifest"]
    listed = ({"template"} if m["template"] else set()) | {f"fit/{f}" for f in m["fits"]} | \
        {f"sequences/{q}" for q in m["sequences"]}
    assert rep.reconcile["adopted"] == len(tiny["after_kill_nodes"] - listed)
    assert rep.written == 4 - len(tiny["after_kill_committed"])
    assert rep.pending == 0 and not rep.failed
    assert_complete_tiny_store(out)
    m = json.loads((out / "manifest.json").read_text())
    # Sequences committed before the kill are untouched.
    for sid, c in tiny["checksums_at_kill"].items():
        assert m["sequences"][sid]["checksum"] == c
    # A second resume has nothing to do.
    (again,) = generate_dataset("tiny", out=str(out))
    assert again.written == 0 and again.cloth_frames == 0 and again.reconcile == {
        "staging_removed": 0, "leftovers_removed": 0, "adopted": 0, "dropped": 0, "corrupt_removed": 0}


def test_reader_api(tiny):
    ds = open_dataset(tiny["out"])
    spec = load_spec("tiny")
    assert ds.garment_name == "tshirt_1k" and ds.body_id.startswith("open-")
    assert ds.material.name == "cotton" and ds.attrs["format_version"] == 1
    assert ds.attrs["spec"]["name"] == "tiny" and ds.attrs["garment"]["hash"]
    assert set(ds.sequence_ids()) == TINY_IDS
    assert ds.sequence_ids("test") == ["walk_fast__b1p2", "walk_fast__zero"]
    assert ds.shape_ids() == ["zero", "b1p2"]
    tpl = ds.template
    V = tpl["vertices"].shape[0]
    assert tpl["vertices"].dtype == np.float32 and tpl["smoothed"].shape == (V, 3)
    assert tpl["faces"].dtype == np.int32 and tpl["skin_weights"].shape == (V, 24)
    np.testing.assert_allclose(tpl["skin_weights"].sum(1), 1.0, atol=1e-5)
    assert tpl["smoothing"]["method"] == "taubin"
    seq = ds.sequence("jumping_jacks__b1p2")
    T = spec.max_frames
    assert seq["garment_vertices"].shape == (T, V, 3) and seq["garment_vertices"].dtype == np.float32
    assert seq["poses"].shape == (T, 24, 3) and seq["trans"].shape == (T, 3) and seq["betas"].shape == (T, 10)
    np.testing.assert_array_equal(seq["betas"][:, 1], 2.0)
    assert seq["rest_garment_vertices"].shape == (spec.rest_frames, V, 3)
    a = seq["attrs"]
    assert (a["motion"], a["split"], a["shape_id"], a["fps"], a["frames"]) == \
        ("jumping_jacks", "train", "b1p2", 30.0, T)
    for key in ("max_penetration", "strain_mean", "strain_max", "solver_retries", "wall_time", "attempts"):
        assert key in a["stats"], key
    assert a["stats"]["wall_time"] > 0 and a["stats"]["attempts"] == 1
    assert set(seq["frame_stats"]) >= {"max_depth", "strain_max", "retries"}
    # Poses are the library clip's frames [start_frame, start_frame + max_frames).
    from simgen.motion import load_motion

    clip = load_motion("jumping_jacks")
    np.testing.assert_allclose(seq["poses"], clip.poses[30:30 + T], atol=1e-6)
    fit = ds.fit("b1p2")
    assert fit["betas"].shape == (10,) and fit["betas"][1] == 2.0
    assert fit["vertices"].shape == (V, 3) and fit["fit_displacement"].shape == (V, 3)
    with pytest.raises(InputError, match="no sequence 'walk__zero'"):
        ds.sequence("walk__zero")
    with pytest.raises(InputError, match="no fit for shape 'b3p1'"):
        ds.fit("b3p1")
    with pytest.raises(InputError, match="split"):
        ds.sequence_ids("validation")


def test_check_in_worker_processes_reports_the_same(tiny, tmp_path, monkeypatch):
    """`check --workers 2` (shares of one sequence here, so that both workers take several) gives
    the report of one process, problems and warnings in the same order, on a store with a
    damaged sequence between sound ones; progress climbs to the total."""
    import shutil

    import simgen.dataset.check as check

    d = tmp_path / "damaged"
    shutil.copytree(tiny["out"], d)
    chunks = sorted((d / "sequences/jumping_jacks__zero/garment_vertices/c").rglob("*"))
    next(c for c in chunks if c.is_file()).unlink()
    serial = check_dataset(d, workers=1)
    monkeypatch.setattr(check, "_SHARE", 1)
    seen = []
    parallel = check_dataset(d, workers=2, progress=lambda n, total: seen.append((n, total)))
    assert not serial.passed and any(p["node"] == "sequences/jumping_jacks__zero" for p in serial.problems)
    assert parallel.to_dict() == serial.to_dict()
    assert seen[-1] == (4, 4) and seen == sorted(seen)
    with pytest.raises(InputError, match="--workers"):
        check_dataset(d, workers=-1)


def test_check_passes_then_finds_damage(tiny, tmp_path, monkeypatch):
    import shutil

    rep = check_dataset(tiny["out"])
    assert rep.passed, rep.format()
    assert rep.sequences == 4 and rep.frames == 20 and rep.frames_checked_body == 20
    assert 0 < rep.max_strain < 1.0
    assert rep.min_body_share > 0.5 and rep.max_support_drop < 0.05 and rep.min_height > 0.5
    # The crossing edges counted on the device while generating (float32 positions widened to
    # float64) equal the check's count from the stored frames.
    ds = open_dataset(tiny["out"])
    for sid in ds.sequence_ids():
        stored = np.asarray(ds.sequence(sid)["frame_stats"]["crossing_edges"])
        listed = rep.crossings.get(sid, {"frames": 0})
        assert int(np.sum(stored > 0)) == listed["frames"], sid
        assert ds.loc.node_attrs(f"sequences/{sid}")["stats"]["crossing_frames"] == listed["frames"]
    # Damage copies of the store, one way each; every one must be found.
    def damaged(name, how, stride=1):
        d = tmp_path / name
        shutil.copytree(tiny["out"], d)
        how(d)
        r = check_dataset(d, stride=stride)
        assert not r.passed, name
        return r

    def nan_frame(d):
        import zarr

        z = zarr.open_array(str(d / "sequences/walk_fast__zero/garment_vertices"), mode="r+")
        x = z[...]
        x[3, 7] = np.nan
        z[...] = x

    r = damaged("nan", nan_frame)
    assert {p["check"] for p in r.problems} == {"checksum"}  # changed after commit: the checksum catches it first

    def drop_chunk(d):
        chunks = sorted((d / "sequences/walk_fast__b1p2/garment_vertices/c").rglob("*"))
        next(p for p in chunks if p.is_file()).unlink()

    r = damaged("chunk", drop_chunk)
    assert any(p["node"] == "sequences/walk_fast__b1p2" for p in r.problems)

    def unlist(d):
        m = json.loads((d / "manifest.json").read_text())
        del m["sequences"]["jumping_jacks__zero"]
        (d / "manifest.json").write_text(json.dumps(m))

    r = damaged("unlisted", unlist)
    assert any(p["check"] == "manifest" and "missing from the manifest" in p["message"] for p in r.problems)

    def remove_node(d):
        shutil.rmtree(d / "sequences/jumping_jacks__b1p2")

    r = damaged("removed", remove_node)
    assert any(p["check"] == "manifest" and p["node"] == "sequences/jumping_jacks__b1p2" for p in r.problems)

    def push_inside(d):
        # Rewrite a sequence (with a valid commit) whose cloth sits 1 cm inside the body: the
        # garment's frames replaced by body vertices pulled 1 cm towards the body's centre line.
        loc = Location(d)
        rel = "sequences/walk_fast__zero"
        arrays = node_arrays(loc, rel)
        attrs = loc.node_attrs(rel)
        attrs.pop("commit")
        ds = open_dataset(d)
        body = ds.load_body()
        posed = body.forward(arrays["betas"], arrays["poses"], arrays["trans"])
        x = arrays["garment_vertices"].copy()
        torso = posed.joints[:, 9]  # spine3
        V = x.shape[1]
        pick = posed.vertices[:, np.linspace(0, body.num_vertices - 1, V).astype(int)]
        direction = torso[:, None] - pick
        direction /= np.linalg.norm(direction, axis=2, keepdims=True)
        arrays["garment_vertices"] = (pick + 0.01 * direction).astype(np.float32)
        shutil.rmtree(d / rel)
        commit = loc.write_node(rel, arrays, attrs)
        m = json.loads((d / "manifest.json").read_text())
        m["sequences"]["walk_fast__zero"]["checksum"] = commit["checksum"]
        (d / "manifest.json").write_text(json.dumps(m))

    r = damaged("inside", push_inside)
    # Body vertices in place of the shirt: inside the body, torn, and not where the shirt rests either.
    assert [p["check"] for p in r.problems if p["node"] == "sequences/walk_fast__zero"] == [
        "inside-body", "off-body", "strain"]
    assert r.max_depth > 5e-3

    def rewrite(d, rel, how):
        loc = Location(d)
        arrays, attrs = node_arrays(loc, rel), loc.node_attrs(rel)
        attrs.pop("commit")
        arrays["garment_vertices"] = how(arrays["garment_vertices"].copy())
        shutil.rmtree(d / rel)
        commit = loc.write_node(rel, arrays, attrs)
        m = json.loads((d / "manifest.json").read_text())
        m["sequences"][rel.split("/")[1]]["checksum"] = commit["checksum"]
        (d / "manifest.json").write_text(json.dumps(m))

    def slide_down(x):
        # From frame 2 on the shirt sits 15 cm lower on the body: it slipped.
        x[2:, :, 1] -= 0.15
        return x

    r = damaged("slipped", lambda d: rewrite(d, "sequences/jumping_jacks__b1p2", slide_down))
    off = [p for p in r.problems if p["check"] == "off-body"]
    assert {p["node"] for p in r.problems} == {"sequences/jumping_jacks__b1p2"} and len(off) == 1
    assert "slipped" in off[0]["message"] and "from frame 2" in off[0]["message"]
    assert 0.12 < r.max_support_drop < 0.18

    def fall(x):
        # From frame 1 on the shirt lies on the floor half a metre beside the body, some of it 5 mm below it.
        x[1:, :, 1] = 0.05 * (x[1:, :, 1] - x[1:, :, 1].min(axis=1, keepdims=True)) - 0.005
        x[1:, :, 0] += 0.5
        return x

    r = damaged("fallen", lambda d: rewrite(d, "sequences/walk_fast__zero", fall))
    messages = [p["message"] for p in r.problems if p["check"] == "off-body"]
    assert len(messages) == 3 and "slipped" in messages[0] and "left the body" in messages[1]
    assert "below the floor" in messages[2] and r.min_height == pytest.approx(-0.005, abs=1e-4)

    def stretch_one_frame(d):
        # One vertex of frame 1 pulled 10 cm out: a tangle on a frame the body stride skips.
        loc = Location(d)
        rel = "sequences/walk_fast__zero"
        arrays, attrs = node_arrays(loc, rel), loc.node_attrs(rel)
        arrays["garment_vertices"] = arrays["garment_vertices"].copy()
        arrays["garment_vertices"][1, 0, 0] += 0.1
        shutil.rmtree(d / rel)
        commit = loc.write_node(rel, arrays, attrs)
        m = json.loads((d / "manifest.json").read_text())
        m["sequences"]["walk_fast__zero"]["checksum"] = commit["checksum"]
        (d / "manifest.json").write_text(json.dumps(m))

    r = damaged("stretched", stretch_one_frame, stride=1000)
    strain = [p for p in r.problems if p["check"] == "strain"]
    assert [p["node"] for p in r.problems] == ["sequences/walk_fast__zero"] and len(strain) == 1
    assert "at frame 1 " in strain[0]["message"] and "1 of 5 frames" in strain[0]["message"]
    # The same stretch where the cloth touches a body self-intersection is counted apart, not failed.
    import simgen.dataset.quality as quality

    real_penetration = quality.body_penetration

    def all_at_self_intersections(points, *args, **kwargs):
        depth, _, distance = real_penetration(points, *args, **kwargs)
        return depth, np.ones(len(depth), dtype=bool), distance

    monkeypatch.setattr(quality, "body_penetration", all_at_self_intersections)
    r = check_dataset(tmp_path / "stretched", stride=1000)
    assert r.passed and r.pinched_strain_frames == 1 and r.max_strain > 1.0 > r.max_strain_regular
    assert [w["check"] for w in r.warnings if w["node"] == "sequences"] == ["strain-pinched"]


def test_write_failure_is_one_error_and_resumable(tmp_path, monkeypatch, capsys):
    """A write that fails half-way through a sequence: one sentence, exit 2, no half node, and the
    same command resumes."""
    from simgen import cli

    out = tmp_path / "store"
    original = Location._write_group

    def failing(self, target, arrays, attrs, chunks, commit):
        if "sequences" in target:
            import zarr

            g = zarr.open_group(self.url(target), mode="w", zarr_format=3)
            g.create_array("garment_vertices", shape=(2, 2), dtype="f4")  # part of the node, then the disk fills
            raise OSError(28, "No space left on device")
        return original(self, target, arrays, attrs, chunks, commit)

    monkeypatch.setattr(Location, "_write_group", failing)
    argv = ["dataset", "generate", "tiny", "--out", str(out), "--motions", "walk_fast", "--shapes", "zero",
            "--max-frames", "2"]
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    assert exc.value.code == 2
    # stderr is not a terminal here: progress comes as "dataset tiny: 10% (...)" lines, then the error.
    err = [line for line in capsys.readouterr().err.strip().splitlines() if not line.startswith("dataset tiny: ")]
    assert len(err) == 1 and "No space left on device" in err[0] and "walk_fast__zero" in err[0] and "rerun" in err[0]
    # Consistent: template and fit committed and listed, no sequence, nothing staged.
    m = json.loads((out / "manifest.json").read_text())
    assert m["template"] and set(m["fits"]) == {"zero"} and m["sequences"] == {}
    assert not (out / "sequences" / "walk_fast__zero").exists() and os.listdir(out / ".staging") == []
    assert check_dataset(out).passed
    monkeypatch.setattr(Location, "_write_group", original)
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    assert exc.value.code in (0, None)
    ds = open_dataset(out)
    assert ds.sequence_ids() == ["walk_fast__zero"] and ds.sequence("walk_fast__zero")["garment_vertices"].shape[0] == 2
    assert check_dataset(out).passed


def _patch_pools(monkeypatch, change) -> list:
    """Pass every job's result through change(job, result) as its pool hands it over; returns the
    pools run, as [pool, ["job id@substeps", ...]] in order of submission (:func:`_runs`)."""
    from simgen.sim.pool import SimulationPool

    pools: list = []
    submit, step = SimulationPool.submit, SimulationPool.step

    def submitted(self, job, tag=None):
        if not pools or pools[-1][0] is not self:
            pools.append((self, []))
        pools[-1][1].append(f"{tag.id}@{self.config.substeps * job.substeps_factor}")
        return submit(self, job, tag)

    monkeypatch.setattr(SimulationPool, "submit", submitted)
    monkeypatch.setattr(SimulationPool, "step", lambda self: [(job, change(job, res)) for job, res in step(self)])
    return pools


def _runs(pools) -> list:
    return [ids for _, ids in pools]


_OUTLIERS = {   # the statistics a shaped slot reads on every frame, and the failure they make
    "depth": ({"max_depth_regular": 2e-3}, "depth outlier: a cloth vertex 2.00 mm inside the body at frame 0"),
    "strain": ({"strain_max": 1.2, "strain_max_regular": 1.2}, "strain outlier: a triangle stretched 120% at frame 0"),
    "pinched": ({"strain_max": 1.5, "strain_max_regular": 0.5}, None),   # at a body self-intersection only
}


@pytest.mark.parametrize("case,retry", [("depth", True), ("depth", False), ("strain", True), ("strain", False),
                                        ("pinched", True)])
def test_an_outlier_stops_its_attempt_at_that_frame_and_is_retried(tmp_path, monkeypatch, case, retry):
    """A sequence whose frames fail the check's rules (a regular vertex 2 mm inside the body, the limit
    being 1 mm; a triangle away from body self-intersections stretched 120%, the limit being 100%:
    the pool's statistics are doctored here for the shaped slots) fails each attempt at its first
    frame, without stepping the rest of its clip, until its last attempt, which is written; with
    execution.retry_depth_outliers / retry_strain_outliers off its first attempt is written as it
    is, and so is a stretch at body self-intersections, which the check counts apart and a smaller
    substep cannot undo."""
    from simgen.sim.frame_stats import FrameStats

    measure = FrameStats.measure
    doctored, message = _OUTLIERS[case]

    def outlying(self, positions, betas, instances=None, host_positions=None):
        rows = measure(self, positions, betas, instances, host_positions)
        for row, b in zip(rows, np.asarray(betas)):
            if row is not None and np.any(b != 0):
                row.update(doctored)
        return rows

    monkeypatch.setattr(FrameStats, "measure", outlying)
    switch = "retry_strain_outliers" if case != "depth" else "retry_depth_outliers"
    spec = micro(max_frames=3, **{switch: retry})
    out = tmp_path / "s"
    (rep,) = generate_dataset(spec, out=str(out))
    assert rep.pending == 0 and not rep.failed and rep.written == 2
    ds = open_dataset(out)
    a = ds.sequence("walk_fast__b1p2")["attrs"]["stats"]
    assert ds.sequence("walk_fast__zero")["attrs"]["stats"]["attempts"] == 1
    protocol, frames = spec.protocol_frames(), ds.sequence_info("walk_fast__b1p2")["frames"]
    seqs = rep.planned_sequences
    planned = (1 + rep.planned_fits + seqs) * protocol + seqs * (frames - 1)   # template and fits: one frame
    if retry and message is not None:
        n = spec.max_attempts
        assert n >= 2 and a["attempts"] == n and a["substeps"] == 2 ** (n - 1) * spec.substeps
        assert [(f["job"], f["attempt"]) for f in rep.failed_attempts] == [("sequence:walk_fast__b1p2", k)
                                                                           for k in range(1, n)]
        assert all(f["message"].startswith(message) for f in rep.failed_attempts)
        assert frames == 3 and rep.cloth_frames == planned + (n - 1) * protocol   # attempts stopped at frame 0
        assert rep.retried == n - 1 and rep.retry_cloth_frames > 0
    else:
        assert a["attempts"] == 1 and rep.retried == 0 and rep.cloth_frames == planned
    if case == "depth":
        assert a["max_penetration"] == pytest.approx(2e-3)


def test_diverged_job_is_retried_with_smaller_steps(tmp_path, monkeypatch):
    """A failing instance is a failure of its job alone; the driver re-runs it in a later pool with
    the substep halved while the others are kept (the last job of its pool: none waits there)."""
    calls = _patch_pools(monkeypatch, lambda j, r: _injected(j) if j.id == "walk_fast__b1p2" and j.attempt == 1
                         else r)
    spec = micro()
    (rep,) = generate_dataset(spec, out=str(tmp_path / "s"))
    assert rep.pending == 0 and not rep.failed and rep.written == 2
    # One pool for every first attempt (template, fits, sequences longest first), then the retry.
    s = spec.substeps
    assert _runs(calls) == [[f"template@{s}", f"zero@{s}", f"b1p2@{s}", f"walk_fast__zero@{s}", f"walk_fast__b1p2@{s}"],
                            [f"walk_fast__b1p2@{2 * s}"]]
    assert rep.retried == 1 and rep.retry_cloth_frames > 0
    ds = open_dataset(tmp_path / "s")
    a = ds.sequence("walk_fast__b1p2")["attrs"]["stats"]
    assert a["attempts"] == 2 and a["substeps"] == 2 * spec.substeps
    assert ds.sequence("walk_fast__zero")["attrs"]["stats"]["attempts"] == 1

    # A failed template relaxation is retried alone first; the fits that waited for it keep their attempt.
    calls = _patch_pools(monkeypatch, lambda j, r: _injected(j) if j.kind == "template" and j.attempt == 1 else r)
    spec1 = spec.with_overrides(shapes=["zero"])
    for overlap in (True, False):
        calls.clear()
        out = tmp_path / f"t-{overlap}"
        (rep,) = generate_dataset(spec1.with_overrides(overlap_writes=overlap), out=str(out))
        assert rep.pending == 0 and not rep.failed
        assert _runs(calls) == [["template@10", "zero@10", "walk_fast__zero@10"], ["template@20"], ["zero@10"]]
        ds = open_dataset(out)
        assert ds.template["stats"]["attempts"] == 2 and ds.fit("zero")["attrs"]["stats"]["substeps"] == 10
        assert ds.manifest["failed"] == {}

    # A job that fails every attempt is recorded as failed: check reports it, the CLI exits 1.
    _patch_pools(monkeypatch, lambda j, r: _injected(j) if j.kind == "sequence" else r)
    spec2 = spec.with_overrides(shapes=["zero"])
    (rep,) = generate_dataset(spec2, out=str(tmp_path / "f"))
    assert list(rep.failed) == ["sequence:walk_fast__zero"] and rep.pending == 1
    r = check_dataset(tmp_path / "f")
    assert not r.passed and [p["check"] for p in r.problems] == ["failed"]


@pytest.mark.parametrize("motions", [1, 2])
def test_a_retry_joins_its_pool_while_the_waiting_work_outlasts_it(tmp_path, monkeypatch, motions):
    """A job that fails while the jobs still waiting for the pool's slots will keep it busy for
    longer than the retry takes (twice its cloth-frames, per slot) runs again in the same pool, in a
    slot at twice the substeps (the pool's next free slot, before the jobs still waiting), and is
    written like a retry run alone: attempts 2, twice the substeps, and the store passes the check.
    With less work waiting (one job as long as the failed one) it runs in a later pool instead."""
    calls = _patch_pools(monkeypatch, lambda j, r: _injected(j) if j.id == "walk_fast__zero" and j.attempt == 1
                         else r)
    library = ["walk_fast", "jumping_jacks"][:motions]
    spec = micro(library=library, batch_size=1, overlap_writes=False)   # one slot: the others wait
    (rep,) = generate_dataset(spec, out=str(tmp_path / "s"))
    assert rep.pending == 0 and not rep.failed and rep.written == 2 * motions
    s = spec.substeps
    first = [f"template@{s}", f"zero@{s}", f"b1p2@{s}", f"walk_fast__zero@{s}"]
    if motions == 2:   # three jobs of 4 cloth-frames wait, the retry takes 8 pool frames
        assert _runs(calls) == [first + [f"walk_fast__zero@{2 * s}", f"walk_fast__b1p2@{s}",
                                         f"jumping_jacks__zero@{s}", f"jumping_jacks__b1p2@{s}"]]
    else:              # one job of 4 waits
        assert _runs(calls) == [first + [f"walk_fast__b1p2@{s}"], [f"walk_fast__zero@{2 * s}"]]
    frames = spec.protocol_frames() + spec.max_frames - 1
    assert rep.retried == 1 and rep.retry_cloth_frames == frames and rep.retry_simulate_wall > 0
    # The first pool's entry: when it began to drain, and its in-pool retries.
    t = rep.tasks[0]
    assert t["ready"] <= t["dry"] <= t["end"]
    # One slot: the feed is found dry as the slot frees, with nothing else in flight.
    assert {k: v for k, v in t["drain"].items() if k != "frame_s"} == {
        "jobs": 0, "frames_left_max": 0, "frames_left_sum": 0, "queued_frames": 0} and t["drain"]["frame_s"] > 0
    assert t["retry_cloth_frames"] == (frames if motions == 2 else 0) and (t["retry_wall"] > 0) == (motions == 2)
    ds = open_dataset(tmp_path / "s")
    a = ds.sequence("walk_fast__zero")["attrs"]["stats"]
    assert a["attempts"] == 2 and a["substeps"] == 2 * s
    assert ds.manifest["failed"] == {} and check_dataset(tmp_path / "s").passed


def test_the_drain_report_counts_the_jobs_taken_as_the_feed_ran_dry(tmp_path, monkeypatch):
    """Two slots, sequences of 4 cloth-frames: the take that empties the feed gets one job for two
    free slots, and that fresh job (all 4 frames left) is the work in flight the pool drains. The
    timeline, here of every frame, counts each slot-frame the pool stepped once."""
    from simgen.dataset import execute

    monkeypatch.setattr(execute, "TIMELINE_EVERY", 1)
    spec = micro(library=["walk_fast", "jumping_jacks"], batch_size=2)
    (rep,) = generate_dataset(spec, out=str(tmp_path / "s"))
    assert rep.written == 4 and spec.protocol_frames() + spec.max_frames - 1 == 4
    (task,) = rep.tasks
    assert task["slots"] == 2 and task["ready"] <= task["dry"] <= task["end"]
    drain = {k: v for k, v in task["drain"].items() if k != "frame_s"}
    assert drain == {"jobs": 1, "frames_left_max": 4, "frames_left_sum": 4, "queued_frames": 0}
    times, busy, walls, steps, retries = zip(*task["timeline"])
    assert sum(busy) == task["cloth_frames"] and set(busy) <= {1, 2} and list(times) == sorted(times)
    assert all(w >= s >= 0 for w, s in zip(walls, steps)) and set(retries) == {0}


class _TwoWorkers:
    """An executor with two workers that runs its pool tasks in this process, the oldest first when
    the driver asks for the next to end, and logs each start (with its jobs) and end; with
    ``share`` the tasks of a round share a :class:`JobFeed`, as on Ray; with ``live`` a task's
    failures for the driver reach it before the task ends, as the Ray executor hands them over
    (next() gives (None, None) first); with ``beside`` that many pools may start beside the busy
    workers (logged as "beside"), as on Ray's GPUs."""

    parallel = 2

    def __init__(self, share: bool = False, live: bool = False, beside: int = 0) -> None:
        self.waiting: list = []
        self.log: list = []
        self.share, self.live, self.beside = share, live, beside
        self.held = None

    def start(self, tasks, budget_s, on_outcome, progress, beside=False):
        from dataclasses import replace

        from simgen.dataset.execute import JobFeed

        if self.share and len(tasks) > 1:
            feed = JobFeed({t.name: t.jobs for t in tasks})
            tasks = [replace(t, feed=feed) for t in tasks]
        handles = []
        for task in tasks:
            handles.append(len(self.log))
            self.log.append(("beside" if beside else "start", handles[-1], [j.id for j in task.jobs]))
            self.waiting.append((handles[-1], task, on_outcome))
        return handles

    def next(self):
        from simgen.dataset.distributed import _for_driver
        from simgen.dataset.execute import run_pool_task

        if self.held is not None:
            (handle, result, rest, on_outcome), self.held = self.held, None
        else:
            handle, task, on_outcome = self.waiting.pop(0)
            outcomes: list = []
            result = run_pool_task(task, on_outcome=outcomes.append)
            early = [o for o in outcomes if self.live and _for_driver(o)]
            rest = [o for o in outcomes if not any(o is e for e in early)]
            if early:
                self.held = handle, result, rest, on_outcome
                for o in early:
                    on_outcome(o)
                return None, None
        for o in rest:
            on_outcome(o)
        self.log.append(("end", handle))
        return handle, result

    def close(self) -> None:
        pass


def test_pools_that_share_a_feed_take_each_others_jobs(tmp_path):
    """Two pool tasks sharing their round's jobs (a JobFeed, as on Ray): the task run first takes
    its own share, then, as its slots free up, the other's job; the other task finds nothing left
    and builds no pool. Every node is written once and the store passes the check."""
    from simgen.dataset import generate

    workers = _TwoWorkers(share=True)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(generate, "_make_executor", lambda ray, spec: workers)
        (rep,) = generate_dataset(micro(batch_size=2), out=str(tmp_path / "s"))
    assert rep.pending == 0 and not rep.failed and rep.written == 2 and rep.retried == 0
    assert workers.log == [("start", 0, ["template", "zero", "b1p2", "walk_fast__b1p2"]),
                           ("start", 1, ["walk_fast__zero"]), ("end", 0), ("end", 1)]
    first, second = rep.tasks
    assert first["slots"] == 2 and second["slots"] == 0 and second["cloth_frames"] == 0
    assert first["cloth_frames"] == rep.cloth_frames == 5 * micro().protocol_frames()
    assert check_dataset(tmp_path / "s").passed


@pytest.mark.parametrize("fails", ["walk_fast__b1p2", "template"])
def test_a_retry_starts_on_the_first_free_worker(tmp_path, monkeypatch, fails):
    """With two workers, a job that fails in the pool that ends first runs again at once on the
    freed worker, while the other pool still steps, not after it; a failed template runs again alone
    and the fits that waited for it start only after it ends."""
    from simgen.dataset import generate

    workers = _TwoWorkers()
    monkeypatch.setattr(generate, "_make_executor", lambda ray, spec: workers)
    _patch_pools(monkeypatch, lambda j, r: _injected(j) if j.id == fails and j.attempt == 1 else r)
    (rep,) = generate_dataset(micro(), out=str(tmp_path / "s"))
    assert rep.pending == 0 and not rep.failed and rep.written == 2 and rep.retried == 1
    # The template and fits with one sequence in the first pool, the other sequence in the second.
    first = ["template", "zero", "b1p2", "walk_fast__b1p2"]
    if fails == "template":
        assert workers.log == [("start", 0, first), ("start", 1, ["walk_fast__zero"]), ("end", 0),
                               ("start", 3, ["template"]), ("end", 1), ("end", 3), ("start", 6, ["zero", "b1p2"]),
                               ("end", 6)]
        assert [t["round"] for t in rep.tasks] == [1, 1, 2, 3]
    else:
        assert workers.log == [("start", 0, first), ("start", 1, ["walk_fast__zero"]), ("end", 0),
                               ("start", 3, ["walk_fast__b1p2"]), ("end", 1), ("end", 3)]
        assert [t["round"] for t in rep.tasks] == [1, 1, 2]
    assert open_dataset(tmp_path / "s").manifest["failed"] == {} and check_dataset(tmp_path / "s").passed


def test_a_failure_reported_before_its_task_ends_starts_its_retry_at_once(tmp_path, monkeypatch):
    """A job that fails in the pool that ends last, reported while that pool still steps (as a Ray
    task reports it to the meter), runs again at once on the worker that is already free, not after
    its pool ends."""
    from simgen.dataset import generate

    workers = _TwoWorkers(live=True)
    monkeypatch.setattr(generate, "_make_executor", lambda ray, spec: workers)
    _patch_pools(monkeypatch, lambda j, r: _injected(j) if j.id == "walk_fast__zero" and j.attempt == 1 else r)
    (rep,) = generate_dataset(micro(), out=str(tmp_path / "s"))
    assert rep.pending == 0 and not rep.failed and rep.written == 2 and rep.retried == 1
    assert workers.log == [("start", 0, ["template", "zero", "b1p2", "walk_fast__b1p2"]),
                           ("start", 1, ["walk_fast__zero"]), ("end", 0), ("start", 3, ["walk_fast__zero"]),
                           ("end", 1), ("end", 3)]
    assert open_dataset(tmp_path / "s").manifest["failed"] == {} and check_dataset(tmp_path / "s").passed


def test_a_retry_starts_beside_busy_workers_where_the_executor_has_room(tmp_path, monkeypatch):
    """Both workers busy when a failure comes in (as on Ray's GPUs, where a pool takes part of its
    GPU): the retry starts at once in a pool beside them, not when the first of them ends; the
    report marks that task and when each was handed to the executor."""
    from simgen.dataset import generate

    workers = _TwoWorkers(live=True, beside=1)
    monkeypatch.setattr(generate, "_make_executor", lambda ray, spec: workers)
    _patch_pools(monkeypatch, lambda j, r: _injected(j) if j.id == "walk_fast__b1p2" and j.attempt == 1 else r)
    (rep,) = generate_dataset(micro(), out=str(tmp_path / "s"))
    assert rep.pending == 0 and not rep.failed and rep.written == 2 and rep.retried == 1
    assert workers.log == [("start", 0, ["template", "zero", "b1p2", "walk_fast__b1p2"]),
                           ("start", 1, ["walk_fast__zero"]), ("beside", 2, ["walk_fast__b1p2"]),
                           ("end", 0), ("end", 1), ("end", 2)]
    assert [(t["round"], t["beside"]) for t in rep.tasks] == [(1, False), (1, False), (2, True)]
    assert all(t["submitted"] <= t["start"] for t in rep.tasks)
    assert rep.tasks[0]["submitted"] == rep.tasks[1]["submitted"] <= rep.tasks[2]["submitted"]
    assert open_dataset(tmp_path / "s").manifest["failed"] == {} and check_dataset(tmp_path / "s").passed


def test_only_retries_of_this_runs_failures_start_beside_a_busy_worker():
    """_Driver._launch with one worker and room for one pool beside it: a job resumed at a later
    attempt (its failure is in the manifest of an earlier run) waits for the free worker; once a
    job has failed in this run, its retry starts beside the busy one."""
    from types import SimpleNamespace

    from simgen.dataset.generate import StoreReport, _Driver

    class OneWorker:
        parallel, beside = 1, 1

        def __init__(self):
            self.started = []

        def start(self, tasks, budget_s, on_outcome, progress, beside=False):
            self.started.append(([j.id for t in tasks for j in t.jobs], beside))
            return [len(self.started) * 10 + i for i in range(len(tasks))]

    workers = OneWorker()
    store = SimpleNamespace(loc=SimpleNamespace(root="/store", is_local=True))
    report = StoreReport(path="/store", garment="g", planned_sequences=3, planned_fits=0, done_before=0)
    driver = _Driver(micro(), store, SimpleNamespace(name="g"), SimpleNamespace(hash="h"), workers, report,
                     None, lambda msg: None, "cpu", 0.0)
    resumed = replace(_job("c", 20), attempt=2)
    queue, running = [_job("a", 30), _job("b", 10), resumed], {}
    rounds, first = driver._launch(queue, running, 0, True, None, 0.0)
    assert workers.started == [(["a", "b"], False)] and queue == [resumed] and not first
    driver.failed_here.add(resumed.key)
    driver._launch(queue, running, rounds, first, None, 0.0)
    assert workers.started[1] == (["c"], True) and queue == []
    assert [b for _, _, b in running.values()] == [False, True]


def test_jobs_a_pool_refused_under_its_deadline_run_in_a_new_pool_while_time_is_left():
    """_Driver._rounds with one worker whose first pool refuses a job under its deadline (as a full
    pool refuses a long retry by its frame time): with budget left the job starts in the next pool;
    with the budget spent, or when the pool also dropped running jobs at its deadline, the run stops
    and leaves it for the next run."""
    from types import SimpleNamespace

    from simgen.dataset.generate import StoreReport, _Driver

    class RefusesOnce:
        parallel, beside = 1, 0

        def __init__(self, abandoned):
            self.started, self.handles, self.abandoned = [], [], abandoned

        def start(self, tasks, budget_s, on_outcome, progress, beside=False):
            self.started.append([j.id for t in tasks for j in t.jobs])
            self.handles += [(len(self.started), t) for t in tasks]
            return [h for h, _ in self.handles[-len(tasks):]]

        def next(self):
            handle, task = self.handles.pop(0)
            time.sleep(0.05)      # the pool's frames
            refused = [j for j in task.jobs if j.id == "b"] if handle == 1 else []
            return handle, {"error": None, "not_done": refused, "abandoned_cloth_frames": self.abandoned,
                            "slots": 2, "cloth_frames": 0, "wall": 0.0, "step_s": 0.0, "write_s": 0.0,
                            "write_wait": 0.0, "retry_cloth_frames": 0, "retry_wall": 0.0, "clock": {},
                            "gpu_memory_high_bytes": None}

    def run(time_budget, abandoned=0):
        workers = RefusesOnce(abandoned)
        store = SimpleNamespace(loc=SimpleNamespace(root="/store", is_local=True), save_manifest=lambda: None,
                                done=lambda kind, node_id: False)
        report = StoreReport(path="/store", garment="g", planned_sequences=2, planned_fits=0, done_before=0)
        driver = _Driver(micro(), store, SimpleNamespace(name="g"), SimpleNamespace(hash="h"), workers, report,
                         None, lambda msg: None, "cpu", 0.0)
        driver._rounds([_job("a", 30), _job("b", 10)], time_budget, time.perf_counter())
        return workers.started, report.stopped

    assert run(600.0) == ([["a", "b"], ["b"]], None)
    started, stopped = run(0.02)
    assert started == [["a", "b"]] and stopped == "time budget of 0.02 s reached"
    assert run(600.0, abandoned=5) == ([["a", "b"]], "time budget of 600 s reached")


def test_ray_executor_hands_failures_over_while_tasks_run_and_counts_them_once():
    """`RayExecutor.next` with a stand-in for Ray: while the task runs, the failures the meter has
    reach the driver at once, in order, and next() returns (None, None) so that their retries can
    start; a failure the meter repeats, one of a task that has ended, and the same failures in the
    task's result are not handed over again, nor anything the task says later about a job it had
    handed to the driver (a run of it that Ray started again)."""
    from types import SimpleNamespace

    from simgen.dataset.distributed import RayExecutor, _Delivered, _for_driver

    def outcome(job, attempt, ok, **extra):
        return {"kind": "sequence", "id": job, "attempt": attempt, "ok": ok, **extra}

    in_pool, handed = outcome("a", 1, False, retry="pool"), outcome("a", 2, False)
    done = outcome("b", 1, True)
    polls = [(5, [("t/1.0", in_pool), ("t/1.0", handed), ("gone/1.0", outcome("c", 1, False))]),
             (9, [("t/1.0", dict(handed))])]
    waits = [[], [], ["ref"]]
    rerun = outcome("a", 1, True)      # the job again, in a run of the task started again
    ray = SimpleNamespace(wait=lambda refs, num_returns, timeout: (waits.pop(0), []),
                          get=lambda x: {"outcomes": [in_pool, done, handed, rerun]} if x == "ref" else x)
    meter = SimpleNamespace(poll=SimpleNamespace(remote=lambda names: polls.pop(0)))
    ex = object.__new__(RayExecutor)
    ex.ray, ex._meter, ex._delivered = ray, meter, _Delivered()
    got, shown = [], []
    ex._pending = {"ref": (SimpleNamespace(name="t/1.0", location="/store"), got.append, shown.append)}
    assert ex.next() == (None, None) and got == [in_pool, handed] and shown == [5]
    assert ex.next() == ("ref", {"outcomes": [in_pool, done, handed, rerun]})
    assert got == [in_pool, handed, done] and shown == [5, 9] and not polls and not waits
    # Another store's task with the same job ids is news.
    other = SimpleNamespace(name="t/1.0", location="/other")
    assert ex._delivered.first(other, handed) and not ex._delivered.first(other, outcome("a", 1, True))
    assert _for_driver(handed) and not _for_driver(done) and not _for_driver(in_pool)
    assert not _for_driver({**handed, "waiting": True})


def test_a_retry_joins_its_pool_only_if_the_waiting_work_covers_it():
    """The in-pool retry rule at its boundary: the retry's pool frames (its cloth-frames times its
    substeps over the pool's) times the slots against the pool frames waiting (queued, and the
    pool's share of the feed). A job of the pool's attempt retries at twice the pool's substeps, a
    job already retried in a pool of attempt 1 at four times."""
    from types import SimpleNamespace

    from simgen.dataset.execute import _PoolRetries, job_cloth_frames

    spec = micro()
    job = _job("a", 30)
    cf = job_cloth_frames(spec, [job])
    for pool_attempt, job_attempt, times in ((1, 1, 2), (2, 2, 2), (1, 2, 4)):
        for slots in (1, 3):
            for waiting, ok in ((cf * times * slots, True), (cf * times * slots - 1, False)):
                pool = SimpleNamespace(queued_frames=waiting // 2, num_slots=slots, frames_left=lambda: [])
                retries = _PoolRetries(spec, pool_attempt, pool, None, lambda protocol, w=waiting: w - w // 2)
                assert retries._ends_in_time(replace(job, attempt=job_attempt)) is ok, (pool_attempt, slots, waiting)


def test_a_retry_also_counts_the_work_in_flight_and_the_drain():
    """The pool's life left (execute.pool_frames_left): with nothing in flight the waiting work per
    slot; with nothing waiting its longest job; a full pool whose jobs have L..1 frames left and
    work waiting ends that work per slot plus about L later; a retry joins while its pool frames fit
    in that life, which the waiting work alone (the old rule) would refuse."""
    from types import SimpleNamespace

    from simgen.dataset.execute import _PoolRetries, job_cloth_frames, pool_frames_left

    assert pool_frames_left(12, [], 3) == 4 and pool_frames_left(0, [], 3) == 0
    full = list(range(1, 101))                 # 100 slots, 1..100 frames left: mean 50.5
    assert pool_frames_left(0, full, 100) == 100
    assert pool_frames_left(1000, full, 100) == pytest.approx(10 + 50.5 + 50.5)
    assert pool_frames_left(8, [40, 2], 4) == 40     # never before the longest job in flight ends
    spec = micro()
    job = _job("a", 30)
    need = 2 * job_cloth_frames(spec, [job])         # attempt 2 at twice the pool's substeps
    # Nothing waiting, one job in flight with k frames left: the pool lives k more frames.
    for left, ok in (([need, 3], True), ([need - 1, 3], False)):
        pool = SimpleNamespace(queued_frames=0, num_slots=4, frames_left=lambda left=left: [("j", n) for n in left])
        retries = _PoolRetries(spec, 1, pool, None, lambda protocol: 0)
        assert retries._ends_in_time(job) is ok, left


def test_job_feed_never_steals_the_template_or_fits():
    """A task that steals takes sequences only: the template and fits stay with the task that runs
    them before its sequences (the fits need the template written)."""
    from simgen.dataset.execute import JobFeed

    template = replace(_job("template", 1), kind="template")
    fit = replace(_job("zero", 1), kind="fit")
    feed = JobFeed({"a": [template, fit, _job("s1", 40)], "b": [_job("s2", 10)]})
    for name in "ab":
        feed.start(name)
    assert [j.id for j, _ in feed.take("b", 3)] == ["s2", "s1"]
    assert [j.id for j, _ in feed.take("a", 3)] == ["template", "zero"]


def _job(name: str, frames: int):
    from simgen.dataset.execute import Job, rest_clip
    from simgen.motion.clip import MotionClip

    c = rest_clip(30.0)
    clip = MotionClip(name, 30.0, np.zeros((frames, 24, 3)), np.zeros((frames, 3)), dict(c.meta))
    return Job("sequence", name, clip, np.zeros(10))


def test_job_feed_hands_out_own_jobs_then_steals_the_longest_left():
    """A task takes its own share first, in order; then the longest job left of any task; a task
    that starts again gets back what its earlier run took and what it handed back, marked to be
    looked up in the store; rest() hands back a share's untaken jobs."""
    from simgen.dataset.execute import JobFeed

    feed = JobFeed({"a": [_job("a1", 50), _job("a2", 10)],
                    "b": [_job("b1", 40), _job("b2", 30), _job("b3", 5)], "c": [_job("c1", 60)]})
    for name in "abc":
        feed.start(name)
    # What one pool can still expect: (195 frames + 6 jobs x (3 - 1) protocol frames) / 3 tasks.
    assert feed.share_left(3) == pytest.approx(69.0)
    ids = lambda taken: [j.id + "*" * marked for j, marked in taken]   # noqa: E731
    assert ids(feed.take("a", 1)) == ["a1"] and feed.left() == 5 and feed.share_left(1) == pytest.approx(145 / 3)
    assert ids(feed.take("a", 2)) == ["a2", "c1"]       # c1 (60) is the longest left
    assert ids(feed.take("a", 1)) == ["b1"]             # then b's, longest first
    assert ids(feed.take("a", 1)) == ["b2"]
    feed.start("a")              # a's run died: what it took comes back first, marked (maybe committed)
    assert ids(feed.take("b", 1)) == ["b3"]
    assert ids(feed.take("a", 10)) == ["a1*", "a2*", "c1*", "b1*", "b2*"] and feed.left() == 0
    assert feed.take("b", 3) == [] and feed.rest("b") == []
    # What a task hands back with rest() comes back to a run of it that starts again.
    feed = JobFeed({"a": [_job("a1", 5), _job("a2", 5)]}, marked=True)
    feed.start("a")
    assert ids(feed.take("a", 1)) == ["a1*"] and [j.id for j in feed.rest("a")] == ["a2"]
    feed.start("a")
    assert ids(feed.take("a", 5)) == ["a1*", "a2*"]


def test_a_task_whose_nodes_are_all_committed_reports_like_any(tmp_path):
    """A pool task run again after its jobs were all committed (a Ray task retried after its worker
    died past its last commit) simulates nothing and returns every field a task returns."""
    from simgen import body as body_pkg
    from simgen.dataset.execute import BatchTask, run_pool_task
    from simgen.dataset.generate import plan_jobs

    spec = micro(shapes=["zero"])
    out = tmp_path / "s"
    (rep,) = generate_dataset(spec, out=str(out))
    assert rep.written == 1
    jobs = plan_jobs(spec, spec.garments[0], body_pkg.load(spec.body))
    again = run_pool_task(BatchTask(location=str(out), spec=spec, garment=spec.garments[0], jobs=jobs))
    # Every field the driver reads from a task (generate._Driver._rounds and _task_entry).
    read = {"outcomes", "error", "not_done", "abandoned_cloth_frames", "slots", "wall", "cloth_frames", "step_s",
            "write_s", "write_wait", "retry_cloth_frames", "retry_wall", "clock", "gpu_memory_high_bytes"}
    assert read <= set(again) and again["cloth_frames"] == 0 and again["retry_cloth_frames"] == 0
    assert [o["reused"] for o in again["outcomes"]] == [True] * len(jobs)


def test_spec_mismatch_and_lock(tiny, tmp_path):
    spec = load_spec("tiny").with_overrides(substeps=5)
    with pytest.raises(InputError, match=r"different spec \(field 'substeps': 10 there, 5 now\)"):
        generate_dataset(spec, out=str(tiny["out"]))
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "file.txt").write_text("x")
    with pytest.raises(InputError, match="is not a simgen dataset store"):
        generate_dataset("tiny", out=str(tmp_path / "junk"))
    # A live writer's lock is respected (this process's parent stands in for one).
    store = tmp_path / "locked"
    generate_dataset(micro(shapes=["zero"]), out=str(store), max_sequences=0)
    import socket

    (store / ".lock").write_text(json.dumps({"pid": os.getppid(), "host": socket.gethostname(), "time": 0}))
    with pytest.raises(InputError, match=f"pid {os.getppid()}"):
        generate_dataset(micro(shapes=["zero"]), out=str(store))


def test_a_store_made_under_another_default_is_not_resumed(tmp_path):
    """The content key holds only what the spec sets; a store whose solver settings or material
    resolved otherwise (a default changed since: the guard's energy test, a measured material) is
    refused by name instead of being finished with other physics. An unbounded friction load (null
    in the store's attributes) resumes, and so does a store that lacks a setting added since."""
    import zarr

    store = tmp_path / "s"
    spec = micro(shapes=["zero"], solver={"friction": {"max_normal_load": float("inf")}})
    generate_dataset(spec, out=str(store), max_sequences=0)
    generate_dataset(spec, out=str(store), max_sequences=0)     # same physics: resumes
    root = zarr.open_group(str(store), mode="r+")
    solver, material = dict(root.attrs["solver"]), dict(root.attrs["material"])
    config = solver["config"]
    flipped = not config["guard_energy"]
    changes = [({**config, "guard_energy": flipped}, material,
                f"solver setting 'guard_energy' = {flipped} there, {not flipped} now"),
               ({**config, "friction": {**config["friction"], "smoothing_velocity": 0.01}}, material,
                "solver setting 'friction.smoothing_velocity'"),
               (config, {**material, "area_density": 2.0 * material["area_density"]}, "material field 'area_density'")]
    for changed_config, changed_material, message in changes:
        root.attrs.update({"solver": {**solver, "config": changed_config}, "material": changed_material})
        with pytest.raises(InputError, match=message):
            generate_dataset(spec, out=str(store), max_sequences=0)
    older = {k: v for k, v in config.items() if k != "guard_energy"}
    root.attrs.update({"solver": {**solver, "config": older}, "material": {**material, "source": "another citation"}})
    generate_dataset(spec, out=str(store), max_sequences=0)


def test_info_and_export(tiny, tmp_path):
    from typer.testing import CliRunner

    from simgen.cli import app

    runner = CliRunner()
    r = runner.invoke(app, ["dataset", "info", str(tiny["out"]), "--json"])
    assert r.exit_code == 0, r.output
    info = json.loads(r.stdout)
    assert info["dataset"]["sequences"] == 4 and info["dataset"]["frames"] == 20
    assert {row["id"] for row in info["sequences"]} == TINY_IDS
    r = runner.invoke(app, ["dataset", "info", str(tiny["out"])])
    assert r.exit_code == 0 and "walk_fast" in r.stdout
    r = runner.invoke(app, ["dataset", "check", str(tiny["out"]), "--json"])
    assert r.exit_code == 0 and json.loads(r.stdout)["passed"]
    r = runner.invoke(app, ["dataset", "check", str(tmp_path / "nothing")])
    assert r.exit_code != 0

    from simgen.dataset import export_sequence
    from simgen.io.usd import read_usd_meshes, validate_usd

    ds = open_dataset(tiny["out"])
    paths = export_sequence(ds, "walk_fast__b1p2", tmp_path / "exp", usd=True, mp4=True, size=(160, 120))
    assert validate_usd(paths["usd"]) == []
    meshes = read_usd_meshes(paths["usd"])
    seq = ds.sequence("walk_fast__b1p2")
    np.testing.assert_allclose(meshes["tshirt_1k"].points, seq["garment_vertices"], atol=1e-6)
    # The body is re-posed from the stored poses/trans/betas: it matches the numpy forward pass.
    body = ds.load_body()
    ref = body.forward(seq["betas"], seq["poses"], seq["trans"]).vertices
    np.testing.assert_allclose(meshes["body"].points, ref, atol=1e-4)
    assert paths["mp4"].stat().st_size > 1000


def _ray_run_with(hook: str, spec, tiny, tmp_path):
    """`--ray local` on the walk_fast sequences of `tiny` with the testing hook ``hook`` (an
    environment variable naming a marker file) set; asserts that the hook fired and that the store
    is complete, passes the check and equals the locally generated one. Returns the report and the
    progress calls, as (seconds since the call, done, total)."""
    pytest.importorskip("ray")
    out, marker = tmp_path / "ray", tmp_path / "hook-marker"
    os.environ[hook] = str(marker)
    t0 = time.time()
    rep_progress = []
    try:
        (rep,) = generate_dataset(spec, out=str(out), ray="local",
                                  progress=lambda done, total: rep_progress.append((time.time() - t0, done, total)))
    finally:
        del os.environ[hook]
    assert marker.exists()  # the injected failure did happen
    assert rep.pending == 0 and not rep.failed
    assert check_dataset(out).passed
    local, remote = open_dataset(tiny["out"]), open_dataset(out)
    assert remote.sequence_ids() == ["walk_fast__b1p2", "walk_fast__zero"]
    for sid in remote.sequence_ids():
        np.testing.assert_allclose(remote.sequence(sid)["garment_vertices"], local.sequence(sid)["garment_vertices"],
                                   atol=1e-5)
    np.testing.assert_allclose(remote.template["smoothed"], local.template["smoothed"], atol=1e-5)
    return rep, rep_progress


def test_ray_local_matches_local(tiny, tmp_path, monkeypatch):
    """`--ray local`: one pool per Ray task on this machine's CPUs (the template and fits in one, the
    sequences dealt out), a task that fails once is retried, and the store equals the locally
    generated one. The tasks report their progress every 0.25 s here (a few seconds of stepping)."""
    import simgen.dataset.distributed as distributed

    monkeypatch.setattr(distributed, "PROGRESS_EVERY_S", 0.25)
    spec = load_spec("tiny").with_overrides(motions=["walk_fast"], batch_size=1)
    rep, progress = _ray_run_with("SIMGEN_DATASET_FAULT_ONCE", spec, tiny, tmp_path)
    assert rep.written == 2
    # Progress comes while the pools step (the tasks report to the driver's meter), not only as
    # tasks end; it never goes back and ends at the total.
    first_end = min(t["end"] for t in rep.tasks)
    assert any(0 < done and at < first_end for at, done, _ in progress), (progress, first_end)
    seen = [done for _, done, _ in progress]
    assert seen == sorted(seen) and seen[-1] == progress[-1][2] == rep.cloth_frames


def test_ray_worker_killed_mid_task_is_replaced(tiny, tmp_path):
    """A Ray worker killed by SIGKILL right after its task committed a node (no exception, no
    cleanup): Ray runs the task again on a fresh worker, which keeps the committed node and
    simulates the rest; the store is complete, passes the check and equals the local one."""
    _ray_run_with("SIMGEN_DATASET_KILL_ONCE", load_spec("tiny").with_overrides(motions=["walk_fast"], batch_size=2),
                  tiny, tmp_path)


def test_ray_failure_reported_while_its_task_runs_is_retried_once(tiny, tmp_path, monkeypatch):
    """`--ray` on a Ray instance that counts one GPU (the pools run on the CPU), with the template's
    first attempt diverging: the worker reports the failure to the driver as it happens and the
    task's result repeats it; the driver counts it once and runs the template again at twice the
    substeps beside the busy pool (Ray places it in the share of the GPU that the pool leaves),
    while that pool still steps; the store is complete, passes the check and holds the same
    sequences as the local one (every job relaxes from the garment, not from the template node)."""
    ray = pytest.importorskip("ray")
    import simgen.dataset.distributed as distributed
    from simgen.dataset import generate

    out, marker = tmp_path / "ray", tmp_path / "diverge-marker"
    spec = load_spec("tiny").with_overrides(motions=["walk_fast"], batch_size=1)   # a long first task
    monkeypatch.setattr(distributed, "PROGRESS_EVERY_S", 0.25)
    monkeypatch.setenv("SIMGEN_DATASET_DIVERGE_ONCE", str(marker))
    src = os.path.dirname(os.path.dirname(os.path.abspath(generate.__file__)))
    ray.init(num_cpus=2, num_gpus=1, include_dashboard=False, log_to_driver=False, configure_logging=False,
             runtime_env={"env_vars": {"PYTHONPATH": src, "SIMGEN_DATASET_DIVERGE_ONCE": str(marker)}})
    try:
        def on_cpu(address, spec):
            executor = distributed.RayExecutor(address, spec)
            assert (executor.parallel, executor.beside) == (1, 1)
            executor.device = "cpu"
            return executor

        monkeypatch.setattr(generate, "_make_executor", on_cpu)
        (rep,) = generate_dataset(spec, out=str(out), ray="local")
    finally:
        ray.shutdown()
    assert marker.exists()
    assert rep.pending == 0 and not rep.failed and rep.retried == 1 and rep.written == 2
    first, retry = (next(t for t in rep.tasks if t["round"] == r) for r in (1, 2))
    assert not first["beside"] and retry["beside"] and retry["start"] < first["end"], rep.tasks
    assert first["worker"]["gpus"] == retry["worker"]["gpus"] == ["0"]
    assert rep.executor_ready is not None and rep.executor_ready <= first["submitted"] <= first["start"]
    ds = open_dataset(out)
    assert ds.manifest["failed"] == {} and Location(out).node_attrs("template")["stats"]["attempts"] == 2
    assert check_dataset(out).passed
    local = open_dataset(tiny["out"])
    for sid in ["walk_fast__b1p2", "walk_fast__zero"]:
        np.testing.assert_allclose(ds.sequence(sid)["garment_vertices"], local.sequence(sid)["garment_vertices"],
                                   atol=1e-5)


def test_object_store_commit_markers():
    """fsspec URLs (no rename): nodes are written in place and committed last; a node without its
    marker is a leftover that the next run deletes, a committed node missing from the manifest is
    verified and adopted."""
    import zarr

    url = "memory://simgen-test-objstore/store"
    spec = micro(shapes=["zero"])
    (rep,) = generate_dataset(spec, out=url)
    assert rep.written == 1 and check_dataset(url).passed
    loc = Location(url)
    # A writer that died mid-node: arrays, no commit marker.
    g = zarr.open_group(loc.url("sequences/walk_fast__ghost"), mode="w", zarr_format=3)
    g.create_array("garment_vertices", shape=(2, 3), dtype="f4")
    # A writer killed between the commit and the manifest rewrite.
    m = json.loads(loc.read_bytes("manifest.json"))
    m["sequences"].pop("walk_fast__zero")
    loc.write_bytes("manifest.json", json.dumps(m).encode())
    r = check_dataset(url)
    assert [p["check"] for p in r.problems] == ["manifest"]
    assert any(w["check"] == "leftover" for w in r.warnings)
    (rep,) = generate_dataset(spec, out=url)
    assert rep.reconcile["leftovers_removed"] == 1 and rep.reconcile["adopted"] == 1 and rep.written == 0
    assert not loc.exists("sequences/walk_fast__ghost")
    assert open_dataset(url).sequence_ids() == ["walk_fast__zero"] and check_dataset(url).passed
    loc.remove("")


def test_one_pool_keeps_its_slots_full(tmp_path, monkeypatch):
    """The generator runs the plan in one simulation pool of execution.batch_size slots: five jobs in
    two slots, each job starting as a slot frees up, every cloth-frame counted once, progress up to
    the total; the store passes the check."""
    from simgen.dataset.execute import job_cloth_frames
    from simgen.sim.pool import SimulationPool

    busy = []
    step = SimulationPool.step

    def counted(self):
        out = step(self)
        busy.append((self.num_slots, self.busy + len(out)))
        return out

    monkeypatch.setattr(SimulationPool, "step", counted)
    seen = []
    spec = micro(batch_size=2)
    (rep,) = generate_dataset(spec, out=str(tmp_path / "b"), progress=lambda d, t: seen.append((d, t)))
    assert rep.written == 2 and not rep.failed and rep.retried == 0
    plan = 1 + 2 + 2  # template, two fits, two one-frame sequences, all of the same length here
    frames = spec.protocol_frames()
    assert rep.cloth_frames == plan * frames == sum(b for _, b in busy)
    # 5 jobs of equal length in 2 slots: 3 waves, the last with one slot idle.
    assert [b for _, b in busy] == [2] * frames + [2] * frames + [1] * frames and {n for n, _ in busy} == {2}
    assert seen[-1][0] == seen[-1][1] == rep.cloth_frames
    assert check_dataset(tmp_path / "b").passed


def _run_stopped_at_retry(monkeypatch, fails, spec, out):
    """Run ``spec`` into ``out`` with the jobs ``fails(job)`` failing their first attempt and the run
    crashing as their retry starts (the manifest keeps the failures); then clear the patches and
    return a fresh pool log (:func:`_patch_pools`) for the rerun."""
    from simgen.sim.pool import SimulationPool

    _patch_pools(monkeypatch, lambda j, r: _injected(j) if fails(j) and j.attempt == 1 else r)
    submit = SimulationPool.submit

    def crash_on_retry(self, job, tag=None):
        if tag.attempt > 1:
            raise RuntimeError("the machine went away")
        return submit(self, job, tag)

    monkeypatch.setattr(SimulationPool, "submit", crash_on_retry)
    with pytest.raises(RuntimeError, match="went away"):
        generate_dataset(spec, out=str(out))
    monkeypatch.undo()
    return _patch_pools(monkeypatch, lambda j, r: r)


def test_a_rerun_resumes_a_retry_at_its_attempt(tmp_path, monkeypatch):
    """A run that stops after a job failed (here it crashes as its retry starts) leaves the failure
    in the manifest; the next run simulates the job at the next attempt, not from the first."""
    spec = micro()
    calls = _run_stopped_at_retry(monkeypatch, lambda j: j.id == "walk_fast__b1p2", spec, tmp_path / "s")
    m = json.loads((tmp_path / "s" / "manifest.json").read_text())
    assert m["failed"]["sequence:walk_fast__b1p2"]["attempts"] == 1 and set(m["sequences"]) == {"walk_fast__zero"}
    (rep,) = generate_dataset(spec, out=str(tmp_path / "s"))
    assert rep.pending == 0 and not rep.failed and rep.written == 1
    assert _runs(calls) == [[f"walk_fast__b1p2@{2 * spec.substeps}"]]
    assert open_dataset(tmp_path / "s").sequence("walk_fast__b1p2")["attrs"]["stats"]["attempts"] == 2


def test_a_resumed_template_retry_runs_before_the_fits_that_need_it(tmp_path, monkeypatch):
    spec = micro().with_overrides(shapes=["zero"])
    calls = _run_stopped_at_retry(monkeypatch, lambda j: j.kind == "template", spec, tmp_path / "s")
    (rep,) = generate_dataset(spec, out=str(tmp_path / "s"))
    assert rep.pending == 0 and not rep.failed
    # The template at its next attempt alone, then the fit that needs it (not first, to wait and run again).
    assert _runs(calls)[:2] == [[f"template@{2 * spec.substeps}"], [f"zero@{spec.substeps}"]]
