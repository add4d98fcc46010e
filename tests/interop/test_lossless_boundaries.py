"""Nothing lost at a format boundary (issue 32 item 6): the last reward of a truncated episode
survives every import (d3rlpy dumps; D4RL files without next_observations), ``rlu export
--format d3rlpy`` writes the file d3rlpy's own ``dump`` writes (checked key by key against
fixtures written by d3rlpy 2.8.1 itself, and read back as d3rlpy's ``load`` reads it), and a
Minari export comes back with its task."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

h5py = pytest.importorskip("h5py")

from rlu.cli import main  # noqa: E402
from rlu.data import DatasetWriter, Schema, open_dataset  # noqa: E402
from rlu.data.d3rlpy_io import export_d3rlpy, import_d3rlpy  # noqa: E402
from rlu.data.d4rl import import_d4rl  # noqa: E402
from rlu.data.synthetic import write_synthetic  # noqa: E402
from rlu.tasks import get_task  # noqa: E402

from .helpers import all_transitions, assert_same_segments  # noqa: E402

FIXTURES = Path(__file__).parent / "fixtures"
WALKER = get_task("control_suite/walker_walk")
PONG = get_task("atari/Pong")
CARTPOLE = get_task("control_suite/cartpole_swingup")


def contents(path: Path) -> dict:
    """Every dataset of an HDF5 file: (dtype, shape, values)."""
    out = {}
    with h5py.File(path, "r") as h5:
        h5.visititems(
            lambda n, o: out.__setitem__(n, (o.dtype.str, o.shape, np.asarray(o[()]).tolist()))
        )
    return out


def d3rlpy_load(path: Path) -> list[tuple]:
    """What ``d3rlpy.dataset.io.load`` (2.8.1) reads from a dump: ``version``, ``columns``
    decoded as UTF-8, ``num_episodes``, then per episode ``<key>_<i>`` (or the tuple
    ``<key>_<i>_<j>``), as (observations, actions, rewards, terminated)."""
    episodes = []
    with h5py.File(path, "r") as h5:
        assert h5["version"][()] != "2.0"
        keys = [s.decode("utf-8") for s in h5["columns"][()]]
        assert keys == ["observations", "actions", "rewards", "terminated"]
        for i in range(int(h5["num_episodes"][()])):
            data = {}
            for key in keys:
                if f"{key}_{i}" in h5:
                    data[key] = h5[f"{key}_{i}"][()]
                else:
                    parts, j = [], 0
                    while f"{key}_{i}_{j}" in h5:
                        parts.append(h5[f"{key}_{i}_{j}"][()])
                        j += 1
                    data[key] = parts
            episodes.append(tuple(data[k] for k in keys))
    return episodes


def d3rlpy_transitions(episodes) -> dict[str, list]:
    """d3rlpy 2.8.1's ``BasicTransitionPicker`` over every transition (``transition_count`` is
    the size if terminated, else the size - 1; after a terminal the next observation is zeros)."""
    out = {k: [] for k in ("observation", "action", "reward", "next_observation", "terminal")}
    for obs, act, rew, terminated in episodes:
        size = len(act)
        for i in range(size if terminated else size - 1):
            last = bool(terminated) and i == size - 1
            out["observation"].append(obs[i])
            out["action"].append(act[i])
            out["reward"].append(rew[i, 0])
            out["next_observation"].append(np.zeros_like(obs[i]) if last else obs[i + 1])
            out["terminal"].append(float(last))
    return out


# --- the last reward of a truncated episode ----------------------------------------------------
def test_d3rlpy_import_keeps_the_last_reward_and_d3rlpys_returns(tmp_path):
    """d3rlpy's ``Episode.compute_return`` sums every row's reward, the last row of a
    truncated episode too (and its returns-to-go start there); rlu keeps it in the final step."""
    ds = open_dataset(import_d3rlpy(FIXTURES / "d3rlpy_walker.h5", tmp_path / "ds", WALKER.id))
    with h5py.File(FIXTURES / "d3rlpy_walker.h5", "r") as h5:
        episodes = [(h5[f"rewards_{i}"][()], bool(h5[f"terminated_{i}"][()])) for i in range(6)]
    for i, (rewards, terminated) in enumerate(episodes):
        seg = ds.segment(i)
        np.testing.assert_array_equal(seg.reward[: len(rewards)], rewards[:, 0])
        assert len(seg) == len(rewards) + terminated  # a terminal gains the zero final step
        assert seg.metadata["episode_return"] == pytest.approx(float(rewards.sum()), rel=1e-6)
    np.testing.assert_allclose(ds.episode_returns(), [r.sum() for r, _ in episodes], rtol=1e-6)
    from rlu.data.validate import validate

    assert validate(tmp_path / "ds").ok


def test_d4rl_without_next_observations_keeps_the_last_reward(tmp_path):
    rng = np.random.default_rng(3)
    n = 12
    terminals = np.zeros(n, bool)
    timeouts = np.zeros(n, bool)
    terminals[3], timeouts[7] = True, True  # episodes: 0-3 terminal, 4-7 timeout, 8-11 trailing
    rows = {
        "observations": rng.standard_normal((n, 5)).astype(np.float32),
        "actions": rng.uniform(-1, 1, (n, 1)).astype(np.float32),
        "rewards": rng.random(n).astype(np.float32),
        "terminals": terminals,
        "timeouts": timeouts,
    }
    with h5py.File(tmp_path / "f.hdf5", "w") as f:
        for k, v in rows.items():
            f.create_dataset(k, data=v)
    ds = open_dataset(import_d4rl(tmp_path / "f.hdf5", tmp_path / "ds", CARTPOLE.id))
    assert ds.length.tolist() == [5, 4, 4]
    for i, (a, b) in enumerate([(0, 4), (4, 8), (8, 12)]):
        seg = ds.segment(i)
        assert seg.metadata["episode_return"] == pytest.approx(float(rows["rewards"][a:b].sum()))
        if i:  # truncated: the last row's observation is the final one, its action and reward kept
            assert seg.reward[-1] == rows["rewards"][b - 1]
            np.testing.assert_array_equal(seg.action[-1], rows["actions"][b - 1])
    np.testing.assert_allclose(
        ds.episode_returns(), [rows["rewards"][a:b].sum() for a, b in [(0, 4), (4, 8), (8, 12)]]
    )


# --- export --format d3rlpy ---------------------------------------------------------------------
@pytest.mark.parametrize(("name", "task"), [("d3rlpy_walker", WALKER), ("d3rlpy_pong", PONG)])
def test_export_d3rlpy_of_an_imported_dump_is_the_dump(name, task, tmp_path):
    """The fixtures were written by d3rlpy 2.8.1's own ``MDPDataset.dump``: import, export, and
    every dataset of the file is the same, key by key (dtype, shape, values)."""
    ds = open_dataset(import_d3rlpy(FIXTURES / f"{name}.h5", tmp_path / "ds", task.id))
    out = export_d3rlpy(ds, tmp_path / "out.h5")
    mine, theirs = contents(out), contents(FIXTURES / f"{name}.h5")
    assert sorted(mine) == sorted(theirs)
    for key in theirs:
        assert mine[key] == theirs[key], key


def test_export_d3rlpy_reads_back_as_d3rlpy_and_rlu_read_it(tmp_path):
    """Synthetic episodes ending in terminals and timeouts: the transitions d3rlpy's loader and
    picker read from the export are rlu's (the next observation after a terminal is zeros in
    d3rlpy), and rlu's import gives the same segments back."""
    schema = Schema.for_task(WALKER)
    src = open_dataset(
        write_synthetic(tmp_path / "src", schema, 6, 7, seed=5, terminal_prob=0.5, vary_length=True)
    )
    out = export_d3rlpy(src, tmp_path / "walker.h5")
    got = d3rlpy_transitions(d3rlpy_load(out))
    b = all_transitions(src)
    keys = list(WALKER.observation_spec)
    flat = np.concatenate([b.observation[k].reshape(len(b.reward), -1) for k in keys], axis=1)
    nxt = np.concatenate([b.next_observation[k].reshape(len(b.reward), -1) for k in keys], axis=1)
    live = b.discount == 1
    np.testing.assert_array_equal(np.asarray(got["observation"]), flat)
    np.testing.assert_array_equal(np.asarray(got["next_observation"])[live], nxt[live])
    assert not np.asarray(got["next_observation"])[~live].any()
    np.testing.assert_array_equal(np.asarray(got["action"]), b.action)
    np.testing.assert_array_equal(np.asarray(got["reward"]), b.reward)
    np.testing.assert_array_equal(np.asarray(got["terminal"]), 1.0 - b.discount)
    back = open_dataset(import_d3rlpy(out, tmp_path / "back", WALKER.id))
    terminal = [bool(src.segment(i).is_terminal[-1]) for i in range(len(src))]
    assert [bool(back.segment(i).is_terminal[-1]) for i in range(len(back))] == terminal
    live_segments = [i for i, t in enumerate(terminal) if not t]
    assert live_segments  # the seed gives both kinds
    for i in range(len(src)):
        s, t = src.segment(i), back.segment(i)
        np.testing.assert_array_equal(s.reward, t.reward)
        np.testing.assert_array_equal(s.action, t.action)
        np.testing.assert_array_equal(s.discount, t.discount)
        for k in keys:  # the final observation after a terminal is zeros in d3rlpy
            end = len(s) - 1 if terminal[i] else len(s)
            np.testing.assert_array_equal(s.observation[k][:end], t.observation[k][:end])


