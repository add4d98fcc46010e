"""D4RL's HDF5 layout and d3rlpy's dump import with the transitions those libraries read."""

from __future__ import annotations

import uuid
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

h5py = pytest.importorskip("h5py")

from rlu.cli import main  # noqa: E402
from rlu.data import Schema, open_dataset  # noqa: E402
from rlu.data.d3rlpy_io import import_d3rlpy  # noqa: E402
from rlu.data.d4rl import import_d4rl, to_d4rl  # noqa: E402
from rlu.data.synthetic import write_synthetic  # noqa: E402
from rlu.tasks import get_task  # noqa: E402

from .helpers import all_transitions, assert_same_segments, assert_same_transitions  # noqa: E402

FIXTURES = Path(__file__).parent / "fixtures"
WALKER = get_task("control_suite/walker_walk")  # orientations 14, velocity 9, height 1 -> 24
KEYS = list(WALKER.observation_spec)


def flat(obs: dict) -> np.ndarray:
    """A dict observation flattened in the task's key order (how D4RL / d3rlpy files hold it)."""
    return np.concatenate(
        [obs[k].reshape(len(obs[k]), WALKER.observation_spec[k].size) for k in KEYS], axis=1
    )


def check_transitions(ds, expected: dict):
    b = all_transitions(ds)
    assert len(b.reward) == len(expected["reward"])
    if len(b.reward) == 0:
        return
    np.testing.assert_array_equal(flat(b.observation), expected["observation"])
    np.testing.assert_array_equal(flat(b.next_observation), expected["next_observation"])
    np.testing.assert_array_equal(b.action, expected["action"])
    np.testing.assert_array_equal(b.reward, np.asarray(expected["reward"], np.float32).reshape(-1))
    np.testing.assert_array_equal(b.discount, 1 - np.asarray(expected["terminal"], np.float32))
    if "next_action" in expected:
        np.testing.assert_array_equal(b.next_action, expected["next_action"])


# --- d3rlpy ------------------------------------------------------------------------------------
def write_d3rlpy_dump(path, episodes):
    """The file ``d3rlpy.dataset.io.dump`` writes (format 2.1), written with h5py the same way."""
    with h5py.File(path, "w") as h5:
        keys = ["observations", "actions", "rewards", "terminated"]
        h5.create_dataset("columns", data=keys)
        h5.create_dataset("num_episodes", data=len(episodes))
        for i, ep in enumerate(episodes):
            for key, value in zip(keys, ep, strict=True):
                h5.create_dataset(f"{key}_{i}", data=value)
        h5.create_dataset("version", data="2.1")


def d3rlpy_transitions(episodes):
    """d3rlpy's BasicTransitionPicker over every transition (a slow reference, loop by loop)."""
    out = {
        k: []
        for k in ("observation", "action", "reward", "next_observation", "next_action", "terminal")
    }
    for obs, act, rew, terminated in episodes:
        count = len(rew) if terminated else len(rew) - 1
        for i in range(count):
            last = terminated and i == len(rew) - 1
            out["observation"].append(obs[i])
            out["action"].append(act[i])
            out["reward"].append(rew[i, 0])
            out["next_observation"].append(np.zeros_like(obs[i]) if last else obs[i + 1])
            out["next_action"].append(np.zeros_like(act[i]) if last else act[i + 1])
            out["terminal"].append(float(last))
    return {k: np.asarray(v) for k, v in out.items()}


def read_d3rlpy_fixture():
    with h5py.File(FIXTURES / "d3rlpy_walker.h5", "r") as h5:
        n = int(h5["num_episodes"][()])
        return [
            tuple(h5[f"{k}_{i}"][()] for k in ("observations", "actions", "rewards", "terminated"))
            for i in range(n)
        ]


def test_d3rlpy_dump_imports_with_the_transitions_d3rlpy_reads(tmp_path):
    """The fixture was written by d3rlpy 2.8.1's MDPDataset.dump; the expected transitions are
    d3rlpy's own BasicTransitionPicker over the dataset d3rlpy loads back from it."""
    ds = open_dataset(import_d3rlpy(FIXTURES / "d3rlpy_walker.h5", tmp_path / "ds", WALKER.id))
    with np.load(FIXTURES / "d3rlpy_walker_transitions.npz", allow_pickle=False) as z:
        expected = {k: z[k] for k in z.files}
    assert str(expected["d3rlpy_version"]) == "2.8.1"
    assert len(ds) == 6 and len(expected["reward"]) == 25
    check_transitions(ds, expected)
    ends = [bool(ds.segment(i).is_terminal[-1]) for i in range(len(ds))]
    assert ends == [e[3] for e in read_d3rlpy_fixture()]
    # and the slow reference agrees with d3rlpy on d3rlpy's own file
    ref = d3rlpy_transitions(read_d3rlpy_fixture())
    for k in ref:
        np.testing.assert_array_equal(ref[k], expected[k].reshape(ref[k].shape), err_msg=k)


