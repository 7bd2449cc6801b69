"""`simgen dataset generate --ray local` whose DRIVER process is killed by SIGKILL mid-run, then resumed.

The Ray workers write and commit the nodes; the driver alone writes the manifest, and only as task
results come back. A driver killed after a worker committed a sequence (before the run ended) leaves
committed nodes the manifest does not list, maybe a half-written node in .staging, a stale lock and
the Ray session it started. The same command run again must adopt the committed nodes (not simulate
them again), simulate the rest, and leave a complete store that passes the check.

The spec is `tiny` cut to one frame per clip with one slot per pool: 4 sequences, 7 jobs of 7
cloth-frames each, dealt into 2 Ray tasks on the 2 CPUs. About a minute on 2 CPU cores.
"""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from simgen.dataset import check_dataset, open_dataset
from simgen.dataset.storage import Location
from test_dataset_store import TINY_IDS, _committed_sequences, assert_complete_tiny_store  # tests/ is on sys.path under pytest

#: tiny, one frame per clip (7 protocol frames + 1), one slot per pool: each job is 7 cloth-frames.
ARGS = ["tiny", "--max-frames", "1", "--batch-size", "1", "--ray", "local"]
JOB_CLOTH_FRAMES = 7
PLANNED_NODES = {"template", "fit/zero", "fit/b1p2"} | {f"sequences/{s}" for s in TINY_IDS}


