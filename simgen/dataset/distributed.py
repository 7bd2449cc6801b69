"""Ray execution of dataset generation (``simgen dataset generate --ray ADDRESS|local``).

The first jobs (:mod:`simgen.dataset.generate`) are dealt into one task per GPU (or per CPU),
and each retry that the driver runs starts as soon as its failure is known (the task reports it at
once, before it returns): on a free GPU, or else beside a running pool, in the share of a GPU that
the pool tasks leave free (``BESIDE_GPU_SHARE``, Ray's fractional GPUs), as long as fewer retry
pools run beside than there are GPUs (else it waits). Each task runs
:func:`simgen.dataset.execute.run_pool_task` in a Ray worker: one simulation pool on its own device
(Ray's GPU resource), kept full until its jobs run out, writing each node straight into the store
as its job ends; it returns the outcomes, and the driver alone rewrites the manifest. Two small
actors sit on the driver's node: the round's :class:`simgen.dataset.execute.JobFeed` (the pools
take their jobs from it as slots free up) and a meter to which every task reports its
cloth-frames every few seconds (the driver's progress) and each failed job as it fails. The store
must be reachable from every worker under the same name: a local folder for ``--ray local`` or a
single machine, a shared filesystem or an fsspec URL (s3://, gs://, ...) for a cluster.

Failures: a task that raises (a worker lost, a transient write error) is retried by Ray up to
``max_retries`` times; a retry re-simulates only the jobs whose node is not committed yet (nodes
are first-writer-wins, so a retry never duplicates one), and what it says about a job that the
earlier run had handed to the driver does not count (:class:`_Delivered`). A diverged instance is
not an exception: it comes back as a failed outcome, run again in its pool or by the driver (see
:mod:`simgen.dataset.generate`).

Ray is optional (``pip install 'simgen[distributed]'``) and imported only here, on first use.
"""

from __future__ import annotations

import os

from simgen.errors import GenerationError, InputError

__all__ = ["RayExecutor", "MAX_TASK_RETRIES"]

MAX_TASK_RETRIES = 2
#: Share of a GPU's Ray resource that a pool started beside another takes (a retry pool); a first
#: pool takes the rest, so that no GPU runs two first pools. The driver starts at most one retry
#: pool beside per GPU; which GPU each lands on is Ray's choice.
BESIDE_GPU_SHARE = 0.25
#: [s] How often a running task reports its cloth-frames to the driver's meter, and the driver
#: shows them while it waits for a task to end.
PROGRESS_EVERY_S = 2.0


class _Meter:
    """Cloth-frames simulated so far by each running pool task, and each job that failed in one, in
    the order they failed (a Ray actor: the tasks report, the driver reads)."""

    def __init__(self) -> None:
        self.frames: dict = {}
        self.failed: list = []   # (task name, outcome) not read yet

    def report(self, name: str, frames: int) -> None:
        self.frames[name] = int(frames)

    def fail(self, name: str, outcome: dict) -> None:
        self.failed.append((name, outcome))

    def poll(self, names: list) -> tuple[int, list]:
        """(cloth-frames of the tasks ``names``, the failures reported since the last poll)."""
        failed, self.failed = self.failed, []
        return sum(self.frames.get(n, 0) for n in names), failed


def _for_driver(outcome: dict) -> bool:
    """A failed job that its own pool does not run again: the driver retries it (or gives up)."""
    return not outcome["ok"] and not outcome.get("waiting") and outcome.get("retry") != "pool"


class _Delivered:
    """What the driver has heard from each running task. A failed outcome comes twice, from the
    meter as it happens and in the task's result, and counts once; and once a task has handed a
    job to the driver (:func:`_for_driver`: the next attempt is the driver's to run), nothing more
    from that task about the job counts: a run of the task that Ray started again after its worker
    died simulates it again. Keys hold the store and the task name (the job ids of the garments of
    one run repeat)."""

    def __init__(self) -> None:
        self.failures: set = set()   # (location, task name, kind, id, attempt)
        self.handed: set = set()     # (location, task name, kind, id)

    def first(self, task, o: dict) -> bool:
        """Whether outcome ``o`` of ``task`` is news to the driver (noted if so)."""
        job = (task.location, task.name, o["kind"], o["id"])
        if job in self.handed or (not o["ok"] and job + (o["attempt"],) in self.failures):
            return False
        if not o["ok"]:
            self.failures.add(job + (o["attempt"],))
        if _for_driver(o):
            self.handed.add(job)
        return True


