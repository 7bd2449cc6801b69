"""SimulationPool (simgen.sim.pool): continuous batching. A job that starts in a slot freed by an
earlier job, while another slot is mid-clip, gives what it gives alone: the slot's garment, body,
velocities and friction contacts start fresh, and its batch mates are not disturbed.

Tiny on purpose: the 1k-triangle T-shirt, 2 + 2 + 1 protocol frames, 3-4 output frames, 3 substeps.
"""


import numpy as np
import pytest
import warp as wp

from simgen.errors import InputError
from simgen.sim import SimulationJob, SimulationPool, SimulationResult, simulate

from test_sim_batch import CFG, inputs  # noqa: F401  (tests/ is on sys.path under pytest; the same tiny inputs)

wp.config.quiet = True


@pytest.fixture(scope="module")
def alone(inputs):
    body, garment, walk, squat = inputs
    return {"long": simulate(garment, body, walk, [1.0, -0.5], CFG, frames=6),
            "short": simulate(garment, body, squat, [-1.0], CFG, frames=2),
            "late": simulate(garment, body, squat, [0.5, 1.0], CFG, frames=3)}


def test_a_freed_slot_takes_the_next_job(inputs, alone):
    body, garment, walk, squat = inputs
    pool = SimulationPool(garment, body, 2, CFG, fps=30.0)
    pool.submit(SimulationJob(walk, betas=[1.0, -0.5], frames=6), tag="long")
    pool.submit(SimulationJob(squat, betas=[-1.0], frames=2), tag="short")
    pool.submit(SimulationJob(squat, betas=[0.5, 1.0], frames=3), tag="late")
    ended, busy, refit = {}, [], []
    while pool.busy or pool.queued:
        pool.fill()
        left = dict(pool.frames_left())
        out = pool.step()
        # Every running job's frames left drop by one a frame, and a job ends on its last one.
        assert {tag for tag, n in left.items() if n == 1} == {tag for tag, _ in out}
        assert dict(pool.frames_left()) == {tag: n - 1 for tag, n in left.items() if n > 1}
        busy.append(pool.busy + len(out))
        refit.append(pool.setup.collider.refit_slots)
        ended.update({tag: (res, pool.frames_run) for tag, res in out})
    protocol = CFG.relax_frames + CFG.ramp_frames + CFG.rest_frames
    # Once "long" has ended (slot 0 idle), the frames refit the body of "late"'s slot only.
    assert refit == [(0, 1)] * (protocol + 5) + [(1,)] * (len(busy) - protocol - 5)
    # long: protocol + 5 stepped frames; short ends after protocol + 1 and "late" takes its slot.
    assert ended["short"][1] == protocol + 1 and ended["long"][1] == protocol + 5
    assert ended["late"][1] == (protocol + 1) + (protocol + 2)
    assert busy == [2] * (protocol + 5) + [1] * (len(busy) - protocol - 5)
    assert pool.cloth_frames == sum(busy) == 3 * protocol + 5 + 1 + 2
    for tag, (res, _) in ended.items():
        ref = alone[tag]
        assert isinstance(res, SimulationResult) and res.positions.shape == ref.positions.shape
        # The instances do not interact; only float summation order may differ.
        assert np.abs(res.positions - ref.positions).max() < 1e-4, tag
        assert np.abs(res.protocol_positions - ref.protocol_positions).max() < 1e-4, tag
        assert list(res.protocol_phases) == list(ref.protocol_phases)
        for k in ("inside_count", "crossing_edges", "retries"):
            assert np.array_equal(res.stats[k], ref.stats[k]), (tag, k)
        assert res.metadata["betas"] == ref.metadata["betas"] and res.metadata["batch_size"] == 2


def test_the_frames_refit_every_active_body_and_leave_idle_ones_out_in_steps():
    """refit_slots: the set the frames refit changes only to hold a slot that became active, or
    when N / 8 of its slots are idle (each change captures the frame's graphs again)."""
    from simgen.sim.frame_runner import refit_slots

    every = tuple(range(16))
    active = np.ones(16, dtype=bool)
    assert refit_slots(active, every) == every
    active[[3]] = False
    assert refit_slots(active, every) == every               # 1 idle of 16: fewer than 16 / 8
    active[[3, 7]] = False
    kept = refit_slots(active, every)
    assert kept == tuple(k for k in every if k not in (3, 7))
    active[7] = True                                          # a job starts in slot 7: it is added
    grown = refit_slots(active, kept)
    assert grown == tuple(k for k in every if k != 3)
    active[0] = False                                         # 1 idle slot in the set: kept
    assert refit_slots(active, grown) == grown
    active[1] = False                                         # 2: the busy slots only
    busy = refit_slots(active, grown)
    assert busy == tuple(k for k in every if k not in (0, 1, 3))
    active[0] = True                                          # added, slot 1 stays out
    assert refit_slots(active, busy) == tuple(k for k in every if k not in (1, 3))
    assert refit_slots(np.zeros(16, dtype=bool), kept) == ()
    assert refit_slots(np.array([True, False]), (0, 1)) == (0,)   # small pools: any idle slot


