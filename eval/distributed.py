"""`denoise-gs eval` and `denoise-gs cost` on a Ray cluster: one Ray task per run, a task graph, one driver.

The unit of work is the serial path's own: `eval.evaluate.run_task(EvalTask)` for one (scene, method,
seed) run, or one cost-sweep point. `RayExecutor.run` submits every unit as a Ray task and returns
the results in the order of its input list, whatever order they finish in, so the rows, `results.json`
and `results.md` are the serial run's.

The task graph: units that write the same pipeline folder (methods of one family and seed, e.g.
`n2v_round1` then `denoise_gs`, and the ablations that link its round 1) form a chain: each waits for
the one before it (`chain_after`), so a shared stage is computed once, by the first, and the next
finds it in the stage cache; chains run in parallel. A unit that only reads a folder an earlier unit
ran (a ground-truth-pose variant reads its method's run and the clean photos' alignment points) waits
for that writer but not for the other readers, so the variants run side by side. The output lock of
each run folder (`eval.pipeline.lock`) stays the safety net for the writers: a second one is refused,
never interleaved. The readers take it in turn (`output_lock(wait=True)`): each holds it for the
seconds it takes to find the folder's stages complete, or, where the run it reads failed, to run the
failed stage again.

Order: given each unit's expected cost, the units are submitted longest remaining chain first
(`submission_order`: a unit's cost plus the costliest chain of units that wait for it), so the long runs
start first and the short ones fill in at the end, instead of a long run starting last beside an idle
worker. Ray starts ready tasks of one kind in the order they were submitted; the results still come
back in the input order.

Threads: each task gets `cpus_per_task` CPUs from Ray (1 by default) and runs with as many torch,
compositor, BLAS and OpenCV threads (`mvgeo.common.threads`), so N tasks on N CPUs do not
oversubscribe the cores; `ClusterSettings.task_threads` overrides the count. The denoiser runs every
torch operation on one thread and spreads fixed-size pieces (a batch's chunks, an image's passes) over
the task's threads (`denoise.parallel`), because a thread count inside an operation would change its
bits: so a task's scores are the serial run's. The workers get `OMP_WAIT_POLICY`
(docs/conventions.md, "Threads").

Code: the workers must run the driver's code. A Ray worker imports what its setup hook needs (`eval`,
`mvgeo`) before Ray puts the driver's working folder first on its `sys.path`, and everything else
after: by default the first from wherever a bare interpreter finds them (the installed or editable
copy), the rest from the driver's working folder. A run started from a folder other than the
installed checkout thus mixed two versions of the code, and its scores differed from the serial
run's. The workers therefore import the project's packages from the folders the driver imports them
from: `PYTHONPATH` puts those first from the start (`worker_env`), the setup hook then keeps them
first whatever Ray adds (`_ProjectFinder`), and every task checks the source digests of the
project's packages against the driver's before it runs (`_check_code`), so a node with other code
at that path fails its task instead of returning other scores.

Storage: the out folder must be at the same path on every node (docs/cluster.md); a task reads its
inputs from it and writes its run folder there, so it is the only state the tasks share.

Ray is imported only when a cluster is used: the serial path (`--workers 1`) never loads it.
"""

from __future__ import annotations

import contextlib
import importlib.abc
import importlib.machinery
import importlib.util
import logging
import os
import re
import shutil
import socket
import sys
import tempfile
from collections.abc import Callable, Hashable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from mvgeo.common.errors import InputError
from mvgeo.common.progress import progress_bar

__all__ = ["PROJECT_PACKAGES", "ClusterSettings", "RayExecutor", "chain_after", "check_ray_address", "project_code",
           "project_roots", "ray_cluster", "submission_order", "warm_slots", "worker_env"]

_log = logging.getLogger(__name__)

#: Object store of a local cluster: the tasks exchange only their small result rows.
LOCAL_OBJECT_STORE_BYTES = 256 * 1024**2

#: Seconds to wait for a TCP connection to `--ray-address` before refusing it.
ADDRESS_TIMEOUT_S = 3.0

