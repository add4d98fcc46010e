"""Every family: our writer then our reader on random data in the exact schema, and one test per
family pinning its alignment rule (what becomes reward_t and discount_t, what the final step is)."""

from __future__ import annotations

import numpy as np
import pytest

from rlu.codecs import example as E
from rlu.data.release import families as Fm
from rlu.data.release.framing import RecordReader, is_gzip
from rlu.domains import records


def _f32(rng, *shape):
    return rng.standard_normal(shape).astype(np.float32)


def window_record(rng, t, obs_dims, camera=False, step_type=None, discount=None):
    rec = {f"observation/{k}": _f32(rng, t, d) for k, d in obs_dims.items()}
    if camera:
        rec[records.CAMERA_KEY] = rng.integers(0, 256, (t, 64, 64, 3), dtype=np.uint8)
    rec["action"] = _f32(rng, t, 2)
    rec["reward"] = _f32(rng, t)
    rec["discount"] = np.ones(t, np.float32) if discount is None else np.float32(discount)
    rec["step_type"] = np.ones(t, np.float32) if step_type is None else np.float32(step_type)
    rec["episodic_reward"] = _f32(rng, t)
    return rec


def atari_record(rng, d_t=1.0, episode_id=5, num_actions=6):
    """A transition of the release's atari family; actions among ``num_actions`` (Pong's 6)."""
    frames = rng.integers(0, 256, (5, 84, 84), dtype=np.uint8)
    return {
        "o_t": np.moveaxis(frames[:4], 0, -1),
        "o_tp1": np.moveaxis(frames[1:], 0, -1),
        "a_t": np.int32(rng.integers(0, num_actions)),
        "a_tp1": np.int32(rng.integers(0, num_actions)),
        "r_t": np.float32(rng.choice([-1, 0, 1])),
        "d_t": np.float32(d_t),
        "episode_id": np.uint64(episode_id),
        "episode_return": np.float32(rng.integers(-21, 21)),
    }


def atari_episode(rng, t, last_discount=0.0):
    disc = np.ones(t, np.float32)
    disc[-1] = last_discount
    r = rng.integers(-3, 4, t).astype(np.float32)
    return {
        "observations": rng.integers(0, 256, (t, 84, 84), dtype=np.uint8),
        "actions": rng.integers(0, 6, t).astype(np.int64),
        "unclipped_rewards": r,
        "clipped_rewards": np.clip(r, -1, 1),
        "discounts": disc,
        "checkpoint_idx": np.int64(3),
        "episode_idx": np.int64(17),
        "episode_return": np.float32(r.sum()),
        "clipped_episode_return": np.float32(np.clip(r, -1, 1).sum()),
    }


def rwrl_record(rng, t=1001, last_discount=1.0, easy=False):
    rec = {
        "observation:position": _f32(rng, t, 3),
        "observation:velocity": _f32(rng, t, 2),
        "action": rng.uniform(-1, 1, (t, 1)).astype(np.float32),
        "reward": _f32(rng, t, 1),
        "discount": np.ones((t, 1), np.float32),
    }
    if easy:
        rec.update({f"observation:dummy-{i}": _f32(rng, t, 1) for i in range(10)})
    rec["discount"][-1] = last_discount
    return rec


def bsuite_record(rng, step_type=(1, 1), discount=(1, 1)):
    return {
        "observation": _f32(rng, 2, 6),
        "action": rng.integers(0, 3, 2).astype(np.int64),
        "reward": _f32(rng, 2),
        "discount": np.float32(discount),
        "episodic_reward": _f32(rng, 2),
        "step_type": np.int64(step_type),
    }