def test_d3rlpy_single_frame_atari_dump_imports_with_the_stacks_d3rlpy_samples(tmp_path):
    """d3rlpy's default Atari layout, (N, 1, 84, 84) frames stacked at sampling time: the fixture
    was written by d3rlpy 2.8.1's MDPDataset.dump, the expected transitions are its own
    FrameStackTransitionPicker(n_frames=4) over what it loads back (channel first, oldest first;
    rlu's stacks are channel last, newest last)."""
    pong = get_task("atari/Pong")
    ds = open_dataset(import_d3rlpy(FIXTURES / "d3rlpy_pong.h5", tmp_path / "ds", pong.id))
    with np.load(FIXTURES / "d3rlpy_pong_transitions.npz", allow_pickle=False) as z:
        exp = {k: z[k] for k in z.files}
    assert str(exp["d3rlpy_version"]) == "2.8.1" and exp["observation"].shape == (14, 4, 84, 84)
    assert len(ds) == 3 and ds.num_steps == 4 + 1 + 6 + 5 + 1  # terminal episodes gain a step
    b = all_transitions(ds)
    np.testing.assert_array_equal(b.observation, np.moveaxis(exp["observation"], 1, -1))
    np.testing.assert_array_equal(b.action, exp["action"].reshape(-1))
    np.testing.assert_array_equal(b.reward, exp["reward"].reshape(-1))
    np.testing.assert_array_equal(b.discount, 1.0 - exp["terminal"].reshape(-1))
    nxt = np.moveaxis(exp["next_observation"], 1, -1)
    live = exp["terminal"].reshape(-1) == 0
    np.testing.assert_array_equal(b.next_observation[live], nxt[live])
    # after a terminal: d3rlpy's next observation is all zeros, rlu's newest frame is zero
    assert not nxt[~live].any() and not b.next_observation[~live][..., -1].any()


def test_h5py_writer_matches_d3rlpys_file(tmp_path):
    write_d3rlpy_dump(tmp_path / "mine.h5", read_d3rlpy_fixture())

    def contents(path):
        out = {}
        with h5py.File(path, "r") as h5:
            h5.visititems(
                lambda n, o: out.__setitem__(n, (o.dtype.str, o.shape, np.asarray(o[()]).tolist()))
            )
        return out

    assert contents(tmp_path / "mine.h5") == contents(FIXTURES / "d3rlpy_walker.h5")


def random_d3rlpy_episodes(rng, lengths, terminated):
    return [
        (
            rng.standard_normal((n, 24)).astype(np.float32),
            rng.uniform(-1, 1, (n, 6)).astype(np.float32),
            rng.random((n, 1), dtype=np.float32),
            bool(t),
        )
        for n, t in zip(lengths, terminated, strict=True)
    ]


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    seed=st.integers(0, 10_000),
    eps=st.lists(st.tuples(st.integers(1, 7), st.booleans()), min_size=1, max_size=6),
)
def test_d3rlpy_round_trip_property(tmp_path, seed, eps):
    tmp = tmp_path / uuid.uuid4().hex
    tmp.mkdir()
    episodes = random_d3rlpy_episodes(np.random.default_rng(seed), *zip(*eps, strict=True))
    write_d3rlpy_dump(tmp / "d.h5", episodes)
    ds = open_dataset(import_d3rlpy(tmp / "d.h5", tmp / "ds", WALKER.id))
    assert len(ds) == len(episodes)
    check_transitions(ds, d3rlpy_transitions(episodes))
    assert [bool(ds.segment(i).is_terminal[-1]) for i in range(len(ds))] == [e[3] for e in episodes]