#: The project's top-level packages (pyproject.toml): a task imports each from the driver's source.
PROJECT_PACKAGES = ("data_synth", "denoise", "eval", "mvgeo", "splat")


@dataclass(frozen=True)
class ClusterSettings:
    """Where the tasks run.

    Attributes:
        workers: tasks at once on a local cluster started for the run (`ray.init(num_cpus=workers)`);
            1 with no `address` is the serial path (no Ray).
        address: an existing cluster's address (`host:port` of its head, or "auto" for the cluster
            `ray start` left on this machine); then the cluster's CPUs set how many tasks run at once.
        cpus_per_task: CPUs Ray reserves for each task.
        gpus_per_task: GPUs Ray reserves for each task (a fraction shares one; 0: none).
        task_threads: torch, compositor, BLAS and OpenCV threads of each task; None: the CPUs Ray gave
            it, so that tasks do not oversubscribe the cores. The denoiser spreads fixed-size pieces over
            them, one torch thread each (`denoise.parallel`): its result does not depend on the count,
            nor do the other stages'.
    """

    workers: int = 1
    address: str | None = None
    cpus_per_task: int = 1
    gpus_per_task: float = 0.0
    task_threads: int | None = None

    def __post_init__(self) -> None:
        if self.workers < 1:
            raise InputError(f"--workers must be at least 1, got {self.workers}")
        if self.cpus_per_task < 1:
            raise InputError(f"cpus_per_task must be at least 1, got {self.cpus_per_task}")
        if self.task_threads is not None and self.task_threads < 1:
            raise InputError(f"--task-threads must be at least 1, got {self.task_threads}")
        if self.task_threads is not None and not self.distributed:
            raise InputError("--task-threads applies to runs on Ray", fix="add --workers N (N > 1) or --ray-address")
        if self.gpus_per_task < 0:
            raise InputError(f"gpus_per_task must be >= 0, got {self.gpus_per_task}")
        if self.address is not None and self.workers > 1:
            raise InputError("--workers and --ray-address are alternatives",
                             fix="--workers N starts a local cluster of N CPUs; with --ray-address the cluster's "
                                 "CPUs decide how many tasks run at once")

    @property
    def distributed(self) -> bool:
        """True when the tasks go to Ray (a local cluster or `address`)."""
        return self.workers > 1 or self.address is not None


_HOST_PORT = re.compile(r"^(?P<host>\[[0-9a-fA-F:]+\]|[A-Za-z0-9.\-]+):(?P<port>\d{1,5})$")


def check_ray_address(address: str) -> None:
    """Refuse an address Ray cannot use here, before anything is written or started.

    "auto" is left to `ray.init` (it finds the cluster `ray start` left on this machine). A
    `host:port` must accept a TCP connection within `ADDRESS_TIMEOUT_S` (the head's GCS port,
    6379 by default).

    Raises:
        InputError: a Ray Client address (`ray://`, which needs `ray[client]`), a malformed
            address, or one that does not answer.
    """
    if address == "auto":
        return
    if address.startswith("ray://"):
        raise InputError(f"--ray-address {address}: Ray Client addresses need the `ray[client]` extra, "
                         "which this environment does not install",
                         fix="give the head's GCS address host:port (6379 by default, as `ray start --head` "
                             "prints) and run this command on a node of the cluster")
    m = _HOST_PORT.match(address)
    if m is None or not 0 < int(m["port"]) < 65536:
        raise InputError(f"--ray-address {address!r} is not host:port", fix="e.g. --ray-address 10.0.0.5:6379, "
                                                                           "or auto")
    host = m["host"].strip("[]")
    try:
        socket.create_connection((host, int(m["port"])), timeout=ADDRESS_TIMEOUT_S).close()
    except OSError as exc:
        raise InputError(f"--ray-address {address}: no Ray head answers there ({exc.strerror or exc})",
                         fix="start the head with `ray start --head` and give the address it prints") from None


