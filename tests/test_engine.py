"""The Monte Carlo task engine: seeds, process pool, Dask, resume, failure isolation, progress."""

from __future__ import annotations

import hashlib
import importlib
import io
import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from zoomcalib.study.engine import (
    THREAD_ENV_VARS,
    Task,
    example_task,
    run_tasks,
    task_fingerprint,
    task_seed,
)

# Task functions used below. The process pool starts its workers with `spawn`, which hands them
# this process's sys.path, so they import this module by name as pytest did.


def counting_task(seed: int, log: str, tag: str, n: int = 3) -> dict:
    """Draw like example_task, and append ``tag`` to the file ``log`` to count executions."""
    with open(log, "a", encoding="utf-8") as stream:
        stream.write(tag + "\n")
    return example_task(seed=seed, n=n)


def failing_task(seed: int, fail: bool = False) -> dict:
    if fail:
        raise ValueError("bad draw\n  on a second line")
    return example_task(seed=seed)


def crashing_task(seed: int, crash: bool = False) -> dict:
    if crash:
        os._exit(3)  # a worker dying outright, as a crash in native code would
    return example_task(seed=seed)


def returns_list_task(seed: int) -> list:
    return [seed]


def thread_settings_task(seed: int) -> dict:
    import cv2

    return {
        "env": {name: os.environ.get(name) for name in THREAD_ENV_VARS},
        "cv2_threads": cv2.getNumThreads(),
    }


def draw_tasks(n: int = 6, size: int = 4) -> list[Task]:
    return [Task(f"trial-{i}", example_task, {"n": size, "scale": 1.0 + i}) for i in range(n)]


def counting_tasks(log: Path, n: int = 8) -> list[Task]:
    return [Task(f"t{i}", counting_task, {"log": str(log), "tag": f"t{i}"}) for i in range(n)]


def executions(log: Path) -> list[str]:
    return log.read_text(encoding="utf-8").split() if log.exists() else []


def resume_setup(tmp_path: Path, seed: int) -> tuple[Path, Path, list[Task], dict]:
    """Log file, cache folder, 8 counting tasks and their results from one uninterrupted run
    (whose log is then cleared)."""
    log = tmp_path / "log.txt"
    tasks = counting_tasks(log)
    uninterrupted = run_tasks(tasks, seed=seed, workers=1)
    log.unlink()
    return log, tmp_path / "cache", tasks, uninterrupted


# --------------------------------------------------------------------------------------------
# Seeds


def test_task_seed_derivation_is_pinned():
    # Recomputed from the documented recipe, and pinned so that a change shows.
    digest = hashlib.sha256(b"zoom-3/trial-17").digest()
    words = [int.from_bytes(digest[i : i + 4], "little") for i in range(0, 16, 4)]
    state = np.random.SeedSequence(2024, spawn_key=words).generate_state(4, dtype=np.uint32)
    expected = sum(int(w) << (32 * i) for i, w in enumerate(state))
    assert task_seed(2024, "zoom-3/trial-17") == expected
    assert task_seed(2024, "zoom-3/trial-17") == 36898079356145839900128379031134509098
    assert task_seed(0, "a") == 3365778924900699383378237478720290929
    seeds = {task_seed(s, k) for s in range(3) for k in ("a", "b", "trial-1", "trial-10")}
    assert len(seeds) == 12
    with pytest.raises(ValueError, match="non-negative"):
        task_seed(-1, "a")


def test_results_do_not_depend_on_workers_or_task_set():
    tasks = draw_tasks()
    inline = run_tasks(tasks, seed=11, workers=1)
    pooled = run_tasks(tasks, seed=11, workers=2)
    assert pooled == inline
    assert list(pooled) == [t.key for t in tasks]
    # A task's numbers depend on its key and the study seed only.
    assert run_tasks(tasks[3:1:-1], seed=11, workers=1) == {
        k: inline[k] for k in ("trial-3", "trial-2")
    }
    assert run_tasks(tasks, seed=12, workers=1)["trial-0"] != inline["trial-0"]
    assert inline["trial-0"]["values"] != inline["trial-1"]["values"]
    seed = task_seed(11, "trial-2")
    expected = 3.0 * np.random.default_rng(seed).standard_normal(4)
    assert inline["trial-2"]["values"] == expected.tolist()


