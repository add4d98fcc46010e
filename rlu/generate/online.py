"""The online actor-learner loop that produces the recorded training runs.

One run = one env, one behaviour agent (D4PG for the control suite and RWRL, distributional MPO
for RWRL at the paper scale, DQN with sticky actions for Atari), a replay of whole episodes and
a recorder. Every episode the actor plays is recorded with its run, seed, checkpoint and episode
index, whatever the agent's quality: the datasets are whole training runs.

Acting: D4PG's ``act`` is deterministic, so the behaviour policy adds Gaussian noise
(``sigma``, Acme's default 0.3) and clips to the action bounds; DMPO (``sigma=None``) samples its
own Gaussian policy, clipped the same way; DQN acts epsilon-greedy with Dopamine's linearly
decayed epsilon (1.0 -> ``epsilon_end`` over ``epsilon_decay_steps``), the agent's own
``act(greedy=False)`` taking the non-random steps. Learning: after ``min_replay``
stored steps, one ``agent.update`` every ``update_every`` env steps on a batch sampled uniformly
from the replay (n-step transitions for D4PG, as Acme's adder; 1-step for DQN, as Dopamine).

Determinism and resumption: every episode resets the env with a seed derived from
``(seed, run, episode)``, so the env carries no state across episodes; the agent, the replay and
the actor's random generator are saved after every chunk of episodes (``RunState``), so a run
resumed from its last chunk produces the same bytes as an uninterrupted one. Torch runs on one
thread here: reductions then do not depend on the machine's core count. The agent may live on a
GPU (``device``); its state is saved device-independently, so a run may resume on another
device (the bytes then follow that device's arithmetic).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rlu.data.episode import Segment
from rlu.generate.recorder import EpisodeRecorder, episode_id
from rlu.tasks import TaskSpec
from rlu.types import ArraySpec, BatchSpec, RluError, Transition


@dataclass(frozen=True)
class OnlineConfig:
    """One behaviour agent's run (see the module docstring)."""

    agent: str
    """The behaviour agent: 'd4pg' (continuous control) or 'dopamine_dqn' (Atari); any registered
    agent whose batch spec samples transitions can play."""
    episodes: int
    """Episodes played (and recorded) per run, at most."""
    env_steps: int | None = None
    """If set, a run also ends with the first episode that reaches this many env steps (Atari's
    budget is in steps: 50M per run in the paper)."""
    preset: str = "small"
    """The agent's preset (rlu.agents); ``agent_overrides`` are applied on top."""
    agent_overrides: Mapping[str, Any] = field(default_factory=dict)
    """Config fields replacing the preset's (e.g. smaller networks at tiny scale)."""
    replay_capacity: int = 100_000
    """Steps the replay holds (oldest whole episodes are dropped first)."""
    min_replay: int = 1_000
    """Stored steps before the first update."""
    update_every: int = 8
    """Env steps per learner update (Acme's D4PG: samples_per_insert 32 at batch 256)."""
    sigma: float | None = 0.3
    """D4PG behaviour noise: standard deviation of the Gaussian added to the action. None: the
    agent's own ``act(greedy=False)`` explores (DMPO samples its Gaussian policy, as Acme's
    behaviour network); either way the action is clipped to the bounds."""
    epsilon_end: float = 0.01
    """DQN: final exploration epsilon (Dopamine)."""
    epsilon_decay_steps: int = 250_000
    """DQN: env steps over which epsilon decays linearly from 1 (Dopamine: 1M frames)."""
    checkpoint_steps: int = 10_000
    """Env steps per checkpoint index (the ``checkpoint`` metadata; Atari's release: 1M)."""
    chunk_episodes: int = 5
    """Episodes per saved part; a crashed run resumes from its last complete chunk."""
    env_settings: Mapping[str, Any] = field(default_factory=dict)
    """Keyword settings of ``rlu.make_env`` (e.g. Atari ``max_episode_steps`` at tiny scale)."""
    policy_dtype: str = "float16"
    """How the behaviour policies kept at each checkpoint store their weights
    (``rlu.generate.policies``): float16 halves them (the bundled cartpole dataset's 18 D4PG
    policies: 2.5 MB, not 4.9 MB, inside its 5 MB budget); 'float32' keeps them exact."""

    def to_json(self) -> dict[str, Any]:
        return {k: (dict(v) if isinstance(v, Mapping) else v) for k, v in asdict(self).items()}


