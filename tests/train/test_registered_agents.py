"""The training loop with every registered baseline (rlu.agents.AGENTS): a few updates on a
synthetic dataset in its task's schema, an interrupted run resumed to the same metrics and
weights, and (where rlu.envs is installed) an evaluation episode in the real env.

An agent whose module does not exist yet is skipped, so this contract runs as soon as the
agents land."""

from __future__ import annotations

import importlib
import importlib.util
import json

import pytest

from rlu.agents import AGENTS

torch = pytest.importorskip("torch")

TASKS = {False: "control_suite/cartpole_swingup", True: "atari/Pong"}
PHASES = {"brac": {"behaviour_steps": 2}}  # a short pre-training phase, run on top of the steps


def _flat(state, prefix=""):
    out = {}
    for k, v in state.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}/"))
        elif isinstance(v, torch.Tensor):
            out[f"{prefix}{k}"] = v
    return out


@pytest.fixture(scope="module")
def synthetic_datasets(tmp_path_factory):
    from rlu.data.store import Schema
    from rlu.data.synthetic import write_synthetic
    from rlu.tasks import get_task

    root = tmp_path_factory.mktemp("agent_data")
    return {
        discrete: str(write_synthetic(root / str(discrete), Schema.for_task(get_task(t)), 3, 40))
        for discrete, t in TASKS.items()
    }


@pytest.mark.parametrize(("name", "discrete"), sorted(AGENTS), ids=lambda x: str(x))
def test_loop_runs_and_resumes_exactly(name, discrete, synthetic_datasets, tmp_path, monkeypatch):
    import rlu.data.views as views
    from rlu.training.restore import evaluate_run
    from rlu.training.train import train
    from tests.fakes import train_config

    cfg = train_config(
        task=TASKS[discrete],
        agent=name,
        dataset=synthetic_datasets[discrete],
        steps=6,
        eval_every=-1,
        log_every=1,
        checkpoint_every=3,
        torch_threads=1,
        overrides={"atari.batch_size": 8}
        if discrete
        else {"batch_size": 8, **PHASES.get(name, {})},
    )
    train(cfg, tmp_path / "a")
    calls = {"n": 0}
    sample = views.Sampler.sample

    def interrupted(self):
        calls["n"] += 1
        if calls["n"] == 5:  # after the checkpoint at step 3, before step 5's update
            raise KeyboardInterrupt
        return sample(self)

    monkeypatch.setattr(views.Sampler, "sample", interrupted)
    with pytest.raises(KeyboardInterrupt):
        train(cfg, tmp_path / "b")
    monkeypatch.setattr(views.Sampler, "sample", sample)
    train(cfg, tmp_path / "b", resume=True)
    metrics = [(tmp_path / r / "metrics.jsonl").read_text() for r in "ab"]
    assert metrics[0] == metrics[1]
    pretrain = json.loads((tmp_path / "a" / "result.json").read_text())["pretrain_steps"]
    assert len(metrics[0].splitlines()) == 6 + pretrain
    assert all(
        all(v == v for v in json.loads(line).values()) for line in metrics[0].splitlines()
    ), "NaN in the metrics"
    last = [tmp_path / r / "checkpoints" / f"step_{6 + pretrain:08d}.pt" for r in "ab"]
    a, b = (_flat(torch.load(path, weights_only=True)["agent"]) for path in last)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    # byte for byte: a resumed run's checkpoint is the uninterrupted run's file
    assert last[0].read_bytes() == last[1].read_bytes()

    if importlib.util.find_spec("rlu.envs") is None:
        return
    res = evaluate_run(tmp_path / "a", episodes=1, num_envs=1, max_steps=10)
    assert res.lengths == (10,)