def test_export_d3rlpy_of_a_camera_task_writes_tuple_observations(tmp_path):
    """A camera beside features (locomotion): d3rlpy's tuple observations, one array per key in
    the task's order; import reads them back."""
    task = get_task("locomotion/rodent_two_touch")
    schema = Schema.for_task(task)
    src = write_synthetic(tmp_path / "src", schema, 2, 4, seed=1, terminal_prob=0.0)
    src = open_dataset(src)  # truncated episodes: d3rlpy keeps their final observations
    out = export_d3rlpy(src, tmp_path / "rodent.h5")
    episodes = d3rlpy_load(out)
    assert len(episodes[0][0]) == len(task.observation_spec)
    assert episodes[0][0][-1].dtype == np.uint8 and episodes[0][0][-1].shape[1:] == (64, 64, 3)
    back = open_dataset(import_d3rlpy(out, tmp_path / "back", task.id))
    assert_same_segments(src, back)


def test_export_d3rlpy_keeps_single_steps_in_the_sidecar(tmp_path):
    """A one-step episode holds no transition: d3rlpy's buffers keep none, so the dump leaves it
    out (d3rlpy reads 2 episodes), and the sidecar brings it back to rlu's import (3)."""
    src = open_dataset(write_synthetic(tmp_path / "src", Schema.for_task(CARTPOLE), 2, 4, seed=1))
    one = src.segment(1)
    with DatasetWriter(tmp_path / "mixed", src.schema) as w:
        w.append(src.segment(0))
        import dataclasses

        w.append(
            dataclasses.replace(
                one,
                observation={k: v[-1:] for k, v in one.observation.items()},
                is_first=np.ones(1, bool),
                **{
                    f: getattr(one, f)[-1:]
                    for f in ("action", "reward", "discount", "is_last", "is_terminal")
                },
            )  # fmt: skip
        )
        w.append(src.segment(1))
    mixed = open_dataset(tmp_path / "mixed")
    out = export_d3rlpy(mixed, tmp_path / "m.h5")
    assert len(d3rlpy_load(out)) == 2
    back = open_dataset(import_d3rlpy(out, tmp_path / "back"))
    assert back.length.tolist() == [len(one), 1, len(one)]
    assert_same_segments(mixed, back)


