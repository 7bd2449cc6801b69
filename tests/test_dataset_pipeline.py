"""The writes behind the pool (`execution.overlap_writes`): each job that ends is written in a
background thread while the simulation pool steps on in the main thread. Outcomes come back in
the order the jobs ended, the store equals the one made with the overlap off, and a failure of
either side leaves a consistent, resumable store and no writer thread behind. `micro` specs in
one-slot pools (template, fits and sequences one after another); a few seconds per run on 2 CPU cores.
"""

import json
import os
import threading
import time

import numpy as np
import pytest

import simgen.dataset.execute as ex
from simgen.dataset import check_dataset, generate_dataset, open_dataset
from simgen.dataset.storage import Location, StoreWriteError
from simgen.dataset.store import node_arrays
from simgen.sim.pool import SimulationPool

from test_dataset_store import micro  # tests/ is on sys.path under pytest

JOBS = ["template", "zero", "b1p2", "walk_fast__zero", "walk_fast__b1p2"]
TIMINGS = {"stats/wall_time", "stats/step_time"}  # host clock readings: differ between any two runs


def _writer_threads() -> list:
    return [t for t in threading.enumerate() if t.name.startswith("simgen-write")]


def _instrument(monkeypatch, write_delay: float = 0.0) -> list:
    """Log (event, job id, on the main thread, time) of each job's end in the pool and of its write;
    each write sleeps write_delay first (a slow disk)."""
    events = []
    lock = threading.Lock()

    def log(what, job_id):
        with lock:
            events.append((what, job_id, threading.current_thread() is threading.main_thread(), time.perf_counter()))

    real_step, real_write = SimulationPool.step, ex.NodeWriter.write

    def step(self):
        out = real_step(self)
        for job, _ in out:
            log("ended", job.id)
        return out

    def write(self, job, res):
        log("write-start", job.id)
        time.sleep(write_delay)
        out = real_write(self, job, res)
        log("write-end", job.id)
        return out

    monkeypatch.setattr(SimulationPool, "step", step)
    monkeypatch.setattr(ex.NodeWriter, "write", write)
    return events


def _ids(events, what) -> list:
    return [i for w, i, *_ in events if w == what]


def test_overlap_in_order_and_same_store_as_sequential(tmp_path, monkeypatch):
    events = _instrument(monkeypatch, write_delay=0.3)
    spec = micro(batch_size=1)
    stores = {}
    for overlap in (True, False):
        events.clear()
        out = tmp_path / f"overlap-{overlap}"
        (rep,) = generate_dataset(spec.with_overrides(overlap_writes=overlap), out=str(out))
        assert rep.written == 2 and rep.pending == 0 and not rep.failed
        assert check_dataset(out).passed
        assert not _writer_threads()
        assert _ids(events, "ended") == JOBS and _ids(events, "write-end") == JOBS  # in the order they ended
        assert all(main for w, _, main, _ in events if w == "ended")
        at = {(w, i): t for w, i, _, t in events}
        if overlap:
            assert not any(main for w, _, main, _ in events if w.startswith("write"))
            for k in range(len(JOBS) - 1):  # job k+1 simulates while job k is written
                assert at[("write-start", JOBS[k])] < at[("ended", JOBS[k + 1])]
            for k in range(2):   # the template and the fits one write at a time (a fit needs the template)
                assert at[("write-end", JOBS[k])] <= at[("write-start", JOBS[k + 1])]
            # (sequences are written by SEQUENCE_WRITE_THREADS threads: theirs may overlap)
            # The phases' sums exceed the wall clock by the hidden write time.
            assert rep.write_wait < rep.write_wall
        else:
            assert all(main for w, _, main, _ in events if w.startswith("write"))
            for k in range(len(JOBS) - 1):
                assert at[("write-end", JOBS[k])] < at[("ended", JOBS[k + 1])]
            assert rep.write_wait == pytest.approx(rep.write_wall)
        stores[overlap] = Location(out)
    # Bit-identical nodes (the simulation is deterministic on the CPU) but for the host timings.
    on, off = stores[True], stores[False]
    for rel in ("template", "fit/zero", "fit/b1p2"):
        a, b = node_arrays(on, rel), node_arrays(off, rel)
        for name in sorted(a):
            np.testing.assert_array_equal(a[name], b[name], err_msg=f"{rel}/{name}")
    for sid in ("walk_fast__zero", "walk_fast__b1p2"):
        a, b = node_arrays(on, f"sequences/{sid}"), node_arrays(off, f"sequences/{sid}")
        assert set(a) == set(b)
        for name in sorted(set(a) - TIMINGS):
            np.testing.assert_array_equal(a[name], b[name], err_msg=f"{sid}/{name}")