def test_pool_workers_are_single_threaded():
    before = {name: os.environ.get(name) for name in THREAD_ENV_VARS}
    tasks = [Task(f"w{i}", thread_settings_task, {}) for i in range(2)]
    results = run_tasks(tasks, workers=2)
    for result in results.values():
        assert result["env"] == dict.fromkeys(THREAD_ENV_VARS, "1")
        assert result["cv2_threads"] == 1
    assert {name: os.environ.get(name) for name in THREAD_ENV_VARS} == before


# --------------------------------------------------------------------------------------------
# Dask


@pytest.fixture(scope="module")
def dask_client():
    distributed = pytest.importorskip("dask.distributed")
    cluster = distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address=None,
    )
    try:
        client = distributed.Client(cluster)
        try:
            yield client
        finally:
            client.close()
    finally:
        cluster.close()


def test_dask_local_cluster_matches_in_process(dask_client, tmp_path):
    tasks = draw_tasks(n=8)
    inline = run_tasks(tasks, seed=5, workers=1)
    assert len(dask_client.scheduler_info()["workers"]) == 2
    assert run_tasks(tasks, seed=5, scheduler=dask_client) == inline
    # By address, with a cache: same numbers, and every result cached.
    address = dask_client.scheduler.address
    assert address.startswith("tcp://127.0.0.1:")
    assert run_tasks(tasks, seed=5, scheduler=address, cache_dir=tmp_path) == inline
    assert len(list(tmp_path.glob("*.json"))) == len(tasks)
    assert dask_client.status == "running"  # a client given by the caller is left open


def test_dask_failure_is_isolated(dask_client):
    tasks = [Task(f"f{i}", failing_task, {"fail": i == 1}) for i in range(3)]
    results = run_tasks(tasks, scheduler=dask_client)
    assert results["f1"] == {"error": "ValueError: bad draw on a second line"}
    assert results["f0"] == run_tasks(tasks[:1], workers=1)["f0"]


def test_missing_dask_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "dask.distributed", None)
    with pytest.raises(ImportError, match=r'pip install "zoomcalib\[distributed\]"'):
        run_tasks(draw_tasks(n=1), scheduler="tcp://127.0.0.1:8786")


def test_bad_scheduler_type():
    pytest.importorskip("dask.distributed")
    with pytest.raises(TypeError, match="scheduler"):
        run_tasks(draw_tasks(n=1), scheduler=8786)


# --------------------------------------------------------------------------------------------
# Resume


@pytest.mark.parametrize("workers", [1, 2])
def test_resume_runs_only_unfinished_tasks(tmp_path, workers):
    log, cache, tasks, uninterrupted = resume_setup(tmp_path, seed=3)

    first = run_tasks(tasks[:4], seed=3, workers=workers, cache_dir=cache)  # the "interrupted" run
    assert sorted(executions(log)) == ["t0", "t1", "t2", "t3"]
    log.unlink()
    resumed = run_tasks(tasks, seed=3, workers=workers, cache_dir=cache)
    assert sorted(executions(log)) == ["t4", "t5", "t6", "t7"]
    assert resumed == uninterrupted
    assert {k: resumed[k] for k in first} == first

    log.unlink()
    assert run_tasks(tasks, seed=3, workers=workers, cache_dir=cache) == uninterrupted
    assert executions(log) == []


