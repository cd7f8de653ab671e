"""A large pair in one compiled call (:mod:`episeg_cv.matching._pair_kernel`, taken by
:func:`episeg_cv.colmap.job.match_pair` on one kernel thread): the same results, bit for bit, as the
pair's stages one by one (:func:`episeg_cv.colmap.job._stages`), for both acceptance modes and the
cases the index treats apart."""

import dataclasses

import numpy as np
import pytest

pytest.importorskip("pycolmap")

from episeg_cv import colmap, scenes, threads  # noqa: E402
from episeg_cv.colmap import job as job_module  # noqa: E402
from episeg_cv.colmap import pipeline as pipeline_module  # noqa: E402
from episeg_cv.features import PRESETS  # noqa: E402
from episeg_cv.matching import _pair_kernel, small  # noqa: E402

FEW = dataclasses.replace(PRESETS["collection"], max_features=400)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return colmap.save_collection(scenes.make_collection(4, image_size=(480, 360), seed=5),
                                  tmp_path_factory.mktemp("pair_kernel_room"))


@pytest.fixture(scope="module")
def jobs(folder, tmp_path_factory):
    """The jobs of ``match_model`` in both modes (the track consensus's loose ratio, and the pair rule)."""
    tmp = tmp_path_factory.mktemp("pair_kernel_run")
    found = []
    real = pipeline_module.match_pairs
    pipeline_module.match_pairs = lambda js: found.extend(js) or real(js)
    try:
        for verify in ("tracks", "pairs"):
            colmap.match_model(folder["model"], folder["images"], tmp / f"{verify}.db", features=FEW, verify=verify,
                               cache_dir=tmp / "cache", log=lambda m: None)
    finally:
        pipeline_module.match_pairs = real
    assert len(found) == 12 and sum(j.loose is None for j in found) == 6
    return found


class _Store:
    """The features of ``store`` with every 7th keypoint without a pinhole position (NaN), and, with
    ``binary``, the descriptors as packed bits (Hamming)."""

    def __init__(self, store, binary=False):
        self.store, self.binary, self.cache = store, binary, {}
        self.norm = "hamming" if binary else store.norm

    def load(self, view):
        if view.name not in self.cache:
            kp, q, d = self.store.load(view)
            q = q.copy()
            q[3::7] = np.nan
            if self.binary:
                d = np.packbits(d > np.median(d, axis=1, keepdims=True), axis=1)
            self.cache[view.name] = (kp, q, d)
        return self.cache[view.name]


def _rotated(job, t):
    """Both cameras moved so that the pose from view 1 to view 2 is a small rotation and exactly ``t``."""
    c, s = np.cos(0.03), np.sin(0.03)
    R = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]) @ job.view1.R
    return dataclasses.replace(job, view1=dataclasses.replace(job.view1, t=np.zeros(3)),
                               view2=dataclasses.replace(job.view2, R=R, t=np.asarray(t, dtype=float)))


def _in_place(job):
    """View 1 against itself from the same centre (``t = 0`` exactly): every segment is a point, the query's own
    keypoint."""
    view = dataclasses.replace(job.view1, t=np.zeros(3))
    return dataclasses.replace(job, view1=view, view2=view)


def _variants(jobs):
    everywhere = (0.0, float("inf"))
    masked, binary = _Store(jobs[0].store), _Store(jobs[0].store, binary=True)
    return {
        "as matched": jobs,
        "no depth ranges": [dataclasses.replace(j, view1=j.view1.with_depth_range(everywhere),
                                                view2=j.view2.with_depth_range(everywhere)) for j in jobs],
        "line": [dataclasses.replace(j, search=j.search.replace(constraint="line")) for j in jobs],
        "cross check": [dataclasses.replace(j, rule=j.rule.replace(cross_check=True)) for j in jobs],
        "no mutual, no padding": [dataclasses.replace(j, rule=j.rule.replace(mutual=False, pad=0)) for j in jobs],
        "pinhole gaps": [dataclasses.replace(j, store=masked) for j in jobs],
        "hamming": [dataclasses.replace(j, store=binary) for j in jobs],
        "pure rotation": [_in_place(j) for j in jobs],
        "epipole at infinity": [_rotated(j, [0.5, 0.1, 0.0]) for j in jobs],
    }


def _same(a, b):
    assert a.index == b.index and a.lengths == b.lengths and a.samples == b.samples
    for name in ("matches", "inliers", "ratios"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), name


@pytest.fixture
def large(monkeypatch):
    """Every pair takes the index path (the small-pair path is the other one); the fused calls counted."""
    monkeypatch.setattr(small, "SMALL_PAIRS", 0)
    calls = []
    real = _pair_kernel.match_pair
    monkeypatch.setattr(_pair_kernel, "match_pair", lambda *a: calls.append(1) or real(*a))
    return calls


@pytest.mark.parametrize("variant", ["as matched", "no depth ranges", "line", "cross check", "no mutual, no padding",
                                     "pinhole gaps", "hamming", "pure rotation", "epipole at infinity"])
def test_fused_pair_equals_the_stages(jobs, large, monkeypatch, variant):
    todo = _variants(jobs)[variant]
    with threads.limited(1):
        fused = [job_module.match_pair(j) for j in todo]
        assert len(large) == len(todo)  # every pair in one compiled call
        batched = job_module.match_pairs(todo[:6]) + job_module.match_pairs(todo[6:])  # (one mode per call)
        assert len(large) == 2 * len(todo)
        monkeypatch.setattr(job_module, "_fusable", lambda *a: False)
        staged = [job_module.match_pair(j) for j in todo]
    assert len(large) == 2 * len(todo)
    assert sum(len(r.inliers) for r in staged) > 0
    assert any(r.ratios is not None for r in staged) and any(r.ratios is None for r in staged)
    for a, b, c in zip(fused, batched, staged):
        _same(a, c)
        _same(b, c)


def test_fused_only_on_one_kernel_thread(jobs, large, monkeypatch):
    job = jobs[0]
    n1, n2 = (len(job.store.load(v)[1]) for v in (job.view1, job.view2))
    with threads.limited(1):
        assert job_module._fusable(job, n1, n2)
        assert not job_module._fusable(dataclasses.replace(job, search=job.search.replace(tol="auto")), n1, n2)
    monkeypatch.setattr(threads, "get_num_threads", lambda: 2)
    assert not job_module._fusable(job, n1, n2)
    job_module.match_pair(job)
    assert large == []  # the stages, on the kernel threads