def test_background_write_failure_is_store_write_error_and_resumable(tmp_path, monkeypatch):
    """A sequence's write fails in the writer thread while the next job simulates: StoreWriteError, the
    jobs before it are in the manifest, the next is never written, nothing is staged, no thread is left."""
    events = _instrument(monkeypatch)
    out = tmp_path / "store"
    spec = micro(batch_size=1)
    original = Location._write_group
    threads = []

    def failing(self, target, arrays, attrs, chunks, commit):
        if "walk_fast__zero" in target:
            import zarr

            threads.append(threading.current_thread().name)
            g = zarr.open_group(self.url(target), mode="w", zarr_format=3)
            g.create_array("garment_vertices", shape=(2, 2), dtype="f4")  # part of the node, then the disk fills
            raise OSError(28, "No space left on device")
        return original(self, target, arrays, attrs, chunks, commit)

    monkeypatch.setattr(Location, "_write_group", failing)
    with pytest.raises(StoreWriteError, match="No space left on device"):
        generate_dataset(spec, out=str(out))
    assert threads and threads[0].startswith("simgen-write")
    assert not _writer_threads()
    assert _ids(events, "write-end") == JOBS[:3]
    assert "walk_fast__b1p2" not in _ids(events, "write-start")  # dropped: no write after a failed one
    m = json.loads((out / "manifest.json").read_text())
    assert m["template"] and set(m["fits"]) == {"zero", "b1p2"} and m["sequences"] == {}
    assert os.listdir(out / "sequences") == ["zarr.json"] and os.listdir(out / ".staging") == []
    assert not (out / ".lock").exists()
    assert check_dataset(out).passed
    monkeypatch.setattr(Location, "_write_group", original)
    (rep,) = generate_dataset(spec, out=str(out))
    assert rep.written == 2 and rep.pending == 0 and not rep.failed and not any(rep.reconcile.values())
    assert open_dataset(out).sequence_ids() == ["walk_fast__b1p2", "walk_fast__zero"]
    assert check_dataset(out).passed


def test_write_failure_with_jobs_still_waiting_is_store_write_error(tmp_path, monkeypatch):
    """A fit's write fails while sequences still wait for the pool's one slot: StoreWriteError (the
    waiting jobs are left for the next run, not taken for a spent time budget), and the same call
    then completes the store."""
    out = tmp_path / "store"
    spec = micro(batch_size=1)
    original = Location._write_group

    def failing(self, target, arrays, attrs, chunks, commit):
        if "zero" in target and "walk_fast" not in target:
            raise OSError(28, "No space left on device")
        return original(self, target, arrays, attrs, chunks, commit)

    monkeypatch.setattr(Location, "_write_group", failing)
    with pytest.raises(StoreWriteError, match="No space left on device"):
        generate_dataset(spec, out=str(out))
    m = json.loads((out / "manifest.json").read_text())
    assert m["template"] and "zero" not in m["fits"] and m["sequences"] == {}
    monkeypatch.setattr(Location, "_write_group", original)
    (rep,) = generate_dataset(spec, out=str(out))
    assert rep.written == 2 and rep.pending == 0 and not rep.failed
    assert check_dataset(out).passed


