"""rlu generate: the recorder's step semantics, selection, determinism and crash resumption."""

from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from rlu.generate.common import select_episodes
from rlu.types import BatchSpec

TASK = "control_suite/cartpole_swingup"


def _files(path: Path) -> dict[str, bytes]:
    files = sorted(p for p in path.rglob("*") if p.is_file())
    return {str(p.relative_to(path)): p.read_bytes() for p in files}


def test_select_keeps_a_third_of_successes_then_subsamples():
    success = np.zeros(30, bool)
    success[[2, 5, 7, 11, 13, 17]] = True
    keep, counts = select_episodes(success, None, np.random.default_rng(0))
    assert counts["successful"] == 6 and counts["successful_kept_after_third"] == 2
    assert success[keep].sum() == 2 and keep.size == 26
    assert np.all(np.diff(keep) > 0)
    keep, counts = select_episodes(success, 10, np.random.default_rng(0))
    assert keep.size == 10 and counts["kept"] == 10
    assert set(keep) <= set(np.flatnonzero(~success)) | set(np.flatnonzero(success))


def test_curve_summary_by_hand():
    from rlu.generate.curves import RunCurve, markdown_table, moving_mean, summarise

    ret = np.arange(12, dtype=np.float64) * 10  # 0, 10, ..., 110
    ret[1] = 1000.0  # windows 0-9 (mean 144) and 1-10 (154) hold it, the last (65) does not
    steps = np.cumsum(np.full(12, 1000))
    np.testing.assert_allclose(moving_mean(ret, 10)[:1], [(ret[:10]).sum() / 10])
    (s,) = summarise([RunCurve(2, ret, steps)])
    assert (s.run, s.episodes, s.env_steps) == (2, 12, 12_000)
    assert s.best_mean == pytest.approx(154.0) and s.best_at_steps == 11_000
    assert s.final_mean == pytest.approx(ret[2:].mean())
    (short,) = summarise([RunCurve(0, ret[:3], steps[:3])])  # fewer than 10: the mean of all
    assert short.best_mean == pytest.approx(ret[:3].mean()) and short.best_at_steps == 3_000
    assert markdown_table([s], 100.0).splitlines()[-1].endswith("| yes |")


def test_progress_counts_a_resumed_runs_earlier_episodes(capsys):
    """A resumed generate's count starts where the runs stopped, not at 0 (on the one display,
    rlu.progress: a non-terminal stderr gets its final line at the end)."""
    from rlu.generate.common import Progress

    bar = Progress(2 * 400, "t")
    bar.report(0, 1, 0.0)  # a fresh run's first episode
    assert bar.done == 1
    bar.report(1, 210, 5.0)  # run 1 resumed after 209 episodes
    assert bar.done == 211  # every report is 1-based per run
    for ep in range(211, 220):
        bar.report(1, ep, 5.0)
    bar.close()
    lines = capsys.readouterr().err.splitlines()
    assert bar.done == 220 and len(lines) == 1, lines
    assert lines[0].startswith("t:") and "220/800 episodes" in lines[0]
    assert "run=1 episode=219 ret=5.0" in lines[0]


def test_replay_n_step_targets_by_hand():
    pytest.importorskip("torch")
    from rlu.data import make_episode
    from rlu.generate.online import Replay
    from rlu.tasks import get_task

    task = get_task(TASK)
    replay = Replay(task, 10, BatchSpec(4, n_step=2, gamma=0.5))
    obs = {
        k: np.arange(5, dtype=np.float32)[:, None].repeat(s.shape[0], 1)
        for k, s in task.observation_spec.items()
    }
    # 4 transitions ending in a terminal state: rewards 1, 2, 3, 4
    ep = make_episode(obs, np.zeros((4, 1), np.float32), [1, 2, 3, 4], terminal=True)
    replay.add(ep)
    assert replay.size == 4  # terminal: the last windows are cut at the terminal
    np.testing.assert_allclose(replay.reward[:4], [1 + 0.5 * 2, 2 + 0.5 * 3, 3 + 0.5 * 4, 4])
    np.testing.assert_array_equal(replay.discount[:4], [1, 1, 0, 0])
    np.testing.assert_array_equal(replay.next[:4], [2, 3, 4, 4])
    # a truncated episode leaves out windows that would cross its end
    ep2 = make_episode(obs, np.zeros((4, 1), np.float32), [1, 1, 1, 1], terminal=False)
    replay.add(ep2)  # does not fit after the first (5 + 5 = 10): fits exactly
    assert replay.size == 4 + 3
    replay.add(ep)  # wraps to 0 and overwrites the first episode whole
    assert replay.size == 3 + 4
    batch = replay.sample(np.random.default_rng(0), 8)
    assert batch.observation["position"].shape == (8, 3)