def _stat(pid: int) -> list | None:
    """/proc/<pid>/stat fields after the command name (state, ppid, ..., starttime at [19]), or None."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()
    except OSError:
        return None


def _descendants(root: int) -> dict:
    """{pid: starttime} of every process below ``root`` (children, their children, ...)."""
    children: dict = {}
    for p in os.listdir("/proc"):
        if p.isdigit() and (st := _stat(int(p))) is not None:
            children.setdefault(int(st[1]), []).append(int(p))
    found, stack = {}, [root]
    while stack:
        for c in children.get(stack.pop(), []):
            if (st := _stat(c)) is not None:
                found[c] = st[19]
                stack.append(c)
    return found


def _session_processes(driver_pid: int) -> dict:
    """{pid: starttime} of processes holding a file of the Ray session that ``driver_pid`` started
    (Ray names it session_<date>_<driver pid>): its agents and workers after their parent died."""
    tag = f"_{driver_pid}/"
    found = {}
    for p in os.listdir("/proc"):
        if not p.isdigit() or int(p) == os.getpid():
            continue
        try:
            links = [os.readlink(f"/proc/{p}/fd/{fd}") for fd in os.listdir(f"/proc/{p}/fd")]
        except OSError:
            continue
        if any("/session_" in ln and tag in ln for ln in links) and (st := _stat(int(p))) is not None:
            found[int(p)] = st[19]
    return found


def _alive(procs: dict) -> dict:
    """The processes of ``procs`` still running (same pid and start time, not a zombie) -> their names."""
    out = {}
    for pid, start in procs.items():
        st = _stat(pid)
        if st is None or st[19] != start or st[0] == "Z":
            continue
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as fh:
                out[pid] = fh.read().split(b"\0")[0].decode(errors="replace") or "?"
        except OSError:
            continue
    return out


def _committed_nodes(out: Path) -> set:
    loc = Location(out)
    nodes = {"template"} if loc.committed("template") else set()
    nodes |= {f"fit/{f}" for f in loc.listdir("fit") if f != "zarr.json" and loc.committed(f"fit/{f}")}
    return nodes | {f"sequences/{s}" for s in _committed_sequences(out)}


def _generate(out: Path, *extra: str) -> subprocess.Popen:
    # The testing hooks of simgen.dataset.execute (SIMGEN_DATASET_KILL_ONCE, ...) stay out of it.
    env = {k: v for k, v in os.environ.items() if not k.startswith("SIMGEN_DATASET_")}
    return subprocess.Popen([sys.executable, "-m", "simgen.cli", "dataset", "generate", *ARGS, "--out", str(out),
                             *extra], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


def _kill_after_first_sequence(out: Path, killed_run: dict) -> tuple[dict, int]:
    """Run the command and SIGKILL its driver as soon as a sequence node is committed; the Ray
    processes under it go into ``killed_run`` ({pid: starttime}). Returns ({sequence: its commit
    record} at the kill, the driver's pid)."""
    proc = _generate(out)
    at_kill = None
    deadline = time.time() + 240
    try:
        while time.time() < deadline and proc.poll() is None:
            committed = _committed_sequences(out) if (out / "sequences").is_dir() else set()
            if committed:
                killed_run.update(_descendants(proc.pid))
                os.kill(proc.pid, signal.SIGKILL)
                at_kill = {n: Location(out).committed(f"sequences/{n}") for n in committed}
                break
            time.sleep(0.2)
    finally:
        if proc.poll() is None and at_kill is None:
            proc.kill()
        log = proc.communicate()[0].decode(errors="replace")
    assert at_kill is not None, f"the run ended (or hung) before a sequence was committed:\n{log[-3000:]}"
    assert proc.returncode == -signal.SIGKILL, log[-3000:]
    # Mid-run: at least one sequence committed, not all of them.
    assert 1 <= len(at_kill) < len(TINY_IDS), at_kill
    return at_kill, proc.pid


def _wait_until_ray_gone(killed_run: dict, driver: int) -> None:
    """The killed driver's Ray cluster goes away: gcs_server, raylet and the workers of its tasks (a
    worker left running could still write into the store while the next run does). The dashboard
    and runtime-env agents may linger a minute or two; the test's `finally` ends them."""
    killed_run.update(_session_processes(driver))
    assert killed_run, "no Ray processes were found under the killed driver"
    essential = ("gcs_server", "raylet", "ray::_run_pool_task", "ray::IDLE")
    wait_until = time.time() + 60
    while time.time() < wait_until:
        left = {p: n for p, n in _alive(killed_run).items() if any(e in n for e in essential)}
        if not left:
            return
        time.sleep(0.2)
    raise AssertionError(f"Ray processes of the killed driver still run: {left}")


@pytest.mark.slow
def test_ray_driver_killed_mid_run_is_resumed(tmp_path):
    """The driver of `--ray local` killed by SIGKILL once a worker committed a sequence: its Ray
    processes go away, and the same command run again adopts the committed nodes untouched (no
    simulation of them: the resumed run's cloth-frames are those of the uncommitted jobs only),
    simulates the rest, and leaves every planned sequence once, no staging, no lock, a manifest that
    lists every node with its checksum, and a store that passes `simgen dataset check --require-complete`."""
    pytest.importorskip("ray")
    out = tmp_path / "store"
    killed_run: dict = {}
    try:
        at_kill, driver = _kill_after_first_sequence(out, killed_run)
        _wait_until_ray_gone(killed_run, driver)

        # What the killed run left, now that nothing of it writes any more.
        committed_nodes = _committed_nodes(out)
        committed_seqs = {n.split("/", 1)[1] for n in committed_nodes if n.startswith("sequences/")}
        assert set(at_kill) <= committed_seqs < TINY_IDS
        commits = {n: Location(out).committed(n) for n in committed_nodes}
        staged = os.listdir(out / ".staging") if (out / ".staging").is_dir() else []
        manifest = json.loads((out / "manifest.json").read_text())
        listed = ({"template"} if manifest["template"] else set()) | {f"fit/{f}" for f in manifest["fits"]} | \
            {f"sequences/{s}" for s in manifest["sequences"]}
        # The driver was killed before every task came back: the manifest misses committed nodes.
        assert committed_nodes - listed
        assert (out / ".lock").exists()  # the killed driver's, stale now

        # 3. The same command again resumes the store to completion.
        report = tmp_path / "resume.json"
        t0 = time.time()
        proc = _generate(out, "--report", str(report))
        try:
            log = proc.communicate(timeout=300)[0].decode(errors="replace")
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        assert proc.returncode == 0, log[-3000:]
        (rep,) = json.loads(report.read_text())
        resume_s = time.time() - t0

        # Committed nodes were adopted (verified, not simulated again); the staged ones removed.
        assert rep["reconcile"] == {"staging_removed": len(staged), "leftovers_removed": 0,
                                    "adopted": len(committed_nodes - listed), "dropped": 0, "corrupt_removed": 0}
        assert rep["done_before"] == len(committed_seqs)
        assert rep["written"] == len(TINY_IDS) - len(committed_seqs)
        # Only the jobs not committed at the kill were simulated (a resume that simulated everything
        # would count all 7 jobs: 49 cloth-frames).
        assert rep["cloth_frames"] == JOB_CLOTH_FRAMES * len(PLANNED_NODES - committed_nodes)
        assert rep["retried"] == 0
        assert rep["pending"] == 0 and rep["failed"] == {}

        # Every planned sequence once, nothing staged, no lock; the manifest lists every node.
        assert_complete_tiny_store(out)
        assert _committed_nodes(out) == PLANNED_NODES
        m = json.loads((out / "manifest.json").read_text())
        # The nodes committed before the kill are the same nodes: same commit record (checksum and
        # commit time), so they were not written again.
        for rel, commit in commits.items():
            assert Location(out).committed(rel) == commit, rel
        for sid, commit in at_kill.items():
            assert m["sequences"][sid]["checksum"] == commit["checksum"]
        assert open_dataset(out).sequence_ids() == sorted(TINY_IDS)
        check = check_dataset(out, require_complete=True)
        assert check.passed, check.format()
        print(f"killed with {sorted(at_kill)} committed; {len(committed_nodes)} nodes adopted or kept; "
              f"resume took {resume_s:.1f} s")
    finally:
        # Whatever of the killed driver's Ray session still runs (seen: ray::DashboardAgent and
        # ray::RuntimeEnvAgent, orphaned, for a minute or two after their raylet died): end it.
        for pid, name in _alive(killed_run).items():
            print(f"ending pid {pid} ({name}), left by the killed driver's Ray session")
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