def chain_after(keys: Sequence[Sequence[Hashable]],
                reads: Sequence[Sequence[Hashable]] | None = None) -> list[tuple[int, ...]]:
    """The task graph of units that share state by key, as readers and writers.

    A unit waits for the last earlier writer of every key it writes or reads; a writer also waits for
    every unit that read one of its keys since that key's last writer. Readers of a key between two
    writers do not wait for each other: they run side by side.

    Args:
        keys: per unit, in the serial order, the keys it writes (units with a common key write the same
            folder).
        reads: per unit, the keys it only reads (None: no unit only reads). A key a unit both writes and
            reads counts as written.

    Returns:
        For each unit, the indices of the earlier units it must wait for (sorted, possibly empty).
    """
    reads = [()] * len(keys) if reads is None else reads
    if len(reads) != len(keys):
        raise ValueError(f"reads has {len(reads)} entries for {len(keys)} units")
    writer: dict[Hashable, int] = {}
    readers: dict[Hashable, list[int]] = {}
    after = []
    for i, (w, r) in enumerate(zip(keys, reads, strict=True)):
        written = set(w)
        only_read = [x for x in r if x not in written]
        deps = {writer[x] for x in (*w, *only_read) if x in writer}
        deps.update(j for x in w for j in readers.get(x, ()))
        after.append(tuple(sorted(deps)))
        for x in w:
            writer[x], readers[x] = i, []
        for x in only_read:
            readers.setdefault(x, []).append(i)
    return after


def submission_order(after: Sequence[Sequence[int]], cost: Sequence[float]) -> list[int]:
    """The units in the order to submit them: highest level first, the list-scheduling rule for a task
    graph on a few workers.

    A unit's level is its cost plus the largest level among the units that wait for it (the remaining
    chain it starts). Units are taken by decreasing level, ties in the serial order. With positive costs a
    unit's level exceeds every waiting unit's, so each unit comes after the units it waits for.

    Args:
        after: for each unit, the indices of earlier units it waits for (`chain_after`).
        cost: for each unit, its expected cost (> 0, any unit, e.g. seconds).

    Returns:
        A permutation of `range(len(after))`.
    """
    n = len(after)
    if len(cost) != n:
        raise ValueError(f"cost has {len(cost)} entries for {n} units")
    if any(not (c > 0) for c in cost):  # also refuses NaN
        raise ValueError(f"costs must be positive, got {list(cost)}")
    level = [float(c) for c in cost]
    for i in range(n - 1, -1, -1):  # the units waiting for i come after it in the serial order
        for d in after[i]:
            if not 0 <= d < i:
                raise ValueError(f"unit {i} waits for {d}: only earlier units are allowed (the serial order)")
            level[d] = max(level[d], float(cost[d]) + level[i])
    return sorted(range(n), key=lambda i: (-level[i], i))


def _task_threads() -> int:
    """The CPUs Ray gave this task (at least 1)."""
    import ray

    cpus = ray.get_runtime_context().get_assigned_resources().get("CPU", 1.0)
    return max(1, int(cpus))


def _warm_worker(modules: Sequence[str], code: Mapping[str, str]) -> int:
    """A worker's first task, submitted as the cluster starts (`RayExecutor.start_workers`): the worker
    process starts and imports `modules` (and computes the project's source digests `_check_code` compares)
    while the driver prepares the runs; returns its process id."""
    for name in modules:
        importlib.import_module(name)
    _check_code(code)
    return os.getpid()


def _run_unit(fn: Callable[[Any], Any], item: Any, threads: int | None, code: Mapping[str, str], *after: Any
              ) -> Any:
    """One Ray task: `fn(item)` with `threads` threads (None: the task's CPUs), after checking that the
    worker imports the driver's `code` (`_check_code`). `after` (the results of the units it waits for)
    only orders it in the graph."""
    from mvgeo.common.threads import native_threads, torch_threads

    _check_code(code)
    threads = threads or _task_threads()
    with torch_threads(threads), native_threads(threads):
        return fn(item)