def derive_seed(*keys: int) -> int:
    """A 31-bit seed from a tuple of non-negative ints (numpy's SeedSequence hashing)."""
    return int(np.random.SeedSequence([int(k) for k in keys]).generate_state(1)[0] >> 1)


# --------------------------------------------------------------------------------- replay
class Replay:
    """Whole episodes in a ring of steps, sampled as (n-step) Transitions by index arithmetic.

    Episodes are stored contiguously (the write position wraps to 0 when one does not fit), so
    ``next`` indices stay inside their episode; an episode any of whose steps is overwritten is
    invalidated whole. Atari frames are stored once and stacked at sample time.
    """

    def __init__(self, task: TaskSpec, capacity: int, spec: BatchSpec):
        if spec.kind != "transition":
            raise RluError(
                f"the online replay samples transitions; the behaviour agent asks for {spec.kind!r}"
            )
        self.capacity, self.n_step, self.gamma = int(capacity), spec.n_step, spec.gamma
        self.reward_clip = spec.reward_clip
        self.frame_stack = 4 if task.domain == "atari" else 1
        spec = task.observation_spec
        c = self.capacity
        if isinstance(spec, ArraySpec):
            shape = spec.shape[:-1] if self.frame_stack > 1 else spec.shape
            self.obs: Any = np.zeros((c, *shape), spec.dtype)
        else:
            self.obs = {k: np.zeros((c, *s.shape), s.dtype) for k, s in spec.items()}
        a = task.action_spec
        self.action = np.zeros((c, *a.shape), a.dtype)
        self.reward = np.zeros(c, np.float32)
        self.discount = np.zeros(c, np.float32)
        self.next = np.zeros(c, np.int64)
        self.valid = np.zeros(c, bool)
        self.episode = np.full(c, -1, np.int64)
        self.start = np.zeros(c, np.int64)
        self.pos = 0
        self.num_episodes = 0
        self._eligible = np.zeros(0, np.int64)

    @property
    def size(self) -> int:
        return int(self._eligible.size)

    def add(self, seg: Segment) -> None:
        n = len(seg)
        if n > self.capacity:
            raise RluError(f"replay_capacity={self.capacity} is smaller than one episode ({n})")
        if self.pos + n > self.capacity:
            self.pos = 0
        sl = slice(self.pos, self.pos + n)
        gone = np.unique(self.episode[sl])
        gone = gone[gone >= 0]
        if gone.size:
            self.valid[np.isin(self.episode, gone)] = False
        if isinstance(self.obs, Mapping):
            for k, buf in self.obs.items():
                buf[sl] = seg.observation[k]
        else:
            self.obs[sl] = seg.observation
        self.action[sl] = seg.action
        # n-step targets of every transition t < n - 1, by k-loop over the window (n is small)
        r = np.zeros(n - 1 + self.n_step, np.float64)
        d = np.zeros(n - 1 + self.n_step, np.float64)
        r[: n - 1], d[: n - 1] = seg.reward[: n - 1], seg.discount[: n - 1]
        if self.reward_clip is not None:  # the agent's BatchSpec: clip per step, then sum
            r = np.clip(r, -self.reward_clip, self.reward_clip)
        terminal = bool(seg.is_terminal[-1])
        ret = np.zeros(n - 1)
        disc = np.ones(n - 1)
        for k in range(self.n_step):
            ret += self.gamma**k * disc * r[k : k + n - 1]
            disc *= d[k : k + n - 1]
        t = np.arange(n - 1)
        ok = (t + self.n_step <= n - 1) | terminal
        self.reward[sl] = 0.0
        self.discount[sl] = 0.0
        self.reward[self.pos : self.pos + n - 1] = ret
        self.discount[self.pos : self.pos + n - 1] = disc
        self.next[sl] = self.pos + np.minimum(np.arange(n) + self.n_step, n - 1)
        self.valid[sl] = False
        self.valid[self.pos : self.pos + n - 1] = ok
        self.episode[sl] = self.num_episodes
        self.start[sl] = self.pos
        self.num_episodes += 1
        self.pos += n
        self._eligible = np.flatnonzero(self.valid)

    def _observation(self, idx: np.ndarray) -> Any:
        if isinstance(self.obs, Mapping):
            return {k: v[idx] for k, v in self.obs.items()}
        if self.frame_stack == 1:
            return self.obs[idx]
        rows = idx[:, None] + np.arange(1 - self.frame_stack, 1)
        keep = rows >= self.start[idx][:, None]
        frames = self.obs[np.maximum(rows, 0)] * keep[:, :, None, None].astype(np.uint8)
        return np.ascontiguousarray(np.moveaxis(frames, 1, -1))

    def sample(self, rng: np.random.Generator, batch_size: int) -> Transition:
        idx = self._eligible[rng.integers(0, self._eligible.size, batch_size)]
        nxt = self.next[idx]
        return Transition(
            observation=self._observation(idx),
            action=self.action[idx],
            reward=self.reward[idx],
            discount=self.discount[idx],
            next_observation=self._observation(nxt),
            next_action=self.action[nxt],
        )

    def state(self) -> dict[str, Any]:
        """Plain tensors, dicts and numbers: loadable with ``torch.load(weights_only=True)``."""
        return {k: _to_tensors(v) for k, v in vars(self).items()}

    def load(self, state: Mapping[str, Any]) -> None:
        vars(self).update({k: _from_tensors(v) for k, v in state.items()})


