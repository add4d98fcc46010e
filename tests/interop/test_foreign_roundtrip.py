"""Lossless round trips of files the libraries wrote (issue 37 item 3): import then export gives
back every array of the original (dtype, shape, every row), its other arrays (D4RL's ``infos/*``
and ``metadata/*``), attributes, Minari's metadata (``env_spec`` with its time limit, wrappers
and kwargs, ``eval_env_spec``, authors, permalink, description, reference scores, requirements,
the dataset id) and episode attributes (uint64 seeds), float64 rewards. The originals are
written by the libraries' own writers: h5py / numpy in D4RL's layout, Minari's
``DataCollector`` recording a Gymnasium env the documented way (``reset(seed=0)`` once, then
``reset()``), d3rlpy's ``ReplayBuffer.dump`` (fixtures/make_d3rlpy_dump.py). rlu's own entries
(``metadata/rlu/*``, ``rlu_*`` attributes and metadata) are the only additions."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

h5py = pytest.importorskip("h5py")

from rlu.data import open_dataset  # noqa: E402
from rlu.data.d3rlpy_io import export_d3rlpy, import_d3rlpy  # noqa: E402
from rlu.data.d4rl import export_d4rl, import_d4rl  # noqa: E402
from rlu.data.validate import validate  # noqa: E402

FIXTURES = Path(__file__).parent / "fixtures"
CARTPOLE = "control_suite/cartpole_swingup"


def hdf5_contents(path: Path) -> dict:
    """Every group and dataset of an HDF5 file with its attributes; datasets as (dtype, shape,
    values, compression). rlu's own entries are left out."""

    def attrs(o):
        return {
            k: (np.asarray(v).dtype.str, np.asarray(v).tolist()) if not isinstance(v, str) else v
            for k, v in o.attrs.items()
            if not k.startswith("rlu_")
        }

    out = {"/": attrs_of_root(path, attrs)}
    with h5py.File(path, "r") as f:

        def visit(name, o):
            if name.startswith("metadata/rlu"):
                return
            if isinstance(o, h5py.Dataset):
                if h5py.check_string_dtype(o.dtype) is not None:
                    value = np.asarray(o.asstr()[()]).tolist()
                else:
                    value = np.asarray(o[()]).tolist()
                dtype = o.dtype.str if o.dtype.kind != "O" else "str"
                out[name] = (dtype, o.shape, value, o.compression, attrs(o))
            elif name != "metadata/rlu":
                out[name] = ("group", attrs(o))

        f.visititems(visit)
    return out


def attrs_of_root(path, attrs):
    with h5py.File(path, "r") as f:
        return attrs(f)


def same(a: dict, b: dict) -> int:
    assert sorted(a) == sorted(b)
    for k in a:
        assert a[k] == b[k], k
    return len(a)


# --- D4RL, written with h5py and numpy in D4RL's layout -------------------------------------------
def d4rl_file(path: Path, next_observations: bool, seed: int = 0) -> int:
    """A D4RL-layout file for cartpole_swingup (5 flat observation features): float64 rewards,
    gzip observations, infos/*, metadata/* (strings, a policy's weights), attributes; episodes
    ending terminal, timed out, in both at once, with a missing timeout (a break in the next
    observations) and a trailing run with neither. Returns its rows."""
    rng = np.random.default_rng(seed)
    lengths = [7, 1, 12, 9, 11, 5]
    n = sum(lengths)
    obs = rng.standard_normal((n, 5)).astype(np.float32)
    nxt = np.concatenate([obs[1:], rng.standard_normal((1, 5)).astype(np.float32)])
    terminals, timeouts = np.zeros(n, bool), np.zeros(n, bool)
    ends = np.cumsum(lengths) - 1
    terminals[ends[0]] = True
    timeouts[ends[1]] = timeouts[ends[2]] = True
    terminals[ends[3]] = timeouts[ends[3]] = True  # gymnasium: terminated and truncated at once
    for e in ends[:-1]:
        nxt[e] = rng.standard_normal(5)  # the final observation; the next row starts anew
    rows = {
        "observations": obs,
        **({"next_observations": nxt} if next_observations else {}),
        "actions": rng.uniform(-1, 1, (n, 1)).astype(np.float32),
        "rewards": rng.standard_normal(n),  # float64, as some D4RL files hold them
        "terminals": terminals,
        "timeouts": timeouts,  # ends[4] has none: continuity says the episode ends there
    }
    extra = {
        "infos/qpos": rng.standard_normal((n, 4)),
        "infos/action_log_probs": rng.standard_normal(n).astype(np.float32),
        "metadata/iteration": np.int64(1_000_000),
        "metadata/policy/fc0/weight": rng.standard_normal((8, 5)),
        "metadata/policy/fc0/bias": rng.standard_normal(8).astype(np.float32),
    }
    if path.suffix == ".npz":
        texts = {"metadata/algorithm": np.asarray("SAC")}
        (np.savez_compressed if seed % 2 else np.savez)(path, **rows, **extra, **texts)
        return n
    with h5py.File(path, "w") as f:
        f.attrs["creator"] = "d4rl-like"
        f.attrs["seed"] = np.int64(seed)
        for k, v in rows.items():
            f.create_dataset(k, data=v, compression="gzip" if k == "observations" else None)
        for k, v in extra.items():
            f.create_dataset(k, data=v)
        f.create_dataset("metadata/algorithm", data="SAC")
        f.create_dataset("metadata/policy/nonlinearity", data="relu")
        f["timeouts"].attrs["note"] = "time limit of 1000 steps"
        f["metadata/policy"].attrs["layers"] = np.array([8, 8], np.int32)
    return n