@pytest.mark.parametrize("workers", [1, 2])
def test_resume_after_real_interruption(tmp_path, workers):
    log, cache, tasks, uninterrupted = resume_setup(tmp_path, seed=4)

    def interrupt_after_three(done, total):
        if done == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_tasks(tasks, seed=4, workers=workers, cache_dir=cache, progress=interrupt_after_three)
    cached = {json.loads(p.read_text())["key"] for p in cache.glob("*.json")}
    assert len(cached) >= 3
    assert len(cached) < len(tasks)
    assert not list(cache.glob(".tmp-*"))  # no partial files left behind

    log.unlink()
    resumed = run_tasks(tasks, seed=4, workers=workers, cache_dir=cache)
    rerun = executions(log)
    assert sorted(rerun) == sorted({t.key for t in tasks} - cached)
    assert resumed == uninterrupted


def test_cache_is_invalidated_by_kwargs_and_seed(tmp_path):
    log = tmp_path / "log.txt"
    tasks = counting_tasks(log, n=3)
    run_tasks(tasks, seed=1, workers=1, cache_dir=tmp_path / "c")
    log.unlink()

    changed = [tasks[0], tasks[1], Task("t2", counting_task, {**tasks[2].kwargs, "n": 5})]
    results = run_tasks(changed, seed=1, workers=1, cache_dir=tmp_path / "c")
    assert executions(log) == ["t2"]
    assert len(results["t2"]["values"]) == 5
    log.unlink()

    run_tasks(changed, seed=2, workers=1, cache_dir=tmp_path / "c")
    assert sorted(executions(log)) == ["t0", "t1", "t2"]


def test_cache_file_contents_and_unsafe_keys(tmp_path):
    keys = ["plain-key_1.0", "zoom 3/trial:1", "../escape", "Ä"]
    tasks = [Task(k, example_task, {"n": 2, "scale": np.float32(2.0)}) for k in keys]
    results = run_tasks(tasks, seed=9, workers=1, cache_dir=tmp_path)
    files = sorted(p.name for p in tmp_path.iterdir())
    assert len(files) == len(keys)
    assert "plain-key_1.0.json" in files
    assert all("/" not in name and not name.startswith(".") for name in files)
    record = json.loads((tmp_path / "plain-key_1.0.json").read_text())
    assert record["key"] == "plain-key_1.0"
    assert record["seed"] == task_seed(9, "plain-key_1.0")
    assert record["fingerprint"] == task_fingerprint(example_task, tasks[0].kwargs, record["seed"])
    assert record["fn"] == "zoomcalib.study.engine:example_task"
    assert record["result"] == results["plain-key_1.0"]


def test_corrupt_cache_file_is_rerun(tmp_path):
    log = tmp_path / "log.txt"
    tasks = counting_tasks(log, n=2)
    expected = run_tasks(tasks, workers=1, cache_dir=tmp_path / "c")
    (tmp_path / "c" / "t1.json").write_text('{"key": "t1", "fingerp')  # e.g. a damaged disk
    log.unlink()
    assert run_tasks(tasks, workers=1, cache_dir=tmp_path / "c") == expected
    assert executions(log) == ["t1"]


# --------------------------------------------------------------------------------------------
# Failures


@pytest.mark.parametrize("workers", [1, 2])
def test_failing_task_does_not_lose_the_others(tmp_path, workers):
    tasks = [Task(f"f{i}", failing_task, {"fail": i == 2}) for i in range(5)]
    results = run_tasks(tasks, seed=8, workers=workers, cache_dir=tmp_path)
    assert list(results) == [t.key for t in tasks]
    assert results["f2"] == {"error": "ValueError: bad draw on a second line"}
    for key in ("f0", "f1", "f3", "f4"):
        assert "values" in results[key]
    assert sorted(p.stem for p in tmp_path.glob("*.json")) == ["f0", "f1", "f3", "f4"]

    # Not cached: a rerun retries it (here it now succeeds).
    fixed = [Task(t.key, failing_task, {"fail": False}) for t in tasks]
    rerun = run_tasks(fixed, seed=8, workers=workers, cache_dir=tmp_path)
    assert "values" in rerun["f2"]
    assert {k: v for k, v in rerun.items() if k != "f2"} == {
        k: v for k, v in results.items() if k != "f2"
    }


