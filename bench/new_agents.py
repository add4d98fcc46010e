"""The newer agents (continuous CRR, IQL, CQL, TD3+BC, ReBRAC; discrete CQL) vs d3rlpy's
implementations of the same algorithms: returns after the same number of updates on the same
data, and updates/s.

    .venv-bench/bin/python bench/new_agents.py                       # all of them, where registered
    .venv-bench/bin/python bench/new_agents.py --agents cql-discrete --steps 1000 --seeds 3
    .venv-bench/bin/python bench/new_agents.py --agents iql --control-data PATH --steps 20000

d3rlpy lives in the bench's own venv (see bench/README.md), never in rlu's dependencies. rlu's
agents are built by name with ``rlu.agents.make_agent``; an agent not registered in
``rlu.agents.AGENTS`` yet is skipped with a line saying so.

Data and evaluation:
- continuous (``crr``, ``iql``, ``cql``, ``td3bc``, ``rebrac``): an rlu dataset of
  control_suite/cartpole_swingup (by default the one the package bundles; ``rlu generate
  control_suite/cartpole_swingup --scale small`` makes a larger one), evaluated in
  dm_control's cartpole swingup through ``rlu.evaluation.evaluate`` for both libraries.
  d3rlpy sees the observation dict concatenated in sorted key order, a vector encoder of the
  widths rlu's config names, and rlu's learning rates, batch size, discount and algorithm
  constants (the mapping: ``agents_continuous.py`` ``d3rlpy_config``).
  Where rlu's agent has a part d3rlpy's lacks (the per-key observation torso, a distributional
  critic, a behaviour-cloning warm-up, ReBRAC's initialisation of its original), d3rlpy runs
  without it: the returns compare the algorithms as each library ships them, at equal widths;
  the rlu config is printed. An agent that asks for dataset statistics (TD3+BC's observation
  normalisation) gets them from ``rlu.data.statistics``, and d3rlpy a
  ``StandardObservationScaler`` with the same mean and std (both divide by std + 1e-3).
- discrete (``cql-discrete``): the corridor of the discrete learning check
  (``tests/agents/test_learning_discrete.py``: 84x84 frames, four stacked, three actions, the
  data's majority action "left" pays 0.1, "right" pays 1.0), recorded through rlu's store as
  whole episodes. d3rlpy reads the same episodes as single frames with its
  ``FrameStackTransitionPicker(4)``: the same stacks, zero frames before the start. Both run
  double DQN + Huber + alpha (logsumexp Q - Q(s, a_data)) on the same network (the learning
  check's narrow Nature CNN: 8-16-16 filters, 64 units), batch 32, Adam 3e-4 with epsilon 1e-7,
  rewards clipped to [-1, 1], discount 0.9 and a hard target copy every 100 updates, as in the
  learning check; ``--alphas`` sets the CQL weights.

Returns: each library trains ``--steps`` updates per seed; the table prints the mean return of
``--episodes`` evaluation episodes per seed and their mean over seeds.

Speed: updates per second of "draw a batch from the library's own sampler + one update" (rlu:
``make_sampler(...).sample()`` then ``agent.update``; d3rlpy: ``sample_transition_batch`` then
``algo.update``), same batch size, same torch thread count (``--threads``), timed in
interleaved rounds in a fresh order each round, median round; wall-clock and process-CPU rates
are both printed with the machine's load average before and after, because the machines this
runs on are shared. Sampling alone is timed too, to show where the time goes. Discrete speed
runs twice: at the learning check's small network (batch 32) and at the paper's Nature CNN
(32-64-64 filters, 512 units, batch 256). The arithmetic per update is not equal: d3rlpy's
DiscreteCQL runs the Q-network on the observations twice with gradients (once inside its TD
error, once for the penalty), rlu's once, so its update does about one forward and backward
pass more.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

# d3rlpy's config of the same algorithm with rlu's widths and constants: one mapping for benches
from agents_continuous import d3rlpy_config as d3rlpy_continuous  # noqa: E402

from rlu.agents import AGENTS, make_agent  # noqa: E402
from rlu.data import open_dataset  # noqa: E402
from rlu.data.statistics import dataset_statistics  # noqa: E402
from rlu.data.views import make_sampler  # noqa: E402
from rlu.system import available_cores  # noqa: E402

CONTINUOUS = ("crr", "iql", "cql", "td3bc", "rebrac")
DISCRETE = ("cql-discrete",)
CONTROL_TASK = "control_suite/cartpole_swingup"
NATURE = {"atari.channels": (32, 64, 64), "atari.hidden_size": 512, "atari.batch_size": 256}


def load_line() -> str:
    one, five, _ = os.getloadavg()
    return f"load average {one:.2f} (1 min), {five:.2f} (5 min) on {available_cores()} cores"


# ----------------------------------------------------------------------------- data


def d3rlpy_buffer(ds, frame_stack: int, discrete: bool, num_actions: int | None = None):
    """rlu's episodes as d3rlpy episodes: a terminal episode keeps its T acting rows (d3rlpy's
    next observation after a terminal is zeros, discount 0), a truncated one keeps its final
    observation as row T + 1, so both libraries see the same T transitions per episode."""
    from d3rlpy.constants import ActionSpace
    from d3rlpy.dataset import (
        BasicTransitionPicker,
        Episode,
        FrameStackTransitionPicker,
        InfiniteBuffer,
        ReplayBuffer,
    )

    episodes = []
    for seg in ds.segments():
        terminated = bool(seg.is_terminal[-1])
        rows = len(seg.action) - 1 if terminated else len(seg.action)
        obs = seg.observation
        if isinstance(obs, dict):
            obs = np.concatenate([obs[k] for k in sorted(obs)], -1).astype(np.float32)
        else:  # single frames (T, H, W) -> d3rlpy's channel-first (T, 1, H, W)
            obs = obs[:, None]
        action = seg.action[:rows]
        action = action.reshape(rows, 1) if discrete else action.astype(np.float32)
        reward = seg.reward[:rows].astype(np.float32).reshape(rows, 1)
        episodes.append(Episode(obs[:rows], action, reward, terminated))
    picker = FrameStackTransitionPicker(frame_stack) if frame_stack > 1 else BasicTransitionPicker()
    space = ActionSpace.DISCRETE if discrete else ActionSpace.CONTINUOUS
    size = num_actions if discrete else int(ds.schema.action.shape[0])
    return ReplayBuffer(
        InfiniteBuffer(), episodes=episodes, transition_picker=picker, action_space=space,
        action_size=size,
    )  # fmt: skip


def corridor(tmp: str, episodes: int):
    """The learning check's corridor dataset (tests/agents/test_learning_discrete.py)."""
    from tests.agents import test_learning_discrete as corridor_check

    path = Path(tmp) / "corridor"
    corridor_check.record(path, episodes=episodes, seed=0)
    return open_dataset(path), corridor_check