def _run_pool_task(task, deadline, meter, every: float):
    # Runs in a Ray worker: quiet Warp, then the same function as local execution, reporting its
    # cloth-frames to the meter every ``every`` seconds (the driver's PROGRESS_EVERY_S) and each
    # failed job as it fails (without waiting for the actor). The deadline is a wall-clock time
    # fixed by the driver, so a task that waits for a GPU or is retried keeps it.
    import time

    import ray

    from simgen._warp_log import quiet_warp
    from simgen.dataset.execute import run_pool_task

    quiet_warp()
    last = [time.monotonic()]

    def progress(frames: int) -> None:
        now = time.monotonic()
        if now - last[0] >= every:
            last[0] = now
            meter.report.remote(task.name, frames)

    def failed(o: dict) -> None:
        # Every failure at once and in order (a retry in this pool too, so that the driver knows the
        # attempt of the next): the driver starts the retries it runs on the first free GPU.
        if not o["ok"] and not o.get("waiting"):
            meter.fail.remote(task.name, o)

    result = run_pool_task(task, deadline=deadline, progress=progress, on_outcome=failed)
    ctx = ray.get_runtime_context()
    result["worker"] = {"node": ctx.get_node_id()[:12], "pid": os.getpid(),
                        "gpus": [str(g) for g in ctx.get_accelerator_ids().get("GPU", [])]}
    return result


class _FeedProxy:
    """A :class:`simgen.dataset.execute.JobFeed` actor as the pool task sees a feed (blocking calls)."""

    def __init__(self, actor) -> None:
        self.actor = actor

    def start(self, name: str) -> None:
        import ray

        ray.get(self.actor.start.remote(name))

    def take(self, name: str, n: int) -> list:
        import ray

        return ray.get(self.actor.take.remote(name, n))

    def share_left(self, protocol_frames: int) -> float:
        import ray

        return ray.get(self.actor.share_left.remote(protocol_frames))

    def rest(self, name: str) -> list:
        import ray

        return ray.get(self.actor.rest.remote(name))


