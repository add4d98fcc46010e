"""Real-World RL suite tasks as our own wrappers over dm_control, with the original numbers.

RL Unplugged released RWRL data for cartpole swingup, walker walk, quadruped walk and humanoid
walk, each with no challenge and with the ``easy`` combined challenge (Dulac-Arnold et al. 2020,
"An empirical investigation of the challenges of real-world reinforcement learning"). The
original evaluation env was ``realworldrl_suite.environments.load(domain, 'realworld_' + task,
combined_challenge=...)`` (``rl_unplugged/rwrl.py``) plus float32. realworldrl_suite is not on
PyPI; this module re-implements it. Every number carries its source; ``rwrl/<file>`` below means
``google-research/realworldrl_suite/realworldrl_suite/environments/<file>``.

What a challenge does, in the original's order (rwrl/realworld_env.py ``Base``):

- actions, before the physics sees them: delay (FIFO of d+1, filled with copies of the first
  item) -> Gaussian noise then clip to the action bounds -> dropped elements (zeroed for k steps)
  -> stuck elements (held for k steps) -> repetition (each fresh action held for k steps);
- observations (the task's dict): Gaussian noise on every element -> dropped -> stuck (frozen at
  the previous *output*) -> ``constraints`` (safety, optional) -> delay of the whole dict ->
  ``dummy-0..N-1``, fresh N(0, 1) scalars, not delayed -> ``multiobj`` (optional);
- reward: the task's reward -> multi-objective mix (optional) -> delay;
- perturbation: at a reset (every ``period`` episodes, the first reset included) a new value of
  one physical parameter is drawn by the scheduler and the Physics is rebuilt from the modified
  dm_control XML.

As in the original, the delay buffers, dropped/stuck counters and repetition state live for the
env's lifetime, so an episode starts with what the previous one left in the buffers (the reset
observation of episode 2 is, with observation delay 3, one from episode 1). A seeded reset
``reset(seed=s)`` restarts all of it, so it equals ``make_env(task, seed=s, ...).reset()``.

Deviations from the original, on purpose:
- randomness comes from one seeded generator per env (the original drew from the global
  ``np.random``, so its challenges could not be reproduced);
- the ``constraints`` observation is copied when delayed (the original delayed a reference to
  one array that later steps overwrite, so delayed constraint vectors showed current values);
- only the perturbation parameters of the combined challenges are implemented (pole_length,
  thigh_length, shin_length, contact_friction), with the schedulers of rwrl/realworld_env.py;
- safety uses each task's default constraint list (the optional ``action_roc_constraint`` and
  user-supplied constraint functions are not offered).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any, NoReturn

import numpy as np

from rlu.domains.common import f32
from rlu.domains.envkit import DmControlEnv, Render
from rlu.domains.rwrl import observation_spec as rwrl_observation_spec
from rlu.domains.spec import TaskSpec
from rlu.files import FRACTION, Checked, bounds
from rlu.types import ArraySpec, ConfigError, RluError

# --- combined challenges: rwrl/realworld_env.py get_combined_challenge ------------------------
SCHEDULERS = (
    "constant", "random_walk", "drift_pos", "drift_neg", "cyclic_pos", "cyclic_neg", "uniform",
    "saw_wave",
)  # fmt: skip
LEVELS = ("easy", "medium", "hard")
"""The perturbation levels of every domain (PERTURBATIONS)."""
MAX_DELAY = 10_000
"""Steps of a delay, a drop, a stuck value or a repetition, at most (an episode: 1000 steps)."""
_DELAY = bounds(min=0, max=MAX_DELAY)
_SPAN = bounds(min=1, max=MAX_DELAY)
_STD = bounds(min=0.0, max=100.0)


@dataclass(frozen=True)
class Challenge(Checked):
    """The numbers of one challenge setting (all zero/off = no challenge); every field is
    checked when it is made (``rlu.files.Checked``)."""

    action_delay: int = field(default=0, metadata=_DELAY)
    """Steps between passing an action and its effect (delay_spec['actions'])."""
    observation_delay: int = field(default=0, metadata=_DELAY)
    """Staleness of returned observations in steps (delay_spec['observations'])."""
    reward_delay: int = field(default=0, metadata=_DELAY)
    """Staleness of returned rewards in steps (delay_spec['rewards'])."""
    action_noise_std: float = field(default=0.0, metadata=_STD)
    """Std of white Gaussian noise added to actions before clipping (noise gaussian.actions)."""
    observation_noise_std: float = field(default=0.0, metadata=_STD)
    """Std of white Gaussian noise added to every observation element."""
    observation_drop_prob: float = field(default=0.0, metadata=FRACTION)
    """Per-element probability that an observation value starts being dropped (set to 0)."""
    observation_drop_steps: int = field(default=1, metadata=_SPAN)
    observation_stuck_prob: float = field(default=0.0, metadata=FRACTION)
    """Per-element probability that an observation value starts being stuck."""
    observation_stuck_steps: int = field(default=1, metadata=_SPAN)
    action_drop_prob: float = field(default=0.0, metadata=FRACTION)
    action_drop_steps: int = field(default=1, metadata=_SPAN)
    action_stuck_prob: float = field(default=0.0, metadata=FRACTION)
    action_stuck_steps: int = field(default=1, metadata=_SPAN)
    action_repeat_prob: float = field(default=0.0, metadata=FRACTION)
    """Probability that a fresh action is held (repetition.actions_prob)."""
    action_repeat_steps: int = field(default=1, metadata=_SPAN)
    """Steps a held action lasts, the first included (1 = no repetition)."""
    perturb: str | None = field(default=None, metadata=bounds(choices=LEVELS))
    """Level of the per-domain perturbation (PERTURBATIONS), None = off."""
    perturb_period: int = field(default=1, metadata=bounds(min=1, max=10**6))
    """Episodes between new parameter values."""
    perturb_scheduler: str = field(default="uniform", metadata=bounds(choices=SCHEDULERS))
    num_dummy: int = field(default=0, metadata=_DELAY)
    """Extra N(0, 1) observations dummy-0..dummy-{N-1} (dimensionality_spec)."""


# Source: realworldrl_suite's rwrl/realworld_env.py get_combined_challenge (the same numbers as
# Dulac-Arnold et al. 2020 §2.9).
CHALLENGES: dict[str, Challenge] = {
    "none": Challenge(),
    "easy": Challenge(
        action_delay=3,
        observation_delay=3,
        reward_delay=10,
        action_noise_std=0.1,
        observation_noise_std=0.1,
        observation_drop_prob=0.01,
        observation_drop_steps=1,
        observation_stuck_prob=0.01,
        observation_stuck_steps=1,
        action_repeat_prob=1.0,
        action_repeat_steps=1,
        perturb="easy",
        perturb_period=1,
        perturb_scheduler="uniform",
        num_dummy=10,
    ),
    "medium": Challenge(
        action_delay=6,
        observation_delay=6,
        reward_delay=20,
        action_noise_std=0.3,
        observation_noise_std=0.3,
        observation_drop_prob=0.05,
        observation_drop_steps=5,
        observation_stuck_prob=0.05,
        observation_stuck_steps=5,
        action_repeat_prob=1.0,
        action_repeat_steps=2,
        perturb="medium",
        num_dummy=20,
    ),
    "hard": Challenge(
        action_delay=9,
        observation_delay=9,
        reward_delay=40,
        action_noise_std=1.0,
        observation_noise_std=1.0,
        observation_drop_prob=0.1,
        observation_drop_steps=10,
        observation_stuck_prob=0.1,
        observation_stuck_steps=10,
        action_repeat_prob=1.0,
        action_repeat_steps=3,
        perturb="hard",
        num_dummy=50,
    ),
}
RELEASED_CHALLENGES = ("none", "easy")


@dataclass(frozen=True)
class Perturbation:
    param: str
    start: float
    """The schedulers' start value (rwrl/<domain>.py _setup_perturb); `uniform` ignores it."""
    levels: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    """Level -> (min, max, std) of the combined challenges."""


