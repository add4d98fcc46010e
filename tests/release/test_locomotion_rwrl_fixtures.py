"""DM Locomotion and RWRL shards TensorFlow wrote (scripts/fixtures/write_locomotion_shard.py,
write_rwrl_shard.py): the reader returns their arrays bit for bit (the locomotion camera as raw
bytes, RWRL's plain TFRecord), and a conversion holds exactly the original loaders' SARSA tuples:
``dm_control_suite.py``'s (o[0], a[0], r[0], d[0], o[1], a[1]) per window, with the keys no
loader parses left out, and ``rwrl.py``'s 1000 tuples per episode (index 0 of action, reward and
discount a placeholder)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rlu.data.release import families as Fm
from rlu.data.release.convert import convert
from rlu.data.release.framing import RecordReader
from rlu.data.store import open_dataset
from rlu.data.validate import validate
from rlu.data.views import TransitionView
from rlu.domains import records

RELEASE = Path(__file__).resolve().parents[1] / "fixtures" / "release"
LOCOMOTION = RELEASE / "dm_locomotion" / "humanoid_corridor" / "seq2" / "train-00000-of-00100"
RWRL = RELEASE / "rwrl" / "combined_challenge_none" / "cartpole" / "swingup" / "20_percent"
RWRL = RWRL / "episodes.tfrecord-00000-of-00006"
UNPARSED = ("walker/sensors_torque", "walker/appendages_pos")  # in the files, in no loader


def _bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def test_tf_written_locomotion_shard_reads_bit_for_bit():
    raw = Fm.read_raw(LOCOMOTION, "dm_locomotion")
    exp = np.load(f"{LOCOMOTION}.npz")
    assert sorted(raw) == sorted([*exp.files, "length"])
    for k in exp.files:
        assert _bits(raw[k], exp[k]), k
    assert raw[records.CAMERA_KEY].shape == (7, 2, 64, 64, 3) and np.all(raw["length"] == 2)


def test_tf_written_locomotion_windows_convert_to_the_loaders_tuples(tmp_path):
    out = tmp_path / "ds"
    convert([LOCOMOTION], "dm_locomotion", "locomotion/humanoid_corridor", out, workers=1)
    exp = np.load(f"{LOCOMOTION}.npz")
    ds = open_dataset(out)
    t = TransitionView(ds).all()
    assert len(t.reward) == len(exp["reward"]) == 7  # one transition per 2-step window
    assert _bits(t.action, exp["action"][:, 0]) and _bits(t.next_action, exp["action"][:, 1])
    assert _bits(t.reward, exp["reward"][:, 0]) and _bits(t.discount, exp["discount"][:, 0])
    assert set(t.observation) == {k.removeprefix("observation/") for k in exp.files
                                  if k.startswith("observation/")} - set(UNPARSED)  # fmt: skip
    for k in t.observation:
        assert _bits(t.observation[k], exp[f"observation/{k}"][:, 0]), k
        assert _bits(t.next_observation[k], exp[f"observation/{k}"][:, 1]), k
    # the fall: the transition into the LAST step has discount 0, and only it is terminal
    terminal = (exp["step_type"][:, 1] == records.LAST) & (exp["discount"][:, 0] == 0)
    assert terminal.tolist() == [False, False, True, False, False, False, False]
    segs = [s for b in Fm.iter_segments(LOCOMOTION, "dm_locomotion") for s in b]
    assert [bool(s.is_terminal[-1]) for s in segs] == terminal.tolist()
    assert [bool(s.is_last[-1]) for s in segs] == (exp["step_type"][:, 1] == records.LAST).tolist()
    assert validate(out).ok


def test_tf_written_rwrl_shard_reads_bit_for_bit():
    reader = RecordReader(RWRL)
    assert len(list(reader)) == 2 and not reader.stats.compressed  # RWRL's files are plain
    raw = Fm.read_raw(RWRL, "rwrl")
    exp = np.load(f"{RWRL}.npz")
    assert sorted(raw) == sorted(exp.files)
    for k in exp.files:
        assert _bits(raw[k], exp[k]), k
    assert raw["reward"].shape == (2, 1001, 1)


def test_tf_written_rwrl_episodes_convert_to_the_loaders_tuples(tmp_path):
    out = tmp_path / "ds"
    convert([RWRL], "rwrl", "rwrl/cartpole_swingup", out, challenge="none", workers=1)
    exp = np.load(f"{RWRL}.npz")
    ds = open_dataset(out)
    t = TransitionView(ds).all()
    # rwrl.py: s = obs[0:1000], a = action[1:1001], r = reward[1:], d = discount[1:],
    # s' = obs[1:1001], a' = action[2:1001] with the last repeated, per episode
    assert len(t.reward) == 2 * 1000
    assert _bits(t.reward, exp["reward"][:, 1:, 0].reshape(-1))
    assert _bits(t.discount, exp["discount"][:, 1:, 0].reshape(-1))
    assert _bits(t.action, exp["action"][:, 1:].reshape(-1, 1))
    a_next = np.concatenate([exp["action"][:, 2:], exp["action"][:, -1:]], axis=1)
    assert _bits(t.next_action, a_next.reshape(-1, 1))
    for k in ("position", "velocity"):
        o = exp[f"observation:{k}"]
        assert _bits(t.observation[k], o[:, :-1].reshape(-1, o.shape[-1])), k
        assert _bits(t.next_observation[k], o[:, 1:].reshape(-1, o.shape[-1])), k
    returns = exp["reward"][:, 1:, 0].sum(axis=1, dtype=np.float64)
    assert np.array_equal(ds.metadata("episode_return"), returns)
    segs = [s for b in Fm.iter_segments(RWRL, "rwrl") for s in b]
    assert [(len(s.reward), bool(s.is_last[-1]), bool(s.is_terminal[-1])) for s in segs] == [
        (1001, True, False)
    ] * 2  # cartpole's episodes end at the time limit
    assert validate(out).ok
