"""R2D2 (rlu.agents.r2d2): its value rescaling and n-step targets on hand-computed numbers, its
loss falling on one repeated batch of DeepMind Lab windows, its LSTM state kept and reset
when acting, and a few training steps from the command line on the converted TF-written
DeepMind Lab shard. (The agent contract test runs it on Atari frame stacks.)"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rlu.agents import make_agent, r2d2  # noqa: E402
from rlu.cli import main  # noqa: E402

TASK = "dmlab/seekavoid_arena_01"
SHARD = Path(__file__).resolve().parents[1] / "fixtures" / "release" / "dmlab"
SHARD = SHARD / "seekavoid_arena_01" / "training_0" / "tfrecord-00000-of-00500"
TINY = {"atari.channels": (4, 8, 8), "atari.hidden_size": 16, "lstm_size": 8}


def test_value_rescaling_and_its_inverse():
    x = torch.tensor([-10.0, -1.0, 0.0, 3.0, 100.0])
    h = r2d2.rescale(x, 1e-3)
    assert h[3].item() == pytest.approx(1.0 + 3e-3)  # sqrt(4) - 1 + eps * 3
    assert h[1].item() == pytest.approx(-(np.sqrt(2) - 1) - 1e-3)
    torch.testing.assert_close(r2d2.unrescale(h, 1e-3), x, rtol=1e-4, atol=1e-4)
    assert torch.equal(r2d2.rescale(x, 0.0), x) and torch.equal(r2d2.unrescale(x, 0.0), x)


def test_n_step_targets_by_hand():
    reward = torch.tensor([[1.0, 2.0, 3.0, 4.0]])
    discount = torch.tensor([[1.0, 1.0, 0.0, 1.0]])  # the transition out of step 2 is terminal
    valid = torch.tensor([[True, True, True, False]])
    q_boot = torch.tensor([[10.0, 20.0, 30.0, 40.0]])
    got = r2d2.n_step_targets(reward, discount, valid, torch.tensor([3]), q_boot, 0.5, 2)
    # t=0: 1 + 0.5*2 + 0.25*Q[2]; t=1: 2 + 0.5*3, then discount 0; t=2: 3 (terminal); t=3: none
    torch.testing.assert_close(got, torch.tensor([[1 + 1 + 0.25 * 30, 3.5, 3.0, 0.0]]))
    # a window cut mid-episode: the last real step (end=2) bootstraps, fewer than n steps
    got = r2d2.n_step_targets(reward, torch.ones(1, 4), valid, torch.tensor([2]), q_boot, 0.5, 2)
    torch.testing.assert_close(got[0, :2], torch.tensor([2 + 0.25 * 30, 2 + 0.5 * 30]))


@pytest.fixture(scope="module")
def converted(tmp_path_factory):
    out = tmp_path_factory.mktemp("dmlab") / "data"
    argv = ["convert", str(SHARD), "--family", "dmlab", "--task", TASK, "--out", str(out)]
    assert main(argv) == 0
    return out


def _agent(**extra):
    from rlu.tasks import get_task

    task = get_task(TASK)
    settings = dict(TINY, **{"atari.batch_size": 8, "sequence_length": 4, "burn_in": 1})
    return make_agent("r2d2", task.observation_spec, task.action_spec, "small", seed=0,
                      **settings, **extra)  # fmt: skip


def test_the_loss_falls_on_one_repeated_batch(converted):
    from rlu.data import make_sampler

    torch.set_num_threads(1)
    # gamma 0: the target is h(r_t), fixed, so the loss is a regression that must fall (with a
    # bootstrap the double-Q argmax of a random network moves the target from update to update)
    agent = _agent(learning_rate=3e-3, **{"atari.gamma": 0.0})
    assert agent.batch_spec.kind == "sequence" and agent.batch_spec.sequence_length == 5
    batch = make_sampler(converted, agent.batch_spec, seed=1).sample()
    losses = [agent.update(batch) for _ in range(30)]
    assert losses[0]["critic/transitions"] > 0
    assert all(np.isfinite(m["critic/loss"]) for m in losses)
    assert losses[-1]["critic/loss"] < 0.5 * losses[0]["critic/loss"]
    assert losses[0]["critic/target"] == losses[-1]["critic/target"]  # the fixed target
    bootstrapped = _agent()  # gamma 0.997: finite, over the same transitions
    metrics = [bootstrapped.update(batch) for _ in range(3)]
    assert all(np.isfinite(v) for m in metrics for v in m.values())
    assert metrics[0]["critic/transitions"] == losses[0]["critic/transitions"]


def test_acting_keeps_each_rows_lstm_state_and_resets_it_where_first(converted):
    from rlu.data import make_sampler

    agent = _agent(**{"atari.eval_epsilon": 0.0})
    batch = make_sampler(converted, agent.batch_spec, seed=2).sample()
    obs = {k: v[:, 0] for k, v in batch.observation.items()}
    first = np.ones(8, bool)
    agent.act(obs, is_first=first)
    h_first = agent._state[0].clone()
    agent.act(obs, is_first=np.zeros(8, bool))  # went on: the state moved
    assert not torch.allclose(agent._state[0], h_first)
    agent.act(obs, is_first=first)  # reset: the same state as the first call's
    torch.testing.assert_close(agent._state[0], h_first)


def test_r2d2_trains_on_the_converted_dmlab_shard(converted, tmp_path):
    run = tmp_path / "run"
    argv = ["train", "--task", TASK, "--agent", "r2d2", "--dataset", str(converted), "--out",
            str(run), "--steps", "3", "--eval-every", "-1", "--device", "cpu", "--quiet",
            "atari.batch_size=4", "sequence_length=3", "burn_in=2", "lstm_size=8",
            "atari.hidden_size=16"]  # fmt: skip
    assert main(argv) == 0
    result = json.loads((run / "result.json").read_text())
    assert result["steps"] == 3 and result["score"] is None
    (last,) = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()][-1:]
    assert last["step"] == 3 and np.isfinite(last["critic/loss"])
