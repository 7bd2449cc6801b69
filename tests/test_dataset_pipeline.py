"""The local executor's pipeline (`execution.overlap_writes`): batch k is written in a background
thread while batch k+1 simulates in the main thread. Results come back in batch order, the store
equals the one made with the overlap off, and a failure of either phase leaves a consistent,
resumable store and no writer thread behind. `micro` specs with one batch per sequence (three
batches: template + fits, then one sequence each); a few seconds per run on 2 CPU cores.
"""

import json
import os
import threading
import time

import numpy as np
import pytest

import simgen.dataset.execute as ex
import simgen.dataset.generate as gen
from simgen.dataset import check_dataset, generate_dataset, open_dataset
from simgen.dataset.storage import Location, StoreWriteError
from simgen.dataset.store import node_arrays

from test_dataset_store import micro  # tests/ is on sys.path under pytest

SETUP, ZERO, B1P2 = ("template", "zero", "b1p2"), ("walk_fast__zero",), ("walk_fast__b1p2",)
TIMINGS = {"stats/wall_time", "stats/step_time"}  # host clock readings: differ between any two runs


def _writer_threads() -> list:
    return [t for t in threading.enumerate() if t.name.startswith("simgen-write")]


def _instrument(monkeypatch, write_delay: float = 0.0) -> list:
    """Log (event, batch ids, on the main thread, time) of both phases and of the results the driver
    gets; each write sleeps write_delay first (a slow disk)."""
    events = []
    lock = threading.Lock()

    def log(what, jobs):
        with lock:
            events.append((what, tuple(j.id for j in jobs), threading.current_thread() is threading.main_thread(),
                           time.perf_counter()))

    real_sim, real_write, real_next = ex.simulate_batch_task, ex.write_batch, gen._LocalExecutor.next_result

    def sim(task, progress=None):
        log("sim-start", task.jobs)
        out = real_sim(task, progress=progress)
        log("sim-end", task.jobs)
        return out

    def write(simulated):
        log("write-start", simulated.task.jobs)
        time.sleep(write_delay)
        out = real_write(simulated)
        log("write-end", simulated.task.jobs)
        return out

    def next_result(self):
        task, result = real_next(self)
        log("result", task.jobs)
        return task, result

    for mod in (ex, gen):  # run_batch (overlap off) calls execute's names, the executor generate's
        monkeypatch.setattr(mod, "simulate_batch_task", sim)
        monkeypatch.setattr(mod, "write_batch", write)
    monkeypatch.setattr(gen._LocalExecutor, "next_result", next_result)
    return events


def _ids(events, what) -> list:
    return [ids for w, ids, *_ in events if w == what]


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
        assert _ids(events, "sim-start") == [SETUP, ZERO, B1P2]
        assert _ids(events, "result") == [SETUP, ZERO, B1P2]  # in submission order
        assert all(main for w, _, main, _ in events if w.startswith("sim"))
        at = {(w, ids): t for w, ids, _, t in events}
        batches = [SETUP, ZERO, B1P2]
        if overlap:
            assert not any(main for w, _, main, _ in events if w.startswith("write"))
            for k in range(2):  # batch k+1 simulates while batch k is written, one write at a time
                assert at[("sim-start", batches[k + 1])] < at[("write-end", batches[k])]
                assert at[("write-end", batches[k])] <= at[("write-start", batches[k + 1])]
            # The phases' sums exceed the wall clock by the hidden write time.
            assert rep.write_wait < rep.write_wall
        else:
            assert all(main for w, _, main, _ in events if w.startswith("write"))
            for k in range(2):
                assert at[("write-end", batches[k])] < at[("sim-start", batches[k + 1])]
            assert rep.write_wait == pytest.approx(rep.write_wall)
        stores[overlap] = Location(out)
    # Bit-identical nodes (the simulation is deterministic on the CPU) but for the host timings.
    on, off = stores[True], stores[False]
    for rel in ("template", "fit/zero", "fit/b1p2"):
        assert on.committed(rel)["checksum"] == off.committed(rel)["checksum"], rel
    for sid in ("walk_fast__zero", "walk_fast__b1p2"):
        a, b = node_arrays(on, f"sequences/{sid}"), node_arrays(off, f"sequences/{sid}")
        assert set(a) == set(b)
        for name in sorted(set(a) - TIMINGS):
            np.testing.assert_array_equal(a[name], b[name], err_msg=f"{sid}/{name}")


def test_background_write_failure_is_store_write_error_and_resumable(tmp_path, monkeypatch):
    """The 2nd batch's write fails in the writer thread while the 3rd simulates: StoreWriteError, the
    1st batch is in the manifest, the 3rd is never written, nothing is staged, no thread is left."""
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
    assert _ids(events, "sim-start") == [SETUP, ZERO, B1P2] and _ids(events, "result") == [SETUP, ZERO]
    assert B1P2 not in _ids(events, "write-start")  # simulated, then dropped: no write after a failed one
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


def test_simulation_error_is_raised_after_the_batch_being_written(tmp_path, monkeypatch):
    """An exception while batch 3 simulates (batch 2 being written) reaches the caller once batch 2 is
    recorded; the store is consistent and the same call resumes it."""
    out = tmp_path / "store"
    spec = micro(batch_size=1)
    original = ex.simulate_jobs

    def crashing(garment, body, jobs, config, progress=None):
        if any(j.id == "walk_fast__b1p2" for j in jobs):
            raise RuntimeError("the device fell off the bus (injected)")
        return original(garment, body, jobs, config, progress=progress)

    monkeypatch.setattr(ex, "simulate_jobs", crashing)
    with pytest.raises(RuntimeError, match="injected"):
        generate_dataset(spec, out=str(out))
    assert not _writer_threads() and not (out / ".lock").exists()
    m = json.loads((out / "manifest.json").read_text())
    assert set(m["sequences"]) == {"walk_fast__zero"} and set(m["fits"]) == {"zero", "b1p2"}
    assert check_dataset(out).passed
    monkeypatch.setattr(ex, "simulate_jobs", original)
    (rep,) = generate_dataset(spec, out=str(out))
    assert rep.written == 1 and rep.pending == 0 and not any(rep.reconcile.values())
    assert check_dataset(out).passed


def test_time_budget_rate_counts_only_the_batches_returned():
    """With the writes overlapped, the first result (the setup batch) comes back after the next
    batch has simulated too: its wall clock covers two batches. The budget's rate must come from
    the returned batches' own simulation and waited-for write time, or a budgeted run stops after
    a batch (seen on the device: 16 of 340 sequences in a 560 s budget, stopped at 105 s)."""
    report = gen.StoreReport(path="x", garment="tshirt", planned_sequences=1, planned_fits=1, done_before=0)
    report.cloth_frames, report.simulate_wall, report.write_wait = 1000, 10.0, 0.5
    report.wall = 95.0  # the setup batch (10 s) and the next sequence batch (85 s) simulated
    assert gen._budget_rate(report, 1) == pytest.approx(1000 / 10.5)
    # Ray: several simulations at once; the throughput of all of them together.
    assert gen._budget_rate(report, 4) == pytest.approx(1000 / 95.0)
    report.simulate_wall = report.write_wait = 0.0
    assert gen._budget_rate(report, 1) == 0.0