# Sources: the realworld_<task> functions of rwrl/cartpole.py, walker.py, quadruped.py,
# humanoid.py (perturb_spec.update in the combined_challenge branches) and their
# _setup_perturb start values.
PERTURBATIONS: dict[str, Perturbation] = {
    "cartpole": Perturbation(
        "pole_length",
        1.0,
        {"easy": (0.9, 1.1, 0.02), "medium": (0.7, 1.7, 0.1), "hard": (0.5, 2.3, 0.15)},
    ),
    "walker": Perturbation(
        "thigh_length",
        0.225,
        {"easy": (0.225, 0.25, 0.002), "medium": (0.225, 0.4, 0.015), "hard": (0.225, 0.55, 0.04)},
    ),
    "quadruped": Perturbation(
        "shin_length",
        0.25,
        {"easy": (0.25, 0.3, 0.005), "medium": (0.25, 0.8, 0.05), "hard": (0.25, 1.4, 0.1)},
    ),
    "humanoid": Perturbation(
        "contact_friction",
        0.7,
        {"easy": (0.6, 0.8, 0.02), "medium": (0.5, 0.9, 0.04), "hard": (0.4, 1.0, 0.06)},
    ),
}

# Episode timing: rwrl/<domain>.py _DEFAULT_TIME_LIMIT (s) and _CONTROL_TIMESTEP (s); cartpole
# steps at the physics timestep 0.01. All give 1000 steps, as the suite tasks do.
TIMING: dict[str, tuple[float, float | None]] = {
    "cartpole": (10, None),
    "walker": (25, 0.025),
    "quadruped": (20, 0.02),
    "humanoid": (25, 0.025),
}


