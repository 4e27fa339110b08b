"""Where independent tasks run: on Dask (a ``LocalCluster`` here, or the cluster at a scheduler's
address), or one after another in this process when Dask is not installed or not wanted.

    with Engine(scheduler=None, workers=2) as engine:      # LocalCluster of 2 worker processes
        for index, result in engine.map(fn, items, desc="fleet", unit="file"):
            ...

Both ``python -m companion fleet`` and ``python -m simvehicle sweep`` use it. Dask is an optional
extra (``pip install 'flowhold[cluster]'``) and is imported only when a cluster is opened, so the
base install never needs it. A worker that dies loses only its task: the scheduler runs it again
once (``distributed.scheduler.allowed-failures`` = 1 on the ``LocalCluster`` we start); a second
death ends that task with ``TaskLost``, which ``map`` yields in place of its result. A progress
bar goes to stderr on a terminal only.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from companion.errors import UsageError

#: how a user gets the cluster mode
INSTALL_HINT = "pip install 'flowhold[cluster]'"
#: how long to wait for a first worker on a cluster that has none yet (s)
WAIT_FOR_WORKERS_S = 30.0
#: how many times a task is run again after its worker died (the LocalCluster's scheduler setting)
RETRIES_AFTER_WORKER_DEATH = 1


def have_dask() -> bool:
    """Whether ``dask.distributed`` can be imported (without importing it)."""
    return importlib.util.find_spec("distributed") is not None and importlib.util.find_spec("dask") is not None


class TaskLost(Exception):
    """A task whose worker died on every try (or that the cluster could not run)."""


class Engine:
    """Runs ``fn(item)`` for every item, in-process or on Dask; a context manager.

    ``scheduler``: address of a running Dask scheduler (``tcp://host:8786``); ``None`` starts a
    ``LocalCluster`` of ``workers`` single-threaded worker processes (default: all cores).
    ``in_process``: no Dask at all, one task after another here (also the mode when Dask is
    not installed and no scheduler is named; ``note`` then says how to get the cluster mode).
    """

    def __init__(self, *, scheduler: str | None = None, workers: int | None = None, in_process: bool = False,
                 progress: bool | None = None) -> None:
        if workers is not None and workers < 1:
            raise UsageError(f"--workers must be >= 1, got {workers}")
        if scheduler is not None and in_process:
            raise UsageError("--scheduler and --in-process exclude each other")
        if scheduler is not None and workers is not None:
            raise UsageError("--workers starts a LocalCluster; with --scheduler the cluster's own workers run "
                             "the tasks (start them with `dask worker ADDRESS`)")
        if scheduler is not None and not have_dask():
            raise UsageError(f"--scheduler needs Dask, which is not installed: {INSTALL_HINT}")
        self.scheduler = scheduler
        self.workers = workers or (os.cpu_count() or 1)
        self.dask = not in_process and (scheduler is not None or have_dask())
        self.note = "" if self.dask or in_process else (
            f"Dask is not installed: running in this process, one file after another "
            f"({INSTALL_HINT} for a LocalCluster on all cores, or --scheduler for a cluster)")
        self.progress = sys.stderr.isatty() if progress is None else progress
        #: the address of Dask's dashboard (needs bokeh), or why there is none
        self.dashboard: str | None = None
        self.dashboard_note = ""
        self.description = "in-process"
        self._client: Any = None
        self._cluster: Any = None
        self._config: Any = None

    # -- lifetime -------------------------------------------------------------------------------

    def __enter__(self) -> Engine:
        if not self.dask:
            return self
        import dask
        from distributed import Client, LocalCluster

        self._config = dask.config.set({"distributed.scheduler.allowed-failures": RETRIES_AFTER_WORKER_DEATH})
        self._config.__enter__()
        try:
            if self.scheduler is None:
                self._cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                                             host="127.0.0.1", dashboard_address="127.0.0.1:0")
                self._client = Client(self._cluster)
                self.description = f"Dask LocalCluster of {self.workers} worker(s)"
            else:
                try:
                    self._client = Client(self.scheduler, timeout=10)
                except (OSError, TimeoutError, ValueError) as exc:
                    raise UsageError(f"--scheduler {self.scheduler}: cannot reach the Dask scheduler ({exc})") \
                        from None
                if not self._client.nthreads():
                    try:
                        self._client.wait_for_workers(1, timeout=WAIT_FOR_WORKERS_S)
                    except TimeoutError:
                        raise UsageError(f"--scheduler {self.scheduler}: the cluster has no worker (waited "
                                         f"{WAIT_FOR_WORKERS_S:g} s); start them with `dask worker "
                                         f"{self.scheduler} --nthreads 1`") from None
                n = sum(self._client.nthreads().values())
                self.workers = max(n, 1)
                self.description = f"Dask cluster at {self.scheduler} ({n} worker thread(s))"
            if importlib.util.find_spec("bokeh") is not None:
                self.dashboard = self._client.dashboard_link or None
            else:
                self.dashboard_note = "Dask's dashboard needs bokeh: pip install 'bokeh>=3.1'"
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        for obj in (self._client, self._cluster):
            if obj is not None:
                try:
                    obj.close()
                except Exception:  # noqa: BLE001 - closing a cluster that is already gone
                    pass
        self._client = self._cluster = None
        if self._config is not None:
            self._config.__exit__(None, None, None)
            self._config = None

    @property
    def n_workers(self) -> int:
        """Worker processes (threads on a remote cluster); 1 in-process."""
        return self.workers if self.dask else 1

    # -- running --------------------------------------------------------------------------------

    def on_every_worker(self, fn: Callable[[], Any]) -> None:
        """Run ``fn()`` once on every worker now (here, in-process): imports and compilation a task
        would otherwise pay on its worker's first task. ``fn`` must be importable by the workers."""
        if self.dask:
            self._client.run(fn)
        else:
            fn()

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any], *, weights: Sequence[int] | None = None,
            desc: str = "tasks", unit: str = "task", names: Sequence[str] | None = None
            ) -> Iterator[tuple[int, Any]]:
        """``(index, fn(items[index]))`` as each task ends (in-process: in order). A task lost
        with its worker yields ``(index, TaskLost(...))``; any other exception of ``fn`` is raised.
        ``weights``: each task's share of the progress bar (e.g. flights per batch); ``names``:
        Dask key prefixes (what the dashboard shows)."""
        from tqdm import tqdm

        total = sum(weights) if weights is not None else len(items)
        bar = tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, disable=not self.progress, leave=False)
        try:
            if not self.dask:
                for i, item in enumerate(items):
                    yield i, fn(item)
                    bar.update(weights[i] if weights is not None else 1)
                return
            yield from self._map_dask(fn, items, weights, bar, names)
        finally:
            bar.close()

    def _map_dask(self, fn: Callable[[Any], Any], items: Sequence[Any], weights: Sequence[int] | None, bar: Any,
                  names: Sequence[str] | None) -> Iterator[tuple[int, Any]]:
        from distributed import as_completed
        from distributed.scheduler import KilledWorker

        client = self._client
        futures = []
        for i, item in enumerate(items):
            key = f"{names[i] if names is not None else getattr(fn, '__name__', 'task')}-{i}-{os.getpid()}-{id(items)}"
            futures.append(client.submit(fn, item, key=key, pure=False))
        index = {f.key: i for i, f in enumerate(futures)}
        try:
            for fut in as_completed(futures):
                i = index[fut.key]
                try:
                    result = fut.result()
                except KilledWorker as exc:
                    result = TaskLost(f"its worker died {RETRIES_AFTER_WORKER_DEATH + 1} times while running it "
                                      f"({exc.__class__.__name__})")
                except (OSError, TimeoutError) as exc:  # the cluster went away under us
                    result = TaskLost(f"the cluster lost it ({exc.__class__.__name__}: {exc})")
                yield i, result
                bar.update(weights[i] if weights is not None else 1)
                fut.release()
        finally:
            for f in futures:
                f.cancel()