def dmlab_record(rng, t=5):
    return {
        "observations_pixels": rng.integers(0, 256, (t, 72, 96, 3), dtype=np.uint8),
        "observations_reward": _f32(rng, t),
        "observations_action": np.eye(15, dtype=np.float32)[rng.integers(0, 15, t)],
        "actions": rng.integers(0, 15, t).astype(np.int64),
        "rewards": _f32(rng, t),
        "discounts": np.ones(t, np.float32),
        "discounted_rewards": _f32(rng, t),
        "episode_id": np.int64(9),
        "start_idx": np.int64(0),
        "episode_return": np.float32(1.5),
    }


def _records(family, rng):
    if family in ("dm_control_suite", "dm_locomotion"):
        cam = family == "dm_locomotion"
        dims = {"walker/joints_pos": 5} if cam else {"position": 3, "velocity": 2}
        return [window_record(rng, 2, dims, camera=cam) for _ in range(12)]
    if family in ("dm_control_suite_episodes", "dm_locomotion_episodes"):
        cam = family == "dm_locomotion_episodes"
        dims = {"walker/joints_pos": 5} if cam else {"position": 3}
        out = []
        for t in (7, 9):
            r = window_record(rng, t, dims, camera=cam)
            r["episode_id"] = np.int64(t)
            r["timestamp"] = np.int64(1234)
            out.append(r)
        return out
    if family == "atari":
        return [atari_record(rng, episode_id=2**64 - 1 - i) for i in range(3)]
    if family == "atari_episodes_ordered":
        return [atari_episode(rng, 6), atari_episode(rng, 4, 1.0)]
    if family == "rwrl":
        return [rwrl_record(rng, 11) for _ in range(2)]
    if family == "bsuite":
        return [bsuite_record(rng) for _ in range(10)]
    if family == "dmlab":
        return [dmlab_record(rng)]
    raise AssertionError(family)


def _expected_raw(family, rec):
    """What the original loader returns for one record we wrote (dtype conventions)."""
    out = dict(rec)
    if family in ("dm_control_suite", "dm_locomotion") or family.endswith("_episodes"):
        out["length"] = np.int32(rec["discount"].shape[0])
    return out


@pytest.mark.parametrize("family", list(Fm.FAMILIES))
def test_round_trip(tmp_path, family):
    rng = np.random.default_rng(hash(family) % 2**32)
    recs = _records(family, rng)
    path = tmp_path / "shard-00000-of-00001"
    Fm.write_shard(path, family, recs)
    assert is_gzip(path) == (family != "rwrl")  # RWRL files are plain TFRecords
    raws = list(Fm.iter_raw(path, family))
    got = [
        {k: v[i] for k, v in b.items()} for b in raws for i in range(len(next(iter(b.values()))))
    ]
    assert len(got) == len(recs)
    for g, r in zip(got, recs, strict=True):
        exp = _expected_raw(family, r)
        assert set(g) == set(exp)
        for k, v in exp.items():
            v = np.asarray(v)
            assert g[k].dtype == v.dtype and g[k].shape == v.shape, k
            assert g[k].tobytes() == v.tobytes(), k
    # and into segments, every one of them well formed
    for batch in Fm.iter_segments(path, family):
        for seg in batch:
            assert len(seg) >= 1
            assert seg.is_terminal[:-1].sum() == 0


def _one(family, tmp_path, recs):
    path = tmp_path / f"{family}-00000-of-00001"
    Fm.write_shard(path, family, recs)
    return [s for b in Fm.iter_segments(path, family) for s in b]