#: Loggers whose levels the workers copy from the driver (`mvgeo.common.log.setup_logging` sets them).
_LOGGERS = ("", "mvgeo", "splat", "denoise", "eval", "data_synth")


def _driver_logging() -> tuple[dict[str, int], str, str | None]:
    """The driver's log levels and its console format, to apply in the workers."""
    levels = {name: logging.getLogger(name).level for name in _LOGGERS}
    fmt, datefmt = "%(levelname).1s %(name)s: %(message)s", None
    for handler in logging.getLogger().handlers:
        if handler.formatter is not None and handler.formatter._fmt:
            fmt, datefmt = handler.formatter._fmt, handler.formatter.datefmt
            break
    return levels, fmt, datefmt


def _package_parent(name: str) -> str | None:
    """The folder this process imports the package `name` from (its package folder's parent), found
    without importing it; None when it has no package folder."""
    module = sys.modules.get(name)
    folders = getattr(module, "__path__", None) if module is not None else None
    if folders is None:
        try:
            spec = importlib.util.find_spec(name)
        except (ImportError, ValueError):
            spec = None
        folders = spec.submodule_search_locations if spec is not None else None
    if not folders:
        return None
    return os.path.dirname(os.path.abspath(next(iter(folders))))


def project_roots() -> list[str]:
    """The folders this process imports the project's packages (`PROJECT_PACKAGES`) from, unique, in order."""
    return list(dict.fromkeys(p for p in map(_package_parent, PROJECT_PACKAGES) if p is not None))


def project_code() -> dict[str, str]:
    """Package name -> source digest (`eval.pipeline.hashing.source_digest`, cached per process) of
    every project package this process can import: what `_check_code` compares in each task."""
    from eval.pipeline.hashing import source_digest

    return {name: source_digest(name) for name in PROJECT_PACKAGES if _package_parent(name) is not None}


def _check_code(driver: Mapping[str, str]) -> None:
    """Raise `InputError` when this process's project packages differ from the driver's digests `driver`.

    Why: a worker that imports another checkout (or a node with other code at the checkout's path)
    would return other code's scores under the driver's run, with nothing in the results to show it.
    """
    mine = project_code()
    differ = sorted(n for n, digest in driver.items() if mine.get(n) != digest)
    if differ:
        where = ", ".join(f"{n} from {_package_parent(n) or 'nowhere'}" for n in differ)
        raise InputError(f"the Ray worker on {socket.gethostname()} imports other code than the driver: {where}",
                         fix="run the same checkout at the same path on every node (docs/cluster.md)")


def worker_env() -> dict[str, str]:
    """Environment variables of the Ray workers.

    `PYTHONPATH`: `project_roots()`, then this process's own `PYTHONPATH`, so that what a worker
    imports before its setup hook runs is the driver's code (module docstring, "Code"); on a
    multi-node cluster the checkout is at the same path on every node (docs/cluster.md).
    `OMP_WAIT_POLICY` (this process's, else PASSIVE), no progress bars, no usage statistics.
    """
    inherited = [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    return {"OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE"), "DGS_NO_PROGRESS": "1",
            "RAY_USAGE_STATS_ENABLED": "0",
            "PYTHONPATH": os.pathsep.join(dict.fromkeys([*project_roots(), *inherited]))}


class _ProjectFinder(importlib.abc.MetaPathFinder):
    """Finds the project's top-level packages in `roots` only (their submodules follow the package).

    Ray puts the driver's working folder in front of a worker's `sys.path` after the setup hook; a
    checkout there would otherwise shadow the driver's packages not yet imported (module docstring).
    """

    def __init__(self, roots: Sequence[str]):
        self.roots = list(roots)

    def find_spec(self, name: str, path: Sequence[str] | None = None, target: object = None
                  ) -> importlib.machinery.ModuleSpec | None:
        if path is not None or name not in PROJECT_PACKAGES:
            return None
        return importlib.machinery.PathFinder.find_spec(name, self.roots)


