"""Scores and aggregates: hand-computed values, and rliable's numbers on the same inputs."""

from __future__ import annotations

import numpy as np
import pytest

from rlu.data.store import DatasetWriter, Schema, open_dataset
from rlu.evaluation import scores
from rlu.segments import make_episode
from rlu.types import ArraySpec, DiscreteSpec, RluError


def test_atari_normalisation_hand_computed():
    # 100 * (score - random) / (best - random)
    assert scores.normalized_score(60.0, 10.0, 110.0) == pytest.approx(50.0)
    assert scores.normalized_score(10.0, 10.0, 110.0) == pytest.approx(0.0)
    assert scores.normalized_score(210.0, 10.0, 110.0) == pytest.approx(200.0)
    np.testing.assert_allclose(scores.normalized_score([-21, 0, 21], -21, 21), [0, 50, 100])
    out = scores.normalize_scores({"Pong": [0.0]}, {"Pong": -20.0}, {"Pong": 20.0})
    np.testing.assert_allclose(out["Pong"], [50.0])
    with pytest.raises(RluError, match="best_behaviour"):
        scores.normalize_scores({"Pong": 1.0}, {"Pong": -20.0}, {})
    with pytest.raises(RluError, match="undefined"):
        scores.normalized_score(1.0, 5.0, 5.0)


def test_aggregates_hand_computed():
    x = np.array([[1.0, 10.0, 100.0], [3.0, 20.0, 300.0]])  # (runs, tasks)
    # per-task means 2, 15, 200
    assert scores.aggregate_mean(x) == pytest.approx((2 + 15 + 200) / 3)
    assert scores.aggregate_median(x) == pytest.approx(15.0)
    # 6 values sorted 1 3 10 20 100 300; cut floor(1.5)=1 each end -> mean(3, 10, 20, 100)
    assert scores.aggregate_iqm(x) == pytest.approx(33.25)
    y = np.arange(8.0).reshape(2, 4)  # cut 2 each end -> mean(2, 3, 4, 5)
    assert scores.aggregate_iqm(y) == pytest.approx(3.5)


def test_task_bootstrap_interval_brackets_the_statistic():
    est, (lo, hi) = scores.task_bootstrap_interval([1.0, 2.0, 3.0, 4.0, 100.0], "median")
    assert est == 3.0
    assert lo <= est <= hi
    assert lo >= 1.0 and hi <= 100.0
    # a constant vector has a degenerate interval
    assert scores.task_bootstrap_interval([5.0] * 4, "mean") == (5.0, (5.0, 5.0))
    # same seed, same interval
    a = scores.task_bootstrap_interval(np.arange(10.0), "mean", seed=3)
    assert a == scores.task_bootstrap_interval(np.arange(10.0), "mean", seed=3)


@pytest.mark.parametrize("aggregate", ["iqm", "mean", "median"])
def test_stratified_bootstrap_equals_rliable(aggregate):
    pytest.importorskip("rliable")
    from rliable import library as rly
    from rliable import metrics

    fn = {
        "iqm": metrics.aggregate_iqm,
        "mean": metrics.aggregate_mean,
        "median": metrics.aggregate_median,
    }[aggregate]
    data = np.random.default_rng(7).gamma(2.0, 50.0, size=(5, 9))
    reps = 3000
    np.random.seed(11)  # rliable's StratifiedBootstrap draws from numpy's global generator
    point, ci = rly.get_interval_estimates(
        {"x": data}, lambda s: np.array([fn(s)]), reps=reps, random_state=None
    )
    est, (lo, hi) = scores.stratified_bootstrap_ci(
        data, aggregate, reps=reps, random_state=np.random.RandomState(11), chunk=700
    )
    assert est == pytest.approx(float(point["x"][0]), rel=1e-12)
    assert lo == pytest.approx(float(ci["x"][0, 0]), rel=1e-12)
    assert hi == pytest.approx(float(ci["x"][1, 0]), rel=1e-12)


def test_stratified_bootstrap_rejects_bad_input():
    with pytest.raises(RluError, match="runs, tasks"):
        scores.stratified_bootstrap_ci(np.zeros(3))
    with pytest.raises(RluError, match="NaN"):
        scores.stratified_bootstrap_ci(np.array([[1.0, np.nan]]))


def test_best_behaviour_from_dataset(tmp_path):
    schema = Schema(ArraySpec((2,), "float32"), DiscreteSpec((), "int64", 3))
    # (run, checkpoint): (1, 0) returns 1, 3 -> mean 2; (1, 1) returns 10, 6 -> mean 8;
    # (2, 0) returns 7 -> mean 7. Run 1's best checkpoint has mean 8 (not the best single
    # episode, 10), run 2's 7: the reference averages the runs' best snapshots, 7.5.
    eps = [(1, 0, 1.0), (1, 0, 3.0), (1, 1, 10.0), (1, 1, 6.0), (2, 0, 7.0)]
    with DatasetWriter(tmp_path / "d", schema, {"source": "test"}) as w:
        for i, (run, ckpt, ret) in enumerate(eps):
            w.append(
                make_episode(
                    np.zeros((3, 2), np.float32),
                    np.zeros(2, np.int64),
                    np.array([ret, 0.0], np.float32),
                    terminal=True,
                    metadata={"episode_id": i, "run": run, "checkpoint": ckpt},
                )
            )
    assert scores.best_behaviour_from_dataset(open_dataset(tmp_path / "d")) == pytest.approx(7.5)


def test_reference_scores_files_load():
    best = scores.load_reference_scores("atari_best_behaviour")
    assert isinstance(best, dict)
    with pytest.raises(RluError, match="missing"):
        scores.load_reference_scores("no_such_scores")


def test_reference_scores_in_the_random_scores_format(tmp_path):
    # the format of rlu/resources/random_scores.json: records with a mean, keyed by task id
    path = tmp_path / "random_scores.json"
    path.write_text(
        '{"format": "rlu.random_scores/1", "provenance": {"seed": 0}, "scores": '
        '{"atari/Pong": {"mean": -20.5, "std": 0.5, "returns": [-21, -20]}, "atari/Breakout": 1}}'
    )
    assert scores.load_reference_scores(str(path)) == {"atari/Pong": -20.5, "atari/Breakout": 1.0}
    with pytest.raises(RluError, match="check the path"):
        scores.load_reference_scores(str(tmp_path / "missing.json"))
