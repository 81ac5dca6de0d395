"""A small task engine for Monte Carlo studies: seeded tasks, process pool or Dask, resumable.

A study is a list of :class:`Task` ``(key, fn, kwargs)``. Running it calls
``fn(**kwargs, seed=<task seed>)`` once per task and collects the returned JSON-serialisable
dicts by key. The engine is generic: it knows nothing of cameras or lenses, only of keys, module
level functions, keyword arguments and seeds.

Seeds
-----
Every task gets its own seed, a 128-bit ``int`` derived from the study seed and the task key
alone (:func:`task_seed`): ``np.random.SeedSequence(seed, spawn_key=K)``, where ``K`` is the
first 16 bytes of the SHA-256 of the UTF-8 key read as four little-endian 32-bit words, gives
four 32-bit words of state, which make the integer. The derivation never uses Python's salted
``hash()`` and does not depend on the order of the tasks, on which tasks are run together, on the
number of workers or on the scheduler, so a task's numbers are the same however the study is run.
A task function makes its generator with ``np.random.default_rng(seed)``.

Where tasks run
---------------
- ``workers=1`` (or a single task to run): in this process, one task after the other.
- ``workers=N``: a local :class:`concurrent.futures.ProcessPoolExecutor` of ``N`` processes
  started with the ``spawn`` method (``fork`` is unsafe in a process that has OpenCV's or a BLAS'
  threads running). The workers start with ``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS`` (and
  the MKL, vecLib and numexpr equivalents) set to 1 and call ``cv2.setNumThreads(1)`` if OpenCV
  is installed, so ``N`` workers use ``N`` cores. Because of ``spawn``, a script that calls
  :func:`run_tasks` with several workers must guard its entry point with
  ``if __name__ == "__main__":``, and the task functions must be importable by name (module
  level functions, not lambdas or closures).
- ``scheduler="tcp://host:8786"`` or a ``dask.distributed.Client``: a Dask cluster (the optional
  extra ``pip install "zoomcalib[distributed]"``). The task functions must be importable on the
  Dask workers.

Resume
------
With ``cache_dir``, the result of every task that succeeds is written to
``cache_dir/<safe key>.json`` as soon as it arrives (written to a temporary file, then renamed,
so a file is either whole or absent). The file records the task's key, seed and a fingerprint of
its function name, keyword arguments and seed; a later run with the same cache directory reuses
a task's file when the fingerprint matches and runs only the other tasks. An interrupted study
therefore resumes from the tasks it had finished, and a task whose arguments or seed changed is
run again.

Failures
--------
A task that raises gives ``{"error": "<ExceptionType>: <message on one line>"}``; the other tasks
go on, and the failed one is not cached, so a rerun with the same cache directory retries it. If
a pool worker dies outright (a crash in native code), the tasks it shared the pool with at that
moment are run again one at a time on a new pool, so only the task that kills its worker gets an
``error`` result, and the study goes on.

Examples
--------
>>> from zoomcalib.study.engine import Task, example_task, run_tasks
>>> tasks = [Task(f"draw-{i}", example_task, {"n": 2}) for i in range(3)]
>>> results = run_tasks(tasks, seed=7, workers=1)
>>> sorted(results)
['draw-0', 'draw-1', 'draw-2']
>>> len(results["draw-1"]["values"])
2
>>> results == run_tasks(tasks[::-1], seed=7, workers=1)
True
"""

from __future__ import annotations

import asyncio
import concurrent.futures as cf
import dataclasses
import hashlib
import importlib.util
import json
import logging
import multiprocessing
import operator
import os
import re
import tempfile
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

__all__ = ["Task", "example_task", "run_tasks", "task_fingerprint", "task_seed"]

logger = logging.getLogger(__name__)

#: Environment variables that cap the threads of OpenMP and the BLAS libraries in workers.
THREAD_ENV_VARS = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
)