def test_d3rlpy_live(tmp_path):
    """With d3rlpy installed (not in the dev extra: it pins gymnasium 1.0.0), its own dump."""
    d3rlpy = pytest.importorskip("d3rlpy")
    from d3rlpy.dataset import BasicTransitionPicker, InfiniteBuffer, ReplayBuffer

    rng = np.random.default_rng(1)
    n = 30
    term = np.zeros(n, np.float32)
    tout = np.zeros(n, np.float32)
    term[[6, 20]] = 1
    tout[[12, 29]] = 1
    md = d3rlpy.dataset.MDPDataset(
        rng.standard_normal((n, 24)).astype(np.float32),
        rng.uniform(-1, 1, (n, 6)).astype(np.float32),
        rng.random(n).astype(np.float32),
        term,
        tout,
    )
    with open(tmp_path / "d.h5", "w+b") as f:
        md.dump(f)
    with open(tmp_path / "d.h5", "rb") as f:
        back = ReplayBuffer.load(f, InfiniteBuffer())
    pick = BasicTransitionPicker()
    ts = [pick(ep, i) for ep in back.episodes for i in range(ep.transition_count)]
    expected = {
        k: np.stack([np.asarray(getattr(t, k)) for t in ts])
        for k in ("observation", "action", "reward", "next_observation", "next_action", "terminal")
    }
    check_transitions(
        open_dataset(import_d3rlpy(tmp_path / "d.h5", tmp_path / "ds", WALKER.id)), expected
    )


# --- D4RL's HDF5 files ---------------------------------------------------------------------------
def write_d4rl_hdf5(path, rows: dict, next_observations: bool = True):
    """A file with the key set of D4RL's own MuJoCo files (hopper-medium-v2 and kin):
    flat arrays at the root, ``infos/...`` and ``metadata/...`` groups (ignored by import)."""
    n = len(rows["rewards"])
    rng = np.random.default_rng(0)
    with h5py.File(path, "w") as f:
        f.create_dataset("observations", data=rows["observations"], compression="gzip")
        if next_observations:
            f.create_dataset("next_observations", data=rows["next_observations"])
        f.create_dataset("actions", data=rows["actions"])
        f.create_dataset("rewards", data=rows["rewards"])
        f.create_dataset("terminals", data=rows["terminals"].astype(bool))
        f.create_dataset("timeouts", data=rows["timeouts"].astype(bool))
        f.create_dataset("infos/action_log_probs", data=rng.standard_normal(n).astype(np.float32))
        f.create_dataset("infos/qpos", data=rng.standard_normal((n, 9)))
        f.create_dataset("infos/qvel", data=rng.standard_normal((n, 9)))
        f.create_dataset("metadata/algorithm", data="SAC")
        f.create_dataset("metadata/iteration", data=np.int64(1000000))
        f.create_dataset("metadata/policy/fc0/weight", data=rng.standard_normal((256, 24)))
        f.create_dataset("metadata/policy/fc0/bias", data=rng.standard_normal(256))
        f.create_dataset("metadata/policy/nonlinearity", data="relu")
        f.create_dataset("metadata/policy/output_distribution", data="tanh_gaussian")


def d4rl_rows(ds):
    d = to_d4rl(ds)
    return {
        "observations": flat({k: d[f"observations/{k}"] for k in KEYS}),
        "next_observations": flat({k: d[f"next_observations/{k}"] for k in KEYS}),
        **{k: d[k] for k in ("actions", "rewards", "terminals", "timeouts")},
    }


def test_d4rl_hdf5_with_the_real_key_set(tmp_path):
    src = open_dataset(
        write_synthetic(tmp_path / "src", Schema.for_task(WALKER), 5, 6, seed=4, vary_length=True)
    )
    rows = d4rl_rows(src)
    write_d4rl_hdf5(tmp_path / "walker-medium-v2.hdf5", rows)
    ds = open_dataset(import_d4rl(tmp_path / "walker-medium-v2.hdf5", tmp_path / "ds", WALKER.id))
    # every row is one transition, in order
    check_transitions(
        ds,
        {
            "observation": rows["observations"],
            "action": rows["actions"],
            "reward": rows["rewards"],
            "next_observation": rows["next_observations"],
            "terminal": rows["terminals"],
        },
    )
    assert_same_segments(src, ds)