@pytest.mark.parametrize("next_observations", [True, False])
@pytest.mark.parametrize("suffix", [".hdf5", ".npz"])
def test_d4rl_file_comes_back_whole(tmp_path, suffix, next_observations):
    orig = tmp_path / f"orig{suffix}"
    n = d4rl_file(orig, next_observations, seed=0 if suffix == ".hdf5" else 1)
    ds = open_dataset(import_d4rl(orig, tmp_path / "ds", CARTPOLE))
    assert validate(tmp_path / "ds").ok
    out = export_d4rl(ds, tmp_path / f"back{suffix}")
    if suffix == ".hdf5":
        assert same(hdf5_contents(orig), hdf5_contents(out)) >= 14
    else:
        a, b = np.load(orig), np.load(out)
        keys = [k for k in b.files if not k.startswith("metadata/rlu/")]
        assert keys == a.files  # the same arrays in the same order
        for k in a.files:
            assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape, k
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    with h5py.File(out, "r") if suffix == ".hdf5" else np.load(out) as got:
        assert len(got["rewards"]) == n and got["rewards"].dtype == np.float64
    # the store holds what is known: every row, the truncated episodes' last rows included
    steps = n + len(ds) if next_observations else n + int(ds.column("is_terminal").sum())
    assert ds.num_steps == steps


def test_d4rl_truncated_last_rows_without_next_observations_are_kept(tmp_path):
    """2,777 rows in, 2,777 out: the last row of each truncated episode is its final step (its
    observation, action and reward; what follows it is unknown: no transition uses it)."""
    rng = np.random.default_rng(4)
    n = 2777
    timeouts = np.zeros(n, bool)
    timeouts[[999, 1999, n - 1]] = True
    with h5py.File(tmp_path / "f.hdf5", "w") as f:
        f["observations"] = rng.standard_normal((n, 5)).astype(np.float32)
        f["actions"] = rng.uniform(-1, 1, (n, 1)).astype(np.float32)
        f["rewards"] = rng.random(n).astype(np.float32)
        f["terminals"] = np.zeros(n, bool)
        f["timeouts"] = timeouts
    ds = open_dataset(import_d4rl(tmp_path / "f.hdf5", tmp_path / "ds", CARTPOLE))
    assert ds.length.tolist() == [1000, 1000, 777] and ds.num_steps == n
    seg = ds.segment(2)
    assert seg.is_last[-1] and not seg.is_terminal[-1]  # the final step: no transition
    with h5py.File(export_d4rl(ds, tmp_path / "back.hdf5"), "r") as back:
        assert back["rewards"].shape == (n,) and "next_observations" not in back
        with h5py.File(tmp_path / "f.hdf5", "r") as f:
            for k in f:
                np.testing.assert_array_equal(back[k][()], f[k][()], err_msg=k)


# --- d3rlpy, written by d3rlpy 2.8.1's own dump ---------------------------------------------------
@pytest.mark.parametrize(
    ("name", "task"),
    [("d3rlpy_walker", "control_suite/walker_walk"), ("d3rlpy_pong", "atari/Pong")],
)
def test_d3rlpy_dump_comes_back_whole(tmp_path, name, task):
    orig = FIXTURES / f"{name}.h5"
    ds = open_dataset(import_d3rlpy(orig, tmp_path / "ds", task))
    out = export_d3rlpy(ds, tmp_path / "back.h5")
    assert same(hdf5_contents(orig), hdf5_contents(out)) > 10