_DISTRIBUTED_HINT = (
    "running tasks on a Dask cluster needs the optional dependency dask[distributed]; "
    'install it with: pip install "zoomcalib[distributed]"'
)
_MAX_ERROR_CHARS = 500
_MAX_BARREN_POOLS = 3
_SAFE_KEY = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")


class Task(NamedTuple):
    """One task of a study.

    Attributes
    ----------
    key : str
        Unique name of the task within the study; it also determines the task's seed.
    fn : callable
        Module-level (picklable, importable) function called as ``fn(**kwargs, seed=seed)``,
        returning a JSON-serialisable dict.
    kwargs : mapping
        Keyword arguments of ``fn``, without ``seed``. For a reliable cache they should be JSON
        values (numbers, strings, lists, dicts), NumPy arrays or scalars, paths or dataclasses
        of these.
    """

    key: str
    fn: Callable[..., Mapping[str, Any]]
    kwargs: Mapping[str, Any]


class _Spec(NamedTuple):
    """A task ready to run: its seed and (with a cache) fingerprint are known."""

    key: str
    fn: Callable[..., Mapping[str, Any]]
    kwargs: dict[str, Any]
    seed: int
    fingerprint: str | None


# --------------------------------------------------------------------------------------------
# Seeds, fingerprints and JSON


def _key_words(key: str) -> tuple[int, ...]:
    """Four 32-bit words from the SHA-256 of ``key`` (a stable, unsalted hash)."""
    digest = hashlib.sha256(key.encode("utf-8")).digest()
    return tuple(int.from_bytes(digest[i : i + 4], "little") for i in range(0, 16, 4))


def task_seed(seed: int, key: str) -> int:
    """Seed of one task, derived from the study seed and the task key.

    Parameters
    ----------
    seed : int
        Study seed, a non-negative integer.
    key : str
        Task key.

    Returns
    -------
    int
        A 128-bit non-negative integer, to be given to ``np.random.default_rng``. It depends on
        ``seed`` and ``key`` only: not on the other tasks, the workers or the scheduler.

    Examples
    --------
    >>> task_seed(0, "a") == task_seed(0, "a") != task_seed(0, "b")
    True
    >>> task_seed(0, "a") != task_seed(1, "a")
    True
    """
    seed = operator.index(seed)
    if seed < 0:
        raise ValueError(f"the study seed must be a non-negative integer, got {seed}")
    sequence = np.random.SeedSequence(seed, spawn_key=_key_words(key))
    words = sequence.generate_state(4, dtype=np.uint32)
    return int.from_bytes(words.astype("<u4").tobytes(), "little")


