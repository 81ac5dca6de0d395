"""Process pools that stop at once on Ctrl-C.

Ctrl-C in a terminal reaches the whole process group. Workers started with
:func:`ignore_interrupt` as their initializer leave it to the main process, which ends them
with :func:`stop_pool` instead of waiting for their running tasks (``shutdown(wait=True)``
joins each worker after its task, and can hang on an idle worker's queue).

The pool supplies the parallelism: its workers run BLAS on one thread. Two workers on two
cores that each start a BLAS thread per core for products of a few hundred rows spend more time
waking threads than computing (``docs/performance.md``, "BLAS threads").
"""

from __future__ import annotations

import contextlib
import functools
import signal
import threading
from concurrent.futures import ProcessPoolExecutor

from threadpoolctl import threadpool_limits

__all__ = ["ignore_interrupt", "interrupts_ignored", "map_in_processes", "one_blas_thread",
           "stop_pool"]


def ignore_interrupt() -> None:
    """Pool initializer: the worker ignores SIGINT (the main process stops the pool) and runs
    BLAS on one thread (module docstring)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    threadpool_limits(1, user_api="blas")


def one_blas_thread(function):
    """Decorator: run ``function`` with BLAS (OpenBLAS, MKL) on one thread. For solvers whose
    products are small (a few hundred columns): there a second thread costs more than it
    gives (``benchmarks/bench_blas_threads.py``; ``docs/performance.md``, "BLAS threads")."""
    @functools.wraps(function)
    def wrapper(*args, **kwargs):
        with threadpool_limits(1, user_api="blas"):
            return function(*args, **kwargs)
    return wrapper


def stop_pool(pool: ProcessPoolExecutor) -> None:
    """Cancel the pool's pending work and end its workers now (terminate, then kill what is
    still alive after a second), then wait briefly for the pool's manager thread to see them
    gone and close its wake-up pipe: left running, it races the interpreter's exit hook for
    that pipe, which then prints a traceback (``OSError: Bad file descriptor``) after the
    interrupt message. A second Ctrl-C while this runs (a user pressing again) is ignored,
    so that it cannot cut the clean-up short and leave workers behind; the handler is
    restored after."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    manager = getattr(pool, "_executor_manager_thread", None)
    with interrupts_ignored():
        pool.shutdown(wait=False, cancel_futures=True)
        for proc in processes:
            if proc.is_alive():
                proc.terminate()
        for proc in processes:
            proc.join(timeout=1.0)
            if proc.is_alive():
                proc.kill()
        if manager is not None:
            manager.join(timeout=0.5)


@contextlib.contextmanager
def interrupts_ignored():
    """Within the block SIGINT is ignored (only in the main thread, where Python handles it;
    elsewhere the block runs as it is); the previous handler is restored after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def map_in_processes(function, items: list[tuple], workers: int) -> list:
    """``[function(*item) for item in items]``, in ``workers`` processes when more than one
    (results in order); Ctrl-C stops the pool at once and is raised again."""
    if workers <= 1 or len(items) <= 1:
        return [function(*item) for item in items]
    pool = ProcessPoolExecutor(max_workers=min(workers, len(items)),
                               initializer=ignore_interrupt)
    try:
        futures = [pool.submit(function, *item) for item in items]
        out = [f.result() for f in futures]
    except BaseException:
        stop_pool(pool)
        raise
    pool.shutdown()
    return out
