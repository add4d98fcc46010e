"""Videos of evaluation episodes on the real envs, read back with ffmpeg and Pillow."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("gymnasium")
imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
pytest.importorskip("PIL")

from rlu.evaluation.rollout import episode_seed, evaluate, task_env_factory  # noqa: E402
from rlu.evaluation.video import INDEX, record_video  # noqa: E402
from rlu.types import RluError  # noqa: E402

CARTPOLE = "control_suite/cartpole_swingup"


def _swing(obs, is_first, reward):
    """A deterministic policy that pushes the cart along its velocity (it swings the pole)."""
    v = np.asarray(obs["velocity"])[:, :1]
    return np.where(v >= 0, 1.0, -1.0).astype(np.float32)


def _frames(path):
    gen = imageio_ffmpeg.read_frames(str(path))
    meta = next(gen)
    w, h = meta["size"]
    return meta, [np.frombuffer(f, np.uint8).reshape(h, w, 3) for f in gen]


def test_an_mp4_per_episode_with_the_evaluation_s_returns(tmp_path):
    pytest.importorskip("dm_control")
    env_fn = task_env_factory(CARTPOLE, render_mode="rgb_array")
    videos = record_video(_swing, env_fn, tmp_path / "v", num_episodes=2, seed=7, max_steps=25)
    ev = evaluate(_swing, env_fn, num_episodes=2, seed=7, num_envs=1, max_steps=25)
    assert [v.episode_return for v in videos] == list(ev.returns)  # the same two episodes
    assert [v.length for v in videos] == [25, 25]
    assert [v.seed for v in videos] == [episode_seed(7, 0), episode_seed(7, 1)]
    meta, frames = _frames(videos[0].path)
    assert meta["codec"] == "h264" and meta["fps"] == 100.0  # cartpole steps 0.01 s: real time
    assert len(frames) == 26 and frames[0].shape == (480 + 24, 640, 3)  # frame + caption strip
    # the first frame is the env's own frame after the seeded reset (up to H.264's loss)
    env = env_fn()
    env.reset(seed=videos[0].seed)
    drawn = env.render().astype(int)
    env.close()
    assert np.abs(frames[0][:480].astype(int) - drawn).mean() < 3
    assert np.abs(frames[-1][:480].astype(int) - drawn).mean() > 0.5  # the cart moved
    index = json.loads((tmp_path / "v" / INDEX).read_text())
    assert [v["episode_return"] for v in index["videos"]] == list(ev.returns)
    assert sorted(p.name for p in (tmp_path / "v").iterdir()) == [
        "episode_000.mp4",
        "episode_001.mp4",
        INDEX,
    ]


def test_gif_keeps_real_time_at_50_frames_a_second(tmp_path):
    pytest.importorskip("dm_control")
    from PIL import Image

    env_fn = task_env_factory(CARTPOLE, render_mode="rgb_array")
    (v,) = record_video(_swing, env_fn, tmp_path, max_steps=20, fmt="gif", caption=False)
    with Image.open(v.path) as gif:
        assert (gif.n_frames, gif.size, gif.info["duration"]) == (11, (640, 480), 20)


def test_atari_frames_are_enlarged_with_square_pixels(tmp_path):
    pytest.importorskip("ale_py")
    env_fn = task_env_factory("atari/Pong", render_mode="rgb_array")
    (v,) = record_video(lambda o, f, r: np.zeros(len(f), np.int64), env_fn, tmp_path, max_steps=6)
    meta, frames = _frames(v.path)
    assert meta["fps"] == 15.0 and len(frames) == 7
    assert frames[0].shape == (2 * 210 + 24, 2 * 160, 3)
    env = env_fn()
    env.reset(seed=v.seed)
    screen = env.render().repeat(2, axis=0).repeat(2, axis=1).astype(int)
    env.close()
    assert np.abs(frames[0][:420].astype(int) - screen).mean() < 4


def test_an_env_without_frames_or_a_bad_format_is_refused_and_nothing_written(tmp_path):
    pytest.importorskip("dm_control")
    with pytest.raises(RluError, match="needs one made with render_mode='rgb_array'"):
        record_video(_swing, task_env_factory(CARTPOLE), tmp_path / "a")
    assert list((tmp_path / "a").iterdir()) == []
    with pytest.raises(RluError, match="use one of mp4, gif"):
        record_video(_swing, task_env_factory(CARTPOLE), tmp_path / "b", fmt="avi")


def test_a_failing_policy_leaves_no_half_written_video(tmp_path):
    pytest.importorskip("dm_control")
    calls = []

    def breaks(obs, is_first, reward):
        calls.append(1)
        if len(calls) > 5:
            raise RuntimeError("policy died")
        return _swing(obs, is_first, reward)

    env_fn = task_env_factory(CARTPOLE, render_mode="rgb_array")
    with pytest.raises(RuntimeError, match="policy died"):
        record_video(breaks, env_fn, tmp_path, max_steps=50)
    assert list(tmp_path.iterdir()) == []


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A (very) short BC run on the shipped cartpole data."""
    pytest.importorskip("torch")
    pytest.importorskip("dm_control")
    from rlu.training.config import RunSettings
    from rlu.training.train import TrainConfig, train

    out = tmp_path_factory.mktemp("trained") / "run"
    run = RunSettings(steps=20, eval_every=-1, checkpoint_every=20)
    train(TrainConfig(task=CARTPOLE, agent="bc", dataset=CARTPOLE, run=run), out)
    return out