def test_rule_control_windows(tmp_path):
    """seq2: reward_0 = reward[0], discount_0 = discount[0] (the loader's r_t, p_t); flags from
    step_type; the LAST step is terminal only when the transition into it has discount 0."""
    rng = np.random.default_rng(0)
    recs = [
        window_record(rng, 2, {"position": 3}, step_type=[0, 1]),
        window_record(rng, 2, {"position": 3}, step_type=[1, 2], discount=[1, 0]),
        window_record(rng, 2, {"position": 3}, step_type=[1, 2], discount=[0, 0]),
        window_record(rng, 2, {"position": 3}, step_type=[1, 2], discount=[1, 1]),
    ]
    segs = _one("dm_control_suite", tmp_path, recs)
    for s, r in zip(segs, recs, strict=True):
        assert s.reward.tolist() == r["reward"].tolist()
        assert s.discount.tolist() == r["discount"].tolist()
        assert np.array_equal(s.observation["position"], r["observation/position"])
    assert segs[0].is_first.tolist() == [True, False] and not segs[0].is_last.any()
    assert segs[1].is_last.tolist() == [False, True] and not segs[1].is_terminal.any()
    assert segs[2].is_terminal.tolist() == [False, True]
    assert not segs[3].is_terminal.any()


def test_rule_seq40_padding_after_last_is_dropped(tmp_path):
    rng = np.random.default_rng(1)
    st = [1] * 5 + [2] + [0] * 4  # Acme pads with zero steps after LAST
    segs = _one("dm_locomotion", tmp_path, [window_record(rng, 10, {"walker/x": 2}, True, st)])
    assert len(segs) == 1 and len(segs[0]) == 6 and segs[0].is_last[-1]
    assert not segs[0].is_first.any()


def test_rule_episode_files_rsa(tmp_path):
    """*_episodes: reward_t = reward[t+1], discount_t = discount[t+1], actions unshifted."""
    rng = np.random.default_rng(2)
    rec = window_record(rng, 5, {"position": 3}, discount=[1, 1, 1, 1, 0])
    rec["episode_id"] = np.int64(-1)
    (s,) = _one("dm_control_suite_episodes", tmp_path, [rec])
    assert s.reward.tolist() == rec["reward"][1:].tolist() + [0.0]
    assert s.discount.tolist() == [1, 1, 1, 0, 0]
    assert np.array_equal(s.action, rec["action"])
    assert s.is_first.tolist() == [1, 0, 0, 0, 0] and s.is_last.tolist() == [0, 0, 0, 0, 1]
    assert s.is_terminal[-1]
    assert s.metadata["episode_id"] == 2**64 - 1
    assert s.metadata["episode_return"] == pytest.approx(float(rec["reward"][1:].sum()))
    # a time-limit end (last discount 1): TFDS appends discount 1, and the episode is not terminal
    rec = window_record(rng, 5, {"position": 3}, discount=[1, 1, 1, 1, 1])
    (tmp_path / "limit").mkdir()
    (s,) = _one("dm_control_suite_episodes", tmp_path / "limit", [rec])
    assert s.discount.tolist() == [1, 1, 1, 1, 1] and not s.is_terminal[-1]


def test_rule_atari_transitions(tmp_path):
    """One record = 2 steps: reward_0 = r_t, discount_0 = d_t; d_t = 0 ends step 1 terminally."""
    rng = np.random.default_rng(3)
    recs = [atari_record(rng, 1.0, 2**63), atari_record(rng, 0.0, 7)]
    segs = _one("atari", tmp_path, recs)
    for s, r in zip(segs, recs, strict=True):
        assert np.array_equal(s.observation[0], r["o_t"]) and np.array_equal(
            s.observation[1], r["o_tp1"]
        )
        assert s.action.tolist() == [r["a_t"], r["a_tp1"]]
        assert s.reward[0] == r["r_t"] and s.discount[0] == r["d_t"]
        assert not s.is_first.any()
    assert segs[0].metadata["episode_id"] == 2**63 and not segs[0].is_last.any()
    assert segs[1].is_last.tolist() == [False, True] and segs[1].is_terminal[1]


