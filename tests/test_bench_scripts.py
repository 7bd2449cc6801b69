"""The benchmark scripts in scripts/ run end to end at tiny sizes on the CPU and print the JSON the
device runs rely on (BENCHMARKS.md quotes these fields). Timings are not asserted."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


def run_script(name: str, *args: str, out: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.run([sys.executable, str(REPO / "scripts" / name), *args, "--out", str(out)],
                          capture_output=True, text=True, env=env, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(out.read_text())


def test_bench_solver_with_a_preset_steps_with_the_specs_settings(tmp_path):
    from simgen.dataset import load_spec

    spec = load_spec("tiny")
    result = run_script("bench_solver.py", "--device", "cpu", "--preset", "tiny", "--batches", "2",
                        "--frames", "2", "--modes", "motion", out=tmp_path / "bench.json")
    assert result["preset"] == "tiny" and result["garment"]["name"] == spec.garments[0]
    assert result["substeps_per_frame"] == spec.substeps
    (row,) = result["runs"]
    assert row["mode"] == "motion" and row["preset"] == "tiny" and row["instances"] == 2
    assert row["newton_iterations"] == spec.solver_config().solver.newton_iterations
    assert row["finite"] and row["failed_instances"] == 0
    assert row["unresolved"] >= 0 and row["retries"] >= 0 and row["ms_per_frame_median"] > 0


def test_bench_self_contact_reports_depth_per_instance_of_the_bench_shapes(tmp_path):
    sys.path.insert(0, str(REPO / "scripts"))
    from bench_solver import shape_batch

    result = run_script("bench_self_contact.py", "--device", "cpu", "--garment", "tshirt_1k", "--motion", "walk",
                        "-n", "2", "--frames", "2", "--preset", "none", "--shapes", "bench", "--skip-none",
                        out=tmp_path / "sc.json")
    assert result["shapes"] == "bench" and list(result["runs"]) == ["self_contact"]
    row = result["runs"]["self_contact"]
    depth = row["depth_regular_mm_per_instance"]
    assert len(depth) == 2 and max(depth) == row["max_depth_regular_mm"]
    assert row["instances_deeper_than_1_3_mm"] == [sum(d > 1.0 for d in depth), sum(d > 3.0 for d in depth)]
    assert row["frames"] == 4  # two instances, two output frames each
    strain = row["strain_regular_max_per_instance"]
    assert len(strain) == 2 and 0.0 < min(strain) and row["instances_strained_over_100_percent"] == sum(
        e > 1.0 for e in strain)
    assert np.allclose(result["betas"], shape_batch(2, 10)) and np.allclose(result["betas"][0], 0.0)


def test_profile_solver_with_a_preset(tmp_path):
    result = run_script("profile_solver.py", "--device", "cpu", "--preset", "tiny", "--batches", "1",
                        "--frames", "1", out=tmp_path / "profile.json")
    assert result["preset"] == "tiny" and result["garment"]["name"] == "tshirt_1k"
    (row,) = result["runs"]
    assert row["instances"] == 1 and row["cg_per_newton"] >= 1 and row["eager_ms_per_frame"] > 0


@pytest.mark.parametrize("overlap", [True, False])
def test_dataset_bench_reports_rates_split_and_retries(tmp_path, overlap):
    sys.path.insert(0, str(REPO / "scripts"))
    try:
        import dataset_bench
    finally:
        sys.path.remove(str(REPO / "scripts"))
    out = tmp_path / "bench.json"
    args = ["--spec", "tiny", "--device", "cpu", "--json", str(out), "--max-sequences", "2"]
    assert dataset_bench.main(args + ([] if overlap else ["--no-overlap-writes"])) == 0
    r = json.loads(out.read_text())
    assert r["spec"] == "tiny" and r["sizes"]["sequences_written_now"] == 2
    assert r["sizes"]["overlap_writes"] is overlap
    assert r["cloth_frames"] > 0 and r["cloth_frames_per_s"] > 0
    split = r["time_split_s"]
    assert split["solver_steps"] > 0 and split["write"] > 0
    assert split["write_hidden"] >= 0 and (overlap or split["write_hidden"] < 1e-6)
    assert r["retries"] == {"jobs": 0, "cloth_frames": 0, "simulate_s": 0.0, "failed_attempts": []}
    assert r["thesis_tshirt_plan"]["sequences"] == 340 and r["projected_thesis_s"] > 0


def test_fit_report_measures_hem_and_sleeves(tmp_path):
    result = run_script("fit_report.py", "--device", "cpu", "--garment", "tshirt_1k", "--frames", "2",
                        "--variants", "no_friction", out=tmp_path / "fit.json")
    assert result["garment"] == "tshirt_1k" and result["frames"] == 2
    assert [r["shape"] for r in result["rows"]] == ["zero", "b0p2", "b0m2"]
    for row in result["rows"]:
        assert row["variant"] == "no_friction" and row["frames"] == 2
        assert 0.0 <= row["hem_cling_frame0"] <= row["hem_cling_max"] <= 1.0
        # The sleeves hang off the arm by centimetres, not metres (measured against the posed body).
        assert 0.0 < row["sleeve_gap_frame45_m"] <= row["sleeve_gap_all_frames_max_m"] < 0.3
        # The walk starts in the T-pose: no frame has the arms down, so there is no arms-down gap.
        assert row["arms_down_frames"] == 0 and row["sleeve_gap_arms_down_max_m"] is None


def test_arm_angle_reads_the_pose():
    """fit_report's arm angle: 90 deg in the rest T-pose, below 45 deg where idle_sway has lowered
    the arms (frame 81, peer_drape's standing pose)."""
    sys.path.insert(0, str(REPO / "scripts"))
    try:
        import fit_report
    finally:
        sys.path.remove(str(REPO / "scripts"))
    from simgen.body import load as load_body
    from simgen.motion import load_motion

    body, clip = load_body("open"), load_motion("idle_sway")
    standing = body.forward(pose=clip.poses[81], trans=clip.trans[81])
    assert abs(fit_report.arm_angle(body.v_template) - 90.0) < 10.0
    # Joints regressed from the posed skin read within a few degrees of the skeleton's own (33 deg
    # for both arms there; 37.5 from the skin).
    joints = standing.joints[0]
    skeleton = max(np.degrees(np.arccos(-(joints[e] - joints[s])[1] / np.linalg.norm(joints[e] - joints[s])))
                   for s, e in fit_report.UPPER_ARMS)
    angle = fit_report.arm_angle(standing.vertices[0])
    assert angle < fit_report.ARMS_DOWN_DEG and abs(angle - skeleton) < 6.0


def test_tshirt_hem_stays_off_the_thighs_in_the_walk(tmp_path):
    """Issue 21's target at a tiny size: the coarse T-shirt in the demo's walk (beta = 0, the
    solver's defaults, the whole start protocol) keeps at most half of its lowest 10 cm more than
    3 mm from the body on every frame. With one Newton iteration per substep (ARCSim's) the share
    reached 0.66 here, 0.79 on the full T-shirt on the GPU (SolverConfig's doc)."""
    result = run_script("peer_drape.py", "--device", "cpu", "--garment", "tshirt_1k", "--motion", "walk",
                        "--frames", "91", "--solvers", "ours", "--variants", "default", out=tmp_path / "walk.json")
    (run,) = result["runs"]
    assert run["finite"] and result["pose"]["motion"] == "walk" and len(run["per_frame"]["hem_cling"]) == 150
    gap = run["sleeve_gap_arms_down_max_after_transition_m"]
    assert gap is not None  # the walk lowers the arms after its first ~0.6 s
    print(f"walk, coarse T-shirt: hem cling max {run['hem_cling_max_after_transition']:.3f}, sleeve gap max "
          f"(arms down) {gap * 100:.1f} cm")
    assert run["hem_cling_max_after_transition"] <= 0.5


def _run_json(name: str, *args: str, out: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.run([sys.executable, str(REPO / "scripts" / name), *args, "--json", str(out)],
                          capture_output=True, text=True, env=env, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(out.read_text())


def test_cg_profile_takes_a_newton_system_out(tmp_path):
    r = _run_json("cg_profile.py", "--device", "cpu", "--garment", "tshirt_1k", "--frames", "1",
                  out=tmp_path / "cg.json")
    assert r["solves"] > 0 and 0 < r["iterations"]["mean"] <= r["cap_per_newton_iteration"]
    assert r["condition_block_jacobi"] > 1 and r["scipy_block_jacobi_uncapped"] > 0
    for key in ("scipy_symmetric_gauss_seidel", "scipy_ilut", "scipy_block_jacobi_warm_start"):
        assert r[key] >= 1


def test_bvh_quality_counts_node_tests_and_the_lattice_costs_the_radix_tree(tmp_path):
    sys.path.insert(0, str(REPO / "scripts"))
    try:
        from bvh_quality import median_split, morton, tests_per_query
    finally:
        sys.path.remove(str(REPO / "scripts"))
    # two disjoint boxes: each query tests the root and both leaves
    lo, hi = np.array([[0.0, 0, 0], [2.0, 0, 0]]), np.array([[1.0, 1, 1], [3.0, 1, 1]])
    assert tests_per_query(lo, hi, median_split(lo, hi)) == 3
    # Warp's morton3: x in each triple's lowest bit, z in its highest
    unit = np.ones(3)
    assert morton(np.array([[0.5 / 1024, 0, 0], [0, 0, 0.5 / 1024], [1.0, 1.0, 1.0]]), np.zeros(3), unit).tolist() == [
        0, 0, 2 ** 30 - 1]
    assert morton(np.array([[1.5 / 1024, 0, 0], [0, 0, 1.5 / 1024]]), np.zeros(3), unit).tolist() == [1, 4]
    one = run_script("bvh_quality.py", "--garment", "tshirt_1k", "--instances", "1", out=tmp_path / "one.json")
    many = run_script("bvh_quality.py", "--garment", "tshirt_1k", "--instances", "64", out=tmp_path / "many.json")
    t1, t64 = one["tests_per_query"], many["tests_per_query"]
    assert t1["radix_own_bounds"] == t1["radix_lattice_bounds"] == t64["radix_own_bounds"]
    assert t64["radix_lattice_bounds"] > 2 * t64["radix_own_bounds"]
    assert t64["median_split"] < 1.5 * t64["radix_own_bounds"]


def test_softtissue_validate_reports_regions_and_modes(tmp_path):
    r = _run_json("softtissue_validate.py", "--device", "cpu", "--clips", "jump:0:0.1", "--shapes", "0",
                  out=tmp_path / "st.json")
    shape = r["clips"]["jump:0:0.1"]["shapes"]["0.0"]
    assert shape["min_det"] > 0 and shape["peak_m"]["head"] == 0.0 and shape["peak_m"]["belly"] > 0
    assert 2.0 <= r["first_mode_hz"]["belly"] <= 15.0


def test_softtissue_runtime_times_a_trained_folder(tmp_path):
    sys.path.insert(0, str(REPO / "tests"))
    from test_softtissue_models import _tiny_body, _tiny_config

    from simgen.learn.softtissue.data import synthetic_softtissue_data
    from simgen.learn.softtissue.train import train_softtissue

    body = _tiny_body()
    data = synthetic_softtissue_data(body, motions=("jump", "walk"), subjects=2, frames=12)
    train_softtissue(data, tmp_path / "m", body=body, config=_tiny_config())
    result = run_script("softtissue_runtime.py", "--model", str(tmp_path / "m"), "--frames", "6",
                        "--repeats", "1", out=tmp_path / "rt.json")
    row = result["devices"]["cpu"]
    assert result["frames"] == 6 and result["commit"] and result["machine"]["cpus"] >= 1
    assert row["streamed_ms_per_frame"][0] > 0 and row["sequence_ms_per_frame"][0] > 0
    assert row["decoder_ms"] > 0 and row["parameters"]["regressor"] > 0


def test_untangle_replay_untangles_the_coarse_tshirt_in_kick(tmp_path):
    """With two Newton iterations and the replay's short start protocol, the coarse T-shirt in kick
    at beta 1 = +2 (no self-contact) crosses itself on every one of its first 28 frames (7-15
    crossing edges). Global intersection analysis alone untangles only a few of them; with the
    previous frame as reference every frame after the first untangled one is untangled, some only
    after untangle's roll-back toward the reference (more than ROLLBACK_AFTER rounds). With the
    default three iterations its first 24 frames never tangle."""
    from simgen.garment.untangle import ROLLBACK_AFTER

    result = run_script("untangle_replay.py", "--frames", "28", "--newton-iterations", "2",
                        out=tmp_path / "untangle.json")
    alone, ref = result["alone"], result["with_reference"]
    assert result["garment"] == "tshirt_1k" and ref["frames_tangled"] == alone["frames_tangled"] > 20
    first = min(row["frame"] for row in ref["frames"] if row["left"] == 0)
    later = [row for row in ref["frames"] if row["frame"] > first]
    assert len(later) >= 20 and all(row["left"] == 0 and row["crossings"] > 0 for row in later)
    assert any(row["rounds"] > ROLLBACK_AFTER for row in later)
    assert alone["frames_untangled"] < ref["frames_untangled"]
    result = run_script("untangle_replay.py", "--frames", "24", out=tmp_path / "untangle3.json")
    assert result["alone"]["frames_tangled"] == result["with_reference"]["frames_tangled"] == 0


def test_bench_frame_stats_host_times_placement_and_strain(tmp_path):
    result = run_script("bench_frame_stats_host.py", "--spec", "tiny", "--slots", "3", "1", "--frames", "3",
                        "--repeats", "2", out=tmp_path / "host.json")
    sizes = result["sizes"]
    assert sizes["garment"] == "tshirt_1k" and 0 < sizes["support_vertices"] < sizes["vertices"]
    assert [r["slots"] for r in result["runs"]] == [3, 1] and all(r["placement_ms"] > 0 for r in result["runs"])
    assert result["sizes"]["sequence_frames"] == 3 and result["strain_summary_s"] > 0


def test_check_bench_times_one_and_several_workers_with_the_same_report(tmp_path):
    sys.path.insert(0, str(REPO / "scripts"))
    try:
        import check_bench
        import dataset_bench
    finally:
        sys.path.remove(str(REPO / "scripts"))
    store = tmp_path / "store"
    assert dataset_bench.main(["--spec", "tiny", "--device", "cpu", "--out", str(store), "--max-sequences", "2"]) == 0
    out = tmp_path / "check.json"
    assert check_bench.main([str(store), "--workers", "1,2", "--device", "cpu", "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert r["benchmark"] == "dataset_check" and r["sizes"]["sequences"] == 2 and r["commit"]
    assert [run["workers"] for run in r["runs"]] == [1, 2, 1]
    assert all(run["passed"] and run["same_report"] and run["wall_s"] > 0 for run in r["runs"])


def test_bench_pool_build_times_the_parts_of_a_pools_start(tmp_path):
    result = run_script("bench_pool_build.py", "--device", "cpu", "--spec", "tiny", "--slots", "2", "--top", "5",
                        out=tmp_path / "build.json")
    assert result["benchmark"] == "pool_build" and result["sizes"] == {"garment": "tshirt_1k",
                                                                        "vertices": result["sizes"]["vertices"],
                                                                        "slots": 2}
    assert min(result["warp_import_init_s"], result["load_s"], result["pool_build_s"]) > 0
    top = result["profile_top"]
    assert len(top) == 5 and "pool.py" in top[0]["function"] and top[0]["cumulative_s"] <= result["pool_build_s"]


def test_bench_pool_occupancy_times_busy_and_idle_slots_and_the_parts_of_a_frame(tmp_path):
    result = run_script("bench_pool_occupancy.py", "--device", "cpu", "--spec", "tiny", "--slots", "2",
                        "--busy", "2", "1", "--warmup", "1", "--frames", "2", "--parts", out=tmp_path / "occ.json")
    assert result["benchmark"] == "pool_occupancy" and result["sizes"]["slots"] == 2
    assert [r["busy"] for r in result["runs"]] == [2, 1]
    for run in result["runs"]:
        parts = run["parts_ms"]
        assert {"frame", "frame/stepping", "frame/statistics/measure", "frame/statistics/measure/crossings",
                "frame/targets"} <= set(parts)
        assert min(parts.values()) >= 0 and run["frame_ms"] >= run["step_ms"] > 0
        # Own times: together they are the synced frames' wall time (the timer's own overhead aside).
        assert sum(parts.values()) == pytest.approx(run["synced_frame_ms"], rel=0.02)


def test_bench_postprocess_times_the_three_post_processes(tmp_path):
    """Each post-process leaves nothing inside; the metric one cuts the noisy input's triangle strain."""
    result = run_script("bench_postprocess.py", "--device", "cpu", "--frames", "3", "--single-frames", "2",
                        "--repeats", "1", out=tmp_path / "post.json")
    rows = result["methods"]
    assert result["benchmark"] == "postprocess" and result["sizes"]["frames"] == 3
    assert set(rows) == {"input", "push", "spread_push", "metric"}
    for name in ("push", "spread_push", "metric"):
        assert rows[name]["inside_percent"] == 0 and rows[name]["single_ms_per_frame"] > 0
    assert rows["metric"]["mean_triangle_strain"] < 0.2 * rows["input"]["mean_triangle_strain"]


def test_train_thesis_generates_trains_both_splits_and_evaluates(tmp_path):
    """scripts/train_thesis.py at CPU size: a 4-motion subset of the tiny preset, both splits, the
    GRU stopped by its validation motions; then the CPU-side plots and USD from what it returned."""
    out, work = tmp_path / "out", tmp_path / "work"
    args = ["--spec", "tiny", "--motions", "jumping_jacks", "walk", "squat", "walk_fast", "--shapes", "zero", "b1p2",
            "--max-frames", "5", "--splits", "motion", "shape", "--val-motions", "1", "--patience", "2",
            "--val-every", "1", "--epochs", "6", "--fit-epochs", "50", "--hidden", "16", "--window", "4",
            "--batch-size", "4", "--timing-frames", "3", "--inside-stride", "2", "--eval-sequences", "2",
            "--compare-frames", "4", "--total-budget", "600", "--gen-budget", "300", "--min-train", "10",
            "--eval-reserve", "30", "--fit-budget", "5", "--device", "cpu", "--work", str(work)]
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}

    def script(*argv: str) -> None:
        proc = subprocess.run([sys.executable, str(REPO / "scripts" / "train_thesis.py"), *argv],
                              capture_output=True, text=True, env=env, timeout=900)
        assert proc.returncode == 0, proc.stderr[-2000:]

    script(*args, "--out", str(out))
    metrics = json.loads((out / "metrics.json").read_text())
    assert "error" not in metrics and set(metrics["splits"]) == {"motion", "shape"}
    phases = metrics["phases"]
    assert phases["load"]["sequences"] == 8
    for by in ("motion", "shape"):
        assert phases[f"load_{by}"]["validation"] >= 1
        wrinkle = phases[f"train_wrinkle_{by}"]
        assert wrinkle["stopped"] in ("converged", "epochs") and 1 <= wrinkle["best_epoch"] <= wrinkle["epochs"]
        assert "held_out_motion" in metrics["splits"][by]["groups"]
        for name in (f"fit_model_{by}.tar", f"compare_{by}.npz", f"training_{by}.png"):
            assert (out / name).is_file(), name
    assert metrics["splits"]["shape"]["test_shapes"] == ["b1p2"]
    script("--plots-from", str(out))
    script("--usd-from", str(out / "compare_shape.npz"), "--usd-out", str(tmp_path / "usd"))
    assert (out / "shape" / "training.png").is_file()
    compared = metrics["splits"]["shape"]["compare"]["sequences"]
    assert len(compared) == len({s.split("__")[0] for s in compared}) >= 1     # different motions
    for sid in compared:
        assert (tmp_path / "usd" / f"compare_shape_{sid}.usdc").stat().st_size > 0


def test_the_part_timer_puts_back_what_it_patched():
    """bench_pool_occupancy's timer: own times by call path, and every patched attribute (a class's
    own, an inherited one, a module's) restored to the very object it was, also after an error."""
    import importlib.util
    import types

    import warp as wp

    spec = importlib.util.spec_from_file_location("bench_pool_occupancy", REPO / "scripts" / "bench_pool_occupancy.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)

    class Base:
        def inner(self):
            return 1

    class Outer(Base):
        def outer(self):
            return self.inner() + mod.helper()

    mod = types.SimpleNamespace(helper=lambda: 2)
    own_outer, helper = Outer.__dict__["outer"], mod.helper
    timer = bench._PartTimer(wp.get_device("cpu"))
    for owner, attr, label in ((Outer, "outer", "outer"), (Outer, "inner", "inner"), (mod, "helper", "helper")):
        timer.patch(owner, attr, label)
    assert Outer().outer() == 3 and set(timer.own) == {"outer", "outer/inner", "outer/helper"}
    timer.restore()
    assert Outer.__dict__["outer"] is own_outer and "inner" not in Outer.__dict__ and mod.helper is helper
    timer.patch(Outer, "outer", "outer")
    Outer.inner = lambda self: 1 / 0
    with pytest.raises(ZeroDivisionError):
        Outer().outer()
    timer.restore()
    assert Outer.__dict__["outer"] is own_outer and not timer._stack