def d4rl_reference(rows):
    """Transitions of a file without next_observations, read as d3rlpy reads D4RL (a loop)."""
    out = {k: [] for k in ("observation", "action", "reward", "next_observation", "terminal")}
    n = len(rows["rewards"])
    start = 0
    for i in range(n):
        end = rows["terminals"][i] or rows["timeouts"][i] or i == n - 1
        if not end:
            out["observation"].append(rows["observations"][i])
            out["next_observation"].append(rows["observations"][i + 1])
        elif rows["terminals"][i]:
            out["observation"].append(rows["observations"][i])
            out["next_observation"].append(np.zeros_like(rows["observations"][i]))
        else:  # a timeout row holds the final observation only
            start = i + 1
            continue
        out["action"].append(rows["actions"][i])
        out["reward"].append(rows["rewards"][i])
        out["terminal"].append(float(bool(rows["terminals"][i])))
        if end:
            start = i + 1
    del start
    return {k: np.asarray(v) for k, v in out.items()}


@settings(
    max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    seed=st.integers(0, 10_000),
    n=st.integers(1, 40),
    p_term=st.floats(0, 0.3),
    p_tout=st.floats(0, 0.3),
    with_next=st.booleans(),
)
def test_d4rl_hdf5_import_property(tmp_path, seed, n, p_term, p_tout, with_next):
    """Random D4RL rows (terminals and timeouts anywhere, a trailing run without either)."""
    tmp = tmp_path / uuid.uuid4().hex
    tmp.mkdir()
    rng = np.random.default_rng(seed)
    obs = rng.standard_normal((n + 1, 24)).astype(np.float32)
    terminals = rng.random(n) < p_term
    timeouts = (rng.random(n) < p_tout) & ~terminals
    rows = {
        "observations": obs[:-1],
        "next_observations": obs[1:],
        "actions": rng.uniform(-1, 1, (n, 6)).astype(np.float32),
        "rewards": rng.random(n).astype(np.float32),
        "terminals": terminals,
        "timeouts": timeouts,
    }
    if with_next:  # a new episode starts from a fresh observation after every end
        ends = np.flatnonzero(terminals | timeouts)
        ends = ends[ends < n - 1]
        rows["observations"][ends + 1] = rng.standard_normal((len(ends), 24))
    write_d4rl_hdf5(tmp / "f.hdf5", rows, next_observations=with_next)
    ds = open_dataset(import_d4rl(tmp / "f.hdf5", tmp / "ds", WALKER.id))
    if with_next:
        check_transitions(
            ds,
            {
                "observation": rows["observations"],
                "action": rows["actions"],
                "reward": rows["rewards"],
                "next_observation": rows["next_observations"],
                "terminal": rows["terminals"],
            },
        )
    else:
        check_transitions(ds, d4rl_reference(rows))


def test_d4rl_round_trip_via_hdf5_property_of_store(tmp_path):
    """rlu -> D4RL rows in an .hdf5 -> rlu keeps every segment (episodes of any ending)."""
    for seed in range(3):
        src = open_dataset(
            write_synthetic(
                tmp_path / f"s{seed}",
                Schema.for_task(WALKER),
                4,
                5,
                seed=seed,
                terminal_prob=0.5,
                vary_length=True,
            )
        )
        write_d4rl_hdf5(tmp_path / f"{seed}.hdf5", d4rl_rows(src))
        back = open_dataset(
            import_d4rl(tmp_path / f"{seed}.hdf5", tmp_path / f"b{seed}", WALKER.id)
        )
        assert_same_transitions(src, back)
        assert_same_segments(src, back)


def test_cli_imports_d3rlpy_and_d4rl_hdf5(tmp_path, capsys):
    assert (
        main(
            [
                "import",
                "--format",
                "d3rlpy",
                str(FIXTURES / "d3rlpy_walker.h5"),
                "--task",
                WALKER.id,
                "--out",
                str(tmp_path / "a"),
            ]
        )
        == 0
    )
    assert "6 episodes" in capsys.readouterr().out
    assert (
        main(
            [
                "import",
                "--format",
                "d3rlpy",
                str(FIXTURES / "d3rlpy_walker.h5"),
                "--out",
                str(tmp_path / "b"),
            ]
        )
        == 2
    )
    assert "--task" in capsys.readouterr().err
    src = open_dataset(write_synthetic(tmp_path / "src", Schema.for_task(WALKER), 2, 3))
    write_d4rl_hdf5(tmp_path / "x.hdf5", d4rl_rows(src))
    assert (
        main(
            [
                "import",
                "--format",
                "d4rl",
                str(tmp_path / "x.hdf5"),
                "--task",
                WALKER.id,
                "--out",
                str(tmp_path / "c"),
            ]
        )
        == 0
    )
    assert_same_transitions(src, open_dataset(tmp_path / "c"))