# ----------------------------------------------------------------------------- d3rlpy configs


def d3rlpy_discrete_cql(c, seed: int):
    """d3rlpy's DiscreteCQL on rlu's discrete CQL config: the same network shape and constants."""
    import d3rlpy
    from d3rlpy.models.encoders import PixelEncoderFactory

    a = c.atari
    filters = [list(f) for f in zip(a.channels, a.kernel_sizes, a.strides, strict=True)]
    d3rlpy.seed(seed)
    return d3rlpy.algos.DiscreteCQLConfig(
        batch_size=a.batch_size,
        learning_rate=c.learning_rate,
        gamma=a.gamma,
        alpha=c.alpha,
        target_update_interval=a.target_update_period,
        optim_factory=d3rlpy.optimizers.AdamFactory(eps=a.adam_eps),
        encoder_factory=PixelEncoderFactory(filters=filters, feature_size=a.hidden_size),
        observation_scaler=d3rlpy.preprocessing.PixelObservationScaler(),
        reward_scaler=d3rlpy.preprocessing.ClipRewardScaler(-a.reward_clip, a.reward_clip),
    ).create(device="cpu:0")


# ----------------------------------------------------------------------------- contestants


class Contestant:
    """One library's learner on one dataset: ``step()`` samples a batch and updates once."""

    def __init__(self, sample: Callable[[], object], update: Callable[[object], object]):
        self.sample, self.update = sample, update

    def step(self) -> None:
        self.update(self.sample())

    def train(self, steps: int) -> None:
        for _ in range(steps):
            self.step()


def discrete_pair(ds, check, alpha: float, seed: int, overrides: dict):
    """(rlu contestant, rlu agent, d3rlpy contestant, d3rlpy algo) for discrete CQL."""
    agent = make_agent("cql", check.OBS, check.ACTION, "small", seed=seed, alpha=alpha, **overrides)
    algo = d3rlpy_discrete_cql(agent.config, seed)
    return pair(ds, agent, algo, d3rlpy_buffer(ds, 4, True, check.ACTION.num_values), seed)


def pair(ds, agent, algo, buffer, seed: int):
    """Both learners on the same data, each drawing batches of the same size its own way."""
    algo.build_with_dataset(buffer)
    sampler = make_sampler(ds, agent.batch_spec, seed=seed)
    size = agent.batch_spec.batch_size
    return (
        Contestant(sampler.sample, agent.update), agent,
        Contestant(lambda: buffer.sample_transition_batch(size), algo.update), algo,
    )  # fmt: skip


