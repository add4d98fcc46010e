"""Atari rewards on the data side: one reward scale (the raw game score) for converted episode
files and for generated data; transition files are clipped-only and say so."""

from __future__ import annotations

import numpy as np
import pytest

from rlu.data.release import families as Fm
from rlu.data.release.convert import convert
from rlu.data.store import DatasetWriter, open_dataset
from rlu.evaluation.scores import best_behaviour_from_dataset
from rlu.tasks import get_task
from rlu.types import FormatError, RluError
from tests.release.test_families import atari_episode, atari_record

TASK = "atari/SpaceInvaders"  # kills score 5-30 points: raw and clipped rewards differ


def _play(steps=300, seed=3):
    """A random-policy episode of the real env, recorded by the generator's recorder, and the
    same steps as an atari_episodes_ordered release record."""
    pytest.importorskip("ale_py")
    from rlu.envs import make_env
    from rlu.generate.recorder import EpisodeRecorder

    task = get_task(TASK)
    env = make_env(TASK, seed=0, max_episode_steps=steps)
    rec = EpisodeRecorder(task, steps)
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    rec.begin(obs)
    frames, actions, rewards = [], [], []
    meta = {"run": 1, "checkpoint": 0, "episode_id": 5}
    seg = None
    while seg is None:
        a = int(rng.integers(env.action_space.n))
        frames.append(obs[..., -1])
        nxt, r, term, trunc, info = env.step(a)
        actions.append(a)
        rewards.append(r)
        seg = rec.step(a, r, nxt, term, trunc, info, meta)
        obs = nxt
    raw = np.asarray(rewards, np.float32)
    disc = np.ones(len(raw), np.float32)
    disc[-1] = 0.0 if seg.is_terminal[-1] else 1.0
    release = {
        "observations": np.stack(frames),
        "actions": np.asarray(actions, np.int64),
        "unclipped_rewards": raw,
        "clipped_rewards": np.clip(raw, -1, 1),
        "discounts": disc,
        "checkpoint_idx": np.int64(0),
        "episode_idx": np.int64(5),
        "episode_return": np.float32(raw.sum()),
        "clipped_episode_return": np.float32(np.clip(raw, -1, 1).sum()),
    }
    return task, seg, release, raw


def test_converted_and_generated_episodes_store_the_same_raw_reward(tmp_path):
    task, seg, release, raw = _play()
    assert raw.max() > 1  # the episode scored: clipping would change it

    gen = tmp_path / "generated"
    from rlu.generate.recorder import schema_for

    with DatasetWriter(gen, schema_for(task), {"source": "test"}) as w:
        w.append(seg)
    shard = tmp_path / "run_1-00000-of-00001"
    Fm.write_shard(shard, "atari_episodes_ordered", [release])
    conv = tmp_path / "converted"
    convert([str(shard)], "atari_episodes_ordered", TASK, conv, workers=1)

    g, c = open_dataset(gen), open_dataset(conv)
    n = len(raw)
    np.testing.assert_array_equal(c.segment(0).reward[:n], raw)
    np.testing.assert_array_equal(g.segment(0).reward[:n], raw)
    for ds in (g, c):
        assert float(ds.metadata("episode_return")[0]) == pytest.approx(float(raw.sum()))
        assert float(ds.metadata("clipped_episode_return")[0]) == pytest.approx(
            float(np.clip(raw, -1, 1).sum())
        )
    assert "raw game score" in c.manifest["provenance"]["reward"]


def test_converted_transitions_are_clipped_and_say_so(tmp_path):
    rng = np.random.default_rng(0)
    recs = [atari_record(rng, 1.0, 9), atari_record(rng, 0.0, 9)]
    shard = tmp_path / "run_1-00000-of-00001"
    Fm.write_shard(shard, "atari", recs)
    out = tmp_path / "ds"
    convert([str(shard)], "atari", "atari/Pong", out, workers=1)
    ds = open_dataset(out)
    # the file's episode_return is the clipped return; the raw one is not in these files
    assert np.isnan(np.asarray(ds.metadata("episode_return"), np.float64)).all()
    assert float(ds.metadata("clipped_episode_return")[0]) == float(recs[0]["episode_return"])
    assert "clipped" in ds.manifest["provenance"]["reward"]
    # so they cannot give the best-behaviour reference (raw returns per checkpoint)
    with pytest.raises(RluError, match="atari_episodes_ordered"):
        best_behaviour_from_dataset(ds)


def test_episode_file_whose_clipped_rewards_disagree_is_rejected(tmp_path):
    ep = atari_episode(np.random.default_rng(1), 5)
    ep["unclipped_rewards"] = np.array([0, 4, 0, -2, 0], np.float32)
    ep["clipped_rewards"] = ep["unclipped_rewards"].copy()  # not clipped: a different scale
    path = tmp_path / "run_1-00000-of-00001"
    Fm.write_shard(path, "atari_episodes_ordered", [ep])
    with pytest.raises(FormatError, match="clipped_rewards"):
        [s for b in Fm.iter_segments(path, "atari_episodes_ordered") for s in b]