class RayExecutor:
    """Runs pool tasks as Ray tasks, one per GPU (or per CPU) at a time, and on GPUs one more beside
    each: the driver starts at most ``parallel`` and ``beside`` and asks for the next to end."""

    def __init__(self, address: str, spec) -> None:
        try:
            import ray
        except ImportError:
            raise InputError("--ray needs Ray: pip install 'simgen[distributed]' (or 'ray>=2.30')") from None
        self.ray = ray
        self._owns = not ray.is_initialized()
        if self._owns:
            kwargs = dict(include_dashboard=False, log_to_driver=False, configure_logging=False)
            # Workers must import this simgen: a source checkout is not on their path by default.
            import simgen

            src = os.path.dirname(os.path.dirname(os.path.abspath(simgen.__file__)))
            env_vars = {k: v for k, v in os.environ.items() if k.startswith("SIMGEN_")}  # SIMGEN_HOME: user assets
            env_vars["PYTHONPATH"] = os.pathsep.join(filter(None, [src, os.environ.get("PYTHONPATH")]))
            env = {"env_vars": env_vars}
            try:
                if address == "local":
                    ray.init(runtime_env=env, **kwargs)
                else:
                    ray.init(address=address, runtime_env=env, **kwargs)
            except (ConnectionError, RuntimeError, ValueError) as exc:
                raise InputError(f"--ray {address}: could not connect to a Ray cluster ({exc})") from None
        resources = ray.cluster_resources()
        gpus = int(resources.get("GPU", 0))
        cpus = max(int(resources.get("CPU", 1)), 1)
        if gpus > 0:
            self.parallel, self.beside, self.device = gpus, gpus, "cuda:0"
            opts = {"num_gpus": 1 - BESIDE_GPU_SHARE, "num_cpus": 1}
        else:
            self.parallel, self.beside, self.device, opts = cpus, 0, "cpu", {"num_cpus": 1}
        self._remote = ray.remote(max_retries=MAX_TASK_RETRIES, retry_exceptions=True, **opts)(_run_pool_task)
        self._remote_beside = self._remote.options(num_gpus=BESIDE_GPU_SHARE) if gpus > 0 else None
        self._meter = ray.remote(num_cpus=0)(_Meter).options(scheduling_strategy=self._here()).remote()
        self._pending: dict = {}   # ObjectRef -> (task, on_outcome, progress)
        self._delivered = _Delivered()

    def _here(self):
        # On the driver's node: a node that the autoscaler retires would take the actor with it.
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        return NodeAffinitySchedulingStrategy(self.ray.get_runtime_context().get_node_id(), soft=True)

    def start(self, tasks, budget_s, on_outcome, progress, beside: bool = False) -> list:
        """Submit the pool tasks of one round, each a Ray task on a GPU (or a CPU) of its own
        (``beside``: in the share of a GPU that another pool leaves free), sharing one
        :class:`JobFeed` actor when there are several (a pool that ends early takes the others'
        jobs); their handles. on_outcome(outcome) for each job, in :meth:`next`: a failure as soon
        as the meter has it, the rest once its task has ended; progress(cloth_frames of the running
        tasks) while :meth:`next` waits."""
        import time
        from dataclasses import replace

        from simgen.dataset.execute import JobFeed

        deadline = None if budget_s is None else time.time() + budget_s
        if len(tasks) > 1:
            actor = self.ray.remote(num_cpus=0)(JobFeed).options(scheduling_strategy=self._here()).remote(
                {t.name: t.jobs for t in tasks})
            tasks = [replace(t, feed=_FeedProxy(actor)) for t in tasks]
        remote = self._remote_beside if beside else self._remote
        refs = []
        for task in tasks:
            ref = remote.remote(task, deadline, self._meter, PROGRESS_EVERY_S)
            self._pending[ref] = (task, on_outcome, progress)
            refs.append(ref)
        return refs

    def next(self):
        """(handle, result) of the next task to end, its outcomes handed to its on_outcome first
        (those the driver has not had yet: :class:`_Delivered`); while none has ended, the running
        tasks' cloth-frames go to progress every few seconds, and (None, None) comes back as soon
        as the meter has new failures of theirs (handed to on_outcome), so that the driver can
        start their retries at once (on a free worker or beside a busy one)."""
        ray = self.ray
        while True:
            ready, _ = ray.wait(list(self._pending), num_returns=1, timeout=PROGRESS_EVERY_S)
            if ready:
                break
            by_name = {entry[0].name: entry for entry in self._pending.values()}
            frames, failed = ray.get(self._meter.poll.remote(list(by_name)))
            next(iter(by_name.values()))[2](frames)
            early = [(by_name[name], o) for name, o in failed
                     if name in by_name and self._delivered.first(by_name[name][0], o)]
            for (_, on_outcome, _), o in early:
                on_outcome(o)
            if early:
                return None, None
        task, on_outcome, _ = self._pending.pop(ready[0])
        result = self._get(ready[0], task)
        for o in result["outcomes"]:
            if self._delivered.first(task, o):
                on_outcome(o)
        return ready[0], result

    def _get(self, ref, task) -> dict:
        ray = self.ray
        try:
            return ray.get(ref)
        except ray.exceptions.RayTaskError as exc:
            cause = exc.cause if getattr(exc, "cause", None) is not None else exc
            if isinstance(cause, InputError):
                raise cause from None
            first = task.jobs[0].id if task.jobs else "?"
            raise GenerationError(f"a Ray task (pool starting with {first!r}, {len(task.jobs)} jobs) failed after "
                                  f"{MAX_TASK_RETRIES} retries: {type(cause).__name__}: {cause}; the store is "
                                  f"consistent, rerun to resume") from None
        except ray.exceptions.RayError as exc:
            raise GenerationError(f"Ray lost a task ({type(exc).__name__}: {exc}); the store is consistent, rerun to "
                                  f"resume") from None

    def close(self) -> None:
        if self._owns and self.ray.is_initialized():
            self.ray.shutdown()