class D3rlpyFramePolicy:
    """d3rlpy's greedy action on rlu's (B, H, W, frames) stacks (d3rlpy is channel-first)."""

    def __init__(self, algo):
        self.algo = algo

    def act(
        self, observation: np.ndarray, greedy: bool = True, is_first=None, reward=None
    ) -> np.ndarray:
        return self.algo.predict(np.ascontiguousarray(observation.transpose(0, 3, 1, 2)))


def continuous_pair(name: str, ds, seed: int, preset: str):
    import d3rlpy

    agent = make_agent(name, ds.schema.observation, ds.schema.action, preset, seed=seed)
    config = d3rlpy_continuous(name, agent.config)
    if agent.batch_spec.statistics:  # both normalise with the same statistics, eps 1e-3
        stats = dataset_statistics(ds, agent.batch_spec.statistics)
        agent.set_statistics(stats)
        mean, std = stats.observation_mean, stats.observation_std
        config.observation_scaler = d3rlpy.preprocessing.StandardObservationScaler(
            mean=np.concatenate([mean[k] for k in sorted(mean)]),
            std=np.concatenate([std[k] for k in sorted(std)]),
        )
    d3rlpy.seed(seed)
    algo = config.create(device="cpu:0")
    return pair(ds, agent, algo, d3rlpy_buffer(ds, 1, False), seed)


def d3rlpy_vector_policy(algo) -> Callable[..., np.ndarray]:
    """A ``rlu.types.Policy`` (observations, ``is_first`` and rewards in, actions out) of
    d3rlpy's greedy action."""

    def policy(observation: dict, is_first=None, reward=None) -> np.ndarray:
        x = np.concatenate([observation[k] for k in sorted(observation)], -1)
        return algo.predict(x.astype(np.float32))

    return policy


# ----------------------------------------------------------------------------- timing


def time_rounds(contestants: dict[str, Contestant], rounds: int, updates: int, warmup: int):
    """Median (wall, CPU) updates/s per contestant over interleaved rounds."""
    for c in contestants.values():
        c.train(warmup)
    wall: dict[str, list[float]] = {n: [] for n in contestants}
    cpu: dict[str, list[float]] = {n: [] for n in contestants}
    order = np.random.default_rng(0)
    for _ in range(rounds):
        # a fresh order every round, so no contestant always runs first after a quiet spell
        for name in order.permutation(list(contestants)):
            w0, c0 = time.perf_counter(), time.process_time()
            contestants[name].train(updates)
            wall[name].append(updates / (time.perf_counter() - w0))
            cpu[name].append(updates / max(time.process_time() - c0, 1e-9))
    return {n: (statistics.median(wall[n]), statistics.median(cpu[n])) for n in contestants}


def speed(title: str, rlu: Contestant, d3: Contestant, args, warmup: int) -> None:
    """Time sample + update, and sampling alone, for both libraries (interleaved rounds)."""
    rates = time_rounds(
        {
            "rlu": rlu, "d3rlpy": d3,
            "rlu sampling": Contestant(rlu.sample, lambda batch: None),
            "d3rlpy sampling": Contestant(d3.sample, lambda batch: None),
        },
        args.rounds, args.updates, warmup,
    )  # fmt: skip
    print(f"  {title}")
    for name, (w, c) in rates.items():
        unit = "batches" if name.endswith("sampling") else "updates"
        print(f"    {name:16s} {w:9.2f} {unit}/s wall  {c:9.2f} {unit} per CPU-second")
    for what, label in (("", "sample + update"), (" sampling", "sampling alone")):
        (rw, rc), (dw, dc) = rates[f"rlu{what}"], rates[f"d3rlpy{what}"]
        print(f"    rlu / d3rlpy, {label}: {rw / dw:.2f}x wall, {rc / dc:.2f}x CPU")


# ----------------------------------------------------------------------------- benches


def bench_discrete(args) -> None:
    episodes = args.corridor_episodes
    print(f"\ndiscrete cql vs d3rlpy DiscreteCQL on the corridor ({episodes} episodes)")
    with tempfile.TemporaryDirectory() as tmp:
        ds, check = corridor(tmp, episodes)
        returns = ds.episode_returns()
        print(
            f"  data: {ds.num_steps} steps, behaviour return {returns.mean():.3f} (majority action "
            f"'left' pays {check.LEFT_REWARD}, 'right' {check.RIGHT_REWARD})"
        )
        overrides = {**check.COMMON, "atari.target_update_period": 100, "atari.gamma": 0.9}
        for alpha in [] if args.speed_only else args.alphas:
            scores: dict[str, list[float]] = {"rlu": [], "d3rlpy": []}
            for seed in range(args.seeds):
                rlu_c, agent, d3_c, algo = discrete_pair(ds, check, alpha, seed, overrides)
                rlu_c.train(args.steps)
                d3_c.train(args.steps)
                scores["rlu"].append(check.evaluate(agent, args.episodes))
                scores["d3rlpy"].append(check.evaluate(D3rlpyFramePolicy(algo), args.episodes))
            print(f"  alpha {alpha}: return after {args.steps} updates, per seed and mean")
            for name, s in scores.items():
                print(f"    {name:8s} {np.round(s, 3).tolist()}  mean {np.mean(s):.3f}")
        print(f"  speed (sample + update), {torch.get_num_threads()} thread(s); {load_line()}")
        sizes = {
            "learning-check network, batch 32": overrides,
            "Nature CNN, batch 256": {**overrides, **NATURE},
        }
        for title, o in sizes.items():
            rlu_c, _, d3_c, _ = discrete_pair(ds, check, 1.0, 0, o)
            speed(title, rlu_c, d3_c, args, warmup=2)
        print(f"  after: {load_line()}")


