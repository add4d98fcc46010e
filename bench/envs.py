"""Env speed: rlu's envs against the raw library loop, and vectorised against single envs.

    MUJOCO_GL=egl .venv/bin/python bench/envs.py            # all domains (~3-5 min)
    MUJOCO_GL=egl .venv/bin/python bench/envs.py --quick    # fewer steps

Overhead: the same random action sequence drives rlu's env and the raw library loop (dm_control
``env.step`` / the bare ALE calls doing Dopamine's preprocessing inline), resetting at episode
ends, for the same number of steps; rounds alternate between the two and the best round of each
counts (the machine is shared, so single timings are noisy). Ratio = raw steps/s / rlu steps/s
(target <= 1.15). Vectorised: total steps/s of ``make_vector_env(num_envs=N)`` over one env
(target >= 1.8x on 2 cores).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from functools import partial

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
os.environ.setdefault("MUJOCO_GL", "egl")

import rlu  # noqa: E402
from rlu.envs import make_vector_env  # noqa: E402


def _actions(space, n, seed=0):
    rng = np.random.default_rng(seed)
    if hasattr(space, "n"):
        return [int(x) for x in rng.integers(space.n, size=n)]
    return list(rng.uniform(-1, 1, (n, *space.shape)).astype(np.float32))


def run_gym(env, actions):
    env.reset(seed=0)
    t0 = time.perf_counter()
    for a in actions:
        _, _, term, trunc, _ = env.step(a)
        if term or trunc:
            env.reset()
    return len(actions) / (time.perf_counter() - t0)


def run_dm(env, actions):
    env.reset()
    t0 = time.perf_counter()
    for a in actions:
        if env.step(a).last():
            env.reset()
    return len(actions) / (time.perf_counter() - t0)


def run_raw_ale(game, actions, max_steps=27_000):
    """Dopamine's preprocessing written inline over the ALE: the floor for any Atari env."""
    import ale_py
    import cv2

    from rlu.domains.atari.env import rom_id

    ale = ale_py.ALEInterface()
    ale.setLoggerMode(ale_py.LoggerMode.Error)
    ale.setFloat("repeat_action_probability", 0.25)
    ale.setInt("random_seed", 0)
    ale.loadROM(ale_py.roms.get_rom_path(rom_id(game)))
    acts = ale.getMinimalActionSet()
    h, w = ale.getScreenDims()
    screens = np.zeros((2, h, w), np.uint8)
    stack = np.zeros((84, 84, 4), np.uint8)
    ale.reset_game()
    steps = 0
    t0 = time.perf_counter()
    for a in actions:
        for t in range(4):
            ale.act(acts[a])
            if ale.game_over():
                break
            if t >= 2:
                ale.getScreenGrayscale(screens[t - 2])
        frame = cv2.resize(
            np.maximum(screens[0], screens[1]), (84, 84), interpolation=cv2.INTER_AREA
        )
        stack = np.concatenate([stack[:, :, 1:], frame[:, :, None]], axis=2)
        steps += 1
        if ale.game_over() or steps >= max_steps:
            ale.reset_game()
            stack = np.zeros((84, 84, 4), np.uint8)
            steps = 0
    return len(actions) / (time.perf_counter() - t0)


def run_gymnasium_atari(game, actions):
    """The stock ale_py + gymnasium wrapper pipeline with the same settings (a second peer)."""
    import ale_py
    import gymnasium as gym
    from gymnasium.wrappers import AtariPreprocessing, FrameStackObservation

    gym.register_envs(ale_py)
    env = gym.make(f"ALE/{game}-v5", frameskip=1, repeat_action_probability=0.25,
                   full_action_space=False, max_num_frames_per_episode=108_000)  # fmt: skip
    env = AtariPreprocessing(env, noop_max=0, frame_skip=4, screen_size=84,
                             terminal_on_life_loss=False, grayscale_obs=True)  # fmt: skip
    env = FrameStackObservation(env, 4, padding_type="zero")
    return run_gym(env, actions)


def best_of(rounds, fns):
    out = [0.0] * len(fns)
    for _ in range(rounds):
        for i, fn in enumerate(fns):
            out[i] = max(out[i], fn())
    return out


