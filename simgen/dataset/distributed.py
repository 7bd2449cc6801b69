"""Ray execution of dataset batches (``simgen dataset generate --ray ADDRESS|local``).

Each batch becomes one Ray task that runs :func:`simgen.dataset.execute.run_batch`: it simulates
the batch (one GPU per task when the cluster has GPUs, else one CPU) and writes its nodes straight
into the store, then returns the outcomes; the driver alone rewrites the manifest. The store must
be reachable from every worker under the same name: a local folder for ``--ray local`` or a
single machine, a shared filesystem or an fsspec URL (s3://, gs://, ...) for a cluster.

Failures: a task that raises (a worker lost, a transient write error) is retried by Ray up to
``max_retries`` times; a retry re-simulates only the jobs whose node is not committed yet (nodes
are first-writer-wins, so a retry never duplicates one). A diverged instance is not an exception:
it comes back as a failed outcome and the driver re-queues it (see :mod:`simgen.dataset.generate`).

Ray is optional (``pip install 'simgen[distributed]'``) and imported only here, on first use.
"""

from __future__ import annotations

import os

from simgen.errors import GenerationError, InputError

__all__ = ["RayExecutor", "MAX_TASK_RETRIES"]

MAX_TASK_RETRIES = 2


def _run_batch_task(task):
    # Runs in a Ray worker: quiet Warp, then the same function as local execution.
    from simgen._warp_log import quiet_warp
    from simgen.dataset.execute import run_batch

    quiet_warp()

    return run_batch(task)


class RayExecutor:
    """Submits batches as Ray tasks; at most one task per GPU (or per CPU) in flight."""

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
            self.parallel, self.device, opts = gpus, "cuda:0", {"num_gpus": 1, "num_cpus": 1}
        else:
            self.parallel, self.device, opts = cpus, "cpu", {"num_cpus": 1}
        self._remote = ray.remote(max_retries=MAX_TASK_RETRIES, retry_exceptions=True, **opts)(_run_batch_task)
        self._pending: dict = {}

    def submit(self, task, progress=None) -> None:
        ref = self._remote.remote(task)
        self._pending[ref] = task

    def in_flight(self) -> int:
        return len(self._pending)

    def next_result(self):

        ray = self.ray
        ready, _ = ray.wait(list(self._pending), num_returns=1)
        ref = ready[0]
        task = self._pending.pop(ref)
        try:
            return task, ray.get(ref)
        except ray.exceptions.RayTaskError as exc:
            cause = exc.cause if getattr(exc, "cause", None) is not None else exc
            if isinstance(cause, InputError):
                raise cause from None
            first = task.jobs[0].id if task.jobs else "?"
            raise GenerationError(f"a Ray task (batch starting with {first!r}, {len(task.jobs)} jobs) failed after "
                                  f"{MAX_TASK_RETRIES} retries: {type(cause).__name__}: {cause}; the store is "
                                  f"consistent, rerun to resume") from None
        except ray.exceptions.RayError as exc:
            raise GenerationError(f"Ray lost a task ({type(exc).__name__}: {exc}); the store is consistent, rerun to "
                                  f"resume") from None

    def close(self) -> None:
        if self._owns and self.ray.is_initialized():
            self.ray.shutdown()
