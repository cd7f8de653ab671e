"""The runner (:mod:`episeg_cv.colmap.runner`): cores, task sizes, and the Dask workers' memory allocator."""

import os
import subprocess
import sys
import threading

import numba
import pytest

import episeg_cv
from episeg_cv.colmap import worker
from episeg_cv.colmap.runner import (DASK_CHUNK_MAX, DASK_CHUNK_MIN, PROCESS_CHUNK, TASKS_PER_WORKER, THREAD_CHUNK,
                                     Runner, available_cores)


def test_task_sizes_in_this_process_and_threads():
    assert Runner(1).chunk(276) == PROCESS_CHUNK > THREAD_CHUNK > 1  # in this process a task is one parallel call
    pool = Runner(2)
    try:
        assert pool.chunk(276) == THREAD_CHUNK and pool.chunk(1) == THREAD_CHUNK
        assert pool.chunk(276, inline=True) == PROCESS_CHUNK  # inline: one parallel call in this thread
    finally:
        pool.close()


def test_a_few_items_are_spread_one_task_per_worker():
    one, pool = Runner(1), Runner(2)
    try:
        assert [one.spread(n) for n in (0, 1, 16)] == [1, 1, 16]
        assert [pool.spread(n) for n in (0, 1, 2, 3, 16)] == [1, 1, 1, 2, 8]
    finally:
        pool.close()
    r = Runner.__new__(Runner)  # a Dask runner's sizing, without a cluster
    r._client, r._pool, r._workers, r.cores = object(), None, 4, 2
    assert r.spread(16) == 4


def test_workers_are_cores_and_every_core_by_default():
    cores = available_cores()
    assert 1 <= cores <= numba.config.NUMBA_NUM_THREADS
    if hasattr(os, "sched_getaffinity"):
        assert cores == min(len(os.sched_getaffinity(0)), numba.config.NUMBA_NUM_THREADS)
    default = Runner()
    try:
        assert default.cores == cores
        assert default.describe == (f"{cores} threads" if cores > 1 else "this process, one core")
    finally:
        default.close()


def _seen(_):
    return threading.current_thread().name, episeg_cv.get_num_threads()


def test_one_worker_runs_everything_on_one_core_in_this_thread():
    runner = Runner(1)
    assert runner.describe == "this process, one core"
    with runner.limits():
        assert episeg_cv.get_num_threads() == 1  # the caller's own kernels too (band, consensus)
        seen = set(runner.imap(_seen, range(5)))
    assert seen == {(threading.current_thread().name, 1)}
    assert episeg_cv.get_num_threads() == numba.get_num_threads()  # the cap is put back


def test_inline_items_run_in_this_thread_and_the_others_on_the_pool():
    runner = Runner(2)
    try:
        with runner.limits():
            inline = set(runner.imap(_seen, range(5), inline=True))
            pooled = set(runner.imap(_seen, range(8)))
    finally:
        runner.close()
    me = threading.current_thread().name
    assert inline == {(me, min(2, numba.get_num_threads()))}  # this thread, its kernels on the runner's cores
    assert {t for t, _ in pooled} <= {f"episeg-worker_{k}" for k in range(2)} and {n for _, n in pooled} == {1}


def test_items_here_use_the_pool_of_threads_or_this_thread_and_never_a_cluster():
    runner = Runner(2)
    try:
        with runner.limits():
            pooled = set(runner.imap_here(_seen, range(8)))
    finally:
        runner.close()
    assert {t for t, _ in pooled} <= {f"episeg-worker_{k}" for k in range(2)} and {n for _, n in pooled} == {1}
    one = Runner(1)
    with one.limits():
        assert set(one.imap_here(_seen, range(3))) == {(threading.current_thread().name, 1)}
    fake = Runner.__new__(Runner)  # a Dask runner's state, without a cluster: its submit would fail
    fake._client, fake._pool = object(), None
    assert list(fake.imap_here(lambda x: x * 2, range(3))) == [0, 2, 4]