def _import_project_from(roots: Sequence[str]) -> None:
    """Make this process import the project's top-level packages from `roots` (a `_ProjectFinder`
    first on `sys.meta_path`, replacing an earlier one)."""
    sys.meta_path[:] = [f for f in sys.meta_path if not isinstance(f, _ProjectFinder)]
    if roots:
        sys.meta_path.insert(0, _ProjectFinder(roots))


def _setup_worker(driver_logging: tuple[dict[str, int], str, str | None],
                  worker_setup: Callable[[], None] | None, roots: Sequence[str] = ()) -> None:
    """Run once in every Ray worker process before its first task: the project's packages from the
    driver's folders `roots` (`_import_project_from`), the driver's log levels and format (the runs'
    messages reach the console, through Ray, as in the serial path), then `worker_setup`."""
    _import_project_from(roots)
    levels, fmt, datefmt = driver_logging
    handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter(fmt, datefmt))
    logging.getLogger().handlers[:] = [handler]
    for name, level in levels.items():
        logging.getLogger(name).setLevel(level)
    if worker_setup is not None:
        worker_setup()


class RayExecutor:
    """Runs units of work as Ray tasks on the connected cluster (see `ray_cluster`)."""

    def __init__(self, settings: ClusterSettings):
        self.settings = settings
        self._warming: list[Any] = []

    def start_workers(self, slots: int, modules: Sequence[str]) -> list[Any]:
        """Start `slots` worker processes now, each importing `modules`, without waiting for them.

        Ray starts a worker process when a task first needs one, and the first task then waits for the
        process to start and import torch and the project (docs/cluster.md, "One machine"). Submitted
        with the runs' own resources, these tasks start the workers while the driver still prepares the
        runs, and Ray reuses the same processes for the runs: the resources go through `.options()`, as
        the runs' do (a `num_gpus` given to `ray.remote` itself would make Ray start a fresh process for
        every GPU task). A warm-up that fails is not waited for: the run on that worker then fails with
        its own error. The refs are kept until the executor goes, so Ray does not report a failed
        warm-up as an unhandled error while the cluster runs.

        Returns:
            The warm-up tasks' object refs; each gives its worker's process id.
        """
        import ray

        if slots < 1:
            return []
        remote = ray.remote(_warm_worker).options(num_cpus=self.settings.cpus_per_task,
                                                  num_gpus=self.settings.gpus_per_task, max_retries=0)
        code = project_code()
        self._warming = [remote.remote(tuple(modules), code) for _ in range(slots)]
        return list(self._warming)

    def run(self, fn: Callable[[Any], Any], items: Sequence[Any], *, after: Sequence[Sequence[int]] | None = None,
            cost: Sequence[float] | None = None, desc: str = "tasks",
            on_done: Callable[[Mapping[int, Any]], None] | None = None) -> list[Any]:
        """`[fn(item) for item in items]`, each call a Ray task, run in parallel as the graph allows.

        Args:
            fn: a picklable function (module level) of one item.
            items: the units, in the serial order.
            after: for each unit, the indices of earlier units it must wait for (default none).
            cost: for each unit, its expected cost (> 0): submitted in `submission_order`. None: in the
                input order.
            desc: the progress bar's label (a bar over finished tasks; `DGS_NO_PROGRESS=1` hides it).
            on_done: called after each finished task with index -> result of every finished task.

        Returns:
            The results in the order of `items`.

        Raises:
            The first exception a task raised, as its own type; the tasks not yet finished are cancelled.
        """
        import ray

        after = [()] * len(items) if after is None else [tuple(a) for a in after]
        if len(after) != len(items):
            raise ValueError(f"after has {len(after)} entries for {len(items)} items")
        for i, deps in enumerate(after):
            if any(not 0 <= d < i for d in deps):
                raise ValueError(f"unit {i} waits for {deps}: only earlier units are allowed (the serial order)")
        order = list(range(len(items))) if cost is None else submission_order(after, cost)
        remote = ray.remote(_run_unit).options(num_cpus=self.settings.cpus_per_task,
                                               num_gpus=self.settings.gpus_per_task, max_retries=0)
        fn_ref = ray.put(fn)
        code = project_code()
        refs: list[Any] = [None] * len(items)
        for i in order:  # a unit comes after the units it waits for: their refs exist
            refs[i] = remote.remote(fn_ref, items[i], self.settings.task_threads, code, *(refs[d] for d in after[i]))
        index = {ref: i for i, ref in enumerate(refs)}
        done: dict[int, Any] = {}
        pending = list(refs)
        with progress_bar(desc=desc, total=len(refs), unit="task") as bar:
            try:
                while pending:
                    ready, pending = ray.wait(pending, num_returns=1)
                    for ref in ready:
                        done[index[ref]] = _get(ray, ref)
                        bar.update(1)
                    if on_done is not None:
                        on_done(dict(done))
            except BaseException:
                for ref in pending:
                    with contextlib.suppress(Exception):
                        ray.cancel(ref)
                raise
        return [done[i] for i in range(len(refs))]


