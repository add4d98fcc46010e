"""Minari's episode API on rlu datasets (issue 37 item 7): ``sample_episodes``,
``filter_episodes``, ``split`` and ``recover_environment`` mean what Minari 0.5's mean, checked
against Minari itself on the same data (rlu's export of the dataset, read by Minari)."""

from __future__ import annotations

import numpy as np
import pytest

minari = pytest.importorskip("minari")

from rlu.data import Schema, TransitionView, open_dataset  # noqa: E402
from rlu.data.minari import export_minari  # noqa: E402
from rlu.data.synthetic import write_synthetic  # noqa: E402
from rlu.tasks import get_task  # noqa: E402
from rlu.types import RluError  # noqa: E402

CARTPOLE = Schema.for_task(get_task("control_suite/cartpole_swingup"))


@pytest.fixture
def both(tmp_path):
    """An rlu dataset and the same data as Minari reads it (rlu's export)."""
    ds = open_dataset(
        write_synthetic(tmp_path / "ds", CARTPOLE, 12, 6, seed=3, terminal_prob=0.4,
                        vary_length=True)
    )  # fmt: skip
    path = export_minari(ds, "rlu/api-v0", root=tmp_path / "m")
    return ds, minari.MinariDataset(path / "data")


def same_episode(a, b):
    assert a.id == b.id
    for k in ("position", "velocity"):
        np.testing.assert_array_equal(a.observations[k], b.observations[k])
    for f in ("actions", "rewards", "terminations", "truncations"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)


def test_episodes_read_as_minari_reads_them(both):
    ds, mds = both
    for a, b in zip(ds.iterate_episodes(), mds.iterate_episodes(), strict=True):
        same_episode(a, b)


def test_sample_episodes_draws_what_minari_draws_with_the_same_seed(both):
    ds, mds = both
    ds.set_seed(7)
    mds.set_seed(7)
    for a, b in zip(ds.sample_episodes(5), mds.sample_episodes(5), strict=True):
        same_episode(a, b)
    assert len({e.id for e in ds.sample_episodes(12)}) == 12  # without replacement
    with pytest.raises(RluError, match="holds 12 episodes"):
        ds.sample_episodes(13)


def test_filter_episodes_keeps_what_minari_keeps(both):
    ds, mds = both

    def cond(ep):
        return bool(ep.terminations[-1]) or ep.rewards.sum() > 2

    mine, theirs = ds.filter_episodes(cond), mds.filter_episodes(cond)
    assert [e.id for e in mine.iterate_episodes()] == theirs.episode_indices.tolist()
    assert 0 < len(mine) < len(ds)
    # a filtered dataset is a dataset: samplers, views and returns see only its episodes
    view = TransitionView(mine)
    assert len(view) == int((mine.length - 1).sum())
    whole = ds.episode_returns()
    np.testing.assert_array_equal(mine.episode_returns(), whole[mine.indices])
    again = mine.filter_episodes(lambda e: True)
    assert [e.id for e in again.iterate_episodes()] == [e.id for e in mine.iterate_episodes()]


def test_split_is_minaris_split(both):
    ds, mds = both
    for a, b in zip(ds.split([4, 5], seed=11), minari.split_dataset(mds, [4, 5], seed=11),
                    strict=True):  # fmt: skip
        assert a.indices.tolist() == b.episode_indices.tolist()
    train, test = ds.split([0.75, 0.25], seed=1)
    assert len(train) == 9 and len(test) == 3
    assert not set(train.indices) & set(test.indices)
    with pytest.raises(RluError, match="more than the dataset's 12"):
        ds.split([10, 5])


def test_recover_environment_is_the_tasks_env(tmp_path):
    pytest.importorskip("dm_control")
    ds = open_dataset(write_synthetic(tmp_path / "ds", CARTPOLE, 1, 3))
    env = ds.recover_environment()
    try:
        assert env.spec.max_episode_steps == 1000
        assert env.spec.kwargs["task_id"] == "control_suite/cartpole_swingup"
        obs, _ = env.reset(seed=0)
        assert set(obs) == {"position", "velocity"}
    finally:
        env.close()