def test_statistics_of_some_slots_equal_those_of_all(inputs):
    """FrameStats.measure on a subset of the slots (a pool's busy ones): their rows equal those of a
    measure of every slot (the body queries of the others are skipped), the others' are None, and a
    measure of every slot afterwards gives the same rows again. Slot 1's garment is moved 2 mm
    inside its body, so that the body queries decide its rows."""
    body, garment, walk, squat = inputs
    pool = SimulationPool(garment, body, 2, CFG, fps=30.0)
    pool.submit(SimulationJob(walk, betas=[1.0, -0.5], frames=4), tag="a")
    pool.submit(SimulationJob(squat, betas=[-1.0], frames=4), tag="b")
    for _ in range(CFG.relax_frames + CFG.ramp_frames + 1):
        pool.step()
    setup, nvg = pool.setup, len(garment.vertices)
    x = setup.state.positions.numpy().copy()
    skin = setup.collider.points.numpy().reshape(2, -1, 3)[1]
    near = skin[np.linspace(0, len(skin) - 1, nvg).astype(int)]
    inward = skin.mean(axis=0) - near
    x[nvg:] = near + 0.002 * inward / np.linalg.norm(inward, axis=1, keepdims=True)
    x = wp.array(x, dtype=wp.vec3, device=setup.state.positions.device)
    betas = pool.runner.betas_now
    every = setup.stats.measure(x, betas)
    assert every[1]["inside_count"] > nvg // 2 and every[1]["body_share"] > 0.5
    one = setup.stats.measure(x, betas, [1])
    assert one[0] is None and one[1] == every[1]
    assert setup.stats.measure(x, betas) == every


def test_a_job_at_twice_the_substeps_shares_the_pool(inputs, alone):
    """A job with substeps_factor 2 (a dataset retry) beside a job at the pool's substeps: each
    gives what it gives alone at its own substeps (the retry's solver steps are half as long, its
    body targets at its own substeps' ends, one frame recorded every two pool frames)."""
    import dataclasses

    body, garment, walk, squat = inputs
    ref = simulate(garment, body, squat, [0.5, 1.0], dataclasses.replace(CFG, substeps=2 * CFG.substeps), frames=3)
    pool = SimulationPool(garment, body, 2, CFG, fps=30.0)
    pool.submit(SimulationJob(walk, betas=[1.0, -0.5], frames=6), tag="long")
    pool.submit(SimulationJob(squat, betas=[0.5, 1.0], frames=3, substeps_factor=2), tag="retry")
    protocol = CFG.relax_frames + CFG.ramp_frames + CFG.rest_frames
    pool.fill()
    assert pool.next_frames() == 2 * (protocol + 2)
    assert pool.frames_left() == [("long", protocol + 5), ("retry", 2 * (protocol + 2))]
    ended = {}
    while pool.busy or pool.queued:
        ended.update({tag: (res, pool.frames_run) for tag, res in pool.step()})
    assert ended["long"][1] == protocol + 5 and ended["retry"][1] == 2 * (protocol + 2)
    assert pool.cloth_frames == (protocol + 5) + (protocol + 2)       # frames of the jobs, not pool frames
    for res, want in ((ended["long"][0], alone["long"]), (ended["retry"][0], ref)):
        assert isinstance(res, SimulationResult) and res.positions.shape == want.positions.shape
        assert np.abs(res.positions - want.positions).max() < 1e-4
        assert np.abs(res.protocol_positions - want.protocol_positions).max() < 1e-4
        for k in ("inside_count", "crossing_edges", "retries"):
            assert np.array_equal(res.stats[k], want.stats[k]), k
        assert res.metadata["substeps"] == want.metadata["substeps"] and res.dt == pytest.approx(want.dt, rel=1e-15)
    # The retry's newton iterations add up over its two pool frames per frame.
    retry = ended["retry"][0]
    assert retry.stats["newton_iterations"][1] == 2 * CFG.substeps * CFG.solver.newton_iterations
    # The slot is back at full steps for the next job.
    assert pool.setup.model.instance_step_divisor.numpy().tolist() == [1, 1]


