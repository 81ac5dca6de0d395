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


def test_the_zoom_wide_entry_points_run_blas_on_one_thread(monkeypatch):
    # their products have a few hundred columns; on two threads the real PTZ sweep's
    # adjustment took 1.5 times as long (docs/performance.md, "BLAS threads")
    import zoomcalib.calibrate.zoomwide as zoomwide

    seen = []

    def stop(*args, **kwargs):
        seen.append(blas_threads())
        raise RuntimeError("stopped here")

    monkeypatch.setattr(zoomwide, "_set_up", stop)
    monkeypatch.setattr(zoomwide, "step_starts", stop)
    with threadpool_limits(2, user_api="blas"):
        for entry in (zoomwide.calibrate_zoom_wide, zoomwide.zoom_wide_starts):
            try:
                entry({})
            except RuntimeError as exc:
                assert "stopped here" in str(exc)
    assert len(seen) == 2 and all(threads and set(threads) == {1} for threads in seen), seen
