"""Process pools that stop at once on Ctrl-C.

Ctrl-C in a terminal reaches the whole process group. Workers started with
:func:`ignore_interrupt` as their initializer leave it to the main process, which ends them
with :func:`stop_pool` instead of waiting for their running tasks (``shutdown(wait=True)``
joins each worker after its task, and can hang on an idle worker's queue).
"""

from __future__ import annotations

import signal
from concurrent.futures import ProcessPoolExecutor

__all__ = ["ignore_interrupt", "map_in_processes", "stop_pool"]


def ignore_interrupt() -> None:
    """Pool initializer: the worker ignores SIGINT (the main process stops the pool)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def stop_pool(pool: ProcessPoolExecutor) -> None:
    """Cancel the pool's pending work and end its workers now (terminate, then kill what is
    still alive after a second), then wait briefly for the pool's manager thread to see them
    gone and close its wake-up pipe: left running, it races the interpreter's exit hook for
    that pipe, which then prints a traceback (``OSError: Bad file descriptor``) after the
    interrupt message."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    manager = getattr(pool, "_executor_manager_thread", None)
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
