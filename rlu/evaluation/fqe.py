"""Fitted Q Evaluation (Le et al. 2019; Paine et al. 2020's offline policy selection): the value
of a policy estimated from logged data only, never from the environment.

``Q`` is regressed on ``r + gamma * discount * Q_target(s', pi(s'))`` over the dataset's SARSA
transitions, with a target network copied every ``target_period`` steps; the estimate is the
mean of ``Q(s_0, pi(s_0))`` over the dataset's first observations. Observations are flattened
and concatenated (dict keys in sorted order); discrete actions use one Q head per action,
continuous actions are an input. The policy is a callable on batched observations, as in
``rlu.evaluation.rollout``. PyTorch is imported when an estimate is computed. ``device`` holds
the whole transition set and the network (the CPU by default); the network is initialised on
the CPU under ``config.seed`` and the minibatch indices come from numpy, so only the arithmetic
depends on the device.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rlu.devices import resolve_device
from rlu.files import (
    FRACTION,
    LAYERS,
    LEARNING_RATE,
    MAX_BATCH,
    MAX_STEPS,
    Checked,
    bounds,
)
from rlu.types import DiscreteSpec, Policy, RluError


@dataclass(frozen=True)
class FQEConfig(Checked):
    """Fitted Q Evaluation's settings: discount, network, optimiser, steps and batches (``rlu report
    --fqe`` takes ``--fqe-steps``)."""

    gamma: float = field(default=0.99, metadata=FRACTION)
    """Discount of the estimated value."""
    hidden: tuple[int, ...] = field(default=(128, 128), metadata=LAYERS)
    """MLP hidden layer sizes."""
    learning_rate: float = field(default=1e-3, metadata=LEARNING_RATE)
    """Adam learning rate."""
    steps: int = field(default=2000, metadata=bounds(min=1, max=MAX_STEPS, metavar="N"))
    """FQE gradient steps."""
    batch_size: int = field(default=256, metadata=bounds(min=1, max=MAX_BATCH, metavar="N"))
    """Transitions per gradient step."""
    target_period: int = field(default=100, metadata=bounds(min=1, max=MAX_STEPS, metavar="N"))
    """Steps between copies of the online network into the target network."""
    seed: int = field(default=0, metadata=bounds(min=0, max=2**63 - 1))
    """Seeds the network initialisation and the minibatch order."""


def _flat(obs: Any) -> np.ndarray:
    if isinstance(obs, Mapping):
        parts = [np.asarray(obs[k], np.float32).reshape(len(obs[k]), -1) for k in sorted(obs)]
        return np.concatenate(parts, axis=1)
    obs = np.asarray(obs)
    return obs.reshape(len(obs), -1).astype(np.float32)


def _all_first(x: Any) -> tuple[np.ndarray, np.ndarray]:
    """``is_first`` and ``reward`` of a policy call whose every row starts an episode."""
    n = len(next(iter(x.values())) if isinstance(x, Mapping) else x)
    return np.ones(n, bool), np.zeros(n, np.float64)


def _actions(actions: Any, discrete: bool, rows: int) -> Any:
    """Actions as the Q network takes them: indices (discrete) or rows of float32 vectors."""
    import torch

    if discrete:
        return torch.as_tensor(np.asarray(actions).astype(np.int64)).reshape(-1)
    return torch.as_tensor(np.asarray(actions).astype(np.float32).reshape(rows, -1))


def _mlp(in_dim: int, hidden: Any, out_dim: int) -> Any:
    """ReLU layers of ``hidden`` widths between ``in_dim`` inputs and ``out_dim`` outputs."""
    import torch

    layers: list[Any] = []
    d = in_dim
    for h in hidden:
        layers += [torch.nn.Linear(d, h), torch.nn.ReLU()]
        d = h
    layers.append(torch.nn.Linear(d, out_dim))
    return torch.nn.Sequential(*layers)


def fqe_estimate(
    transitions: Any,
    initial_observations: Any,
    policy: Policy,
    action_spec: Any,
    config: FQEConfig = FQEConfig(),
    device: Any = "cpu",
    progress: Any = None,
) -> float:
    """FQE estimate of ``policy``'s value at the data's initial observations.

    ``transitions`` is an ``rlu.types.Transition`` batch holding the whole (or a subsample of
    the) dataset; ``initial_observations`` are the first observations of its episodes.
    ``progress``: an ``rlu.progress.Progress`` counting the gradient steps (or None).
    """
    import torch

    n = len(transitions.reward)
    if n == 0:
        raise RluError("FQE needs at least one transition; the dataset is empty")
    discrete = isinstance(action_spec, DiscreteSpec)
    rng = np.random.default_rng(config.seed)
    dev = resolve_device(device)

    obs = torch.from_numpy(_flat(transitions.observation))
    next_obs = torch.from_numpy(_flat(transitions.next_observation))
    init = torch.from_numpy(_flat(initial_observations))
    # the policy sees observations only, in the env's format
    # every observation is valued on its own: a recurrent policy starts afresh on each row (a
    # return-conditioned one from its target return, at timestep 0)
    next_act = np.asarray(policy(transitions.next_observation, *_all_first(transitions.action)))
    init_act = np.asarray(policy(initial_observations, *_all_first(initial_observations)))
    reward = torch.as_tensor(np.asarray(transitions.reward, np.float32))
    discount = torch.as_tensor(np.asarray(transitions.discount, np.float32))
    act, next_act_t, init_act_t = (
        _actions(a, discrete, rows)
        for a, rows in ((transitions.action, n), (next_act, n), (init_act, len(init)))
    )
    # a discrete Q network values every action of an observation, a continuous one the pair
    in_dim = obs.shape[1] if discrete else obs.shape[1] + act.shape[1]
    out_dim = action_spec.num_values if discrete else 1

    obs, next_obs, init, reward, discount, act, next_act_t, init_act_t = (
        t.to(dev) for t in (obs, next_obs, init, reward, discount, act, next_act_t, init_act_t)
    )
    # inputs standardised with data statistics (what the network sees is data only)
    mu = obs.mean(0)
    sd = obs.std(0, unbiased=False).clamp_min(1e-6)

    def q_values(net: Any, o: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        x = (o - mu) / sd
        if discrete:
            return net(x).gather(1, a[:, None])[:, 0]
        return net(torch.cat([x, a], dim=1))[:, 0]

    with torch.random.fork_rng(devices=[]):  # leaves the caller's global torch RNG untouched
        torch.manual_seed(config.seed)
        net = _mlp(in_dim, config.hidden, out_dim).to(dev)
        target = _mlp(in_dim, config.hidden, out_dim).to(dev)
    target.load_state_dict(net.state_dict())
    opt = torch.optim.Adam(net.parameters(), lr=config.learning_rate)
    for step in range(config.steps):
        if progress is not None:
            progress.update(1)
        if step % config.target_period == 0:
            target.load_state_dict(net.state_dict())
        idx = torch.from_numpy(rng.integers(0, n, size=min(config.batch_size, n))).to(dev)
        with torch.no_grad():
            y = reward[idx] + config.gamma * discount[idx] * q_values(
                target, next_obs[idx], next_act_t[idx]
            )
        loss = torch.nn.functional.mse_loss(q_values(net, obs[idx], act[idx]), y)
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        return float(q_values(net, init, init_act_t).mean())


def dataset_fqe_inputs(ds: Any) -> tuple[Any, Any]:
    """(all SARSA transitions, first observations of every episode) of an rlu dataset."""
    from rlu.data.views import DatasetView, TransitionView

    view = TransitionView(ds)
    starts = np.asarray(ds.start, np.int64)
    first = np.asarray(ds.column("is_first"))[starts]
    seg = np.flatnonzero(first)
    init = DatasetView(ds).observation(seg, starts[seg])
    return view.all(), init


def fqe_selection(
    records: Sequence[Mapping[str, Any]],
    datasets: Mapping[str, str],
    policy_of: Callable[[str], tuple[Policy, Any]],
    config: FQEConfig = FQEConfig(),
    device: Any = "cpu",
    quiet: bool = False,
) -> dict[str, Any]:
    """Offline policy selection by FQE: per (task, agent), every configuration's policies (one
    per seed, from ``policy_of(run) -> (policy, action_spec)``) are valued by FQE on the task's
    dataset (data only); the configuration with the best mean estimate is chosen and scored
    against the true returns (Spearman rank correlation, regret@1). Progress (FQE gradient
    steps over every run) on stderr unless ``quiet``."""
    from collections import defaultdict
    from dataclasses import asdict

    from rlu.data import open_dataset
    from rlu.evaluation.protocols import select_by_estimate
    from rlu.progress import Progress

    groups: dict[tuple[str, str], dict[str, list[Mapping[str, Any]]]] = defaultdict(
        lambda: defaultdict(list)
    )
    for r in records:
        groups[(r["task"], r["agent"])][r["config"]].append(r)
    inputs: dict[str, Any] = {}
    selections = []
    bar = Progress(len(records) * config.steps, "FQE", "steps", quiet=quiet)
    for (task, agent), by_config in sorted(groups.items()):
        if task not in datasets:
            raise RluError(f"no dataset recorded for task {task!r}; FQE needs the sweep's data")
        if task not in inputs:
            inputs[task] = dataset_fqe_inputs(open_dataset(datasets[task]))
        transitions, init = inputs[task]
        estimates, true = {}, {}
        for label, runs in sorted(by_config.items()):
            values = []
            for r in runs:
                policy, action_spec = policy_of(r["run"])
                values.append(fqe_estimate(transitions, init, policy, action_spec, config, device,
                                           progress=bar))  # fmt: skip
            estimates[label] = float(np.mean(values))
            true[label] = float(np.mean([r["score"] for r in runs]))
        selection = select_by_estimate(estimates, true)
        selections.append(
            {
                "task": task,
                "agent": agent,
                "estimates": estimates,
                "true_returns": true,
                **asdict(selection),
            }  # fmt: skip
        )
    bar.close()
    return {"selections": selections}
