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

The replay holds whole episodes and builds its n-step transitions and Atari frame stacks with
the store's own maths (``rlu.data.views``: ``n_step_targets``, ``stack_frames``), so the online
agent learns from the transitions an offline agent would sample from the recorded data.

Determinism and resumption: every seed is a stream of ``rlu.seeds.seed_stream`` under the run
(``rlu.generate.common``); every episode resets the env with its own, so the env carries no
state across episodes; the agent, the replay and the actor's random generator are saved after
every chunk of episodes (``state.pt``, through ``rlu.training.checkpoints``), so a run resumed from
its last chunk produces the same bytes as an uninterrupted one, and a damaged state file is an error
naming it. Torch runs on one
thread here: reductions then do not depend on the machine's core count. The agent may live on a
GPU (``device``); its state is saved device-independently, so a run may resume on another
device (the bytes then follow that device's arithmetic).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rlu.data.views import n_step_counts, n_step_targets, stack_frames
from rlu.files import FRACTION, MAX_STEPS, STEPS, Checked, bounds
from rlu.generate.common import ACTOR, AGENT, ENV, EPISODE, run_rng, run_seed
from rlu.generate.config import GenerateConfig
from rlu.generate.recorder import EpisodeRecorder, episode_id, schema_for
from rlu.segments import Segment
from rlu.tasks import TaskSpec, get_task
from rlu.types import ArraySpec, BatchSpec, FormatError, RluError, Transition

MAX_EPISODES = MAX_STEPS
"""Episodes of one run, at most: no more than its steps (Atari's runs end at their env_steps)."""


@dataclass(frozen=True)
class OnlineConfig(Checked):
    """One behaviour agent's run (see the module docstring); every field is checked when it is
    made (``rlu.files.Checked``)."""

    agent: str
    """The behaviour agent: 'd4pg' (continuous control) or 'dopamine_dqn' (Atari); any registered
    agent whose batch spec samples transitions can play."""
    episodes: int = field(metadata=bounds(min=1, max=MAX_EPISODES))
    """Episodes played (and recorded) per run, at most."""
    env_steps: int | None = field(default=None, metadata=STEPS)
    """If set, a run also ends with the first episode that reaches this many env steps (Atari's
    budget is in steps: 50M per run in the paper)."""
    preset: str = "small"
    """The agent's preset (rlu.agents); ``agent_overrides`` are applied on top."""
    agent_overrides: Mapping[str, Any] = field(default_factory=dict)
    """Config fields replacing the preset's (e.g. smaller networks at tiny scale)."""
    replay_capacity: int = field(default=100_000, metadata=STEPS)
    """Steps the replay holds (oldest whole episodes are dropped first)."""
    min_replay: int = field(default=1_000, metadata=bounds(min=0, max=MAX_STEPS))
    """Stored steps before the first update."""
    update_every: int = field(default=8, metadata=STEPS)
    """Env steps per learner update (Acme's D4PG: samples_per_insert 32 at batch 256)."""
    sigma: float | None = field(default=0.3, metadata=bounds(min=0.0, max=100.0))
    """D4PG behaviour noise: standard deviation of the Gaussian added to the action. None: the
    agent's own ``act(greedy=False)`` explores (DMPO samples its Gaussian policy, as Acme's
    behaviour network); either way the action is clipped to the bounds."""
    epsilon_end: float = field(default=0.01, metadata=FRACTION)
    """DQN: final exploration epsilon (Dopamine)."""
    epsilon_decay_steps: int = field(default=250_000, metadata=STEPS)
    """DQN: env steps over which epsilon decays linearly from 1 (Dopamine: 1M frames)."""
    checkpoint_steps: int = field(default=10_000, metadata=STEPS)
    """Env steps per checkpoint index (the ``checkpoint`` metadata; Atari's release: 1M)."""
    chunk_episodes: int = field(default=5, metadata=bounds(min=1, max=MAX_EPISODES))
    """Episodes per saved part; a crashed run resumes from its last complete chunk."""
    env_settings: Mapping[str, Any] = field(default_factory=dict)
    """Keyword settings of ``rlu.make_env`` (e.g. Atari ``max_episode_steps`` at tiny scale)."""
    policy_dtype: str = field(default="float16", metadata=bounds(choices=("float16", "float32")))
    """How the behaviour policies kept at each checkpoint store their weights
    (``rlu.generate.policies``): float16 halves them (the bundled cartpole dataset's 18 D4PG
    policies: 2.5 MB, not 4.9 MB, inside its 5 MB budget); 'float32' keeps them exact."""

    def to_json(self) -> dict[str, Any]:
        return {k: (dict(v) if isinstance(v, Mapping) else v) for k, v in asdict(self).items()}


# --------------------------------------------------------------------------------- replay
class Replay:
    """Whole episodes in a ring of rows, sampled as (n-step) Transitions by index arithmetic.

    An episode is stored as the store stores it: its frame prefix (Atari: ``frame_stack - 1``
    frames of zeros), then its steps, contiguously (the write position wraps to 0 when one does
    not fit), so ``next`` indices and frame stacks stay inside their episode; an episode any of
    whose rows is overwritten is invalidated whole. The n-step targets are computed once per
    episode with the store view's function, and frames are stacked at sample time as it does.
    """

    def __init__(self, task: TaskSpec, capacity: int, spec: BatchSpec):
        if spec.kind != "transition":
            raise RluError(
                f"the online replay samples transitions; the behaviour agent asks for {spec.kind!r}"
            )
        self.capacity, self.n_step, self.gamma = int(capacity), spec.n_step, spec.gamma
        self.reward_clip = spec.reward_clip
        schema = schema_for(task)  # the recorder's: Atari stores single frames, stacked here
        self.frame_stack = schema.frame_stack
        c = self.capacity
        obs = schema.observation
        if isinstance(obs, ArraySpec):
            self.obs: Any = np.zeros((c, *obs.shape), obs.dtype)
        else:
            self.obs = {k: np.zeros((c, *s.shape), s.dtype) for k, s in obs.items()}
        a = task.action_spec
        self.action = np.zeros((c, *a.shape), a.dtype)
        self.reward = np.zeros(c, np.float32)  # the n-step reward of the transition at a row
        self.discount = np.zeros(c, np.float32)
        self.next = np.zeros(c, np.int64)
        self.valid = np.zeros(c, bool)
        self.episode = np.full(c, -1, np.int64)
        self.pos = 0
        self.num_episodes = 0
        self._eligible = np.zeros(0, np.int64)

    @property
    def size(self) -> int:
        return int(self._eligible.size)

    def add(self, seg: Segment) -> None:
        n, pad = len(seg), self.frame_stack - 1
        if pad + n > self.capacity:
            raise RluError(f"replay_capacity={self.capacity} is smaller than one episode ({n})")
        if self.pos + pad + n > self.capacity:
            self.pos = 0
        block = slice(self.pos, self.pos + pad + n)
        gone = np.unique(self.episode[block])
        gone = gone[gone >= 0]
        if gone.size:
            self.valid[np.isin(self.episode, gone)] = False
        first = self.pos + pad  # the row of the episode's step 0
        steps = slice(first, first + n)
        if isinstance(self.obs, Mapping):
            for k, buf in self.obs.items():
                buf[steps] = seg.observation[k]
        else:
            if pad:
                prefix = seg.frame_prefix
                self.obs[self.pos : first] = 0 if prefix is None else prefix
            self.obs[steps] = seg.observation
        self.action[steps] = seg.action
        t = np.arange(n - 1)
        reward, discount, nxt = n_step_targets(
            seg.reward,
            seg.discount,
            t,
            np.full(n - 1, n - 1),
            self.n_step,
            self.gamma,
            self.reward_clip,
        )
        count = int(n_step_counts(np.array([n]), seg.is_terminal[-1:], self.n_step)[0])
        self.reward[block] = 0.0
        self.discount[block] = 0.0
        self.next[block] = first + n - 1
        self.valid[block] = False
        self.reward[first : first + n - 1] = reward
        self.discount[first : first + n - 1] = discount
        self.next[first : first + n - 1] = first + nxt
        self.valid[first : first + count] = True
        self.episode[block] = self.num_episodes
        self.num_episodes += 1
        self.pos += pad + n
        self._eligible = np.flatnonzero(self.valid)

    def _observation(self, rows: np.ndarray) -> Any:
        if isinstance(self.obs, Mapping):
            return {k: v[rows] for k, v in self.obs.items()}
        if self.frame_stack == 1:
            return self.obs[rows]
        return stack_frames(self.obs, rows - (self.frame_stack - 1), self.frame_stack)

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

    _ARRAYS = ("obs", "action", "reward", "discount", "next", "valid", "episode")

    def state(self) -> dict[str, Any]:
        """Tensors and ints only: loadable with ``torch.load(weights_only=True)``."""
        import torch

        def tensor(v: np.ndarray) -> Any:
            return torch.from_numpy(np.ascontiguousarray(v))

        arrays = {}
        for name in self._ARRAYS:
            v = getattr(self, name)
            arrays[name] = (
                {k: tensor(x) for k, x in v.items()} if isinstance(v, Mapping) else tensor(v)
            )
        return {"arrays": arrays, "pos": self.pos, "num_episodes": self.num_episodes}

    def load(self, state: Any, where: str, fix: str) -> None:
        """Restore :meth:`state`; anything that is not this replay's (other entries, shapes,
        dtypes, indices outside the ring) is a FormatError naming ``where`` and ``fix``."""
        import torch

        def bad(what: str) -> FormatError:
            return FormatError(f"{where}: the replay's {what}; {fix}")

        def array(v: Any, like: np.ndarray, name: str) -> np.ndarray:
            if not isinstance(v, torch.Tensor):
                raise bad(f"entry {name!r} is a {type(v).__name__}, not a tensor")
            out = v.numpy()
            if out.shape != like.shape or out.dtype != like.dtype:
                raise bad(
                    f"entry {name!r} is {out.dtype}{list(out.shape)}; this replay holds "
                    f"{like.dtype}{list(like.shape)}"
                )
            return out

        if not isinstance(state, Mapping) or set(state) != {"arrays", "pos", "num_episodes"}:
            raise bad("state is not the one rlu generate saves")
        arrays = state["arrays"]
        if not isinstance(arrays, Mapping) or set(arrays) != set(self._ARRAYS):
            raise bad(f"arrays are not {', '.join(self._ARRAYS)}")
        loaded: dict[str, Any] = {}
        for name in self._ARRAYS:
            mine, theirs = getattr(self, name), arrays[name]
            if isinstance(mine, Mapping):
                if not isinstance(theirs, Mapping) or set(theirs) != set(mine):
                    raise bad(f"observation keys differ from the task's ({', '.join(mine)})")
                loaded[name] = {k: array(theirs[k], mine[k], f"{name}/{k}") for k in mine}
            else:
                loaded[name] = array(theirs, mine, name)
        pos, count = state["pos"], state["num_episodes"]
        for key, value, top in (("pos", pos, self.capacity), ("num_episodes", count, None)):
            if (
                isinstance(value, bool)
                or not isinstance(value, int)
                or value < 0
                or (top is not None and value > top)
            ):
                raise bad(f"entry {key!r} is {value!r}, not a count of this replay")
        nxt, episode = loaded["next"], loaded["episode"]
        if nxt.size and (nxt.min() < 0 or nxt.max() >= self.capacity):
            raise bad(f"'next' holds rows outside the ring of {self.capacity}")
        if episode.size and (episode.min() < -1 or episode.max() >= count):
            raise bad("'episode' holds episodes it never stored")
        vars(self).update(loaded)
        self.pos, self.num_episodes = pos, count
        self._eligible = np.flatnonzero(self.valid)


# --------------------------------------------------------------------------------- a run
def make_behaviour_agent(
    task: TaskSpec, cfg: OnlineConfig, seed: int, device: Any = "cpu"
) -> Any:  # an agent of rlu.agents
    from rlu.agents import make_agent

    return make_agent(
        cfg.agent,
        task.observation_spec,
        task.action_spec,
        cfg.preset,
        seed,
        device=device,
        **cfg.agent_overrides,
    )


@dataclass(frozen=True)
class RunHooks:
    """What a run hands its episodes, chunks and agent to (the recipes differ only here)."""

    write_chunk: Callable[[int, list[Segment]], None]
    """``write_chunk(chunk_index, segments)``: a finished chunk of recorded episodes."""
    on_episode: Callable[[int, int, Segment], None] | None = None
    """``on_episode(run, episodes_played, segment)`` after every episode (progress)."""
    on_chunk: Callable[[int, int], None] | None = None
    """``on_chunk(run, chunk_index)`` once a chunk and the run's state are on disk (tests
    interrupt there)."""
    on_snapshot: Callable[[int, Any, list[Segment]], None] | None = None
    """``on_snapshot(chunk_index, agent, segments)`` after each chunk (RWRL keeps policy
    snapshots this way)."""
    on_checkpoint: Callable[[int, int, int, Any], None] | None = None
    """``on_checkpoint(checkpoint, env_steps, episode, agent)`` before the first episode of every
    checkpoint id (the recipe keeps the behaviour policies this way; a run resumed from its last
    chunk calls it again for the checkpoints after that chunk, with the same agent)."""


STATE_KEYS = ("done", "agent", "replay", "rng", "episode", "env_steps", "last_checkpoint")
"""The entries of a run's ``state.pt``."""


def run_online(
    config: GenerateConfig, online: OnlineConfig, run: int, run_dir: Path, hooks: RunHooks
) -> None:
    """Play run ``run`` of ``config`` with the behaviour agent ``online``, resuming from
    ``run_dir/state.pt``; every finished chunk of recorded episodes goes to
    ``hooks.write_chunk``, then the run's state is saved (see :class:`RunHooks`)."""
    import torch

    from rlu.envs import make_env
    from rlu.training.checkpoints import load_state, save_state

    task, seed, cfg = get_task(config.task), config.seed, online
    run_dir.mkdir(parents=True, exist_ok=True)
    state_path = run_dir / "state.pt"
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        agent = make_behaviour_agent(task, cfg, run_seed(seed, run, AGENT), config.device)
        batch_size = agent.batch_spec.batch_size
        env = make_env(task.id, seed=run_seed(seed, run, ENV), **cfg.env_settings)
        max_steps = int(cfg.env_settings.get("max_episode_steps", task.episode_length))
        recorder = EpisodeRecorder(task, max_steps)
        replay = Replay(task, cfg.replay_capacity, agent.batch_spec)
        rng = run_rng(seed, run, ACTOR)
        episode, env_steps, last_checkpoint = 0, 0, -1
        if state_path.exists():
            fix = (
                f"remove {run_dir} to play run {run} again from its start (the other runs keep "
                "their work), or the whole work folder to start afresh"
            )
            st = load_state(state_path, STATE_KEYS, fix)
            if _restore(state_path, st, fix, agent, replay, rng, cfg):
                return
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
                if hooks.on_checkpoint is not None:
                    hooks.on_checkpoint(checkpoint, env_steps, episode, agent)
                last_checkpoint = checkpoint
            obs, _ = env.reset(seed=run_seed(seed, run, EPISODE, episode))
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
            if hooks.on_episode is not None:
                hooks.on_episode(run, episode, seg)
            if len(chunk) == cfg.chunk_episodes or finished():
                chunk_index = (episode - 1) // cfg.chunk_episodes
                hooks.write_chunk(chunk_index, chunk)
                if hooks.on_snapshot is not None:
                    hooks.on_snapshot(chunk_index, agent, chunk)
                chunk = []
                done = finished()
                state = {
                    "done": done,
                    "agent": None if done else agent.state_dict(),
                    "replay": None if done else replay.state(),
                    "rng": rng.bit_generator.state,
                    "episode": episode,
                    "env_steps": env_steps,
                    "last_checkpoint": last_checkpoint,
                }
                save_state(state_path, state)
                if hooks.on_chunk is not None:
                    hooks.on_chunk(run, chunk_index)
        env.close()
    finally:
        torch.set_num_threads(threads)


def _restore(
    path: Path,
    st: Mapping[str, Any],
    fix: str,
    agent: Any,
    replay: Replay,
    rng: np.random.Generator,
    cfg: OnlineConfig,
) -> bool:
    """Load a run's saved state into its agent, replay and generator; True if the run had
    finished. Anything that is not a state this run could have saved is a FormatError naming
    the file and ``fix`` (never a traceback from deep inside torch or numpy)."""
    if not isinstance(st["done"], bool):
        raise FormatError(f"{path}: entry 'done' is {st['done']!r}, not true or false; {fix}")
    if st["done"]:
        return True
    for key, low in (("episode", 0), ("env_steps", 0), ("last_checkpoint", -1)):
        v = st[key]
        if isinstance(v, bool) or not isinstance(v, int) or v < low:
            raise FormatError(f"{path}: entry {key!r} is {v!r}, not a count of this run; {fix}")
    if (
        st["episode"] >= cfg.episodes
        or st["last_checkpoint"] > st["env_steps"] // cfg.checkpoint_steps
    ):
        raise FormatError(f"{path}: its counters do not belong to a run of these settings; {fix}")
    try:
        agent.load_state_dict(st["agent"])
    except (RuntimeError, KeyError, ValueError, TypeError, AttributeError, IndexError) as e:
        why = str(e).splitlines()[0][:200] if str(e) else type(e).__name__
        raise FormatError(
            f"{path}: its agent state does not fit the behaviour agent ({why}); {fix}"
        ) from None
    replay.load(st["replay"], str(path), fix)
    try:
        rng.bit_generator.state = st["rng"]
    except (KeyError, ValueError, TypeError, AttributeError, OverflowError) as e:
        why = str(e).splitlines()[0][:200] if str(e) else type(e).__name__
        raise FormatError(f"{path}: its random generator state is damaged ({why}); {fix}") from None
    return False
