"""Exact numbers of Decision Transformer's pieces (rlu.agents.dt) on tiny inputs worked out by
hand: the two action losses, both learning-rate schedules, the return to go an acting step
conditions on, the token order, the acting context's bookkeeping, minGPT's weight-decay split,
and the causal mask (what a prediction may and may not see)."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rlu.agents import dt  # noqa: E402
from rlu.types import ArraySpec  # noqa: E402


def close(a, b, tol=1e-6):
    np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b, np.float64), atol=tol)


def test_continuous_loss_is_the_mean_square_over_weighted_steps_and_dimensions():
    predicted = torch.tensor([[[0.5, 0.0], [-1.0, 1.0], [0.0, 0.0]]])
    action = torch.tensor([[[0.0, 0.0], [-1.0, 0.0], [1.0, 1.0]]])
    weight = torch.tensor([[1.0, 1.0, 0.0]])  # the third step is padding
    loss, metrics = dt.continuous_action_loss(predicted, action, weight)
    # step 1: (0.25 + 0) / 2, step 2: (0 + 1) / 2, step 3 left out
    close(loss, (0.125 + 0.5) / 2)
    assert metrics["actor/loss"] is loss
    nothing, _ = dt.continuous_action_loss(predicted, action, torch.zeros(1, 3))
    assert nothing.item() == 0.0  # no real step: 0, not NaN


def test_discrete_loss_is_the_cross_entropy_over_weighted_steps():
    logits = torch.tensor([[[0.0, math.log(3.0)], [2.0, 0.0], [0.0, 5.0]]])
    action = torch.tensor([[1, 1, 0]])
    weight = torch.tensor([[1.0, 1.0, 0.0]])
    loss, metrics = dt.discrete_action_loss(logits, action, weight)
    # softmax(0, ln 3) = (1/4, 3/4): -ln(3/4); softmax(2, 0)[1] = 1 / (1 + e^2)
    close(loss, (math.log(4 / 3) + math.log(1 + math.e**2)) / 2)
    close(metrics["actor/accuracy"], 0.5)  # step 1 right, step 2 wrong, step 3 not counted


def test_gym_learning_rate_warms_up_linearly_then_stays():
    c = dt.DTConfig(warmup_steps=4)
    got = [dt.learning_rate_multiplier(step, c) for step in range(6)]
    assert got == [0.25, 0.5, 0.75, 1.0, 1.0, 1.0]  # LambdaLR: min((step + 1) / warmup, 1)


def test_atari_learning_rate_counts_tokens_and_decays_by_a_cosine_to_a_tenth():
    a = dt.AtariDT(batch_size=2, context_length=5, warmup_tokens=25, final_tokens=125)
    m = [dt.learning_rate_multiplier(step, a) for step in range(14)]
    assert m[0] == 1.0  # the Atari code sets its rate after an update: the first runs at 1
    close(m[1:3], [10 / 25, 20 / 25])  # 10 tokens an update, linear up to 25
    close(m[3], 0.5 * (1 + math.cos(math.pi * 5 / 100)))  # 30 tokens: 5 of the 100 past warm-up
    close(m[8], 0.5 * (1 + math.cos(math.pi * 55 / 100)))
    assert m[12] == 0.1 and m[13] == 0.1  # past final_tokens: the floor (the cosine stops)


def test_paper_schedules_in_the_codes_units():
    a = dt.AtariDT()
    assert a.warmup_tokens == 512 * 20 and a.final_tokens == 2 * 500_000 * 3 * 30
    # the first update at the base rate, then 3,840 tokens an update: warm for 2 more updates
    assert [dt.learning_rate_multiplier(s, a) for s in (0, 1, 2)] == [1.0, 0.375, 0.75]
    assert dt.learning_rate_multiplier(3, a) == pytest.approx(1.0, abs=1e-5)
    assert dt.learning_rate_multiplier(10**6, a) == 0.1


def test_return_to_go_starts_at_the_target_and_loses_each_reward():
    previous = torch.tensor([0.9, 0.5, 0.3])
    reward = torch.tensor([100.0, 7.0, -50.0])
    first = torch.tensor([False, True, False])
    got = dt.next_return_to_go(previous, reward, first, 850.0, 1000.0)
    close(got, [0.9 - 0.1, 0.85, 0.3 + 0.05])
    as_tensor = dt.next_return_to_go(previous, reward, first, torch.tensor(850.0), 1000.0)
    close(as_tensor, got)


def test_tokens_interleave_return_state_action_per_step():
    r, s, a = (torch.full((1, 2, 1), v) for v in (1.0, 2.0, 3.0))
    s[0, 1] = 20.0
    a[0, 1] = 30.0
    r[0, 1] = 10.0
    assert dt.interleave(r, s, a).flatten().tolist() == [1, 2, 3, 10, 20, 30]


def test_push_restarts_rolls_and_fills_the_next_slot():
    k = 2
    ctx = dt.Context(
        states=torch.tensor([[[1.0], [2.0]], [[3.0], [4.0]], [[5.0], [0.0]]]),
        actions=torch.tensor([[7, 8], [9, 10], [11, 0]]),
        returns=torch.tensor([[0.1, 0.2], [0.3, 0.4], [0.5, 0.0]]),
        timesteps=torch.tensor([[3, 4], [8, 9], [0, 0]]),
        length=torch.tensor([2, 2, 1]),
    )
    first = torch.tensor([True, False, False])  # row 0 restarts, row 1 is full, row 2 has room
    state = torch.tensor([[-1.0], [-2.0], [-3.0]])
    new, slot = dt.push(ctx, state, torch.tensor([0.9, 0.8, 0.7]), torch.tensor([0, 10, 1]), first)
    assert slot.tolist() == [0, 1, 1] and new.length.tolist() == [1, 2, 2]
    assert new.states[:, :, 0].tolist() == [[-1.0, 2.0], [4.0, -2.0], [5.0, -3.0]]
    assert new.timesteps.tolist() == [[0, 4], [9, 10], [0, 1]]
    close(new.returns, [[0.9, 0.2], [0.4, 0.8], [0.5, 0.7]])
    # the new step's action slot is empty until the agent acts; row 1 dropped its oldest step
    assert new.actions.tolist() == [[0, 8], [10, 0], [11, 0]]
    assert new.states.shape[1] == k and ctx.length.tolist() == [2, 2, 1]  # the old one is intact


def test_weight_decay_falls_on_linear_and_convolution_weights_only():
    model = torch.nn.Sequential(
        torch.nn.Conv2d(1, 2, 3), torch.nn.Linear(3, 4), torch.nn.LayerNorm(4),
        torch.nn.Embedding(5, 4),
    )  # fmt: skip
    model.register_parameter("position", torch.nn.Parameter(torch.zeros(3)))
    decay, rest = dt.decay_groups(model, 0.1)
    assert decay["weight_decay"] == 0.1 and rest["weight_decay"] == 0.0
    assert {id(p) for p in decay["params"]} == {id(model[0].weight), id(model[1].weight)}
    assert len(rest["params"]) == 6  # two biases, LayerNorm's two, the embedding, the position


@pytest.mark.parametrize("discrete", [False, True])
def test_a_prediction_sees_its_return_and_state_and_nothing_after_them(discrete):
    """The causal mask over (R_t, s_t, a_t): the action predicted at step t changes with R_t and
    s_t, and not with a_t or any later token; so padding after the real steps changes nothing."""
    torch.manual_seed(0)
    if discrete:
        c = dt.AtariDT(context_length=3, num_layers=2, num_heads=2, hidden_size=8, dropout=0.0)
        model = dt.AtariDTModel((36, 36, 4), 5, c).eval()
        actions = torch.tensor([[1, 2, 3]])
        states = model.state_tokens(torch.randint(0, 255, (1, 3, 36, 36, 4), dtype=torch.uint8), 2)
    else:
        c = dt.DTConfig(context_length=3, num_layers=2, num_heads=2, hidden_size=8, dropout=0.0)
        spec = {"x": ArraySpec((3,), "float32")}
        model = dt.ContinuousDT(spec, 2, c).eval()
        actions = torch.rand(1, 3, 2) * 2 - 1
        states = model.state_tokens({"x": torch.randn(1, 3, 3)}, 2)
    returns, timesteps = torch.tensor([[0.5, 0.4, 0.1]]), torch.tensor([[4, 5, 6]])
    with torch.no_grad():
        base = model(states, actions, returns, timesteps)
        later = actions.clone()
        later[0, 1:] = later[0, 1:].flip(-1) if not discrete else torch.tensor([4, 0])
        moved = states.clone()
        moved[0, 2] += torch.randn(moved.shape[-1])  # not a uniform shift: LayerNorms undo it
        other_r = returns.clone()
        other_r[0, 1] = -3.0
        a = model(states, later, returns, timesteps)  # a_2, a_3 changed
        s = model(moved, actions, returns, timesteps)  # s_3 changed
        r = model(states, actions, other_r, timesteps)  # R_2 changed
        short = model(states[:, :2], actions[:, :2], returns[:, :2], timesteps[:, :2])
    close(a[0, :2], base[0, :2], 1e-6)  # step 2's prediction never sees a_2
    close(s[0, :2], base[0, :2], 1e-6)
    close(short[0], base[0, :2], 1e-6)  # the third step works as padding would
    assert not torch.allclose(s[0, 2], base[0, 2]) and not torch.allclose(r[0, 1], base[0, 1])
    close(r[0, 0], base[0, 0], 1e-6)