def _to_tensors(v: Any) -> Any:
    import torch

    if isinstance(v, np.ndarray):
        return ("ndarray", torch.from_numpy(np.ascontiguousarray(v)))
    if isinstance(v, Mapping):
        return {k: _to_tensors(x) for k, x in v.items()}
    if isinstance(v, np.generic):
        return v.item()
    return v


def _from_tensors(v: Any) -> Any:
    if isinstance(v, tuple) and len(v) == 2 and v[0] == "ndarray":
        return v[1].numpy()
    if isinstance(v, Mapping):
        return {k: _from_tensors(x) for k, x in v.items()}
    return v


# --------------------------------------------------------------------------------- a run
def make_behaviour_agent(task: TaskSpec, cfg: OnlineConfig, seed: int, device: Any = "cpu"):
    from rlu.agents import make_agent

    return make_agent(
        cfg.agent, task.observation_spec, task.action_spec, cfg.preset, seed, device=device,
        **cfg.agent_overrides,
    )  # fmt: skip


def _save_atomic(obj: Any, path: Path) -> None:
    import torch

    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as fh:
        torch.save(obj, fh)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def run_online(
    task: TaskSpec,
    cfg: OnlineConfig,
    seed: int,
    run: int,
    run_dir: Path,
    write_chunk: Callable[[int, list[Segment]], None],
    on_episode: Callable[[int, int, Segment], None] | None = None,
    on_chunk: Callable[[int, int], None] | None = None,
    on_snapshot: Callable[[int, Any, list[Segment]], None] | None = None,
    device: Any = "cpu",
    on_checkpoint: Callable[[int, int, int, Any], None] | None = None,
) -> None:
    """Play run ``run`` of ``cfg`` (resuming from ``run_dir/state.pt``), handing each finished
    chunk of recorded episodes to ``write_chunk(chunk_index, segments)``, then saving its state
    and calling ``on_chunk(run, chunk_index)``. ``on_snapshot(chunk_index, agent, segments)``
    sees the agent after each chunk (RWRL keeps policy snapshots this way);
    ``on_checkpoint(checkpoint, env_steps, episode, agent)`` sees it before the first episode of
    every checkpoint id (the recipe keeps the behaviour policies this way; a run resumed from
    its last chunk calls it again for the checkpoints after that chunk, with the same agent)."""
    import torch

    from rlu.envs import make_env

    run_dir.mkdir(parents=True, exist_ok=True)
    state_path = run_dir / "state.pt"
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        run_seed = derive_seed(seed, run)
        agent = make_behaviour_agent(task, cfg, run_seed, device)
        batch_size = agent.batch_spec.batch_size
        env = make_env(task.id, seed=run_seed, **cfg.env_settings)
        max_steps = int(cfg.env_settings.get("max_episode_steps", task.episode_length))
        recorder = EpisodeRecorder(task, max_steps)
        replay = Replay(task, cfg.replay_capacity, agent.batch_spec)
        rng = np.random.default_rng([seed, run, 1])
        episode, env_steps, last_checkpoint = 0, 0, -1
        if state_path.exists():
            st = torch.load(state_path, weights_only=True, map_location="cpu")
            if st["done"]:
                return
            agent.load_state_dict(st["agent"])
            replay.load(st["replay"])
            rng.bit_generator.state = st["rng"]
            episode, env_steps = st["episode"], st["env_steps"]
            last_checkpoint = st["last_checkpoint"]
        discrete = task.discrete
        if not discrete:
            lo = np.asarray(task.action_spec.minimum, np.float32)  # type: ignore[union-attr]
            hi = np.asarray(task.action_spec.maximum, np.float32)  # type: ignore[union-attr]
            a_shape = task.action_spec.shape
        num_actions = task.action_dim
        chunk: list[Segment] = []

        def finished() -> bool:
            return episode >= cfg.episodes or (
                cfg.env_steps is not None and env_steps >= cfg.env_steps
            )

        while not finished():
            checkpoint = env_steps // cfg.checkpoint_steps
            meta = {
                "run": run,
                "seed": seed,
                "checkpoint": checkpoint,
                "episode_index": episode,
                "episode_id": episode_id(run, episode),
            }
            if checkpoint > last_checkpoint:
                if on_checkpoint is not None:
                    on_checkpoint(checkpoint, env_steps, episode, agent)
                last_checkpoint = checkpoint
            obs, _ = env.reset(seed=derive_seed(seed, run, 2, episode))
            recorder.begin(obs)
            while True:
                if discrete:
                    frac = min(1.0, env_steps / max(1, cfg.epsilon_decay_steps))
                    eps = 1.0 + frac * (cfg.epsilon_end - 1.0)
                    if rng.random() < eps:
                        action = np.int64(rng.integers(num_actions))
                    else:
                        action = agent.act(obs[None], greedy=False)[0]
                else:
                    batch_obs = {k: v[None] for k, v in obs.items()}
                    if cfg.sigma is None:  # a stochastic policy explores by itself
                        action = np.clip(agent.act(batch_obs, greedy=False)[0], lo, hi)
                    else:
                        action = agent.act(batch_obs)[0]
                        noise = rng.standard_normal(a_shape).astype(np.float32)
                        action = np.clip(action + cfg.sigma * noise, lo, hi)
                obs, reward, terminated, truncated, info = env.step(action)
                env_steps += 1
                if replay.size >= cfg.min_replay and env_steps % cfg.update_every == 0:
                    agent.update(replay.sample(rng, batch_size))
                seg = recorder.step(action, reward, obs, terminated, truncated, info, meta)
                if seg is not None:
                    break
            replay.add(seg)
            chunk.append(seg)
            episode += 1
            if on_episode is not None:
                on_episode(run, episode, seg)
            if len(chunk) == cfg.chunk_episodes or finished():
                chunk_index = (episode - 1) // cfg.chunk_episodes
                write_chunk(chunk_index, chunk)
                if on_snapshot is not None:
                    on_snapshot(chunk_index, agent, chunk)
                chunk = []
                done = finished()
                _save_atomic(
                    {
                        "done": done,
                        "agent": None if done else agent.state_dict(),
                        "replay": None if done else replay.state(),
                        "rng": rng.bit_generator.state,
                        "episode": episode,
                        "env_steps": env_steps,
                        "last_checkpoint": last_checkpoint,
                    },
                    state_path,
                )
                if on_chunk is not None:
                    on_chunk(run, chunk_index)
        env.close()
    finally:
        torch.set_num_threads(threads)