def test_rule_atari_episodes(tmp_path):
    """Rewards unshifted; a terminal episode's discounts shift left with 0 appended (TFDS)."""
    rng = np.random.default_rng(4)
    term, trunc = atari_episode(rng, 5, 0.0), atari_episode(rng, 4, 1.0)
    s1, s2 = _one("atari_episodes_ordered", tmp_path, [term, trunc])
    assert s1.reward.tolist() == term["unclipped_rewards"].tolist()
    assert s1.discount.tolist() == [1, 1, 1, 0, 0] and s1.is_terminal[-1]
    assert s2.discount.tolist() == [1, 1, 1, 1] and not s2.is_terminal.any()
    assert s1.observation.shape == (5, 84, 84)  # single frames, stacked at sample time
    assert s1.metadata["episode_id"] == 3 * 10**10 + 17 and s1.metadata["checkpoint"] == 3


def test_rule_rwrl_placeholder(tmp_path):
    """Index 0 of action/reward/discount is a placeholder (rwrl.py): everything moves one step
    earlier, the last action repeats; ':' nesting becomes '/'."""
    rng = np.random.default_rng(5)
    rec = rwrl_record(rng, 6, last_discount=0.0, easy=True)
    (s,) = _one("rwrl", tmp_path, [rec])
    a = rec["action"]
    assert np.array_equal(s.action, np.concatenate([a[1:], a[-1:]]))
    assert s.reward.tolist() == rec["reward"][1:, 0].tolist() + [0.0]
    assert s.discount.tolist() == [1, 1, 1, 1, 0, 0] and s.is_terminal[-1]
    assert set(s.observation) == {"position", "velocity", *(f"dummy-{i}" for i in range(10))}
    assert s.metadata["episode_return"] == pytest.approx(float(rec["reward"][1:].sum()))


def test_rule_bsuite(tmp_path):
    """gamma_0 = discount[0] * (step_type[1] != LAST): every LAST is terminal."""
    rng = np.random.default_rng(6)
    recs = [bsuite_record(rng, (1, 2), (1, 1)), bsuite_record(rng, (0, 1), (1, 1))]
    s1, s2 = _one("bsuite", tmp_path, recs)
    assert s1.discount[0] == 0 and s1.is_terminal[1]
    assert s2.discount[0] == 1 and s2.is_first[0] and not s2.is_last.any()
    assert s1.reward[0] == recs[0]["reward"][0]


def test_rule_dmlab_bgr(tmp_path):
    """DMLab PNGs hold BGR: the loader-shaped view keeps it, the segment is RGB."""
    rng = np.random.default_rng(7)
    rec = dmlab_record(rng)
    path = tmp_path / "dmlab-00000-of-00001"
    Fm.write_shard(path, "dmlab", [rec])
    raw = Fm.read_raw(path, "dmlab")
    assert np.array_equal(raw["observations_pixels"][0], rec["observations_pixels"])
    (s,) = [s for b in Fm.iter_segments(path, "dmlab") for s in b]
    assert np.array_equal(s.observation["pixels"], rec["observations_pixels"][..., ::-1])
    assert s.reward.tolist() == rec["rewards"].tolist()


def test_missing_feature_is_a_clear_error(tmp_path):
    path = tmp_path / "x"
    from rlu.data.release.framing import write_records

    write_records(path, [E.encode_example({"a_t": np.array([1])})])
    with pytest.raises(Exception, match="'o_t' is missing"):
        list(Fm.iter_raw(path, "atari"))


def test_skip_mode_counts_bad_records(tmp_path):
    rng = np.random.default_rng(8)
    path = tmp_path / "s"
    Fm.write_shard(path, "dm_control_suite", [window_record(rng, 2, {"p": 2}) for _ in range(10)])
    data = bytearray(path.read_bytes())
    import gzip

    raw = bytearray(gzip.decompress(bytes(data)))
    raw[20] ^= 0xFF  # first record's payload
    path.write_bytes(gzip.compress(bytes(raw)))
    rd = RecordReader(path, on_error="skip")
    n = sum(len(next(iter(b.values()))) for b in Fm.iter_raw(path, "dm_control_suite", reader=rd))
    assert n == 9 and rd.stats.skipped == 1
