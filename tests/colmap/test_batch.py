"""Many small pairs in one compiled call (:func:`episeg_cv.colmap.job.match_pairs`): the results of
:func:`~episeg_cv.colmap.job.match_pair`, pair by pair."""

import dataclasses

import numpy as np
import pytest

pytest.importorskip("pycolmap")

from episeg_cv import colmap, scenes  # noqa: E402
from episeg_cv.colmap import job as job_module  # noqa: E402
from episeg_cv.colmap import pipeline as pipeline_module  # noqa: E402
from episeg_cv.features import PRESETS  # noqa: E402
from episeg_cv.matching import small  # noqa: E402

FEW = dataclasses.replace(PRESETS["collection"], max_features=300)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return colmap.save_collection(scenes.make_collection(5, image_size=(480, 360), seed=4),
                                  tmp_path_factory.mktemp("small_room"))


def _jobs(folder, tmp_path, monkeypatch, **options):
    """The jobs ``match_model`` hands to the runner (300 features an image: small pairs)."""
    jobs = []
    real = pipeline_module.match_pairs
    monkeypatch.setattr(pipeline_module, "match_pairs", lambda js: jobs.extend(js) or real(js))
    report = colmap.match_model(folder["model"], folder["images"], tmp_path / "db.db", features=FEW,
                                cache_dir=tmp_path / "cache", **options)
    monkeypatch.setattr(pipeline_module, "match_pairs", real)
    return jobs, report


def _same(a, b):
    assert [r.index for r in a] == [r.index for r in b]
    for x, y in zip(a, b):
        assert np.array_equal(x.matches, y.matches) and np.array_equal(x.inliers, y.inliers)
        assert x.matches.dtype == y.matches.dtype == np.uint32 and x.inliers.dtype == np.uint32
        assert x.lengths == y.lengths and x.samples == y.samples
        assert (x.ratios is None and y.ratios is None) or np.array_equal(x.ratios, y.ratios)


@pytest.mark.parametrize("verify", ["tracks", "pairs"])
def test_batch_equals_pair_by_pair(folder, tmp_path, monkeypatch, verify):
    jobs, report = _jobs(folder, tmp_path, monkeypatch, verify=verify)
    assert len(jobs) == 10 and report.n_inliers > 0
    calls = []
    for name in ("pairs", "pairs_parallel"):  # (serial or parallel: by the thread count)
        real = getattr(small._sk, name)
        monkeypatch.setattr(small._sk, name, lambda *a, real=real: calls.append(1) or real(*a))
    batch = job_module.match_pairs(jobs)
    assert calls == [1]  # one call for the ten pairs
    assert sum(len(r.inliers) for r in batch) > 0
    _same(batch, [job_module.match_pair(j) for j in jobs])


def test_mixed_small_and_large_pairs_keep_their_order(folder, tmp_path, monkeypatch):
    jobs, _ = _jobs(folder, tmp_path, monkeypatch)
    sizes = sorted(len(j.store.load(j.view1)[1]) * len(j.store.load(j.view2)[1]) for j in jobs)
    monkeypatch.setattr(small, "SMALL_PAIRS", sizes[len(sizes) // 2])  # about half the pairs take the index
    reversed_jobs = jobs[::-1]
    _same(job_module.match_pairs(reversed_jobs), [job_module.match_pair(j) for j in reversed_jobs])
    assert job_module.match_pairs([]) == []


def test_small_pairs_on_two_workers_give_identical_databases(folder, tmp_path):
    dbs = []
    for workers in (1, 2):
        db = tmp_path / f"w{workers}.db"
        colmap.match_model(folder["model"], folder["images"], db, features=FEW, workers=workers,
                           cache_dir=tmp_path / "cache")
        dbs.append(colmap.read_database_matches(db))
    assert dbs[0].keys() == dbs[1].keys() and len(dbs[0]) == 10
    for k in dbs[0]:
        assert np.array_equal(dbs[0][k][0], dbs[1][k][0]) and np.array_equal(dbs[0][k][1], dbs[1][k][1])