def _to_json(obj: Any) -> Any:
    """``json`` fallback for NumPy values, paths, sets and dataclasses."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, set | frozenset):
        return sorted(obj, key=repr)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return dataclasses.asdict(obj)
    raise TypeError(f"an object of type {type(obj).__name__} is not JSON-serialisable")


def _function_name(fn: Callable[..., Any]) -> str:
    module = getattr(fn, "__module__", None)
    qualname = getattr(fn, "__qualname__", None)
    if not module or not qualname:
        raise TypeError(
            f"task function {fn!r} has no module and qualified name; use a module-level function"
        )
    return f"{module}:{qualname}"


def task_fingerprint(fn: Callable[..., Any], kwargs: Mapping[str, Any], seed: int) -> str:
    """Fingerprint of a task: the SHA-256 of its function name, keyword arguments and seed.

    Parameters
    ----------
    fn : callable
        Task function (its ``module:qualname`` enters the fingerprint, not its code).
    kwargs : mapping
        Keyword arguments, serialised as canonical JSON (sorted keys; NumPy arrays as lists,
        dataclasses as dicts).
    seed : int
        The task seed (:func:`task_seed`).

    Returns
    -------
    str
        Hexadecimal digest.

    Raises
    ------
    TypeError
        If an argument cannot be serialised.
    """
    payload = {"fn": _function_name(fn), "kwargs": dict(kwargs), "seed": int(seed)}
    try:
        text = json.dumps(payload, sort_keys=True, separators=(",", ":"), default=_to_json)
    except TypeError as exc:
        raise TypeError(
            f"cannot fingerprint the arguments of {payload['fn']} for the cache: {exc}"
        ) from exc
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _one_line(exc: BaseException) -> str:
    """``"Type: message"`` on one line, at most 500 characters."""
    message = " ".join(str(exc).split())
    text = f"{type(exc).__name__}: {message}" if message else type(exc).__name__
    if len(text) > _MAX_ERROR_CHARS:
        text = text[: _MAX_ERROR_CHARS - 3] + "..."
    return text


# --------------------------------------------------------------------------------------------
# What runs in a worker

_threads_limited = False


def _limit_threads() -> None:
    """Cap OpenMP/BLAS/OpenCV threads to 1 in this (worker) process, once."""
    global _threads_limited
    if _threads_limited:
        return
    _threads_limited = True
    for name in THREAD_ENV_VARS:
        os.environ[name] = "1"  # for the libraries this process loads from now on
    if importlib.util.find_spec("cv2") is not None:
        import cv2

        cv2.setNumThreads(1)
    if importlib.util.find_spec("threadpoolctl") is not None:  # BLAS already loaded
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)


def _execute(
    fn: Callable[..., Mapping[str, Any]], kwargs: dict[str, Any], seed: int, limit_threads: bool
) -> tuple[bool, str]:
    """Run one task; return ``(True, result as JSON text)`` or ``(False, one-line error)``.

    Exceptions never leave this function, so nothing unpicklable crosses a process boundary.
    """
    if limit_threads:
        _limit_threads()
    try:
        result = fn(**kwargs, seed=seed)
        if not isinstance(result, Mapping):
            raise TypeError(f"the task returned a {type(result).__name__}, not a dict")
        text = json.dumps(dict(result), default=_to_json)
    except Exception as exc:
        return False, _one_line(exc)
    return True, text


def example_task(seed: int, n: int = 3, scale: float = 1.0) -> dict[str, Any]:
    """Example task: draw ``n`` normal numbers with the task's seed.

    It shows the contract of a task function (module level, keyword arguments, a ``seed``
    keyword, a JSON-serialisable dict back) and serves the tests.

    Parameters
    ----------
    seed : int
        Task seed, given by the engine.
    n : int, optional
        Number of draws.
    scale : float, optional
        Standard deviation.

    Returns
    -------
    dict
        ``values`` (list of ``n`` floats) and their ``mean``.

    Examples
    --------
    >>> example_task(seed=1, n=2) == example_task(seed=1, n=2)
    True
    """
    rng = np.random.default_rng(seed)
    values = scale * rng.standard_normal(n)
    return {"values": values.tolist(), "mean": float(values.mean())}


# --------------------------------------------------------------------------------------------
# Cache


def _cache_name(key: str) -> str:
    """File name of a key: the key itself when it is a plain name, else a sanitised key + hash."""
    if _SAFE_KEY.fullmatch(key):
        return f"{key}.json"
    cleaned = re.sub(r"[^A-Za-z0-9._-]+", "_", key).strip("._-")[:80]
    digest = hashlib.sha256(key.encode("utf-8")).hexdigest()[:16]
    return f"{cleaned}-{digest}.json" if cleaned else f"{digest}.json"


class _Cache:
    """One JSON file per finished task in a directory."""

    def __init__(self, directory: str | os.PathLike[str]) -> None:
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)

    def path(self, key: str) -> Path:
        return self.directory / _cache_name(key)

    def load(self, spec: _Spec) -> dict[str, Any] | None:
        """The cached result of ``spec``, or None if absent, unreadable or stale."""
        path = self.path(spec.key)
        try:
            record = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            return None
        except (OSError, ValueError) as exc:
            logger.warning("ignoring unreadable cache file %s: %s", path, _one_line(exc))
            return None
        if (
            not isinstance(record, dict)
            or record.get("key") != spec.key
            or record.get("fingerprint") != spec.fingerprint
            or not isinstance(record.get("result"), dict)
        ):
            return None
        return record["result"]

    def store(self, spec: _Spec, result: dict[str, Any]) -> None:
        """Write the result of ``spec`` atomically (temporary file, then rename)."""
        record = {
            "key": spec.key,
            "fn": _function_name(spec.fn),
            "seed": spec.seed,
            "fingerprint": spec.fingerprint,
            "result": result,
        }
        text = json.dumps(record)
        fd, tmp = tempfile.mkstemp(dir=self.directory, prefix=".tmp-", suffix=".json")
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as stream:
                stream.write(text)
                stream.flush()
                os.fsync(stream.fileno())
            os.replace(tmp, self.path(spec.key))
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise


# --------------------------------------------------------------------------------------------
# Progress


class _Progress:
    """Counts finished tasks and reports them to a callable or an ``update(1)`` object."""

    def __init__(self, progress: Any, total: int) -> None:
        self.progress = progress
        self.total = total
        self.done = 0

    def step(self) -> None:
        self.done += 1
        if self.progress is None:
            return
        update = getattr(self.progress, "update", None)
        if callable(update):
            update(1)
        else:
            self.progress(self.done, self.total)


# --------------------------------------------------------------------------------------------
# Runners

_Finish = Callable[[_Spec, bool, str], None]


def _run_inline(todo: list[_Spec], finish: _Finish) -> None:
    # Same thread counts as a worker, so that multi-threaded reductions (OpenCV's solvers, BLAS)
    # add up in the same order and the numbers match a pool or Dask run to the last bit.
    cv2 = None
    if importlib.util.find_spec("cv2") is not None:
        import cv2
    before = cv2.getNumThreads() if cv2 is not None else None
    limits = None
    if importlib.util.find_spec("threadpoolctl") is not None:
        from threadpoolctl import threadpool_limits

        limits = threadpool_limits(1)
    try:
        if cv2 is not None:
            cv2.setNumThreads(1)
        for spec in todo:
            ok, payload = _execute(spec.fn, spec.kwargs, spec.seed, False)
            finish(spec, ok, payload)
    finally:
        if cv2 is not None:
            cv2.setNumThreads(before)
        if limits is not None:
            limits.restore_original_limits()


@contextmanager
def _single_threaded_children() -> Iterator[None]:
    """Set the thread caps in ``os.environ`` while worker processes are spawned, then restore."""
    saved = {name: os.environ.get(name) for name in THREAD_ENV_VARS}
    os.environ.update({name: "1" for name in THREAD_ENV_VARS})
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _run_pool(todo: list[_Spec], n_workers: int, finish: _Finish) -> None:
    """Run on a spawn-started process pool, at most ``2 n_workers`` tasks submitted at a time.

    If a worker dies, every task in flight fails with ``BrokenProcessPool``; those tasks become
    suspects and are rerun one at a time on a new pool, so that only the task that kills its
    worker when run alone gets an error. If the pool breaks ``_MAX_BARREN_POOLS`` times before any
    task has succeeded (workers that cannot start), the remaining tasks get an error instead.
    """
    context = multiprocessing.get_context("spawn")
    position = {spec.key: i for i, spec in enumerate(todo)}
    pending = deque(todo)
    suspects: deque[_Spec] = deque()
    in_flight: dict[cf.Future[tuple[bool, str]], tuple[_Spec, bool]] = {}
    executor: cf.ProcessPoolExecutor | None = None
    n_broken = n_succeeded = 0
    with _single_threaded_children():
        try:
            while pending or suspects or in_flight:
                if executor is None:
                    if n_broken >= _MAX_BARREN_POOLS and n_succeeded == 0:
                        message = (
                            f"RuntimeError: not run: the worker processes died {n_broken} times "
                            "before any task finished (can they import the task function and the "
                            "main script?)"
                        )
                        for spec in [*suspects, *pending]:
                            finish(spec, False, message)
                        break
                    executor = cf.ProcessPoolExecutor(max_workers=n_workers, mp_context=context)
                broken = False
                while not broken and (suspects or pending):
                    if suspects and in_flight:
                        break  # a suspect runs alone
                    if not suspects and len(in_flight) >= 2 * n_workers:
                        break
                    queue = suspects if suspects else pending
                    spec = queue.popleft()
                    try:
                        future = executor.submit(_execute, spec.fn, spec.kwargs, spec.seed, True)
                    except BrokenProcessPool:
                        queue.appendleft(spec)
                        broken = True
                    else:
                        in_flight[future] = (spec, queue is suspects)
                if in_flight:
                    done, _ = cf.wait(in_flight, return_when=cf.FIRST_COMPLETED)
                    for future in sorted(done, key=lambda f: position[in_flight[f][0].key]):
                        spec, alone = in_flight.pop(future)
                        error = future.exception()
                        if error is None:
                            n_succeeded += 1
                            finish(spec, *future.result())
                        elif not isinstance(error, BrokenProcessPool):  # e.g. not picklable
                            finish(spec, False, _one_line(error))
                        elif alone:
                            broken = True
                            finish(spec, False, f"{_one_line(error)} (this task, run alone)")
                        else:
                            broken = True
                            suspects.append(spec)
                if broken and not in_flight:
                    logger.warning("a worker process died; starting a new process pool")
                    executor.shutdown(wait=True, cancel_futures=True)
                    executor = None
                    n_broken += 1
        finally:
            if executor is not None:
                executor.shutdown(wait=True, cancel_futures=True)


def _import_distributed() -> Any:
    try:
        import dask.distributed as distributed
    except ImportError as exc:
        raise ImportError(_DISTRIBUTED_HINT) from exc
    return distributed


def _run_dask(todo: list[_Spec], scheduler: Any, finish: _Finish) -> None:
    """Run on a Dask cluster, given its scheduler address or a connected ``Client``."""
    distributed = _import_distributed()
    own_client = isinstance(scheduler, str)
    if own_client:
        client = distributed.Client(scheduler)
    elif callable(getattr(scheduler, "submit", None)):
        client = scheduler
    else:
        raise TypeError(
            "scheduler must be a Dask scheduler address such as 'tcp://127.0.0.1:8786' or a "
            f"dask.distributed.Client, got {type(scheduler).__name__}"
        )
    futures: dict[Any, _Spec] = {}
    try:
        for spec in todo:
            future = client.submit(_execute, spec.fn, spec.kwargs, spec.seed, True, pure=False)
            futures[future] = spec
        for future in distributed.as_completed(list(futures)):
            spec = futures.pop(future)
            try:
                ok, payload = future.result()
            except (Exception, asyncio.CancelledError) as exc:  # e.g. KilledWorker
                ok, payload = False, _one_line(exc)
            finish(spec, ok, payload)
    finally:
        if futures:
            client.cancel(list(futures))
        if own_client:
            client.close()


def _default_workers() -> int:
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


# --------------------------------------------------------------------------------------------
# Entry point


def _prepare(tasks: Iterable[Task | tuple[Any, Any, Any]], seed: int, cached: bool) -> list[_Spec]:
    specs: list[_Spec] = []
    seen: set[str] = set()
    for item in tasks:
        key, fn, kwargs = item
        if not isinstance(key, str) or not key:
            raise ValueError(f"a task key must be a non-empty string, got {key!r}")
        if key in seen:
            raise ValueError(f"duplicate task key {key!r}")
        seen.add(key)
        if not callable(fn):
            raise TypeError(f"task {key!r}: fn is not callable")
        kwargs = dict(kwargs or {})
        if "seed" in kwargs:
            raise ValueError(f"task {key!r}: kwargs must not contain 'seed', the engine gives it")
        value = task_seed(seed, key)
        fingerprint = task_fingerprint(fn, kwargs, value) if cached else None
        specs.append(_Spec(key, fn, kwargs, value, fingerprint))
    return specs


def run_tasks(
    tasks: Iterable[Task | tuple[str, Callable[..., Mapping[str, Any]], Mapping[str, Any]]],
    *,
    seed: int = 0,
    workers: int | None = None,
    scheduler: Any = None,
    cache_dir: str | os.PathLike[str] | None = None,
    progress: Any = None,
) -> dict[str, dict[str, Any]]:
    """Run the tasks of a study, each with its own seed; resumable; failures isolated.

    Parameters
    ----------
    tasks : iterable of Task or (key, fn, kwargs)
        The tasks; keys must be unique non-empty strings. ``fn`` is called as
        ``fn(**kwargs, seed=task_seed(seed, key))`` and returns a JSON-serialisable dict (NumPy
        arrays and scalars in it are converted to lists and numbers).
    seed : int, optional
        Study seed (non-negative). Each task's seed is derived from it and the task's key
        (:func:`task_seed`), so the results do not depend on ``workers`` or ``scheduler``.
    workers : int, optional
        Number of local worker processes when ``scheduler`` is None; ``1`` runs the tasks in
        this process. Default: the number of CPUs this process may use. Never more processes
        than tasks to run. Ignored with a ``scheduler``.
    scheduler : str or dask.distributed.Client, optional
        Run on a Dask cluster instead: its scheduler address (``"tcp://127.0.0.1:8786"``; a
        client is opened and closed here) or a connected client (left open). Needs the optional
        extra ``pip install "zoomcalib[distributed]"``.
    cache_dir : path, optional
        Directory of the per-task result files. Each successful result is written there as soon
        as it arrives; tasks whose file is present and whose fingerprint (function name,
        kwargs, seed: :func:`task_fingerprint`) matches are not run again.
    progress : callable or object with ``update``, optional
        Told of every finished task, cached ones included (they come first): an object with an
        ``update`` method (a ``click.progressbar(length=len(tasks))`` or a tqdm bar) gets
        ``update(1)``; any other callable gets ``progress(n_done, n_total)``. Called in this
        process; an exception it raises stops the run (finished tasks stay cached).

    Returns
    -------
    dict
        ``{key: result}`` in the order of ``tasks``. A task that raised has
        ``{"error": "<ExceptionType>: <message on one line>"}``; it is not cached.

    Raises
    ------
    ValueError
        On a duplicate or empty key, ``seed`` in a task's kwargs, a negative seed or fewer than
        one worker.
    TypeError
        With ``cache_dir``, if a task's kwargs cannot be fingerprinted (see :class:`Task`).
    ImportError
        If ``scheduler`` is given and ``dask.distributed`` is not installed.
    """
    n_workers = _default_workers() if workers is None else operator.index(workers)
    if n_workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    specs = _prepare(tasks, seed, cache_dir is not None)
    cache = _Cache(cache_dir) if cache_dir is not None else None
    tracker = _Progress(progress, len(specs))
    results: dict[str, dict[str, Any]] = {}

    todo: list[_Spec] = []
    for spec in specs:
        hit = cache.load(spec) if cache is not None else None
        if hit is None:
            todo.append(spec)
        else:
            results[spec.key] = hit
            tracker.step()
    if cache is not None:
        logger.info("%d of %d tasks found in %s", len(specs) - len(todo), len(specs), cache_dir)

    def finish(spec: _Spec, ok: bool, payload: str) -> None:
        if ok:
            result = json.loads(payload)
            if cache is not None:
                cache.store(spec, result)
        else:
            logger.warning("task %r failed: %s", spec.key, payload)
            result = {"error": payload}
        results[spec.key] = result
        tracker.step()

    if todo:
        if scheduler is not None:
            _run_dask(todo, scheduler, finish)
        else:
            n_workers = min(n_workers, len(todo))
            if n_workers == 1:
                _run_inline(todo, finish)
            else:
                _run_pool(todo, n_workers, finish)
    return {spec.key: results[spec.key] for spec in specs}
