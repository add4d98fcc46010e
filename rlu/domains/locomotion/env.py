"""DM Locomotion: the 7 RL Unplugged tasks with the walker's 64x64x3 egocentric camera.

The builders copy the original's (``rl_unplugged/dm_control_suite.py`` ``_build_*``), not
dm_control's examples, whose humanoid parameters differ. Every number below is the
original's.
The original then wrapped each env in: action normalisation to [-1, 1] -> clip -> float32 ->
keep the dataset's observation keys; ``rlu.domains.envkit.DmControlEnv`` does the same.

Rendering: the camera is rendered offscreen on every step through MuJoCo's GL backend
(``MUJOCO_GL=egl`` or ``osmesa``; rlu sets ``egl`` when unset) with the default renderer
settings, which is what made the dataset frames. ``camera=False`` removes the camera from the
observations (for speed; random-policy returns and other proprio-only uses). ``render_mode=
"rgb_array"`` draws a third-person view (the walker's ``walker/side`` tracking camera) for
videos; it is separate from the egocentric observation and changes nothing in it.

Seeding: ``make_env(task, seed=s)`` passes ``random_state=s`` to ``composer.Environment`` and
seeds the global-numpy draws some tasks make (see ``_Seeded``); ``reset(seed=s)`` rebuilds the
env with seed s (~0.5-2 s), unseeded resets continue the seeded streams.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

from rlu.domains.envkit import DmControlEnv, Render
from rlu.domains.spec import TaskSpec
from rlu.types import RluError

CAMERA_KEY = "walker/egocentric_camera"


def _rodent() -> Any:
    from dm_control.locomotion import walkers

    return walkers.Rat(observable_options={"egocentric_camera": dict(enabled=True)})


def _humanoid() -> Any:
    from dm_control.locomotion import walkers

    return walkers.CMUHumanoidPositionControlled(
        name="walker", observable_options={"egocentric_camera": dict(enabled=True)}
    )


def _env(task: Any, time_limit: float, seed: int | None) -> Any:
    from dm_control import composer

    return composer.Environment(
        time_limit=time_limit,
        task=task,
        random_state=seed,
        strip_singleton_obs_buffer_dim=True,
    )


def rodent_bowl_escape(seed: int | None) -> Any:
    from dm_control.locomotion import arenas, tasks

    walker = _rodent()
    arena = arenas.bowl.Bowl(size=(20.0, 20.0), aesthetic="outdoor_natural")
    task = tasks.escape.Escape(
        walker=walker, arena=arena, physics_timestep=0.001, control_timestep=0.02
    )
    return _env(task, 20, seed)


def rodent_mazes(seed: int | None) -> Any:
    from dm_control.locomotion import arenas, props, tasks

    walker = _rodent()
    wall_textures = arenas.labmaze_textures.WallTextures(style="style_01")
    arena = arenas.mazes.RandomMazeWithTargets(
        x_cells=11,
        y_cells=11,
        xy_scale=0.5,
        z_height=0.3,
        max_rooms=4,
        room_min_size=4,
        room_max_size=5,
        spawns_per_room=1,
        targets_per_room=3,
        wall_textures=wall_textures,
        aesthetic="outdoor_natural",
    )
    task = tasks.random_goal_maze.ManyGoalsMaze(
        walker=walker,
        maze_arena=arena,
        target_builder=functools.partial(
            props.target_sphere.TargetSphere,
            radius=0.05,
            height_above_ground=0.125,
            rgb1=(0, 0, 0.4),
            rgb2=(0, 0, 0.7),
        ),
        target_reward_scale=50.0,
        contact_termination=False,
        control_timestep=0.02,
        physics_timestep=0.001,
    )
    return _env(task, 30, seed)


def rodent_gaps(seed: int | None) -> Any:
    from dm_control.composer.variation import distributions
    from dm_control.locomotion import arenas, tasks

    walker = _rodent()
    arena = arenas.corridors.GapsCorridor(
        corridor_width=2,
        platform_length=distributions.Uniform(low=0.4, high=0.8),
        gap_length=distributions.Uniform(low=0.05, high=0.2),
        corridor_length=40,
        aesthetic="outdoor_natural",
    )
    task = tasks.corridors.RunThroughCorridor(
        walker=walker,
        arena=arena,
        walker_spawn_position=(5, 0, 0),
        walker_spawn_rotation=0,
        target_velocity=1.0,
        contact_termination=False,
        terminate_at_height=-0.3,
        physics_timestep=0.001,
        control_timestep=0.02,
    )
    return _env(task, 30, seed)


def rodent_two_touch(seed: int | None) -> Any:
    from dm_control.locomotion import arenas, props, tasks

    walker = _rodent()
    arena = arenas.floors.Floor(size=(10.0, 10.0), aesthetic="outdoor_natural")
    task = tasks.reach.TwoTouch(
        walker=walker,
        arena=arena,
        target_builders=[functools.partial(props.target_sphere.TargetSphereTwoTouch, radius=0.025)],
        randomize_spawn_rotation=True,
        target_type_rewards=[25.0],
        shuffle_target_builders=False,
        target_area=(1.5, 1.5),
        physics_timestep=0.001,
        control_timestep=0.02,
    )
    return _env(task, 30, seed)


def humanoid_walls(seed: int | None) -> Any:
    from dm_control.composer.variation import colors, distributions
    from dm_control.locomotion import arenas, tasks

    walker = _humanoid()
    wall_rgba = colors.RgbVariation(
        r=distributions.Uniform(low=0.5, high=0.6),
        g=distributions.Uniform(low=0.21, high=0.41),
        b=0,
        alpha=1,
    )
    arena = arenas.WallsCorridor(
        wall_gap=5.0,
        wall_width=distributions.Uniform(low=1, high=7),
        wall_height=distributions.Uniform(low=2.5, high=4.0),
        swap_wall_side=distributions.Bernoulli(prob=0.5),
        wall_rgba=wall_rgba,
        corridor_width=10,
        corridor_length=100,
    )
    task = tasks.RunThroughCorridor(
        walker=walker,
        arena=arena,
        walker_spawn_rotation=1.57,  # pi / 2, as the original writes it
        physics_timestep=0.005,
        control_timestep=0.03,
    )
    return _env(task, 30, seed)


def humanoid_corridor(seed: int | None) -> Any:
    from dm_control.locomotion import arenas, tasks

    walker = _humanoid()
    arena = arenas.EmptyCorridor(corridor_width=10, corridor_length=100)
    task = tasks.RunThroughCorridor(
        walker=walker,
        arena=arena,
        walker_spawn_rotation=1.57,
        physics_timestep=0.005,
        control_timestep=0.03,
    )
    return _env(task, 30, seed)


def humanoid_gaps(seed: int | None) -> Any:
    from dm_control.composer.variation import distributions
    from dm_control.locomotion import arenas, tasks

    walker = _humanoid()
    arena = arenas.GapsCorridor(
        corridor_width=10,
        platform_length=distributions.Uniform(low=0.3, high=2.5),
        gap_length=distributions.Uniform(low=0.75, high=1.25),
        corridor_length=100,
    )
    task = tasks.RunThroughCorridor(
        walker=walker,
        arena=arena,
        walker_spawn_position=(2, 0, 0),
        walker_spawn_rotation=1.57,
        physics_timestep=0.005,
        control_timestep=0.03,
    )
    return _env(task, 30, seed)


BUILDERS = {
    "humanoid_corridor": humanoid_corridor,
    "humanoid_walls": humanoid_walls,
    "humanoid_gaps": humanoid_gaps,
    "rodent_gaps": rodent_gaps,
    "rodent_two_touch": rodent_two_touch,
    "rodent_bowl_escape": rodent_bowl_escape,
    "rodent_mazes": rodent_mazes,
}


class _Seeded:
    """A composer env whose global-numpy randomness is seeded too.

    Some dm_control locomotion code draws from the *global* ``np.random`` (TwoTouch's spawn
    rotation and target placement, the maze's labmaze seed and textures), so a RandomState alone
    does not make an episode a function of the seed. Every build, reset and step runs with the
    global generator seeded from this env's own stream and restored afterwards. A seeded reset
    rebuilds the env (labmaze keeps a generator that cannot be reseeded): ``reset(seed=s)`` is
    then exactly ``make_env(task, seed=s).reset()``.
    """

    def __init__(
        self, builder: Callable[[int | None], Any], seed: int | None, camera: bool
    ) -> None:
        self._builder = builder
        self._camera = camera
        self.env: Any = None
        self.rebuild(seed)

    def rebuild(self, seed: int | None) -> None:
        import numpy as np

        if self.env is not None:
            self.env.close()
        g = None if seed is None else int(np.random.SeedSequence(seed).generate_state(1)[0])
        self._global = np.random.RandomState(g)
        self.env = self._global_seeded(self._builder, seed)
        if not self._camera:
            # The tasks switch the camera on themselves; switch it off after building.
            self.env.task._walker.observables.egocentric_camera.enabled = False  # noqa: SLF001

    def _global_seeded(self, fn: Callable[..., Any], *args: Any) -> Any:
        import numpy as np

        state = np.random.get_state()
        np.random.seed(self._global.randint(2**31))
        try:
            return fn(*args)
        finally:
            np.random.set_state(state)

    def reset(self) -> Any:
        return self._global_seeded(self.env.reset)

    def step(self, action: Any) -> Any:
        return self._global_seeded(self.env.step, action)

    def action_spec(self) -> Any:
        return self.env.action_spec()

    def observation_spec(self) -> Any:
        return self.env.observation_spec()

    def reward_spec(self) -> Any:
        return self.env.reward_spec()

    def discount_spec(self) -> Any:
        return self.env.discount_spec()

    def close(self) -> None:
        # composer.Environment.close frees its physics and fails when called again.
        if self.env is not None:
            self.env.close()
            self.env = None


# The render view: the walker's tracking camera from the side (both walkers have one), so the
# whole body stays in the frame as it runs down a 100 m corridor.
RENDER_CAMERA = "walker/side"


def make(
    task: TaskSpec,
    seed: int | None = None,
    camera: bool = True,
    render: Render | None = None,
    **settings: Any,
) -> DmControlEnv:
    if settings:
        raise RluError(
            f"{task.id}: unknown env settings {sorted(settings)}; locomotion has `camera`"
        )
    env = _Seeded(BUILDERS[task.env["builder"]], seed, camera)
    spec = dict(task.observation_spec)  # type: ignore[arg-type]  # dm_control observes a dict
    if not camera:
        del spec[CAMERA_KEY]
    return DmControlEnv(
        env,
        spec,
        env.rebuild,
        physics=lambda: env.env.physics,
        control_timestep=env.env.control_timestep(),
        name=task.id,
        render=render,
        camera=RENDER_CAMERA,
    )