def test_recorder_terminal_and_truncation():
    pytest.importorskip("dm_control")
    from rlu.envs import make_env
    from rlu.generate.recorder import EpisodeRecorder, record_policy
    from rlu.tasks import get_task

    task = get_task(TASK)
    env = make_env(TASK, seed=0)
    rec = EpisodeRecorder(task)
    seg = record_policy(env, lambda o: np.zeros(1, np.float32), rec, seed=3, metadata={"run": 1})
    assert len(seg) == task.episode_length + 1
    assert seg.is_first[0] and seg.is_last[-1] and not seg.is_terminal[-1]
    assert seg.discount[-2] == 1.0  # truncation keeps the discount
    assert seg.metadata["run"] == 1
    np.testing.assert_allclose(seg.metadata["episode_return"], seg.reward.sum(), rtol=1e-6)
    again = record_policy(env, lambda o: np.zeros(1, np.float32), rec, seed=3)
    np.testing.assert_array_equal(again.observation["position"], seg.observation["position"])


_CHILD = textwrap.dedent(
    """
    import sys
    from rlu.generate import GenerateConfig, generate
    TASK, OUT = sys.argv[1:3]

    def on_chunk(run, chunk):
        print("chunk", run, chunk, flush=True)
        sys.stdin.read()  # block until the parent kills us

    generate(GenerateConfig(TASK, scale="tiny", runs=1, seed=7, progress=False), OUT, on_chunk)
    """
)