def test_bad_results_and_unpicklable_functions_become_errors():
    results = run_tasks([Task("list", returns_list_task, {})], workers=1)
    assert results["list"] == {"error": "TypeError: the task returned a list, not a dict"}

    tasks = [Task("lambda", lambda seed: {"x": 1}, {}), *draw_tasks(n=2)]
    results = run_tasks(tasks, workers=2)
    assert set(results["lambda"]) == {"error"}
    assert "\n" not in results["lambda"]["error"]
    assert "values" in results["trial-0"] and "values" in results["trial-1"]
    assert run_tasks(tasks[:1], workers=1)["lambda"] == {"x": 1}  # fine in-process


def test_crashed_worker_does_not_stop_the_study():
    tasks = [Task(f"c{i}", crashing_task, {"crash": i == 1}) for i in range(7)]
    results = run_tasks(tasks, workers=2)
    assert list(results) == [t.key for t in tasks]
    # The tasks in flight with the crash are rerun one at a time: only the culprit fails.
    assert "BrokenProcessPool" in results["c1"]["error"]
    assert "run alone" in results["c1"]["error"]
    others = [t for t in tasks if t.key != "c1"]
    assert {k: v for k, v in results.items() if k != "c1"} == run_tasks(others, workers=1)


def test_workers_that_always_die_do_not_loop(tmp_path, monkeypatch):
    # A module that imports in this process but kills any pool worker that imports it.
    (tmp_path / "engine_deadly_module.py").write_text(
        "import multiprocessing, os\n"
        "if multiprocessing.parent_process() is not None:\n"
        "    os._exit(7)\n"
        "def task(seed):\n"
        "    return {'seed': seed}\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    deadly = importlib.import_module("engine_deadly_module")
    tasks = [Task(f"d{i}", deadly.task, {}) for i in range(12)]
    results = run_tasks(tasks, workers=2)
    assert all(set(r) == {"error"} for r in results.values())
    assert "not run" in results["d11"]["error"]
    assert run_tasks(tasks[:2], workers=1)["d0"] == {"seed": task_seed(0, "d0")}


# --------------------------------------------------------------------------------------------
# Progress and validation


def test_progress_callable_and_update_object(tmp_path):
    tasks = draw_tasks(n=4)
    run_tasks(tasks[:2], workers=1, cache_dir=tmp_path)
    calls = []
    run_tasks(tasks, workers=1, cache_dir=tmp_path, progress=lambda d, t: calls.append((d, t)))
    assert calls == [(1, 4), (2, 4), (3, 4), (4, 4)]

    class Bar:
        def __init__(self):
            self.n = 0

        def update(self, step):
            self.n += step

    bar = Bar()
    run_tasks(tasks, workers=2, progress=bar)
    assert bar.n == 4


def test_click_progressbar_is_accepted():
    import click

    tasks = draw_tasks(n=3)
    with click.progressbar(length=len(tasks), file=io.StringIO()) as bar:
        run_tasks(tasks, workers=1, progress=bar)
        assert bar.pos == 3


def test_invalid_input(tmp_path):
    with pytest.raises(ValueError, match="duplicate"):
        run_tasks([("a", example_task, {}), ("a", example_task, {})], workers=1)
    with pytest.raises(ValueError, match="seed"):
        run_tasks([("a", example_task, {"seed": 1})], workers=1)
    with pytest.raises(ValueError, match="workers"):
        run_tasks([("a", example_task, {})], workers=0)
    with pytest.raises(ValueError, match="key"):
        run_tasks([("", example_task, {})], workers=1)
    with pytest.raises(TypeError, match="fingerprint"):
        run_tasks([("a", example_task, {"n": object()})], workers=1, cache_dir=tmp_path)
    assert run_tasks([], workers=1) == {}