# --- Minari, recorded by its DataCollector --------------------------------------------------------
def record(minari_root: Path, episodes: int):
    pytest.importorskip("jax")  # Minari's EpisodeBuffer uses jax.tree_util
    gym = pytest.importorskip("gymnasium")
    from minari import DataCollector

    env = DataCollector(gym.make("CartPole-v1", max_episode_steps=80), record_infos=True)
    env.action_space.seed(0)
    env.reset(seed=0)  # Minari's docs: seed once, later resets draw 64-bit seeds
    for _ in range(episodes):
        while True:
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            if terminated or truncated:
                break
        env.reset()
    mds = env.create_dataset(
        "cartpole/random-v0",
        eval_env=gym.make("CartPole-v1", max_episode_steps=200).spec,
        algorithm_name="random",
        author="A. Researcher",
        author_email="a.researcher@example.org",
        code_permalink="https://example.org/code/commit/abc",
        ref_min_score=9.0,
        ref_max_score=500.0,
        description="24 episodes of a random CartPole policy",
        requirements=["gymnasium>=1.0"],
    )
    env.close()
    return mds


def minari_contents(path: Path) -> tuple[dict, dict]:
    meta = json.loads((path / "data" / "metadata.json").read_text())
    meta = {k: v for k, v in meta.items() if not k.startswith("rlu_")}
    return meta, hdf5_contents(path / "data" / "main_data.hdf5")


def test_minari_datacollector_dataset_comes_back_whole(tmp_path, monkeypatch):
    minari = pytest.importorskip("minari")
    from rlu.data.minari import export_minari, import_minari

    root = tmp_path / "minari"
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    mds = record(root, 24)
    seeds = [m["seed"] for m in mds.storage.get_episode_metadata(range(24))]
    assert seeds[0] == 0 and max(seeds) >= 1 << 63  # uint64 seeds, which int64 cannot hold
    ds = open_dataset(import_minari("cartpole/random-v0", tmp_path / "ds"))
    assert validate(tmp_path / "ds").ok
    assert ds.recover_environment().spec.max_episode_steps == 80  # the recorded time limit
    assert ds.recover_environment(eval_env=True).spec.max_episode_steps == 200
    assert ds.metadata("seed")[0] == 0  # the seeds that fit int64 are rlu's seed metadata
    orig = tmp_path / "orig"
    shutil.move(root / "cartpole" / "random-v0", orig)
    path = export_minari(ds)  # under the dataset's own id
    assert path == root / "cartpole" / "random-v0"
    (meta_a, h5_a), (meta_b, h5_b) = minari_contents(orig), minari_contents(path)
    assert meta_a == meta_b and len(meta_a) >= 18
    assert same(h5_a, h5_b) >= 24 * 7
    back = minari.load_dataset("cartpole/random-v0")
    assert back.env_spec.max_episode_steps == 80 and back.env_spec == mds.env_spec
    assert back.recover_environment(eval_env=True).spec.max_episode_steps == 200
    ep = next(back.iterate_episodes([3]))
    assert ep.rewards.dtype == np.float64


def test_recover_environment_makes_no_unregistered_entry_point(tmp_path, monkeypatch):
    """Files are data, never code: a recorded spec whose entry point Gymnasium has not
    registered for its id is refused, not imported."""
    minari = pytest.importorskip("minari")
    gym = pytest.importorskip("gymnasium")
    from gymnasium.envs.registration import EnvSpec
    from minari.data_collector import EpisodeBuffer

    from rlu.data.minari import import_minari
    from rlu.types import RluError

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "m"))
    box = gym.spaces.Box(-1, 1, (2,), np.float32)
    buf = EpisodeBuffer(
        observations=np.zeros((3, 2), np.float32),
        actions=np.zeros((2, 2), np.float32),
        rewards=np.zeros(2),
        terminations=np.array([False, True]),
        truncations=np.zeros(2, bool),
    )
    mds = minari.create_dataset_from_buffers(
        "evil/spec-v0", [buf], observation_space=box, action_space=box
    )
    spec = EnvSpec("CartPole-v1", entry_point="os:system", kwargs={"command": "touch x"})
    mds.storage.update_metadata({"env_spec": spec.to_json()})
    ds = open_dataset(import_minari("evil/spec-v0", tmp_path / "ds"))
    with pytest.raises(RluError, match="not registered in Gymnasium with that entry point"):
        ds.recover_environment()
    assert not (tmp_path / "x").exists()