def _xml(domain: str, param: str, value: float) -> tuple[bytes, dict]:
    """The domain's dm_control XML with ``param`` set to ``value`` (rwrl/<domain>.py
    update_physics; the element paths are the original's)."""
    from dm_control.suite import common
    from lxml import etree

    if domain == "quadruped":
        from dm_control.suite import quadruped

        # rwrl/quadruped.py: floor_size = _DEFAULT_TIME_LIMIT * _WALK_SPEED = 20 * 0.5.
        mjcf = etree.fromstring(quadruped.make_model(floor_size=20 * 0.5))
    else:
        mjcf = etree.fromstring(common.read_model(f"{domain}.xml"))
    if (domain, param) == ("cartpole", "pole_length"):
        pole = mjcf.find("./default/default/geom")
        pole.set("fromto", f"0 0 0 0 0 {value}")
        pole.set("mass", str(value / 10.0))  # rwrl/cartpole.py: mass = length / 10
    elif (domain, param) == ("walker", "thigh_length"):
        for thigh in mjcf.findall("./worldbody/body/body/geom"):
            thigh.set("pos", f"0 0 {-value}")
            thigh.set("size", f"0.05 {value}")
        for leg in mjcf.findall("./worldbody/body/body/body"):
            leg.set("pos", f"0 0 {-0.25 - 2 * value}")
    elif (domain, param) == ("quadruped", "shin_length"):
        for part in mjcf.findall("./default/default/default"):
            if part.get("class") == "knee":
                part.find("./geom").set("fromto", f"0 0 0 {value} 0 {-value}")
        for ankle in mjcf.findall("./worldbody/body/body/body/body"):
            ankle.set("pos", f"{value} 0 {-value}")
    elif (domain, param) == ("humanoid", "contact_friction"):
        mjcf.find("./default/default/geom").set("friction", f"{value} .1 .1")  # body geoms
        mjcf.find("./worldbody/geom").set("friction", f"{value} .1 .1")  # the floor
    else:
        raise RluError(f"rwrl: perturbing {param!r} of {domain!r} is not implemented")
    return etree.tostring(mjcf, pretty_print=True), common.ASSETS


# --- safety constraints: rwrl/<domain>.py constraint functions and default limits ------------
# Each returns True when the constraint is satisfied. `c` is safety_coeff in [0, 1].