def bench_continuous(name: str, args) -> None:
    from rlu.data.bundled import bundled_dataset
    from rlu.evaluation import evaluate, task_env_factory
    from rlu.training.loop import greedy_policy

    path = args.control_data or bundled_dataset(CONTROL_TASK)
    ds = open_dataset(path)
    print(f"\n{name} vs d3rlpy on {path} ({ds.num_steps} steps), preset {args.preset!r}")
    try:
        pairs = [continuous_pair(name, ds, seed, args.preset) for seed in range(args.seeds)]
    except AttributeError as e:
        print(f"  skip {name}: the d3rlpy mapping reads a field rlu's config lacks ({e}); update "
              "d3rlpy_config in bench/agents_continuous.py")  # fmt: skip
        return
    print(f"  rlu config: {dataclasses.asdict(pairs[0][1].config)}")
    env_fn = task_env_factory(CONTROL_TASK)
    scores: dict[str, list[float]] = {"rlu": [], "d3rlpy": []}
    for rlu_c, agent, d3_c, algo in [] if args.speed_only else pairs:
        rlu_c.train(args.steps)
        d3_c.train(args.steps)
        for lib, policy in (("rlu", greedy_policy(agent)), ("d3rlpy", d3rlpy_vector_policy(algo))):
            result = evaluate(policy, env_fn, args.episodes, seed=1000)
            scores[lib].append(float(np.mean(result.returns)))
    if not args.speed_only:
        print(f"  return after {args.steps} updates, per seed and mean")
        for lib, s in scores.items():
            print(f"    {lib:8s} {np.round(s, 1).tolist()}  mean {np.mean(s):.1f}")
    print(f"  speed (sample + update), {torch.get_num_threads()} thread(s); {load_line()}")
    rlu_c, _, d3_c, _ = continuous_pair(name, ds, 0, args.preset)
    speed(f"batch {pairs[0][1].batch_spec.batch_size}", rlu_c, d3_c, args, warmup=5)
    print(f"  after: {load_line()}")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--agents", nargs="+", default=[*CONTINUOUS, *DISCRETE],
                   choices=[*CONTINUOUS, *DISCRETE])  # fmt: skip
    p.add_argument("--steps", type=int, default=1000, help="updates per library and seed")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--episodes", type=int, default=5, help="evaluation episodes per seed")
    p.add_argument("--alphas", type=float, nargs="+", default=[0.1, 1.0],
                   help="discrete CQL weights (the learning check uses 0.1)")  # fmt: skip
    p.add_argument("--corridor-episodes", type=int, default=300)
    p.add_argument("--control-data", default=None, help="an rlu cartpole_swingup dataset")
    p.add_argument("--preset", default="small", help="rlu preset of the continuous agents")
    p.add_argument("--rounds", type=int, default=5, help="interleaved timing rounds")
    p.add_argument("--updates", type=int, default=10, help="timed updates per round")
    p.add_argument("--threads", type=int, default=1, help="torch threads for both libraries")
    p.add_argument("--speed-only", action="store_true", help="skip the returns, time only")
    args = p.parse_args(argv)
    sys.stdout.reconfigure(line_buffering=True)  # long runs: show each result as it comes
    torch.set_num_threads(args.threads)
    try:
        import d3rlpy
        import structlog
    except ImportError:
        sys.exit("d3rlpy is not installed here: run this in the bench venv (bench/README.md)")
    # d3rlpy logs an info line per dataset it builds; only its warnings are worth printing here
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    print(f"torch {torch.__version__}, d3rlpy {d3rlpy.__version__}, {args.threads} thread(s); "
          f"{load_line()}")  # fmt: skip
    for name in args.agents:
        discrete = name in DISCRETE
        key = (name.removesuffix("-discrete"), discrete)
        if key not in AGENTS:
            kind = "discrete" if discrete else "continuous"
            print(f"\nskip {name}: no {kind} agent {key[0]!r} in rlu.agents.AGENTS yet")
            continue
        if discrete:
            bench_discrete(args)
        else:
            bench_continuous(name, args)


if __name__ == "__main__":
    main()
