"""DeepMind Lab as a domain: its tasks in ``rlu list`` as data only, a TensorFlow-written shard
(scripts/fixtures/write_dmlab_shard.py) converted from the command line into exactly the arrays
TensorFlow was given (frames back in RGB), a damaged shard refused with the file named, and the
env refused with what is missing (no traceback)."""

from __future__ import annotations

import gzip
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from rlu.cli import main
from rlu.types import RluError

TASK = "dmlab/seekavoid_arena_01"
SHARD = Path(__file__).resolve().parents[1] / "fixtures" / "release" / "dmlab"
SHARD = SHARD / "seekavoid_arena_01" / "training_0" / "tfrecord-00000-of-00500"


def test_dmlab_tasks_are_listed_as_data_only(capsys):
    assert main(["list", "--domain", "dmlab"]) == 0
    out = capsys.readouterr().out
    for level in ("seekavoid_arena_01", "explore_object_rewards_few", "rooms_watermaze"):
        assert f"dmlab/{level}" in out
    assert "5 tasks" in out
    assert "dmlab: data only, no env (DeepMind Lab is data only here: deepmind_lab is not" in out
    assert main(["list", "--domain", "bsuite"]) == 0
    assert "data only" not in capsys.readouterr().out  # bsuite has an env
    assert main(["info", TASK]) == 0
    assert 'data_only: "no env: DeepMind Lab is data only here' in capsys.readouterr().out


def test_making_the_env_refuses_with_what_is_missing():
    import rlu

    with pytest.raises(RluError) as e:
        rlu.make_env(TASK)
    msg = str(e.value)
    assert msg.startswith(f"{TASK}: DeepMind Lab is data only here")
    assert "rlu convert FILE --family dmlab" in msg and "--eval-every -1" in msg
    if e.value.__class__ is RluError and "not installed" in msg:  # without deepmind_lab
        assert "bazel build" in msg


def _convert(tmp_path: Path, shard: Path = SHARD) -> Path:
    out = tmp_path / "data"
    argv = ["convert", str(shard), "--family", "dmlab", "--task", TASK, "--out", str(out)]
    assert main(argv) == 0
    return out


def test_a_tf_written_dmlab_shard_converts_to_its_arrays(tmp_path):
    from rlu.data.store import open_dataset

    ds = open_dataset(_convert(tmp_path))
    exp = np.load(f"{SHARD}.npz")
    n, t = exp["actions"].shape
    assert ds.schema.task_id == TASK and ds.num_segments == n == 3 and ds.num_steps == n * t
    assert sorted(ds.schema.observation) == ["last_action", "last_reward", "pixels"]
    assert ds.manifest["provenance"]["run"] == "training_0"  # the shard's run folder
    for i in range(n):
        s = ds.segment(i)
        pixels = np.asarray(s.observation["pixels"])
        assert pixels.dtype == np.uint8 and pixels.shape == (t, 72, 96, 3)
        assert np.array_equal(pixels, exp["rgb"][i])  # RGB: the stored BGR reversed
        assert np.array_equal(pixels, exp["observations_pixels"][i][..., ::-1])
        assert np.array_equal(s.observation["last_action"], exp["observations_action"][i])
        assert np.array_equal(s.observation["last_reward"], exp["observations_reward"][i])
        assert np.array_equal(s.action, exp["actions"][i])
        assert np.array_equal(s.reward, exp["rewards"][i])
        assert np.array_equal(s.discount, exp["discounts"][i])
        assert s.is_first.tolist() == [True] + [False] * (t - 1)
        assert s.is_last.tolist() == [False] * (t - 1) + [True]
        assert not s.is_terminal.any()  # discount 1 throughout: the level's time limit ends it
        assert s.metadata["episode_id"] == exp["episode_id"][i]
        assert s.metadata["episode_return"] == exp["episode_return"][i]
    # the last action one-hot is the previous step's action
    s = ds.segment(0)
    assert np.array_equal(np.asarray(s.observation["last_action"])[1:].argmax(-1), s.action[:-1])


def test_the_release_reader_returns_the_stored_arrays():
    from rlu.data.release import families as Fm

    exp = np.load(f"{SHARD}.npz")
    raw = Fm.read_raw(SHARD, "dmlab")
    for k in exp.files:
        if k == "rgb":
            continue
        got = np.asarray(raw[k]).astype(exp[k].dtype)
        assert got.shape == exp[k].shape and got.tobytes() == exp[k].tobytes(), k
    segments = [s for b in Fm.iter_segments(SHARD, "dmlab") for s in b]
    assert len(segments) == 3
    for s, rgb in zip(segments, exp["rgb"], strict=True):
        assert np.array_equal(s.observation["pixels"], rgb)


def test_the_env_refusal_is_one_line_from_the_command_line(tmp_path, capsys):
    # a run that evaluates needs the env: the refusal comes before anything is written
    data = _convert(tmp_path)
    argv = ["train", "--task", TASK, "--agent", "bc", "--dataset", str(data), "--out",
            str(tmp_path / "run"), "--steps", "1", "--device", "cpu", "--quiet"]  # fmt: skip
    pytest.importorskip("torch")
    assert main(argv) != 0
    err = capsys.readouterr().err
    assert "DeepMind Lab is data only here" in err and "Traceback" not in err


def test_bc_trains_5_steps_on_the_converted_shard(tmp_path):
    pytest.importorskip("torch")
    run = tmp_path / "run"
    argv = ["train", "--task", TASK, "--agent", "bc", "--dataset", str(_convert(tmp_path)),
            "--out", str(run), "--steps", "5", "--eval-every", "-1", "--device", "cpu",
            "--quiet", "atari.batch_size=4"]  # fmt: skip
    assert main(argv) == 0
    result = json.loads((run / "result.json").read_text())
    assert result["steps"] == 5 and result["score"] is None  # never evaluated: no env
    metrics = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert metrics[-1]["step"] == 5 and np.isfinite(metrics[-1]["actor/bc_loss"])