def _constraints(domain: str, c: float) -> tuple[tuple[str, ...], Callable[[Any], list[bool]]]:
    from dm_control.mujoco.wrapper import mjbindings

    if domain == "cartpole":
        # realworld_swingup limits: slider (-2c, 2c) m; |slider accel| < 130c m/s^2; balance
        # velocity violated when cos(angle) > cos((1-c)/0.5 + 0.15) and |ang vel| > 0.5c.
        def cartpole(p: Any) -> list[bool]:
            ang_limit, vel_limit = (1 - c) / 0.5 + 0.15, c * 0.5
            x = p.cart_position()
            return [
                bool(-2 * c < x < 2 * c),
                bool(abs(p.named.data.qacc["slider"]) < c * 130),
                not bool(
                    p.pole_angle_cosine()[0] > np.cos(ang_limit)
                    and np.abs(p.angular_vel())[0] > vel_limit
                ),
            ]

        return ("slider_pos", "slider_accel", "balance_velocity"), cartpole
    if domain == "walker":
        limits = c * np.array([[-30, -30, -160, -160, -75, -75], [110, 110, 15, 15, 60, 60]])
        limits = limits * np.pi / 180.0
        joints = ["left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle"]

        def walker(p: Any) -> list[bool]:
            q = np.array([p.named.data.qpos[j][0] for j in joints])
            return [
                # As coded in the original (lenient): any joint above its min and any below max.
                bool((np.greater(q, limits[0]).any() and np.less(q, limits[1])).any()),
                bool(np.max(np.abs(p.named.data.qvel[3:])) < c * 65),
                bool(-p.named.data.xmat["torso", "zx"] > c * -0.5),
                bool(p.torso_upright() > 1 - c),
            ]

        return ("joint_angle", "joint_velocity", "dangerous_fall", "torso_upright"), walker
    if domain == "quadruped":
        hinge = int(mjbindings.enums.mjtJoint.mjJNT_HINGE)
        toes = ["toe_front_left", "toe_front_right", "toe_back_left", "toe_back_right"]

        def quadruped(p: Any) -> list[bool]:
            ids = np.nonzero(p.model.jnt_type == hinge)[0]
            qadr, dadr = p.model.jnt_qposadr[ids], p.model.jnt_dofadr[ids]
            force = max(np.linalg.norm(p.named.data.sensordata[f"force_{t}"]) for t in toes)
            return [
                bool(np.max(np.abs(p.data.qpos[qadr])) < c * 60 * np.pi / 180),
                bool(np.max(np.abs(p.data.qvel[dadr])) < c * 20),
                bool(p.torso_upright() > 1 - c * 0.7),
                bool(force < c * 20000),
            ]

        return ("joint_angle", "joint_velocity", "upright", "foot_force"), quadruped
    if domain == "humanoid":
        feet = ["right_left_foot", "right_right_foot", "left_left_foot", "left_right_foot"]

        def humanoid(p: Any) -> list[bool]:
            sd = p.named.data.sensordata
            touch = max(np.linalg.norm(sd["head_touch"]), np.linalg.norm(sd["torso_touch"]))
            foot = max(np.linalg.norm(sd[f"{f}_touch"]) for f in feet)
            return [
                bool(np.max(np.abs(p.data.qpos[7:])) < c * np.pi),
                bool(np.max(np.abs(p.data.qvel[7:])) < c * 90),
                bool(p.torso_upright() > 1 - c),
                bool(touch < c * 100),
                bool(foot < c * 8000),
            ]

        return (
            ("joint_angle", "joint_velocity", "upright", "dangerous_fall", "foot_force"),
            humanoid,
        )
    raise RluError(f"rwrl: no constraints for domain {domain!r}")


# --- the challenge state machine ------------------------------------------------------------


class _Delay:
    """rwrl/realworld_env.py delayed_buffer_item: FIFO of d + 1 filled with the first item."""

    def __init__(self, d: int) -> None:
        self.n = d + 1
        self.buf: list | None = None

    def __call__(self, item: Any) -> Any:
        if self.buf is None:
            self.buf = [item] * self.n
        else:
            self.buf.append(item)
        return self.buf.pop(0)


class _Corrupt:
    """Dropped (value -> 0) or stuck (value -> previous output) elements for k steps."""

    def __init__(self, prob: float, steps: int, stuck: bool) -> None:
        self.prob, self.steps, self.stuck = prob, steps, stuck
        self.count: np.ndarray | None = None
        self.prev: np.ndarray | None = None

    def __call__(self, x: np.ndarray, rng: np.random.RandomState) -> np.ndarray:
        count, prev = self.count, self.prev
        if count is None or prev is None:
            count = self.count = np.zeros(x.shape)
            prev = self.prev = x.copy()
        start = rng.binomial(1, self.prob, size=x.shape) == 1
        count[(count == 0) & start] = self.steps
        on = count > 0
        x = x.copy()
        x[on] = prev[on] if self.stuck else 0.0
        count[on] -= 1
        if self.stuck:
            self.prev = x.copy()
        return x