def test_rlu_evaluate_video_films_the_episodes_it_scores(trained, tmp_path, capsys, monkeypatch):
    """Two of the three scored episodes, on two envs in lockstep, filmed as they are played:
    each video's return is the very return the evaluation lists; progress on stderr."""
    from rlu.cli import main

    monkeypatch.setenv("RLU_PROGRESS", "lines")
    argv = ["evaluate", str(trained), "--eval-episodes", "3", "--eval-envs", "2",
            "--eval-max-steps", "30", "--video", str(tmp_path / "v"), "--video-episodes", "2",
            "--video-size", "320x240"]  # fmt: skip
    assert main(argv) == 0
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    returns = [float(r) for r in lines[0].split("returns ")[1].split(", ")]
    filmed = [float(line.split("return ")[1].split(",")[0]) for line in lines[1:]]
    assert len(returns) == 3 and filmed == returns[:2]
    index = json.loads((tmp_path / "v" / INDEX).read_text())
    ev = json.loads(_json_eval(trained, capsys))  # the same evaluation without the videos
    assert [v["episode_return"] for v in index["videos"]] == ev["returns"][:2]  # exactly
    assert lines[1].startswith(str(tmp_path / "v" / "episode_000.mp4"))
    meta, frames = _frames(tmp_path / "v" / "episode_001.mp4")
    assert len(frames) == 31 and frames[0].shape == (240 + 24, 320, 3)  # --video-size
    err = captured.err.splitlines()
    says = f"filming episodes 0-1 of the 3 it scores, as they are played, into {tmp_path / 'v'}"
    assert says in err[0]
    assert [line for line in err if line.startswith("evaluate: 100% 3/3 episodes")] == [err[-1]]
    assert err[-1].endswith("steps=90")
    assert sorted(p.name for p in (tmp_path / "v").iterdir()) == [
        "episode_000.mp4",
        "episode_001.mp4",
        INDEX,
    ]


def _json_eval(run, capsys):
    from rlu.cli import main

    argv = ["evaluate", str(run), "--eval-episodes", "3", "--eval-envs", "2", "--eval-max-steps",
            "30", "--json", "--quiet"]  # fmt: skip
    assert main(argv) == 0
    return capsys.readouterr().out