def test_items_here_run_on_the_driver_threads_beside_a_dask_cluster():
    """With Dask, the band's sample pairs run on this process's cores (idle meanwhile), not on the cluster
    and not on one thread."""
    pytest.importorskip("distributed")
    runner = Runner(2, "local:1")
    try:
        with runner.limits():
            here = set(runner.imap_here(_seen, range(8)))
        assert sorted(runner.imap(_square, range(5))) == [0, 1, 4, 9, 16]  # imap: still the cluster
        assert runner._client.run(os.getpid) and os.getpid() not in runner._client.run(os.getpid).values()
    finally:
        runner.close()
    assert {t for t, _ in here} <= {f"episeg-worker_{k}" for k in range(2)} and {n for _, n in here} == {1}


def _square(x):
    return x * x


@pytest.mark.parametrize("n_items, workers, want", [
    (276, 2, 35), (276, 8, 9), (276, 16, DASK_CHUNK_MIN), (10, 2, DASK_CHUNK_MIN), (100000, 2, DASK_CHUNK_MAX), (0, 2, DASK_CHUNK_MIN),
])
def test_dask_tasks_are_a_few_per_worker_within_bounds(n_items, workers, want):
    r = Runner.__new__(Runner)  # the sizing alone, without a cluster
    r._client, r._pool, r._workers = object(), None, workers
    assert r.chunk(n_items) == want
    if DASK_CHUNK_MIN < want < DASK_CHUNK_MAX:
        assert -(-n_items // want) <= TASKS_PER_WORKER * workers


_FAULTS = """
import resource, numpy as np
from episeg_cv.colmap.worker import undo_malloc_trim
changed = undo_malloc_trim()
for _ in range(3):  # warm
    a = np.ones(1 << 20); del a
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(200):  # 8 MiB arrays, allocated, touched and freed
    a = np.ones(1 << 20); del a
print(changed, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_dask_workers_get_glibc_large_allocations_back():
    """Dask's MALLOC_TRIM_THRESHOLD_ made every large array fault in fresh pages; undo_malloc_trim restores
    the heap reuse (and changes nothing where the variable is not set)."""
    env = {**os.environ, "MALLOC_TRIM_THRESHOLD_": "65536"}
    base = {k: v for k, v in os.environ.items() if k != "MALLOC_TRIM_THRESHOLD_"}
    run = lambda e, code: subprocess.run([sys.executable, "-c", code], env=e, capture_output=True, text=True,  # noqa: E731
                                         timeout=120).stdout.split()
    changed, faults = run(env, _FAULTS)
    trimmed = run(env, _FAULTS.replace("changed = undo_malloc_trim()", "changed = 'kept'"))
    untouched = run(base, _FAULTS)
    assert changed == "True" and untouched[0] == "False"
    assert int(trimmed[1]) > 100 * 200  # 2048 pages an array, faulted in each time
    assert int(faults) < 2000 and int(untouched[1]) < 2000


def test_worker_plugin_undoes_the_trim_setting(monkeypatch):
    pytest.importorskip("distributed")
    from episeg_cv.colmap import _dask

    calls = []
    monkeypatch.setattr(_dask, "undo_malloc_trim", lambda: calls.append("malloc"))
    monkeypatch.setattr(_dask, "single_thread", lambda: calls.append("threads"))
    monkeypatch.setattr(_dask, "warm_up", lambda: calls.append("kernels"))
    _dask.WarmWorker(None).setup()
    assert calls == ["malloc", "threads", "kernels"]
    assert worker.MMAP_THRESHOLD < worker.TRIM_THRESHOLD


def test_local_cluster_workers_run_without_the_statistical_profiler():
    pytest.importorskip("distributed")
    r = Runner(scheduler="local:1")
    try:
        seen = r._client.run(lambda: __import__("dask").config.get("distributed.worker.profile.enabled"))
        assert list(seen.values()) == [False]
        assert r.chunk(276) == DASK_CHUNK_MAX and r.describe == "a local Dask cluster of 1 workers"
    finally:
        r.close()
