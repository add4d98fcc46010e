"""rlu's own datasets of every family it stores, made the way a user makes them: release records
written in the release's exact schema (``families.write_shard``), then ``rlu.data.release.convert``
(the converter ``rlu convert`` runs). Episodes of many lengths (1, 2 and more steps), terminal
and truncated ends, actions inside the action space unless asked otherwise."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rlu.data.release.convert import convert
from rlu.data.release.families import write_shard
from rlu.domains.records import CAMERA_KEY, FIRST, LAST, MID
from rlu.tasks import get_task

FAMILIES = ("control_episodes", "seq2_windows", "rwrl", "atari_episodes", "locomotion")
LENGTHS = (1, 2, 5, 9)
"""Steps of the episodes of each dataset (one terminal, the others truncated)."""


def _f32(rng, *shape):
    return rng.standard_normal(shape).astype(np.float32)


def _actions(rng, t, dim, outside):
    a = rng.uniform(-1, 1, (t, dim)).astype(np.float32)
    if outside:
        a[t // 2, 0] = 1.5  # D4PG's exploration noise before the env's clipping
    return a


def _control_episode(rng, t, terminal, outside, obs_dims, adim, camera=False):
    rec = {f"observation/{k}": _f32(rng, t, d) for k, d in obs_dims.items()}
    if camera:
        rec[CAMERA_KEY] = rng.integers(0, 256, (t, 64, 64, 3), dtype=np.uint8)
    rec["action"] = _actions(rng, t, adim, outside)
    rec["reward"] = _f32(rng, t)
    rec["discount"] = np.ones(t, np.float32)
    if terminal:
        rec["discount"][-1] = 0.0
    return rec


def _windows(rng, episodes, outside, obs_dims, adim):
    """seq2 windows of whole episodes as Acme's adder writes them: one per step, the one
    starting at an episode's LAST step padded with a zero step (a segment of one step)."""
    out = []
    for t, terminal in episodes:
        obs = {k: _f32(rng, t + 1, d) for k, d in obs_dims.items()}
        act = _actions(rng, t + 1, adim, outside)
        rew, disc = _f32(rng, t + 1), np.ones(t + 1, np.float32)
        st = np.full(t + 1, MID, np.float32)
        st[0], st[t - 1] = FIRST, LAST
        if terminal:
            disc[t - 2] = 0.0  # the transition into LAST ends in a terminal state
        for v in (*obs.values(), act, rew, disc):
            v[t:] = 0  # padding after LAST
        st[t] = FIRST
        for i in range(t):
            j = slice(i, i + 2)
            rec = {f"observation/{k}": v[j] for k, v in obs.items()}
            rec.update(action=act[j], reward=rew[j], discount=disc[j], step_type=st[j])
            rec["episodic_reward"] = np.zeros(2, np.float32)
            out.append(rec)
    return out


def _rwrl_episode(rng, t, terminal, outside):
    rec = {
        "observation:position": _f32(rng, t, 3),
        "observation:velocity": _f32(rng, t, 2),
        "action": _actions(rng, t, 1, outside),
        "reward": _f32(rng, t, 1),
        "discount": np.ones((t, 1), np.float32),
    }
    if terminal:
        rec["discount"][-1] = 0.0
    return rec


def _atari_episode(rng, t, terminal, index):
    r = rng.integers(-3, 4, t).astype(np.float32)
    disc = np.ones(t, np.float32)
    if terminal:
        disc[-1] = 0.0
    return {
        "observations": rng.integers(0, 256, (t, 84, 84), dtype=np.uint8),
        "actions": rng.integers(0, 6, t).astype(np.int64),
        "unclipped_rewards": r,
        "clipped_rewards": np.clip(r, -1, 1),
        "discounts": disc,
        "checkpoint_idx": np.int64(3),
        "episode_idx": np.int64(index),
        "episode_return": np.float32(r.sum()),
        "clipped_episode_return": np.float32(np.clip(r, -1, 1).sum()),
    }


def make_family(
    name: str, dest: Path, seed: int = 0, outside: bool = False, lengths=LENGTHS
) -> Path:
    """Write family ``name``'s dataset at ``dest`` (a new folder); returns ``dest``.

    ``outside``: one action per episode lies outside the action space (as the release's
    control-suite actions can: D4PG's noise before the env clips it). Atari actions are always
    inside (the data hold only legal actions)."""
    rng = np.random.default_rng(seed)
    dest = Path(dest)
    shard = dest.with_name(dest.name + ".shard")
    ends = [(t, i == 1) for i, t in enumerate(lengths)]  # the second episode is terminal
    cartpole = dict(position=3, velocity=2)
    kw: dict = {}
    if name == "control_episodes":
        family, task = "dm_control_suite_episodes", "control_suite/cartpole_swingup"
        records = [_control_episode(rng, t, term, outside, cartpole, 1) for t, term in ends]
    elif name == "seq2_windows":
        family, task = "dm_control_suite", "control_suite/cartpole_swingup"
        records = _windows(rng, [(max(t, 2), term) for t, term in ends], outside, cartpole, 1)
    elif name == "rwrl":
        family, task = "rwrl", "rwrl/cartpole_swingup"
        records = [_rwrl_episode(rng, t, term, outside) for t, term in ends]
        kw["challenge"] = "none"
    elif name == "atari_episodes":
        family, task = "atari_episodes_ordered", "atari/Pong"
        records = [_atari_episode(rng, t, term, i) for i, (t, term) in enumerate(ends)]
        kw["run"] = 1
    elif name == "locomotion":
        family, task = "dm_locomotion_episodes", "locomotion/rodent_two_touch"
        spec = get_task(task).observation_spec
        dims = {
            k.removeprefix("walker/"): v.shape[0] for k, v in spec.items() if v.shape != (64, 64, 3)
        }
        dims = {f"walker/{k}": d for k, d in dims.items()}
        records = [
            _control_episode(rng, t, term, outside, dims, 38, camera=True) for t, term in ends
        ]
    else:
        raise ValueError(name)
    write_shard(shard, family, records)
    convert([shard], family, task, dest, workers=1, **kw)
    shard.unlink()
    return dest