def test_cli_export_d3rlpy(tmp_path, capsys):
    src = write_synthetic(tmp_path / "src", Schema.for_task(CARTPOLE), 2, 4, seed=1)
    assert main(["export", str(src), "--format", "d3rlpy", "-o", str(tmp_path / "c.h5")]) == 0
    assert "wrote" in capsys.readouterr().out and len(d3rlpy_load(tmp_path / "c.h5")) == 2
    assert main(["export", str(src), "--format", "d3rlpy"]) == 2
    assert "needs -o/--out: X.h5" in capsys.readouterr().err
    assert main(["export", str(src), "--format", "d3rlpy", "-o", str(tmp_path / "c.npz")]) == 2
    assert "X.h5" in capsys.readouterr().err
    assert not list(tmp_path.glob(".*partial*"))


# --- Minari: the task and the final step come back ------------------------------------------------
def test_minari_import_keeps_the_task_rlu_exported(tmp_path):
    pytest.importorskip("minari")
    from rlu.data.minari import export_minari, import_minari

    for task in (CARTPOLE, PONG):
        name = task.id.split("/")[1].replace("_", "-")
        src = open_dataset(write_synthetic(tmp_path / name, Schema.for_task(task), 2, 4, seed=1))
        path = export_minari(src, f"rlu/{name}-v0", root=tmp_path / "m")
        back = open_dataset(import_minari(path, tmp_path / f"{name}_back"))
        assert back.schema.task_id == task.id
        assert back.schema == src.schema
        assert_same_segments(src, back)


def test_the_last_reward_survives_d3rlpy_to_minari_and_back(tmp_path):
    pytest.importorskip("minari")
    from rlu.data.minari import export_minari, import_minari

    ds = open_dataset(import_d3rlpy(FIXTURES / "d3rlpy_walker.h5", tmp_path / "ds", WALKER.id))
    path = export_minari(ds, "rlu/walker-v0", root=tmp_path / "m")
    back = open_dataset(import_minari(path, tmp_path / "back"))
    assert back.schema.task_id == WALKER.id
    assert_same_segments(ds, back)
    np.testing.assert_array_equal(back.metadata("episode_return"), ds.metadata("episode_return"))