def test_video_folders_are_checked_before_any_work(trained, tmp_path, capsys):
    """'' , the run itself, a dataset, a symbolic link, something else's folder: refused at once,
    nothing written; counts that cannot be filmed too."""
    from rlu.cli import main
    from rlu.data.bundled import bundled_dataset

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (tmp_path / "link").symlink_to(elsewhere)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    before = {p: p.stat().st_mtime_ns for p in trained.rglob("*")}
    cases = [
        ("", "--video is empty"),
        (str(trained), "is or contains the input"),
        (str(trained / "checkpoints"), "is or contains the input"),
        (str(bundled_dataset()), "is or contains the input"),
        (str(tmp_path / "link"), "is a symbolic link"),
        (str(mine), "is not an rlu video folder (it has no videos.json)"),
    ]
    for video, says in cases:
        code = main(["evaluate", str(trained), "--eval-episodes", "1", "--video", video])
        err = capsys.readouterr().err
        assert code == 2 and says in err, (video, err)
    for extra, says in [
        (["--video-episodes", "0"], "--video-episodes 0; film at least one"),
        (["--video-episodes", "2"], "more than the 1 episodes the evaluation scores"),
    ]:
        code = main(["evaluate", str(trained), "--eval-episodes", "1", "--video",
                     str(tmp_path / "new"), *extra])  # fmt: skip
        assert code == 2 and says in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["evaluate", str(trained), "--video", str(tmp_path / "new"), "--video-size", "9x9"])
    assert "write it as WIDTHxHEIGHT" in capsys.readouterr().err
    assert list(elsewhere.iterdir()) == [] and not (tmp_path / "new").exists()
    assert (mine / "notes.txt").read_text() == "mine"
    assert {p: p.stat().st_mtime_ns for p in trained.rglob("*")} == before


def test_a_link_planted_at_a_video_is_refused_and_its_target_kept(tmp_path):
    pytest.importorskip("dm_control")
    target = tmp_path / "precious.mp4"
    target.write_bytes(b"not yours")
    out = tmp_path / "v"
    out.mkdir()
    (out / "episode_000.mp4").symlink_to(target)
    env_fn = task_env_factory(CARTPOLE, render_mode="rgb_array", render_size=(48, 64))
    with pytest.raises(RluError, match="episode_000.mp4: is a symbolic link"):
        record_video(_swing, env_fn, out, max_steps=3)
    assert target.read_bytes() == b"not yours"
    assert sorted(p.name for p in out.iterdir()) == ["episode_000.mp4"]  # no temporary left


@pytest.mark.parametrize(
    ("script", "says"),
    [
        ("exec sleep 600\n", "took no video frame for 0.5 s; it may be hung"),
        ("exit 3\n", "stopped reading frames (exit code 3)"),
    ],
    ids=["never_reads", "dies"],
)
def test_an_ffmpeg_that_hangs_or_dies_is_a_clear_error(tmp_path, monkeypatch, script, says):
    pytest.importorskip("dm_control")
    import rlu.evaluation.video as video

    fake = tmp_path / "ffmpeg"
    fake.write_text("#!/bin/sh\n" + script)
    fake.chmod(0o755)
    monkeypatch.setenv("IMAGEIO_FFMPEG_EXE", str(fake))
    monkeypatch.setattr(video, "ENCODER_TIMEOUT", 0.5)
    env_fn = task_env_factory(CARTPOLE, render_mode="rgb_array")  # 640x480: over a pipe's buffer
    with pytest.raises(RluError) as e:
        record_video(_swing, env_fn, tmp_path / "v", max_steps=5)
    assert says in str(e.value) and str(fake) in str(e.value)
    assert list((tmp_path / "v").iterdir()) == []  # the temporary removed


def test_the_video_extra_holds_what_gymnasiums_record_video_needs(tmp_path):
    """moviepy is in the extra, and Gymnasium's RecordVideo writes a real MP4 with it."""
    import tomllib
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    project = tomllib.loads((root / "pyproject.toml").read_text())["project"]
    extras = project["optional-dependencies"]
    assert any(r.startswith("moviepy") for r in extras["video"])
    pytest.importorskip("moviepy")
    pytest.importorskip("dm_control")
    from gymnasium.wrappers import RecordVideo

    import rlu

    env = rlu.make_env(CARTPOLE, seed=0, render_mode="rgb_array", render_size=(96, 128))
    folder = tmp_path / "record"
    env = RecordVideo(env, str(folder), episode_trigger=lambda e: True, disable_logger=True)
    env.reset(seed=0)
    for _ in range(5):
        env.step(env.action_space.sample())
    env.close()
    (mp4,) = folder.glob("*.mp4")
    assert len(_frames(mp4)[1]) >= 5