def test_tiny_generation_is_deterministic_and_resumes_after_sigkill(tmp_path, capsys):
    pytest.importorskip("torch")
    pytest.importorskip("dm_control")
    from rlu.cli import main
    from rlu.data import open_dataset
    from rlu.data.validate import validate
    from rlu.generate import GenerateConfig, generate

    # the reference through the CLI, its learning curves drawn
    ref, png = tmp_path / "ref", tmp_path / "curves" / "ref.png"
    argv = ["generate", TASK, "--scale", "tiny", "--seeds", "1", "--seed", "7", "--out", str(ref)]
    assert main([*argv, "--no-progress", "--curves", str(png)]) == 0
    printed = capsys.readouterr().out
    assert "| run | episodes | env steps | best 10-episode mean" in printed
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert validate(ref).ok
    ds = open_dataset(ref)
    assert len(ds) == 2
    assert [ds.segment(i).metadata["episode_index"] for i in range(2)] == [0, 1]
    prov = ds.manifest["provenance"]
    assert prov["command"].startswith(f"rlu generate {TASK} --scale tiny")
    # every recorded episode's return and length, per run (all kept at this scale)
    assert prov["runs"] == [
        {
            "run": 0,
            "episode_return": [round(float(r), 3) for r in ds.metadata("episode_return")],
            "episode_steps": [1000, 1000],
        }
    ]

    out = tmp_path / "crashed"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    child = subprocess.Popen(
        [sys.executable, "-c", _CHILD, TASK, str(out)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    line = child.stdout.readline()  # the child has written run 0's first chunk and its state
    assert line.strip() == "chunk 0 0", line
    child.send_signal(signal.SIGKILL)
    child.wait()
    child.stdin.close()
    child.stdout.close()
    work = tmp_path / ".crashed.generate"
    assert (work / "run_000" / "state.pt").exists() and not out.exists()

    resumed_chunks = []
    config = GenerateConfig(TASK, scale="tiny", runs=1, seed=7, progress=False)
    got = generate(config, out, on_chunk=lambda r, c: resumed_chunks.append((r, c)))
    assert resumed_chunks == [(0, 1)]  # chunk 0 was not played again
    assert _files(got) == _files(ref)
    assert not work.exists()


def test_resume_with_other_settings_is_refused(tmp_path):
    from rlu.generate import GenerateConfig, generate
    from rlu.types import RluError

    work = tmp_path / ".d.generate"
    work.mkdir()
    (work / "settings.json").write_text(
        '{"task": "control_suite/cartpole_swingup", "scale": "laptop", "runs": 3, "seed": 1}'
    )
    with pytest.raises(RluError, match="other settings"):
        generate(GenerateConfig(TASK, scale="tiny", runs=1, seed=7, progress=False), tmp_path / "d")


def _record(task_id: str, episodes: int, settings: dict, tmp_path: Path):
    """Random-policy episodes through the recorder, stored, plus the env's own observations."""
    from rlu.data import DatasetWriter, open_dataset
    from rlu.envs import make_env
    from rlu.generate.recorder import EpisodeRecorder, schema_for
    from rlu.tasks import get_task

    task = get_task(task_id)
    env = make_env(task_id, seed=0, **settings)
    rec = EpisodeRecorder(task, settings.get("max_episode_steps"))
    rng = np.random.default_rng(0)
    segs, seen = [], []
    for e in range(episodes):
        obs, _ = env.reset(seed=e)
        rec.begin(obs)
        seen.append(obs)
        while True:
            if task.discrete:
                a = np.int64(rng.integers(task.action_dim))
            else:
                a = rng.uniform(-1, 1, task.action_spec.shape).astype(np.float32)
            obs, r, term, trunc, info = env.step(a)
            seg = rec.step(a, r, obs, term, trunc, info, {"episode_index": e})
            if seg is None:
                seen.append(obs)
            else:
                segs.append(seg)
                break
    with DatasetWriter(tmp_path / "ds", schema_for(task)) as w:
        for s in segs:
            w.append(s)
    return task, segs, seen, open_dataset(tmp_path / "ds")


def test_atari_frames_stack_back_to_the_envs_observations_in_store_and_replay(tmp_path):
    pytest.importorskip("ale_py")
    pytest.importorskip("torch")
    from rlu.data import TransitionView
    from rlu.generate.online import Replay

    task, segs, seen, ds = _record("atari/Pong", 2, {"max_episode_steps": 12}, tmp_path)
    view = TransitionView(ds).all()
    # every transition's observation is exactly the env's (84, 84, 4) stack at that step
    np.testing.assert_array_equal(view.observation, np.stack(seen))
    replay = Replay(task, 100, BatchSpec(4, gamma=0.99))
    for s in segs:
        replay.add(s)
    got = replay._observation(replay._eligible)
    np.testing.assert_array_equal(got, view.observation)
    np.testing.assert_array_equal(
        replay._observation(replay.next[replay._eligible]), view.next_observation
    )
    # stored as the store does, after 3 frames of zeros: a ring that wraps (the third episode
    # overwrites the first) still stacks inside each episode
    ring = Replay(task, 3 + len(segs[0]) + 2 * (3 + len(segs[1])) - 1, BatchSpec(4, gamma=0.99))
    for s in (segs[1], segs[1], segs[0]):
        ring.add(s)
    assert ring.size == len(segs[0]) - 1 + len(segs[1]) - 1
    np.testing.assert_array_equal(ring._observation(ring._eligible), view.observation)
    assert (
        ds.segment(0).metadata["clipped_episode_return"] == ds.segment(0).metadata["episode_return"]
    )


def test_replay_n_step_transitions_equal_the_store_view(tmp_path):
    pytest.importorskip("dm_control")
    pytest.importorskip("torch")
    from rlu.data import TransitionView
    from rlu.generate.online import Replay

    task, segs, _, ds = _record(TASK, 2, {}, tmp_path)
    view = TransitionView(ds, n_step=3, gamma=0.9).all()
    replay = Replay(task, 5_000, BatchSpec(4, n_step=3, gamma=0.9))
    for s in segs:
        replay.add(s)
    idx = replay._eligible
    assert idx.size == len(view.reward)
    # one n-step implementation (rlu.data.views): the same numbers to the bit
    np.testing.assert_array_equal(replay.reward[idx], view.reward)
    np.testing.assert_array_equal(replay.discount[idx], view.discount)
    np.testing.assert_array_equal(replay.action[replay.next[idx]], view.next_action)
    for k in task.observation_spec:
        np.testing.assert_array_equal(replay.obs[k][idx], view.observation[k])
        np.testing.assert_array_equal(replay.obs[k][replay.next[idx]], view.next_observation[k])


def test_rwrl_snapshot_rollouts_at_tiny_scale(tmp_path):
    pytest.importorskip("torch")
    pytest.importorskip("dm_control")
    import json

    from rlu.data import open_dataset
    from rlu.data.validate import validate
    from rlu.generate import GenerateConfig, generate
    from rlu.tasks import RWRL_EASY_DUMMY_KEYS

    config = GenerateConfig("rwrl/cartpole_swingup", scale="tiny", runs=1, seed=1, progress=False)
    out = generate(config, tmp_path / "rw")
    names = json.loads((out / "rwrl.json").read_text())["datasets"]
    assert names == [f"{c}_{s}" for c in ("easy", "none") for s in ("large", "medium", "small")]
    for name in names:
        assert validate(out / name).ok, name
    easy, none = open_dataset(out / "easy_large"), open_dataset(out / "none_large")
    assert set(RWRL_EASY_DUMMY_KEYS) <= set(easy.schema.observation)
    assert not set(RWRL_EASY_DUMMY_KEYS) & set(none.schema.observation)
    assert len(none) == 2 and len(open_dataset(out / "none_small")) == 1
    snap = none.manifest["provenance"]["snapshots"][0]
    assert snap["return"] >= 0.75 * snap["converged"]
    assert not (tmp_path / ".rw.generate").exists()


def test_runs_in_worker_processes_give_the_one_process_bytes(tmp_path):
    pytest.importorskip("torch")
    pytest.importorskip("dm_control")
    from rlu.generate import GenerateConfig, generate
    from rlu.workers import Backend

    config = GenerateConfig(TASK, scale="tiny", runs=2, seed=3, progress=False)
    one = generate(config, tmp_path / "one")
    two = generate(dataclasses.replace(config, backend=Backend(workers=2)), tmp_path / "two")
    assert _files(two) == _files(one)


@pytest.mark.slow  # a local Ray instance: ~30 s idle, minutes on a loaded machine
def test_ray_backend_gives_the_local_bytes(tmp_path):
    pytest.importorskip("ray")
    pytest.importorskip("torch")
    pytest.importorskip("dm_control")
    from rlu.generate import GenerateConfig, generate
    from rlu.workers import Backend

    config = GenerateConfig(TASK, scale="tiny", runs=2, seed=3, progress=False)
    local = generate(config, tmp_path / "local")
    ray = generate(dataclasses.replace(config, backend=Backend("ray")), tmp_path / "ray")
    assert _files(ray) == _files(local)


def test_user_policy_recipe_is_deterministic_and_skips_finished_chunks(tmp_path):
    pytest.importorskip("dm_control")
    from rlu.data import open_dataset
    from rlu.generate import GenerateConfig, generate
    from tests.generate import policies

    spec = "tests.generate.policies:uniform"
    config = GenerateConfig(TASK, scale="tiny", runs=1, seed=5, progress=False, policy=spec)
    ref = generate(config, tmp_path / "ref")
    ds = open_dataset(ref)
    assert len(ds) == 2
    assert ds.manifest["provenance"]["command"].endswith(f"--policy {spec} --out DIR")
    # an interrupted run: chunk 0 finished, chunk 1 lost
    again = generate(dataclasses.replace(config, keep_work=True), tmp_path / "again")
    work = tmp_path / ".again.generate"
    import shutil

    shutil.rmtree(again)
    shutil.rmtree(work / "run_000" / "part_00001")
    policies.BUILT.clear()
    again = generate(config, tmp_path / "again")
    assert len(policies.BUILT) == 1  # only the lost chunk was played again
    assert _files(again) == _files(ref)


def test_locomotion_needs_a_policy(tmp_path):
    from rlu.generate import GenerateConfig, generate
    from rlu.types import RluError

    with pytest.raises(RluError, match="--policy"):
        generate(GenerateConfig("locomotion/rodent_gaps", scale="tiny"), tmp_path / "x")


@pytest.mark.slow  # ~75 s CPU: rodent episodes of 1500 steps with the camera rendered
def test_locomotion_records_a_user_policy_with_its_camera(tmp_path):
    pytest.importorskip("dm_control")
    from rlu.data import open_dataset
    from rlu.data.validate import validate
    from rlu.generate import GenerateConfig, generate

    config = GenerateConfig(
        "locomotion/rodent_gaps",
        scale="tiny",
        progress=False,
        policy="tests.generate.policies:uniform",
    )
    out = generate(config, tmp_path / "loco")
    assert validate(out).ok
    ds = open_dataset(out)
    sel = ds.manifest["provenance"]["selection"]
    assert (
        sel["recorded"] == 2
        and sel["kept"] == sel["recorded"] - sel["successful"] + (sel["successful"] + 2) // 3
    )
    assert ds.segment(0).observation["walker/egocentric_camera"].shape[1:] == (64, 64, 3)


def test_atari_tiny_generation_trains_dopamines_dqn_deterministically_and_resumes(tmp_path):
    pytest.importorskip("torch")
    pytest.importorskip("ale_py")
    import json

    from rlu.data import open_dataset
    from rlu.generate import GenerateConfig, generate

    config = GenerateConfig("atari/Pong", scale="tiny", runs=1, seed=5, progress=False)
    ref = generate(config, tmp_path / "ref")
    settings = json.loads((ref / "manifest.json").read_text())["provenance"]["settings"]
    assert settings["online"]["agent"] == "dopamine_dqn"
    assert settings["agent_config"]["rmsprop_epsilon"] == 1e-5  # Dopamine's optimiser
    assert [open_dataset(ref).segment(i).metadata["episode_index"] for i in range(2)] == [0, 1]

    class Interrupted(Exception):
        pass

    def stop(run: int, chunk: int) -> None:
        raise Interrupted  # after run 0's first chunk and its state are on disk

    with pytest.raises(Interrupted):
        generate(config, tmp_path / "again", on_chunk=stop)
    assert (tmp_path / ".again.generate" / "run_000" / "state.pt").exists()
    resumed: list[tuple[int, int]] = []
    again = generate(config, tmp_path / "again", on_chunk=lambda r, c: resumed.append((r, c)))
    assert resumed == [(0, 1)]  # chunk 0 was not played again; the agent and replay resumed
    assert _files(again) == _files(ref)