def test_recurrent_bc_trains_5_steps_on_the_converted_windows(tmp_path):
    torch = pytest.importorskip("torch")
    from rlu.agents import discrete_common as dc
    from rlu.agents import make_agent
    from rlu.agents.bc_discrete import bc_loss
    from rlu.data import make_sampler
    from rlu.tasks import get_task

    run = tmp_path / "run"
    argv = ["train", "--task", TASK, "--agent", "bc", "--dataset", str(_convert(tmp_path)),
            "--out", str(run), "--steps", "5", "--eval-every", "-1", "--device", "cpu",
            "--quiet", "atari.batch_size=4", "recurrent=True", "sequence_length=6",
            "lstm_size=16"]  # fmt: skip
    assert main(argv) == 0
    metrics = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert metrics[-1]["step"] == 5 and np.isfinite(metrics[-1]["actor/bc_loss"])
    # the loss is the cross-entropy over the real steps that are not an episode's last
    task = get_task(TASK)
    agent = make_agent("bc", task.observation_spec, task.action_spec, "small", recurrent=True,
                       sequence_length=6, lstm_size=16, **{"atari.batch_size": 4})  # fmt: skip
    assert agent.batch_spec.kind == "sequence" and agent.batch_spec.sequence_length == 6
    batch = make_sampler(tmp_path / "data", agent.batch_spec, seed=3).sample()
    with torch.no_grad():
        frames = dc.frames(dc.time_steps(batch.observation, 0, 6))
        logits, _ = agent.network(frames, 4, 6)
    keep = (batch.mask & ~batch.is_last).reshape(-1)
    assert 0 < keep.sum() < keep.size
    action = torch.as_tensor(batch.action.reshape(-1))
    expected = torch.nn.functional.cross_entropy(logits.reshape(24, -1)[keep], action[keep])
    got, _ = bc_loss(logits.reshape(24, -1), action, torch.as_tensor(keep).float())
    torch.testing.assert_close(got, expected)
    assert agent.update(batch)["actor/bc_loss"] == pytest.approx(expected.item(), rel=1e-5)


def test_the_discrete_networks_read_the_last_action_and_reward(tmp_path):
    torch = pytest.importorskip("torch")
    from rlu.agents import discrete_common as dc
    from rlu.data import make_sampler
    from rlu.tasks import get_task
    from rlu.types import BatchSpec

    task = get_task(TASK)
    batch = make_sampler(_convert(tmp_path), BatchSpec(4), seed=0).sample()
    shapes, actions = dc.check_specs("bc", task.observation_spec, task.action_spec)
    assert dict(shapes) == {"pixels": (72, 96, 3), "last_action": (15,), "last_reward": ()}
    torch.manual_seed(0)
    net = dc.QNetwork(shapes, actions, dc.SMALL)
    assert net.torso.output_size == 32 * 5 * 8 + 15 + 1  # 72x96 -> 5x8 after the convolutions
    obs = dc.frames(batch.observation)
    q = net(obs)
    assert q.shape == (4, 15) and torch.isfinite(q).all()
    for key in ("last_action", "last_reward"):  # each vector changes the output
        changed = {**obs, key: obs[key] + 1.0}
        assert not torch.allclose(net(changed), q), key
    with pytest.raises(Exception, match="needs 'pixels'"):
        dc.check_specs("bc", {"rgb": task.observation_spec["pixels"]}, task.action_spec)


def _damaged(tmp_path: Path, how: str) -> Path:
    path = tmp_path / "dmlab" / "seekavoid_arena_01" / "training_0" / SHARD.name
    path.parent.mkdir(parents=True)
    body = SHARD.read_bytes()
    if how == "truncated":
        path.write_bytes(body[:5000])
    else:  # one payload byte flipped, the gzip stream itself intact
        plain = bytearray(gzip.decompress(body))
        plain[3000] ^= 0xFF
        path.write_bytes(gzip.compress(bytes(plain)))
    return path


@pytest.mark.parametrize(
    "how,why", [("truncated", "truncated record"), ("flipped", "payload CRC mismatch")]
)
def test_a_damaged_shard_is_refused_naming_the_file(tmp_path, capsys, how, why):
    from rlu.data.release.convert import convert

    path = _damaged(tmp_path, how)
    out = tmp_path / "out"
    argv = ["convert", str(path), "--family", "dmlab", "--task", TASK, "--out", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"rlu: error: {path}: {why}" in err and "download it again" in err
    assert "Traceback" not in err and not out.exists()
    with pytest.raises(RluError, match=why):
        convert([str(path)], "dmlab", TASK, tmp_path / "out2")


def test_a_record_of_the_wrong_frame_size_is_refused(tmp_path):
    from rlu.data.release import families as Fm
    from rlu.data.release.convert import convert

    raw = {k: v[0] for k, v in np.load(f"{SHARD}.npz").items() if k != "rgb"}
    raw["observations_pixels"] = np.ascontiguousarray(raw["observations_pixels"][:, :64])
    path = tmp_path / "training_0" / SHARD.name
    path.parent.mkdir()
    Fm.write_shard(path, "dmlab", [raw])
    with pytest.raises(RluError, match=r"observations_pixels.*72"):
        convert([str(path)], "dmlab", TASK, tmp_path / "out")
    shutil.rmtree(tmp_path / "out", ignore_errors=True)