def test_simulation_error_is_raised_after_the_jobs_being_written(tmp_path, monkeypatch):
    """An exception while the last sequence simulates (the one before it being written) reaches the
    caller once that write is recorded; the store is consistent and the same call resumes it."""
    out = tmp_path / "store"
    spec = micro(batch_size=1)
    original = SimulationPool.step

    def crashing(self):
        if any(run.tag.id == "walk_fast__b1p2" for run in self._running.values()):
            raise RuntimeError("the device fell off the bus (injected)")
        return original(self)

    monkeypatch.setattr(SimulationPool, "step", crashing)
    with pytest.raises(RuntimeError, match="injected"):
        generate_dataset(spec, out=str(out))
    assert not _writer_threads() and not (out / ".lock").exists()
    m = json.loads((out / "manifest.json").read_text())
    assert set(m["sequences"]) == {"walk_fast__zero"} and set(m["fits"]) == {"zero", "b1p2"}
    assert check_dataset(out).passed
    monkeypatch.setattr(SimulationPool, "step", original)
    (rep,) = generate_dataset(spec, out=str(out))
    assert rep.written == 1 and rep.pending == 0 and not any(rep.reconcile.values())
    assert check_dataset(out).passed


def test_a_job_whose_ground_truth_fails_fails_alone(tmp_path, monkeypatch):
    """An exception while one job's node is computed (not a store write) fails that job, attempt
    after attempt, and the pool writes the others."""
    real = ex._frame_stats

    def broken(result, faces, rest_inverse):
        if result.metadata["key"] == "sequence:walk_fast__b1p2":
            raise FloatingPointError("a broken statistic (injected)")
        return real(result, faces, rest_inverse)

    monkeypatch.setattr(ex, "_frame_stats", broken)
    out = tmp_path / "s"
    (rep,) = generate_dataset(micro(batch_size=2), out=str(out))
    assert rep.written == 1 and list(rep.failed) == ["sequence:walk_fast__b1p2"]
    assert "FloatingPointError" in rep.failed["sequence:walk_fast__b1p2"]
    assert open_dataset(out).sequence_ids() == ["walk_fast__zero"] and not _writer_threads()


def test_a_pool_is_freed_when_its_task_ends(tmp_path, monkeypatch):
    """Nothing keeps a finished pool (and its device memory) alive: the next pool is sized from the
    free memory."""
    import weakref

    pools = []
    init = SimulationPool.__init__

    def tracked(self, *args, **kwargs):
        init(self, *args, **kwargs)
        pools.append(weakref.ref(self))

    monkeypatch.setattr(SimulationPool, "__init__", tracked)
    (rep,) = generate_dataset(micro(batch_size=2), out=str(tmp_path / "s"), time_budget=600.0)
    assert rep.written == 2 and pools and all(ref() is None for ref in pools)


def test_time_budget_stops_the_pool(tmp_path):
    """With no time left the driver starts nothing; a pool past its deadline stops after the frame
    that measured the frame time: the jobs it had started are dropped unwritten, and the next run
    simulates everything."""
    from simgen.dataset.execute import BatchTask, _load_body
    from simgen.dataset.generate import plan_jobs

    out = tmp_path / "store"
    spec = micro(batch_size=1)
    (rep,) = generate_dataset(spec, out=str(out), time_budget=1e-9)
    assert rep.stopped and rep.written == 0 and rep.pending == 2 and rep.cloth_frames == 0
    body = _load_body(spec.body)
    jobs = plan_jobs(spec, "tshirt_1k", body)
    task = BatchTask(location=str(out), spec=spec, garment="tshirt_1k", jobs=jobs, body_hash=body.hash)
    r = ex.run_pool_task(task, deadline=time.perf_counter())
    assert r["outcomes"] == [] and sorted(j.id for j in r["not_done"]) == sorted(JOBS) and r["cloth_frames"] == 1
    assert r["abandoned_cloth_frames"] == spec.protocol_frames()  # the template's, of which one was run
    assert Location(out).committed("template") is None
    (rep,) = generate_dataset(spec, out=str(out))
    assert rep.written == 2 and rep.pending == 0 and check_dataset(out).passed