def test_a_gate_stops_a_job_at_the_frame_it_names(inputs, alone):
    """The gate sees each animation frame's row as the job records it (strain_max: the most stretched
    triangle, measured on the device, as the dataset check's float64 measure gives it from the
    recorded positions); a message ends the job there as a failure, and its slot takes the next job,
    which gives what it gives alone."""
    from simgen.dataset.quality import triangle_rest_inverse, triangle_strain
    from simgen.sim import SimulationFailure

    body, garment, walk, squat = inputs
    pool = SimulationPool(garment, body, 1, CFG, fps=30.0)
    pool.submit(SimulationJob(walk, betas=[1.0, -0.5], frames=6), tag="long")
    pool.submit(SimulationJob(squat, betas=[-1.0], frames=2), tag="short")
    seen = []

    def gate(tag, k, row):
        seen.append((tag, k, row["strain_max"]))
        # Away from body self-intersections (none here: every triangle counts) the stretch is the same.
        assert row["self_intersection_count"] > 0 or row["strain_max_regular"] == row["strain_max"]
        assert row["strain_max_regular"] <= row["strain_max"]
        return "past the limit" if (tag, k) == ("long", 2) else None

    pool.gate = gate
    ended = {}
    while pool.busy or pool.queued:
        ended.update({tag: (res, pool.frames_run) for tag, res in pool.step()})
    protocol = CFG.relax_frames + CFG.ramp_frames + CFG.rest_frames
    fail = ended["long"][0]
    assert isinstance(fail, SimulationFailure)
    assert (fail.phase, fail.frame, fail.message) == ("animate", 2, "past the limit")
    assert ended["long"][1] == protocol + 2 and ended["short"][1] == 2 * protocol + 3   # frames 3-5 never stepped
    assert [(t, k) for t, k, _ in seen] == [("long", 0), ("long", 1), ("long", 2), ("short", 0), ("short", 1)]
    res = ended["short"][0]
    assert np.abs(res.positions - alone["short"].positions).max() < 1e-4
    rest_inv = triangle_rest_inverse(garment.vertices, garment.faces)
    for ref, got in ((alone["long"].positions[:3], [s for t, _, s in seen if t == "long"]),
                     (res.positions, res.stats["strain_max"])):
        want = triangle_strain(ref, garment.faces, rest_inv).max(axis=1)
        np.testing.assert_allclose(got, want, atol=2e-4)
    assert np.ptp(want) > 1e-3      # frames that differ, so the comparison tells them apart


def test_accept_refuses_jobs_and_abandon_stops_them(inputs):
    body, garment, walk, squat = inputs
    pool = SimulationPool(garment, body, 1, CFG, fps=30.0)
    for tag in ("a", "b", "c"):
        pool.submit(SimulationJob(squat, frames=2), tag=tag)
    asked = []
    pool.accept = lambda tag, frames: asked.append((tag, frames)) or tag != "b"
    assert pool.step() == [] and pool.busy == 1 and pool.queued == 2
    assert pool.abandon() == ["a"] and pool.busy == 0
    out = [tag for _ in range(20) for tag, _ in pool.step()]
    protocol = CFG.relax_frames + CFG.ramp_frames + CFG.rest_frames
    # "b" is refused when the slot frees up; "c" then runs whole in the slot "a" left.
    assert asked == [(t, protocol + 1) for t in "abc"] and pool.refused == ["b"] and out == ["c"]
    assert pool.busy == pool.queued == 0


def test_a_job_dropped_before_its_first_frame_leaves_its_slot_idle(inputs):
    """fill() places a job; abandon() before any frame: the slot never starts (all its vertices
    pinned, no body) and later frames leave it where it is."""
    body, garment, walk, squat = inputs
    pool = SimulationPool(garment, body, 2, CFG, fps=30.0)
    pool.submit(SimulationJob(squat, frames=2), tag="a")
    pool.submit(SimulationJob(squat, frames=2), tag="b")
    pool.fill()
    assert pool.abandon() == ["a", "b"]
    pool.submit(SimulationJob(squat, frames=2), tag="c")
    x0 = pool.setup.state.positions.numpy().copy()
    pool.step()
    starts = np.asarray(pool.setup.model.vertex_start)
    pinned, ids = pool.setup.model.vertex_pinned.numpy(), pool.setup.collider.mesh_ids.numpy()
    assert pool.busy == 1 and pinned[starts[1]:starts[2]].all() and ids[1] == 0
    np.testing.assert_array_equal(pool.setup.state.positions.numpy()[starts[1]:starts[2]], x0[starts[1]:starts[2]])


def test_pool_input_errors(inputs):
    body, garment, walk, squat = inputs
    from simgen.motion.ops import resample

    with pytest.raises(InputError, match="slots >= 1"):
        SimulationPool(garment, body, 0, CFG, fps=30.0)
    with pytest.raises(InputError, match="frame rate"):
        SimulationPool(garment, body, 1, CFG)
    pool = SimulationPool(garment, body, 1, CFG, fps=30.0)
    with pytest.raises(InputError, match="60 fps"):
        pool.submit(SimulationJob(resample(squat, 60.0)))
    with pytest.raises(InputError, match="no slot"):
        pool.submit(SimulationJob(squat, material="denim"))
    with pytest.raises(InputError, match="frames must be"):
        pool.submit(SimulationJob(squat, frames=0))
    with pytest.raises(InputError, match="power of two"):
        pool.submit(SimulationJob(squat, substeps_factor=3))
    assert pool.queued == 0 and pool.step() == []
