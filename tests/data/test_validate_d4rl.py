"""``rlu validate`` finds each kind of problem; the D4RL layout round-trips and cuts correctly."""

from __future__ import annotations

import uuid

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rlu.cli import main
from rlu.data import Schema, TransitionView, open_dataset
from rlu.data.d4rl import d4rl_segments, export_d4rl, import_d4rl, to_d4rl
from rlu.data.synthetic import write_synthetic
from rlu.tasks import get_task

CARTPOLE = Schema.for_task(get_task("control_suite/cartpole_swingup"))


def _poke(path, rel, index, value, dtype):
    arr = np.memmap(path / rel, dtype=dtype, mode="r+")
    arr[index] = value
    arr.flush()
    del arr


def test_valid_dataset_passes(tmp_path, capsys):
    path = write_synthetic(tmp_path / "ds", CARTPOLE, 3, 5)
    assert main(["validate", str(path)]) == 0
    assert "valid" in capsys.readouterr().out


@pytest.mark.parametrize(
    "rel,index,value,dtype,needle",
    [
        ("steps/observation/position.bin", 4, np.nan, "<f4", "NaN or inf"),
        ("steps/reward.bin", 2, 100.0, "<f4", "stores return"),
        ("steps/is_first.bin", 2, True, "bool", "is_first inside"),
        ("steps/is_last.bin", 1, True, "bool", "is_last before"),
        ("steps/discount.bin", 1, 0.0, "<f4", "discount 0 but its episode goes on"),
    ],
)
def test_each_problem_is_found(tmp_path, capsys, rel, index, value, dtype, needle):
    path = write_synthetic(tmp_path / "ds", CARTPOLE, 2, 5, terminal_prob=0.0)
    _poke(path, rel, index, value, dtype)
    assert main(["validate", "--no-checksums", str(path)]) == 1
    out = capsys.readouterr().out
    assert needle in out and rel.split("/")[-1] in out
    assert main(["validate", str(path)]) == 1  # and the checksum no longer matches
    assert "sha256" in capsys.readouterr().out


def test_validate_reports_a_missing_manifest(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert main(["validate", str(tmp_path / "empty")]) == 1
    assert "no manifest" in capsys.readouterr().out


def test_d4rl_export_keys_and_flags(tmp_path):
    path = write_synthetic(tmp_path / "ds", CARTPOLE, 4, 3, seed=2)
    ds = open_dataset(path)
    d = to_d4rl(ds)
    assert {
        "observations/position",
        "next_observations/velocity",
        "actions",
        "rewards",
        "terminals",
        "timeouts",
    } <= set(d)
    assert len(d["rewards"]) == 4 * 3
    ends = d["terminals"] | d["timeouts"]
    assert ends.reshape(4, 3)[:, -1].all() and not ends.reshape(4, 3)[:, :-1].any()
    assert not (d["terminals"] & d["timeouts"]).any()
    ret = ds.metadata("episode_return")
    np.testing.assert_allclose(d["rewards"].reshape(4, 3).sum(1), ret, rtol=1e-5)


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 6), term=st.floats(0, 1))
def test_d4rl_round_trip_property(tmp_path, seed, n, term):
    tmp_path = tmp_path / uuid.uuid4().hex  # hypothesis reuses the fixture across examples
    src = write_synthetic(
        tmp_path / "src", CARTPOLE, n, 4, seed=seed, terminal_prob=term, vary_length=True
    )
    npz = export_d4rl(open_dataset(src), tmp_path / "x.npz")
    back = open_dataset(import_d4rl(npz, tmp_path / "back", CARTPOLE.task_id))
    a, b = TransitionView(open_dataset(src)).all(), TransitionView(back).all()
    for f in ("action", "reward", "discount"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    for k in a.observation:
        np.testing.assert_array_equal(a.observation[k], b.observation[k])
        np.testing.assert_array_equal(a.next_observation[k], b.next_observation[k])
    src_ds = open_dataset(src)
    whole = src_ds.length > 1  # a one-step episode holds no transition, so D4RL cannot carry it
    assert len(back) == int(whole.sum())
    np.testing.assert_array_equal(
        back.column("is_terminal")[back.start + back.length - 1],
        src_ds.column("is_terminal")[src_ds.start + src_ds.length - 1][whole],
    )


def test_import_cuts_where_next_observation_breaks(tmp_path):
    """Files in the wild miss timeouts; a break in observation continuity still cuts."""
    obs = np.arange(10, dtype=np.float32).reshape(5, 2)
    nxt = obs + 100  # never continues into the next row
    d = {
        "observations": obs,
        "next_observations": nxt,
        "actions": np.zeros((5, 1), np.float32),
        "rewards": np.ones(5, np.float32),
        "terminals": np.array([0, 0, 1, 0, 0], bool),
        "timeouts": np.zeros(5, bool),
    }
    segs = d4rl_segments(d)
    assert [len(s) for s in segs] == [2] * 5


def test_import_from_hdf5_in_d4rl_layout(tmp_path):
    h5py = pytest.importorskip("h5py")
    rng = np.random.default_rng(0)
    obs = rng.standard_normal((7, 3)).astype(np.float32)
    vel = rng.standard_normal((7, 2)).astype(np.float32)
    # two episodes: 3 steps ending in a timeout, then 3 steps ending terminal
    o_pos, o_vel = np.delete(obs, 3, 0), np.delete(vel, 3, 0)
    n_pos = np.concatenate([obs[1:4], obs[4:7]])
    n_vel = np.concatenate([vel[1:4], vel[4:7]])
    o_pos, o_vel = np.concatenate([obs[0:3], obs[3:6]]), np.concatenate([vel[0:3], vel[3:6]])
    with h5py.File(tmp_path / "d.hdf5", "w") as f:
        f["observations/position"], f["observations/velocity"] = o_pos, o_vel
        f["next_observations/position"], f["next_observations/velocity"] = n_pos, n_vel
        f["actions"] = rng.uniform(-1, 1, (6, 1)).astype(np.float32)
        f["rewards"] = np.arange(6, dtype=np.float32)
        f["terminals"] = np.array([0, 0, 0, 0, 0, 1], bool)
        f["timeouts"] = np.array([0, 0, 1, 0, 0, 0], bool)
    ds = open_dataset(import_d4rl(tmp_path / "d.hdf5", tmp_path / "ds", CARTPOLE.task_id))
    assert len(ds) == 2 and ds.length.tolist() == [4, 4]
    t = TransitionView(ds).all()
    assert t.reward.tolist() == [0, 1, 2, 3, 4, 5]
    assert t.discount.tolist() == [1, 1, 1, 1, 1, 0]
    np.testing.assert_array_equal(t.next_observation["position"], n_pos)


def test_cli_export_import(tmp_path, capsys):
    path = write_synthetic(tmp_path / "ds", CARTPOLE, 2, 3)
    assert main(["export", str(path), "--format", "d4rl", "-o", str(tmp_path / "o.npz")]) == 0
    assert (
        main(
            [
                "import",
                str(tmp_path / "o.npz"),
                "--format",
                "d4rl",
                "--task",
                CARTPOLE.task_id,
                "--out",
                str(tmp_path / "back"),
            ]
        )
        == 0
    )
    assert main(["validate", str(tmp_path / "back")]) == 0
