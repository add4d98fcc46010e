"""Dataset statistics for agents that ask for them: chunked passes equal numpy's one pass, the
episode's last step carries no reward, returns come from whole episodes only."""

from __future__ import annotations

import numpy as np
import pytest

import rlu.data.statistics as statistics
from rlu.data import open_dataset
from rlu.data.provenance import data_source
from rlu.data.statistics import dataset_statistics
from rlu.data.store import Schema
from rlu.data.synthetic import write_synthetic
from rlu.tasks import get_task
from rlu.types import BatchSpec, RluError, SpecError

CARTPOLE = Schema.for_task(get_task("control_suite/cartpole_swingup"))
ATARI = Schema.for_task(get_task("atari/Pong"))


@pytest.fixture
def cartpole(tmp_path):
    return open_dataset(write_synthetic(tmp_path / "c", CARTPOLE, 7, 23, seed=3, vary_length=True))


def test_observation_statistics_in_chunks_equal_one_pass(cartpole, monkeypatch):
    monkeypatch.setattr(statistics, "CHUNK_ROWS", 5)  # many uneven chunks
    stats = dataset_statistics(cartpole, ("observation",))
    assert set(stats.observation_mean) == set(CARTPOLE.observation)
    for key in CARTPOLE.observation:
        x = np.asarray(cartpole.column(f"observation/{key}"), np.float64)
        np.testing.assert_allclose(stats.observation_mean[key], x.mean(0), rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(stats.observation_std[key], x.std(0), rtol=1e-5, atol=1e-7)
    assert stats.reward_mean is None and stats.return_min is None  # not asked for


def test_reward_and_return_statistics(cartpole):
    stats = dataset_statistics(cartpole, ("reward", "return"))
    reward = np.asarray(cartpole.column("reward"), np.float64)
    last = np.asarray(cartpole.column("is_last"), bool)
    assert stats.reward_mean == pytest.approx(reward[~last].mean())
    assert stats.reward_max == reward[~last].max() and stats.reward_min == reward[~last].min()
    returns = cartpole.episode_returns()
    assert (stats.return_min, stats.return_max) == (returns.min(), returns.max())
    assert stats.observation_mean is None


def test_images_and_windows_are_refused_with_the_reason(tmp_path):
    atari = open_dataset(write_synthetic(tmp_path / "a", ATARI, 2, 9))
    with pytest.raises(RluError, match="holds images"):
        dataset_statistics(atari, ("observation",))
    with pytest.raises(SpecError, match="the data gives observation, reward, return"):
        BatchSpec(32, statistics=("median",))


def test_data_source_of_each_writer(cartpole):
    assert data_source(cartpole.manifest) == {"source": "synthetic", "steps": cartpole.num_steps}
    assert data_source({"provenance": {"source": "rl_unplugged release", "family": "f",
                                       "files": [{}, {}], "run": 2}}) == {
        "source": "release", "family": "f", "files": 2, "run": 2}  # fmt: skip
    made = {"generator": "rlu generate", "command": "rlu generate x", "settings": {"scale": "tiny"}}
    assert data_source({"provenance": made}) == {
        "source": "generated", "command": "rlu generate x", "scale": "tiny"}  # fmt: skip
    assert data_source({"provenance": {"source": "d4rl"}}) == {"source": "imported",
                                                              "format": "d4rl"}  # fmt: skip
    assert data_source({}) == {"source": "unknown"}
