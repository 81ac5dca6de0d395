"""The process pools' workers and the small-product solvers run BLAS on one thread."""

from __future__ import annotations

from threadpoolctl import threadpool_info, threadpool_limits

from zoomcalib.pool import map_in_processes, one_blas_thread


def blas_threads() -> list[int]:
    """The thread count of every BLAS library loaded here."""
    return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]


def test_one_blas_thread_holds_inside_the_call_only():
    with threadpool_limits(2, user_api="blas"):
        before = blas_threads()
        inside = one_blas_thread(blas_threads)()
        after = blas_threads()
    assert before and all(n == 2 for n in before), before
    assert inside == [1] * len(before)
    assert after == before


def test_pool_workers_run_blas_on_one_thread():
    with threadpool_limits(2, user_api="blas"):
        in_workers = map_in_processes(blas_threads, [(), ()], workers=2)
        here = blas_threads()
    assert all(n == 2 for n in here), here
    assert all(threads and set(threads) == {1} for threads in in_workers), in_workers