def _get(ray: Any, ref: Any) -> Any:
    """`ray.get(ref)`, raising a failed task's own exception (a `RayTaskError` wraps it)."""
    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError as err:
        cause = getattr(err, "cause", None)
        if isinstance(cause, BaseException):
            raise cause from None
        raise


@contextlib.contextmanager
def ray_cluster(settings: ClusterSettings, *, worker_setup: Callable[[], None] | None = None,
                preload: Sequence[str] = (), tasks: int | None = None) -> Iterator[RayExecutor | None]:
    """Connect to Ray for the block: None for the serial path, else an executor on the cluster.

    - `settings.workers > 1`: starts a local cluster of that many CPUs (no dashboard, node address
      127.0.0.1, usage statistics off, its runtime files and logs in a temporary folder that is
      removed after the cluster has shut down at the end of the block);
    - `settings.address`: connects to that cluster (and leaves it running at the end);
    - a Ray already initialised in this process (a notebook, a test) is used as it is and left so.

    `worker_setup` runs once in every worker process before its first task (after the driver's log
    level is applied there). The workers import the project's packages from the folders this process
    imports them from (`worker_env`, `_setup_worker`; module docstring, "Code").

    `preload`: modules the tasks import (e.g. "eval.evaluate"). When it names any, one worker per task
    slot of the cluster (started, connected to or already initialised; `warm_slots`), and no more than
    `tasks` (the number of runs to come, when known), is started as soon as the cluster is up and
    imports them (`RayExecutor.start_workers`), so that the workers' start overlaps the driver's
    preparation.

    Raises:
        InputError: the cluster cannot be started or reached.
    """
    if not settings.distributed:
        yield None
        return
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # nothing leaves the machine
    os.environ.setdefault("RAY_DEDUP_LOGS", "0")  # every run's messages, as the serial path prints them
    if not sys.stderr.isatty():
        os.environ.setdefault("RAY_COLOR_PREFIX", "0")  # plain text in log files
    import ray

    if ray.is_initialized():
        yield _executor(ray, settings, preload, tasks)
        return
    if settings.address is not None:
        check_ray_address(settings.address)
    env = worker_env()
    driver_logging = _driver_logging()
    roots = project_roots()

    def setup_hook() -> None:  # a named function: Ray labels the hook with its __name__
        _setup_worker(driver_logging, worker_setup, roots)

    runtime_env = {"env_vars": env, "worker_process_setup_hook": setup_hook}
    kwargs: dict[str, Any] = {"include_dashboard": False, "runtime_env": runtime_env,
                              "logging_level": logging.WARNING, "log_to_driver": True}
    if settings.address is not None:
        with _connected(ray, {**kwargs, "address": settings.address}, settings, None, preload, tasks) as executor:
            yield executor
        return
    # Short path: Ray's Unix sockets live in it (at most 107 bytes). The workers run at the driver's niceness,
    # as the serial path's work does; Ray's own default (15) starves them beside any other work on the machine.
    # Ray adds `worker_niceness` to the niceness of its raylet, which inherits the driver's: 0 keeps it (the
    # driver's own niceness here would count it twice, e.g. 10 -> 19 under `nice -n 10`).
    temp_dir = tempfile.mkdtemp(prefix="dgs-ray-")
    kwargs.update(num_cpus=settings.workers, object_store_memory=LOCAL_OBJECT_STORE_BYTES, _temp_dir=temp_dir,
                  _system_config={"worker_niceness": 0})
    with _loopback_only(), _connected(ray, kwargs, settings, temp_dir, preload, tasks) as executor:
        yield executor