# --- rlu export --format d4rl: the file its name says ---------------------------------------------
def d4rl_get_dataset(path, observation_shape, action_shape):
    """D4RL's own reader (d4rl/offline_env.py ``OfflineEnv.get_dataset``, D4RL 1.1): every HDF5
    dataset by ``visititems`` read with ``[:]`` (``[()]`` for scalars), then its sanity checks."""
    data, keys = {}, []

    def visitor(name, item):
        if isinstance(item, h5py.Dataset):
            keys.append(name)

    with h5py.File(path, "r") as f:
        f.visititems(visitor)
        for k in keys:
            try:
                data[k] = f[k][:]
            except ValueError:
                data[k] = f[k][()]
    for key in ("observations", "actions", "rewards", "terminals"):
        assert key in data, f"Dataset is missing key {key}"
    n = data["observations"].shape[0]
    assert data["observations"].shape[1:] == observation_shape
    assert data["actions"].shape[1:] == action_shape
    assert data["rewards"].shape == (n,) and data["terminals"].shape == (n,)
    return data


@pytest.mark.parametrize("suffix", [".hdf5", ".npz"])
def test_export_d4rl_writes_the_format_its_name_says_and_round_trips(tmp_path, suffix, capsys):
    src = write_synthetic(
        tmp_path / "src", Schema.for_task(WALKER), 4, 6, seed=1, terminal_prob=0.5,
        vary_length=True,
    )  # fmt: skip
    out = tmp_path / f"walker{suffix}"
    assert main(["export", str(src), "--format", "d4rl", "-o", str(out)]) == 0
    magic = out.read_bytes()[:8]
    if suffix == ".npz":
        assert magic[:4] == b"PK\x03\x04"  # a zip archive, what numpy.savez writes
    else:
        assert magic == b"\x89HDF\r\n\x1a\n"  # the HDF5 signature
        d = d4rl_get_dataset(out, (24,), (6,))
        expected = all_transitions(open_dataset(src))
        np.testing.assert_array_equal(d["observations"], flat(expected.observation))
        np.testing.assert_array_equal(d["next_observations"], flat(expected.next_observation))
        np.testing.assert_array_equal(d["actions"], expected.action)
        np.testing.assert_array_equal(d["rewards"], expected.reward)
        assert d["terminals"].dtype == bool and d["timeouts"].dtype == bool
        assert d["metadata/rlu/task_id"] == WALKER.id.encode()
        assert [k.decode() for k in d["metadata/rlu/observation_keys"]] == KEYS
    assert not [p for p in tmp_path.iterdir() if "partial" in p.name]
    argv = ["import", str(out), "--format", "d4rl", "--task", WALKER.id, "--out"]
    assert main([*argv, str(tmp_path / "back")]) == 0
    back = open_dataset(tmp_path / "back")
    assert_same_transitions(open_dataset(src), back)
    assert_same_segments(open_dataset(src), back)


def test_export_d4rl_of_stacked_frames_and_of_a_camera_round_trips(tmp_path):
    """Atari: stacked (N, 84, 84, 4) uint8 rows; a camera beside features: one array per key."""
    from rlu.data.d4rl import export_d4rl

    for task_id in ("atari/Pong", "locomotion/rodent_two_touch"):
        schema = Schema.for_task(get_task(task_id))
        src = open_dataset(write_synthetic(tmp_path / task_id, schema, 2, 5, seed=2))
        name = task_id.replace("/", "_")
        out = export_d4rl(src, tmp_path / f"{name}.hdf5")
        with h5py.File(out, "r") as f:
            if task_id == "atari/Pong":
                assert f["observations"].shape == (len(all_transitions(src).reward), 84, 84, 4)
                assert f["observations"].compression == "gzip"
            else:
                assert isinstance(f["observations"], h5py.Group)
        back = open_dataset(import_d4rl(out, tmp_path / f"{name}_back", task_id))
        assert_same_segments(src, back)


def test_export_d4rl_refuses_an_unknown_extension(tmp_path, capsys):
    src = write_synthetic(tmp_path / "src", Schema.for_task(WALKER), 2, 3)
    for name in ("out.zip", "out", "out.hdf"):
        assert main(["export", str(src), "--format", "d4rl", "-o", str(tmp_path / name)]) == 2
        err = capsys.readouterr().err
        assert "unknown D4RL file type" in err and "X.hdf5" in err and "X.npz" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]  # nothing half-written
