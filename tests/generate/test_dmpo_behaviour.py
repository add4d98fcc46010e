"""DMPO as a behaviour agent: the online loop and the RWRL rollouts let it sample its own
Gaussian (``sigma=None``), its kept policies act the same way; the RWRL ``paper`` scale is it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from rlu.generate.scales import get_scale
from rlu.tasks import get_task

TINY_DMPO = {
    "policy_layers": (32, 32),
    "critic_layers": (32, 32),
    "batch_size": 32,
    "num_samples": 4,
}


def tiny_dmpo_scale(task_id: str):
    tiny = get_scale(get_task(task_id), "tiny")
    online = dataclasses.replace(tiny.online, agent="dmpo", sigma=None, agent_overrides=TINY_DMPO)
    return dataclasses.replace(tiny, online=online)


def test_rwrl_paper_scale_is_acmes_dmpo():
    pytest.importorskip("torch")
    from rlu.agents import make_config

    online = get_scale(get_task("rwrl/walker_walk"), "paper").online
    assert (online.agent, online.preset, online.sigma) == ("dmpo", "paper", None)
    assert (online.update_every, online.min_replay, online.replay_capacity) == (8, 1_000, 10**6)
    assert make_config("dmpo", False, "paper").batch_size / online.update_every == 32  # per insert
    # the control suite itself keeps D4PG, the paper's agent there
    assert get_scale(get_task("control_suite/walker_walk"), "paper").online.agent == "d4pg"
    assert get_scale(get_task("rwrl/walker_walk"), "laptop").online.agent == "d4pg"


def test_dmpo_recipe_samples_its_policy_and_keeps_it(tmp_path, monkeypatch):
    pytest.importorskip("torch")
    pytest.importorskip("dm_control")
    import json

    from rlu.data import open_dataset
    from rlu.generate import GenerateConfig, generate, recipe
    from rlu.generate.policies import list_policies, load_behaviour_policy

    task = "control_suite/cartpole_swingup"
    monkeypatch.setattr(recipe, "get_scale", lambda t, s: tiny_dmpo_scale(task))
    config = GenerateConfig(task, scale="tiny", runs=1, seed=3, progress=False)
    out = generate(config, tmp_path / "a")
    again = generate(config, tmp_path / "b")
    ds = open_dataset(out)
    assert ds.manifest["provenance"]["settings"]["online"]["sigma"] is None
    for p in sorted(q for q in out.rglob("*") if q.is_file()):  # deterministic
        assert (again / p.relative_to(out)).read_bytes() == p.read_bytes(), p
    actions = np.concatenate([ep.action for ep in ds.segments()])
    assert np.abs(actions).max() <= 1.0 and actions.std() > 0.3  # a sampled, clipped Gaussian
    info = list_policies(ds)[0]
    meta = json.loads(
        (out / f"policies/run_{info.run:03d}/checkpoint_{info.checkpoint:05d}.json").read_text()
    )
    assert meta["agent"] == "dmpo" and meta["exploration"] == {"sample": True}
    obs = {k: v[:4] for k, v in ds.segment(0).observation.items()}
    greedy = load_behaviour_policy(ds, info.run, info.checkpoint)
    np.testing.assert_array_equal(greedy(obs), greedy(obs))  # the mean, deterministic
    explore = load_behaviour_policy(ds, info.run, info.checkpoint, exploration=True, seed=1)
    a, b = explore(obs), explore(obs)
    assert not np.array_equal(a, b) and np.abs(a).max() <= 1.0


def test_rwrl_rollouts_with_a_dmpo_behaviour_agent(tmp_path, monkeypatch):
    pytest.importorskip("torch")
    pytest.importorskip("dm_control")
    from rlu.data import open_dataset
    from rlu.data.validate import validate
    from rlu.generate import GenerateConfig, generate, rwrl

    monkeypatch.setattr(rwrl, "get_scale", lambda t, s: tiny_dmpo_scale("rwrl/cartpole_swingup"))
    config = GenerateConfig("rwrl/cartpole_swingup", scale="tiny", runs=1, seed=1, progress=False)
    out = generate(config, tmp_path / "rw")
    none = open_dataset(out / "none_large")
    assert validate(out / "none_large").ok
    assert none.manifest["provenance"]["settings"]["online"]["agent"] == "dmpo"
    actions = np.concatenate([ep.action for ep in none.segments()])
    assert np.abs(actions).max() <= 1.0 and actions.std() > 0.3