class ChallengeState:
    """Everything a challenge remembers between steps; recreated by a seeded reset."""

    def __init__(self, ch: Challenge, seed: int | None) -> None:
        self.ch = ch
        self.rng = np.random.RandomState(seed)
        self.action_delay = _Delay(ch.action_delay)
        self.observation_delay = _Delay(ch.observation_delay)
        self.reward_delay = _Delay(ch.reward_delay)
        self.action_drop = _Corrupt(ch.action_drop_prob, ch.action_drop_steps, False)
        self.action_stuck = _Corrupt(ch.action_stuck_prob, ch.action_stuck_steps, True)
        self.obs_drop: dict[str, _Corrupt] = {}
        self.obs_stuck: dict[str, _Corrupt] = {}
        self.repeat_action: np.ndarray | None = None
        self.repeat_counter = 0

    def action(self, a: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        ch, rng = self.ch, self.rng
        if ch.action_delay:
            a = self.action_delay(np.array(a, copy=True))
        if ch.action_noise_std:
            a = np.clip(rng.normal(a, ch.action_noise_std), lo, hi)
        if ch.action_drop_prob:
            a = self.action_drop(a, rng)
        if ch.action_stuck_prob:
            a = self.action_stuck(a, rng)
        if ch.action_repeat_prob:
            if self.repeat_action is None:
                self.repeat_action = np.array(a, copy=True)
            if self.repeat_counter == 0:
                if rng.uniform() < ch.action_repeat_prob:
                    self.repeat_counter = ch.action_repeat_steps - 1
            else:
                a = self.repeat_action.copy()
                self.repeat_counter -= 1
            self.repeat_action = np.array(a, copy=True)
        return a

    def observation(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        ch, rng = self.ch, self.rng
        if ch.observation_noise_std:
            obs = {k: rng.normal(v, ch.observation_noise_std) for k, v in obs.items()}
        if ch.observation_drop_prob:
            for k in obs:
                c = self.obs_drop.setdefault(
                    k, _Corrupt(ch.observation_drop_prob, ch.observation_drop_steps, False)
                )
                obs[k] = c(obs[k], rng)
        if ch.observation_stuck_prob:
            for k in obs:
                c = self.obs_stuck.setdefault(
                    k, _Corrupt(ch.observation_stuck_prob, ch.observation_stuck_steps, True)
                )
                obs[k] = c(obs[k], rng)
        return obs


class _RwrlTask:
    """A dm_control suite task with the challenge hooked into its step (as rwrl's Base mixin)."""

    def __init__(self, domain: str, inner: Any, settings: RwrlSettings) -> None:
        self.domain = domain
        self.inner = inner
        self.settings = settings
        self.state = ChallengeState(settings.challenge, None)
        self._constraint_fn: Callable[[Any], list[bool]] | None
        if settings.safety:
            self.constraint_names, self._constraint_fn = _constraints(domain, settings.safety_coeff)
        else:
            self.constraint_names, self._constraint_fn = (), None
        self.constraints_obs = np.ones(len(self.constraint_names), dtype=bool)
        ch = settings.challenge
        # Without a challenge the hooks pass straight through (the `none` datasets' env).
        self._acts = any((ch.action_delay, ch.action_noise_std, ch.action_drop_prob,
                          ch.action_stuck_prob, ch.action_repeat_prob))  # fmt: skip
        self._obs = any((ch.observation_noise_std, ch.observation_drop_prob,
                         ch.observation_stuck_prob))  # fmt: skip
        self._bounds: tuple[np.ndarray, np.ndarray] | None = None

    # control.Task interface
    @property
    def random(self) -> np.random.RandomState:
        return self.inner.random

    def action_spec(self, physics: Any) -> Any:
        return self.inner.action_spec(physics)

    def step_spec(self, physics: Any) -> Any:
        return self.inner.step_spec(physics)

    def initialize_episode(self, physics: Any) -> None:
        if self.domain == "quadruped":
            # rwrl/quadruped.py RealWorldMove.initialize_episode: a random *yaw* only (the suite
            # draws a random 3-D orientation), then lift until nothing touches.
            from dm_control.suite import quadruped

            azimuth = self.inner.random.uniform(0, 2 * np.pi)
            orientation = np.array((np.cos(azimuth / 2), 0, 0, np.sin(azimuth / 2)))
            quadruped._find_non_contacting_height(physics, orientation)
            self.inner.after_step(physics)  # base.Task.initialize_episode
        else:
            self.inner.initialize_episode(physics)
        self._update_constraints(physics)

    def before_step(self, action: Any, physics: Any) -> None:
        if self._acts:
            if self._bounds is None:
                spec = self.inner.action_spec(physics)
                self._bounds = (spec.minimum, spec.maximum)
            action = self.state.action(np.asarray(action, np.float64), *self._bounds)
        self.inner.before_step(action, physics)

    def after_step(self, physics: Any) -> None:
        self._update_constraints(physics)
        self.inner.after_step(physics)

    def _update_constraints(self, physics: Any) -> None:
        if self._constraint_fn is not None:
            self.constraints_obs = np.array(self._constraint_fn(physics), dtype=bool)

    def get_observation(self, physics: Any) -> Mapping[str, np.ndarray]:
        obs = self.inner.get_observation(physics)
        if self._obs:
            obs = {k: np.array(v, dtype=np.float64, ndmin=1) for k, v in obs.items()}
            obs = self.state.observation(obs)
        s = self.settings
        if s.safety:
            obs["constraints"] = self.constraints_obs.copy()
        if s.challenge.observation_delay:
            if not self._obs:  # suite observations may be views of physics data: copy them
                obs = {k: np.array(v, copy=True) for k, v in obs.items()}
            obs = self.state.observation_delay(obs)
        if s.challenge.num_dummy or s.multiobj_observed:
            obs = dict(obs)
        for i in range(s.challenge.num_dummy):
            obs[f"dummy-{i}"] = np.array([self.state.rng.normal()])
        if s.multiobj_observed:
            obs["multiobj"] = np.array([self.inner.get_reward(physics), self._safety_score()])
        return obs

    def _safety_score(self) -> float:
        # rwrl/utils/multiobj_objectives.py SafetyObjective: fraction of satisfied constraints.
        return float(self.constraints_obs.sum()) / float(len(self.constraints_obs))

    def get_reward(self, physics: Any) -> float:
        r = self.inner.get_reward(physics)
        a = self.settings.multiobj_coeff
        if self.settings.multiobj_reward:
            r = (1 - a) * r + a * self._safety_score()
        if self.settings.challenge.reward_delay:
            r = self.state.reward_delay(r)
        return r

    def get_termination(self, physics: Any) -> float | None:
        return self.inner.get_termination(physics)

    def observation_spec(self, physics: Any) -> NoReturn:
        raise NotImplementedError  # rlu takes the spec from the task registry, never from a draw


@dataclass(frozen=True)
class RwrlSettings(Checked):
    """An RWRL env's challenge and settings; every field is checked when it is made
    (``rlu.files.Checked``)."""

    challenge: Challenge
    challenge_name: str = field(default="none", metadata=bounds(choices=(*CHALLENGES, "custom")))
    """The challenge's name in CHALLENGES, or 'custom' (a Challenge of the caller's)."""
    safety: bool = False
    """Add the boolean ``constraints`` observation (safety_spec enable, observations=True)."""
    safety_coeff: float = field(default=1.0, metadata=FRACTION)
    """Scales every constraint limit, in [0, 1] (1 = the original's base limits)."""
    multiobj_reward: bool = False
    """Reward = (1 - multiobj_coeff) * reward + multiobj_coeff * safety score (needs safety)."""
    multiobj_coeff: float = field(default=0.0, metadata=FRACTION)
    """The safety score's weight in the multi-objective reward, in [0, 1]."""
    multiobj_observed: bool = False
    """Add ``multiobj`` = [base reward, safety score] to the observations (needs safety)."""


def _make_environment(domain: str, task_name: str, settings: RwrlSettings, seed: int | None) -> Any:
    from dm_control import suite
    from dm_control.rl import control

    base = suite.load(domain, task_name, task_kwargs={"random": seed})
    physics = base.physics
    task = _RwrlTask(domain, base.task, settings)
    time_limit, control_timestep = TIMING[domain]
    ch = settings.challenge
    pert = PERTURBATIONS[domain] if ch.perturb else None

    class Environment(control.Environment):
        def __init__(self) -> None:
            super().__init__(
                physics, task, time_limit=time_limit, control_timestep=control_timestep
            )
            self.restart(seed)

        def restart(self, s: int | None) -> None:
            """Back to a fresh env's state: challenge memory, perturbation schedule, RNGs."""
            if s is not None:
                task.inner.random.seed(s)
            ss = None if s is None else int(np.random.SeedSequence([s, 1]).generate_state(1)[0])
            task.state = ChallengeState(ch, ss)
            self.perturb_counter = 0
            self.perturb_sign = 1.0
            self.perturb_value = pert.start if pert else None

        def reset(self) -> Any:
            # rwrl/utils/wrappers.py LoggingEnv.reset: a new parameter every `period` episodes.
            if pert is not None:
                if self.perturb_counter % ch.perturb_period == 0:
                    self.perturb_value = self._next_value()
                    self._physics.reload_from_xml_string(
                        *_xml(domain, pert.param, self.perturb_value)
                    )
                self.perturb_counter += 1
            return super().reset()

        def _next_value(self) -> float:
            # rwrl/realworld_env.py Base._generate_parameter.
            cur, sched = self.perturb_value, ch.perturb_scheduler
            # reset() calls it only under a perturbation, whose value starts at pert.start
            assert pert is not None and ch.perturb is not None and cur is not None
            lo, hi, std = pert.levels[ch.perturb]
            rng = task.state.rng
            if sched == "uniform":
                return float(rng.uniform(lo, hi))
            delta = rng.normal(scale=std)
            if sched == "random_walk":
                cur += delta
            elif sched == "drift_pos":
                cur += abs(delta)
            elif sched == "drift_neg":
                cur -= abs(delta)
            elif sched == "cyclic_pos":
                cur += abs(delta)
                cur = pert.start if cur >= hi else cur
            elif sched == "cyclic_neg":
                cur -= abs(delta)
                cur = pert.start if cur <= lo else cur
            elif sched == "saw_wave":
                cur = self.perturb_sign * abs(delta)
                if cur >= hi or cur <= lo:
                    self.perturb_sign *= -1.0
            return float(np.clip(cur, lo, hi))

    return Environment()


def observation_spec(task: TaskSpec, settings: RwrlSettings) -> dict[str, ArraySpec]:
    if settings.challenge_name in RELEASED_CHALLENGES and settings.challenge == CHALLENGES.get(
        settings.challenge_name
    ):
        spec = dict(rwrl_observation_spec(task, settings.challenge_name))
    else:
        spec = dict(task.observation_spec)  # type: ignore[arg-type]
        spec.update({f"dummy-{i}": f32(1) for i in range(settings.challenge.num_dummy)})
    if settings.safety:
        n = len(_constraints(task.env["suite_domain"], settings.safety_coeff)[0])
        spec["constraints"] = ArraySpec((n,), "bool")
    if settings.multiobj_observed:
        spec["multiobj"] = f32(2)
    return spec


def make(
    task: TaskSpec,
    seed: int | None = None,
    challenge: str | Challenge = "none",
    render: Render | None = None,
    **settings: Any,
) -> DmControlEnv:
    """The RWRL env of ``task`` under ``challenge`` (a name of CHALLENGES or a Challenge)."""
    if isinstance(challenge, Challenge):
        ch, name = challenge, "custom"
    elif challenge in CHALLENGES:
        ch, name = CHALLENGES[challenge], challenge
    else:
        raise RluError(
            f"{task.id}: unknown RWRL challenge {challenge!r}; use one of {sorted(CHALLENGES)} "
            "(the release has 'none' and 'easy') or an rlu.domains.rwrl.env.Challenge"
        )
    overrides = {k: settings.pop(k) for k in list(settings) if k in Challenge.__annotations__}
    try:
        if overrides:
            ch, name = replace(ch, **overrides), "custom"
        s = RwrlSettings(ch, name, **settings)
    except TypeError as e:
        raise RluError(
            f"{task.id}: bad RWRL setting ({e}); see rlu.domains.rwrl.env.RwrlSettings"
        ) from e
    except ConfigError as e:  # a setting out of its bounds: the task, the field, value, bound
        raise ConfigError(f"{task.id}: {e}") from None
    if (s.multiobj_reward or s.multiobj_observed) and not s.safety:
        raise RluError(f"{task.id}: the multi-objective settings need safety=True")
    domain = task.env["suite_domain"]
    env = _make_environment(domain, task.env["suite_task"], s, seed)
    return DmControlEnv(
        env,
        observation_spec(task, s),
        env.restart,
        physics=lambda: env.physics,
        control_timestep=env.control_timestep(),
        name=f"{task.id} ({name} challenge)",
        render=render,
        camera=0,  # as the control suite: each model's first camera
    )