def overhead(args):
    from dm_control import suite

    from rlu.domains.locomotion import env as locomotion

    rows = []
    n = 2000 if args.quick else 10000
    for tid, dom, task in [
        ("control_suite/cheetah_run", "cheetah", "run"),
        ("control_suite/humanoid_run", "humanoid", "run"),
        ("rwrl/walker_walk", "walker", "walk"),
    ]:
        env = rlu.make_env(tid, seed=0)
        raw = suite.load(dom, task, task_kwargs={"random": 0})
        acts = _actions(env.action_space, n)
        r, o = best_of(args.rounds, [partial(run_dm, raw, acts), partial(run_gym, env, acts)])
        rows.append((tid + (" (challenge none)" if tid.startswith("rwrl") else ""), r, o))
    easy = rlu.make_env("rwrl/walker_walk", seed=0, challenge="easy")
    acts = _actions(easy.action_space, n)
    rows.append(("rwrl/walker_walk (easy: challenge work)", rows[-1][1], run_gym(easy, acts)))

    loco = [
        ("locomotion/rodent_gaps", True, 40 if args.quick else 100),
        ("locomotion/humanoid_corridor", False, 300 if args.quick else 1000),
    ]
    for tid, cam, steps in loco:
        env = rlu.make_env(tid, seed=0, camera=cam)
        raw = locomotion.BUILDERS[rlu.get_task(tid).env["builder"]](0)
        if not cam:
            raw.task._walker.observables.egocentric_camera.enabled = False
        acts = _actions(env.action_space, steps)
        # Short rounds, more of them: these envs are slow and their timings swing with the load.
        fns = [partial(run_dm, raw, acts), partial(run_gym, env, acts)]
        r, o = best_of(2 * args.rounds, fns)
        rows.append((f"{tid} (camera {'on' if cam else 'off'})", r, o))

    for game in ["Pong", "MsPacman"]:
        env = rlu.make_env(f"atari/{game}", seed=0)
        acts = _actions(env.action_space, n)
        fns = [partial(run_raw_ale, game, acts), partial(run_gym, env, acts),
               partial(run_gymnasium_atari, game, acts)]  # fmt: skip
        r, o, g = best_of(args.rounds, fns)
        rows.append((f"atari/{game}", r, o))
        rows.append((f"atari/{game} (peer: gymnasium AtariPreprocessing)", r, g))

    print(f"\n{'overhead: task':58s} {'raw/s':>9s} {'rlu/s':>9s} {'raw/rlu':>8s}  target <= 1.15")
    for name, r, o in rows:
        print(f"{name:58s} {r:9.0f} {o:9.0f} {r / o:8.2f}")


def vectorised(args):
    rows = []
    q = args.quick
    cases = [  # (task, steps per measurement, backend, N)
        ("control_suite/humanoid_run", 1000 if q else 4000, "process", 2),
        ("control_suite/humanoid_run", 1000 if q else 4000, "process", 8),
        ("control_suite/cheetah_run", 1000 if q else 4000, "process", 2),
        ("control_suite/cheetah_run", 1000 if q else 4000, "process", 8),
        ("control_suite/cheetah_run", 1000 if q else 4000, "async", 2),
        ("control_suite/cheetah_run", 1000 if q else 4000, "sync", 8),
        ("locomotion/rodent_gaps", 40 if q else 150, "process", 2),
        ("atari/Pong", 2000 if q else 8000, "ale", 2),
        ("atari/Pong", 2000 if q else 8000, "ale", 8),
        ("atari/Pong", 2000 if q else 8000, "process", 2),
    ]
    for tid, steps, backend, n in cases:
        single = rlu.make_env(tid, seed=0)
        acts = _actions(single.action_space, steps)
        venv = make_vector_env(tid, num_envs=n, seed=0, backend=backend)
        venv.reset(seed=0)
        batch = [venv.action_space.sample() for _ in range(max(steps // n, 10))]

        def run_vector(venv=venv, batch=batch, n=n):
            t0 = time.perf_counter()
            for a in batch:
                venv.step(a)
            return len(batch) * n / (time.perf_counter() - t0)

        # Interleaved rounds, best of each: the machine is shared and its load moves.
        s, v = best_of(args.rounds, [partial(run_gym, single, acts), run_vector])
        venv.close()
        single.close()
        rows.append((f"{tid} [{backend}, N={n}]", s, v))
    print(
        f"\n{'vectorised: task':58s} {'1 env/s':>9s} {'N envs/s':>9s} {'speedup':>8s}"
        "  target >= 1.8"
    )
    for name, s, v in rows:
        print(f"{name:58s} {s:9.0f} {v:9.0f} {v / s:8.2f}")


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--quick", action="store_true")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--only", choices=["overhead", "vector"])
    args = p.parse_args()
    print(f"cores: {len(os.sched_getaffinity(0))}, load average: {os.getloadavg()}")
    if args.only != "vector":
        overhead(args)
    if args.only != "overhead":
        vectorised(args)


if __name__ == "__main__":
    main()