def warm_slots(resources: Mapping[str, float], settings: ClusterSettings, tasks: int | None = None) -> int:
    """How many tasks of `settings`' shape the cluster's `resources` (`ray.cluster_resources()`) run at
    once, limited by its CPUs and, for GPU tasks, its GPUs; at most `tasks` when given."""
    slots = int(resources.get("CPU", 0) // settings.cpus_per_task)
    if settings.gpus_per_task > 0:
        # 1e-9: a fraction 1/N of a GPU, N times, is the whole GPU despite rounding
        slots = min(slots, int(resources.get("GPU", 0) / settings.gpus_per_task + 1e-9))
    return max(0, slots if tasks is None else min(slots, tasks))


def _executor(ray: Any, settings: ClusterSettings, preload: Sequence[str], tasks: int | None) -> RayExecutor:
    """The executor on the connected cluster, its workers started now when `preload` names modules."""
    executor = RayExecutor(settings)
    if preload:
        executor.start_workers(warm_slots(ray.cluster_resources(), settings, tasks), preload)
    return executor


@contextlib.contextmanager
def _loopback_only() -> Iterator[None]:
    """Keep a local cluster on 127.0.0.1: Ray otherwise binds its services to the machine's outward
    address even for one node. Ray's switch for that (`ENABLE_RAY_CLUSTER`, from the environment
    variable below) is read when ray loads, and the cluster's processes inherit the variable."""
    from ray._private import ray_constants

    saved_env, saved = os.environ.get(_CLUSTER_VAR), ray_constants.ENABLE_RAY_CLUSTER
    os.environ[_CLUSTER_VAR] = "0"
    ray_constants.ENABLE_RAY_CLUSTER = False
    try:
        yield
    finally:
        ray_constants.ENABLE_RAY_CLUSTER = saved
        if saved_env is None:
            os.environ.pop(_CLUSTER_VAR, None)
        else:
            os.environ[_CLUSTER_VAR] = saved_env


_CLUSTER_VAR = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


@contextlib.contextmanager
def _connected(ray: Any, kwargs: dict[str, Any], settings: ClusterSettings, temp_dir: str | None,
               preload: Sequence[str] = (), tasks: int | None = None) -> Iterator[RayExecutor]:
    """`ray.init(**kwargs)` for the block (with a worker per task slot started when `preload` names
    modules), then `ray.shutdown()` and `temp_dir` removed."""
    try:
        ray.init(**kwargs)
    except BaseException as exc:
        ray.shutdown()  # whatever it had started
        if temp_dir is not None:
            shutil.rmtree(temp_dir, ignore_errors=True)
        if not isinstance(exc, ConnectionError | ValueError):
            raise
        where = f"the Ray cluster at {settings.address}" if settings.address else "a local Ray cluster"
        raise InputError(f"cannot start or reach {where}: {exc}",
                         fix="check `ray status` on the head, or run with --workers 1") from None
    try:
        cpus = ray.cluster_resources().get("CPU", 0)
        _log.info("Ray: %g CPUs, %d per task", cpus, settings.cpus_per_task)
        if cpus < settings.cpus_per_task:
            raise InputError(f"the Ray cluster has {cpus:g} CPUs, fewer than one task needs "
                             f"({settings.cpus_per_task})", fix="join worker nodes, or use --workers")
        yield _executor(ray, settings, preload, tasks)
    finally:
        ray.shutdown()
        if temp_dir is not None:
            shutil.rmtree(temp_dir, ignore_errors=True)
