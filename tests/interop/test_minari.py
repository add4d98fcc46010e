"""Minari in and out, judged by Minari's own code (load_dataset, iteration, DataCollector)."""

from __future__ import annotations

import json
import uuid

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

minari = pytest.importorskip("minari")
gym = pytest.importorskip("gymnasium")

from rlu.cli import main  # noqa: E402
from rlu.data import DatasetWriter, Schema, Segment, make_episode, open_dataset  # noqa: E402
from rlu.data.minari import _flatten, export_minari, import_minari, spaces_for  # noqa: E402
from rlu.data.synthetic import write_synthetic  # noqa: E402
from rlu.data.views import DatasetView  # noqa: E402
from rlu.tasks import get_task  # noqa: E402
from rlu.types import RluError  # noqa: E402

from .helpers import assert_same_segments, assert_same_transitions  # noqa: E402

CARTPOLE = Schema.for_task(get_task("control_suite/cartpole_swingup"))
RODENT = Schema.for_task(get_task("locomotion/rodent_two_touch"))  # nested keys, a 64x64x3 camera
PONG = Schema.for_task(get_task("atari/Pong"))


@pytest.fixture
def minari_root(tmp_path, monkeypatch):
    root = tmp_path / "minari"
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    return root


def check_minari_iteration(ds, mds):
    """Minari's own iteration returns the arrays of rlu's segments, in order."""
    assert mds.total_episodes == len(ds)
    assert mds.total_steps == ds.num_steps - len(ds)
    view = DatasetView(ds)
    for i, ep in enumerate(mds.iterate_episodes()):
        seg = ds.segment(i)
        n = len(seg) - 1
        if ds.schema.frame_stack > 1:
            steps = np.arange(ds.start[i], ds.start[i] + len(seg))
            np.testing.assert_array_equal(
                ep.observations, view.observation(np.full_like(steps, i), steps)
            )
        elif isinstance(seg.observation, dict):
            obs = _flatten(ep.observations)
            assert set(obs) == set(seg.observation)
            for k in obs:
                np.testing.assert_array_equal(obs[k], seg.observation[k], err_msg=k)
        else:
            np.testing.assert_array_equal(ep.observations, seg.observation)
        np.testing.assert_array_equal(ep.actions, seg.action[:n])
        np.testing.assert_array_equal(ep.rewards, seg.reward[:n])
        terminal = bool(seg.is_terminal[-1])
        assert list(ep.terminations) == [False] * (n - 1) + [terminal]
        assert list(ep.truncations) == [False] * (n - 1) + [not terminal]
        np.testing.assert_array_equal(1.0 - ep.terminations, seg.discount[:n])


@pytest.mark.parametrize(
    "schema,name", [(CARTPOLE, "cartpole"), (RODENT, "rodent"), (PONG, "pong")]
)
def test_export_loads_in_minari_and_imports_back(tmp_path, minari_root, schema, name):
    src = write_synthetic(tmp_path / "src", schema, 3, 6, seed=3, vary_length=True)
    ds = open_dataset(src)
    path = export_minari(ds, f"rlu/{name}-v0")
    assert path == minari_root / "rlu" / f"{name}-v0"
    mds = minari.load_dataset(f"rlu/{name}-v0")
    assert mds.observation_space == spaces_for(schema)[0]
    check_minari_iteration(ds, mds)
    meta = list(mds.storage.get_episode_metadata([1]))[0]
    assert meta["rlu_episode_id"] == 1 and meta["rlu_seed"] == 3
    back = open_dataset(import_minari(f"rlu/{name}-v0", tmp_path / "back", schema.task_id))
    assert_same_segments(ds, back)
    assert back.segment(2).metadata["episode_id"] == 2


def test_dict_spaces_are_nested_by_slash(minari_root):
    obs_space, act_space = spaces_for(RODENT)
    assert isinstance(obs_space["walker"], gym.spaces.Dict)
    assert obs_space["walker"]["egocentric_camera"] == gym.spaces.Box(0, 255, (64, 64, 3), np.uint8)
    assert act_space == gym.spaces.Box(-1.0, 1.0, (38,), np.float32)
    assert spaces_for(PONG)[1] == gym.spaces.Discrete(6)


def _window(schema, rng, n, first, last, terminal):
    """A release-style segment: possibly mid-episode (no is_first), possibly not ending it."""
    obs = (
        rng.integers(0, 256, (n, 84, 84), np.uint8)
        if schema.frame_stack > 1
        else {
            k: rng.standard_normal((n, *s.shape)).astype(s.dtype)
            for k, s in schema.observation.items()
        }
    )
    flags_first = np.zeros(n, bool)
    flags_first[0] = first
    flags_last = np.zeros(n, bool)
    flags_last[-1] = last
    term = np.zeros(n, bool)
    term[-1] = last and terminal
    discount = np.ones(n, np.float32)
    if last:
        discount[-1] = 0.0
        if terminal:
            discount[-2] = 0.0
    action = (
        rng.integers(0, 6, n)
        if schema.frame_stack > 1
        else rng.uniform(-1, 1, (n, *schema.action.shape)).astype(np.float32)
    )
    if last:
        action[-1] = 0
    reward = rng.random(n, dtype=np.float32)
    if last:
        reward[-1] = 0
    prefix = None
    if schema.frame_stack > 1:
        prefix = (
            np.zeros((3, 84, 84), np.uint8)
            if first
            else rng.integers(0, 256, (3, 84, 84), np.uint8)
        )
    return Segment(obs, action, reward, discount, flags_first, flags_last, term, {}, prefix)


@pytest.mark.parametrize("schema", [CARTPOLE, PONG], ids=["cartpole", "pong"])
def test_release_windows_round_trip(tmp_path, minari_root, schema):
    rng = np.random.default_rng(0)
    with DatasetWriter(tmp_path / "src", schema) as w:
        for first, last, terminal in [
            (True, False, False),
            (False, False, False),
            (False, True, True),
            (False, True, False),
        ]:
            w.append(_window(schema, rng, 5, first, last, terminal))
    ds = open_dataset(tmp_path / "src")
    export_minari(ds, "rlu/windows-v0")
    back = open_dataset(import_minari("rlu/windows-v0", tmp_path / "back", schema.task_id))
    assert_same_transitions(ds, back)
    assert_same_segments(ds, back)


@settings(
    max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 5), term=st.floats(0, 1))
def test_minari_round_trip_property(tmp_path, minari_root, seed, n, term):
    tmp = tmp_path / uuid.uuid4().hex
    src = write_synthetic(
        tmp / "src", CARTPOLE, n, 5, seed=seed, terminal_prob=term, vary_length=True
    )
    ds = open_dataset(src)
    path = export_minari(ds, f"rlu/prop{uuid.uuid4().hex[:8]}-v0", root=tmp / "m")
    check_minari_iteration(ds, minari.MinariDataset(path / "data"))
    back = open_dataset(import_minari(path, tmp / "back", CARTPOLE.task_id))
    assert_same_segments(ds, back)


def test_cli_export_and_import(tmp_path, capsys):
    src = write_synthetic(tmp_path / "src", CARTPOLE, 2, 4, seed=1)
    root = tmp_path / "m"
    assert (
        main(
            [
                "export",
                str(src),
                "--format",
                "minari",
                "--id",
                "rlu/cli-v1",
                "--minari-dir",
                str(root),
            ]
        )
        == 0
    )
    assert (root / "rlu" / "cli-v1" / "data" / "main_data.hdf5").exists()
    assert (
        main(
            [
                "import",
                "--format",
                "minari",
                "rlu/cli-v1",
                "--minari-dir",
                str(root),
                "--task",
                CARTPOLE.task_id,
                "--out",
                str(tmp_path / "back"),
            ]
        )
        == 0
    )
    assert "2 episodes" in capsys.readouterr().out
    assert_same_segments(open_dataset(src), open_dataset(tmp_path / "back"))
    # the same id again is refused, and the first export is left as it was
    assert (
        main(
            [
                "export",
                str(src),
                "--format",
                "minari",
                "--id",
                "rlu/cli-v1",
                "--minari-dir",
                str(root),
            ]
        )
        == 2
    )
    assert "already exists" in capsys.readouterr().err
    assert main(["export", str(src), "--format", "minari", "--minari-dir", str(root)]) == 2
    assert "--id" in capsys.readouterr().err


def test_bad_id_is_refused(tmp_path):
    ds = open_dataset(write_synthetic(tmp_path / "src", CARTPOLE, 1, 3))
    with pytest.raises(RluError, match="NAMESPACE/NAME-vN"):
        export_minari(ds, "rlu/noversion", root=tmp_path / "m")
    assert not (tmp_path / "m" / "rlu" / "noversion").exists()


# --- a dataset that Minari's own DataCollector recorded from a Gymnasium env -------------------
def _record(env, dataset_id, episodes, seed):
    pytest.importorskip("jax")  # Minari's EpisodeBuffer uses jax.tree_util
    from minari import DataCollector

    env = DataCollector(env)
    rng = np.random.default_rng(seed)
    env.action_space.seed(seed)  # the random policy is seeded too: the same episodes every run
    env.reset(seed=seed)
    for _ in range(episodes):
        while True:
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            if terminated or truncated:
                break
        env.reset(seed=int(rng.integers(1 << 30)))
    mds = env.create_dataset(dataset_id, algorithm_name="random", description="test")
    env.close()
    return mds


def check_against_minari(mds, ds):
    """rlu's transitions equal the ones read from Minari's own episodes, endings included."""
    view_rows = {"o": [], "a": [], "r": [], "o2": [], "d": []}
    ends = []
    for ep in mds.iterate_episodes():
        obs = _flatten(ep.observations) if isinstance(ep.observations, dict) else ep.observations
        n = len(ep.rewards)
        for t in range(n):
            pick = (
                (lambda x, i: {k: v[i] for k, v in x.items()})
                if isinstance(obs, dict)
                else (lambda x, i: x[i])
            )
            view_rows["o"].append(pick(obs, t))
            view_rows["o2"].append(pick(obs, t + 1))
            view_rows["a"].append(ep.actions[t])
            view_rows["r"].append(ep.rewards[t])
            view_rows["d"].append(0.0 if ep.terminations[t] else 1.0)
        ends.append((bool(ep.terminations[-1]), bool(ep.truncations[-1])))
    from .helpers import all_transitions

    b = all_transitions(ds)
    if isinstance(b.observation, dict):
        for k in b.observation:
            np.testing.assert_array_equal(
                b.observation[k], np.stack([o[k] for o in view_rows["o"]])
            )
            np.testing.assert_array_equal(
                b.next_observation[k], np.stack([o[k] for o in view_rows["o2"]])
            )
    else:
        np.testing.assert_array_equal(b.observation, np.stack(view_rows["o"]))
        np.testing.assert_array_equal(b.next_observation, np.stack(view_rows["o2"]))
    np.testing.assert_array_equal(b.action, np.asarray(view_rows["a"]).reshape(b.action.shape))
    np.testing.assert_array_equal(b.reward, np.asarray(view_rows["r"], np.float32))
    np.testing.assert_array_equal(b.discount, np.asarray(view_rows["d"], np.float32))
    terminal_ends = [ds.segment(i).is_terminal[-1] for i in range(len(ds))]
    assert terminal_ends == [t for t, _ in ends]
    return ends


def test_datacollector_cartpole_imports_with_identical_transitions(tmp_path, minari_root):
    env = gym.make("CartPole-v1", max_episode_steps=20)  # random play: falls, or runs out of time
    mds = _record(env, "gym/cartpole-random-v0", 12, seed=5)
    ds = open_dataset(import_minari("gym/cartpole-random-v0", tmp_path / "ds"))
    assert ds.schema.observation.shape == (4,) and ds.schema.action.num_values == 2
    ends = check_against_minari(mds, ds)
    # both endings were exercised: the pole fell (terminal), and the time ran out (truncated)
    assert any(t for t, _ in ends) and any(tr and not t for t, tr in ends)


class NestedDictEnv(gym.Env):
    """A small real Gymnasium env with cartpole_swingup's observation keys under a nested Dict,
    that terminates at random and is truncated by TimeLimit."""

    def __init__(self):
        box = gym.spaces.Box(-np.inf, np.inf, (3,), np.float32)
        self.observation_space = gym.spaces.Dict(
            {"position": box, "velocity": gym.spaces.Box(-np.inf, np.inf, (2,), np.float32)}
        )
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def _obs(self):
        return {
            "position": self.np_random.standard_normal(3).astype(np.float32),
            "velocity": self.np_random.standard_normal(2).astype(np.float32),
        }

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return self._obs(), {}

    def step(self, action):
        return self._obs(), float(action[0]), bool(self.np_random.random() < 0.15), False, {}


def test_datacollector_dict_env_imports_into_a_task(tmp_path, minari_root):
    env = gym.wrappers.TimeLimit(NestedDictEnv(), max_episode_steps=8)
    mds = _record(env, "gym/dict-random-v0", 10, seed=2)
    ds = open_dataset(import_minari("gym/dict-random-v0", tmp_path / "ds", CARTPOLE.task_id))
    assert ds.schema.task_id == CARTPOLE.task_id
    ends = check_against_minari(mds, ds)
    assert any(t for t, _ in ends) and any(tr and not t for t, tr in ends)


def test_export_in_chunks_keeps_order_and_metadata(tmp_path):
    src = open_dataset(write_synthetic(tmp_path / "src", CARTPOLE, 7, 4, seed=8, vary_length=True))
    path = export_minari(src, "rlu/chunks-v0", root=tmp_path / "m", chunk_steps=5)
    mds = minari.MinariDataset(path / "data")
    check_minari_iteration(src, mds)
    metas = list(mds.storage.get_episode_metadata(range(7)))
    assert [m["rlu_episode_id"] for m in metas] == list(range(7))
    back = open_dataset(import_minari(path, tmp_path / "back", CARTPOLE.task_id))
    assert_same_segments(src, back)


def test_single_step_segments_go_to_the_sidecar(tmp_path):
    """Minari cannot store an episode without a step: Minari reads the 2 longer ones, and the
    sidecar gives rlu's import all 4 back, in order."""

    def ep(n, seed):
        rng = np.random.default_rng(seed)
        obs = {
            k: rng.standard_normal((n + 1, *s.shape)).astype(np.float32)
            for k, s in CARTPOLE.observation.items()
        }
        return make_episode(
            obs,
            rng.uniform(-1, 1, (n, 1)).astype(np.float32),
            rng.random(n).astype(np.float32),
            terminal=bool(seed % 2),
        )

    with DatasetWriter(tmp_path / "src", CARTPOLE) as w:
        for n, seed in [(3, 0), (0, 1), (2, 2), (0, 3)]:
            w.append(ep(n, seed))
    src = open_dataset(tmp_path / "src")
    path = export_minari(src, "rlu/short-v0", root=tmp_path / "m")
    mds = minari.MinariDataset(path / "data")
    assert mds.total_episodes == 2
    assert (path / "rlu_sidecar.npz").is_file()
    back = open_dataset(import_minari(path, tmp_path / "back", CARTPOLE.task_id))
    assert back.length.tolist() == [4, 1, 3, 1]
    assert_same_segments(src, back)


@settings(
    max_examples=10, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    seed=st.integers(0, 10_000),
    eps=st.lists(
        st.tuples(st.integers(1, 6), st.sampled_from(["term", "trunc", "both", "neither"])),
        min_size=1,
        max_size=5,
    ),
    discrete=st.booleans(),
)
def test_minari_import_property(tmp_path, seed, eps, discrete):
    """Random episodes that Minari itself stores (any ending, either action type) import into
    rlu with the transitions Minari's iteration gives."""
    from minari.data_collector import EpisodeBuffer

    tmp = tmp_path / uuid.uuid4().hex
    rng = np.random.default_rng(seed)
    buffers = []
    for n, end in eps:
        term, trunc = np.zeros(n, bool), np.zeros(n, bool)
        term[-1] = end in ("term", "both")
        trunc[-1] = end in ("trunc", "both")
        act = rng.integers(0, 3, n) if discrete else rng.uniform(-2, 2, (n, 2)).astype(np.float32)
        buffers.append(
            EpisodeBuffer(
                observations=rng.standard_normal((n + 1, 5)).astype(np.float32),
                actions=act,
                rewards=rng.standard_normal(n),
                terminations=term,
                truncations=trunc,
            )
        )
    act_space = gym.spaces.Discrete(3) if discrete else gym.spaces.Box(-2, 2, (2,), np.float32)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MINARI_DATASETS_PATH", str(tmp / "m"))
        mds = minari.create_dataset_from_buffers(
            "rand/episodes-v0",
            buffers,
            observation_space=gym.spaces.Box(-np.inf, np.inf, (5,)),
            action_space=act_space,
            algorithm_name="random",
        )
    ds = open_dataset(import_minari(tmp / "m" / "rand" / "episodes-v0", tmp / "ds"))
    ends = check_against_minari(mds, ds)
    assert ends == [(e in ("term", "both"), e in ("trunc", "both")) for _, e in eps]


# --- the environment and provenance of an export ------------------------------------------------
def test_recover_environment_of_the_bundled_export_is_rlus_env(tmp_path, minari_root):
    """Minari's own load_dataset(...).recover_environment() makes rlu's env from the stored spec,
    and the description says where the data came from (the manifest's provenance)."""
    pytest.importorskip("dm_control")
    from rlu.data.bundled import bundled_dataset

    ds = open_dataset(bundled_dataset())
    export_minari(ds, "rlu/cartpole-bundled-v0")
    mds = minari.load_dataset("rlu/cartpole-bundled-v0")
    assert mds.env_spec.id == "rlu/control_suite-cartpole_swingup-v0"
    assert mds.env_spec.kwargs == {"task_id": "control_suite/cartpole_swingup"}
    desc = mds.storage.metadata["description"]
    assert "rlu generate control_suite/cartpole_swingup --scale laptop" in desc
    assert "40 of 180 recorded episodes kept" in desc and "unknown" not in desc
    assert json.loads(mds.storage.metadata["rlu_provenance"]) == ds.manifest["provenance"]
    env = mds.recover_environment()
    obs, _ = env.reset(seed=0)
    assert mds.observation_space.contains(obs)
    assert env.unwrapped.spec.id == mds.env_spec.id
    obs, reward, terminated, truncated, _ = env.step(env.action_space.sample())
    assert mds.observation_space.contains(obs) and np.isfinite(reward) and not terminated
    env.close()


def test_export_spec_carries_the_recorded_settings(tmp_path, minari_root):
    """An RWRL 'easy' dataset's spec makes the env with challenge 'easy' (its dummy features)."""
    pytest.importorskip("dm_control")
    from rlu.tasks import rwrl_observation_spec

    task = get_task("rwrl/cartpole_swingup")
    schema = Schema.for_task(task, observation=rwrl_observation_spec(task, "easy"))
    prov = {
        "source": "rl_unplugged release",
        "family": "rwrl",
        "challenge": "easy",
        "code_version": "rlu 0.1.0",
        "files": [{"name": "cartpole_swingup-00000-of-00001", "bytes": 1, "records": 2}],
    }
    src = write_synthetic(tmp_path / "src", schema, 2, 5, seed=0)
    with DatasetWriter(tmp_path / "easy", schema, prov) as w:
        for i in range(2):
            w.append(open_dataset(src).segment(i))
    export_minari(open_dataset(tmp_path / "easy"), "rlu/rwrl-easy-v0")
    mds = minari.load_dataset("rlu/rwrl-easy-v0")
    assert mds.env_spec.kwargs == {"task_id": "rwrl/cartpole_swingup", "challenge": "easy"}
    desc = mds.storage.metadata["description"]
    assert desc.startswith("The original RL Unplugged release") and "cartpole_swingup-00000" in desc
    env = mds.recover_environment()
    obs, _ = env.reset(seed=0)
    assert set(obs) == set(schema.observation) and mds.observation_space.contains(obs)
    env.close()


def test_kept_source_without_ends_names_the_file(tmp_path):
    # an import always keeps "ends"; a sidecar archive without it is refused, naming the file
    # (it was a TypeError on None)
    from rlu.data.foreign import NpzFile
    from rlu.data.minari import _SourceEpisodes
    from rlu.types import FormatError

    path = tmp_path / "minari.npz"
    np.savez(path, rewards=np.zeros(3, np.float32))
    with NpzFile(path, "re-import the file") as z:
        extras = _SourceEpisodes({"episodes": [{"steps": 3}]}, ({}, z))
        with pytest.raises(FormatError, match=r"minari\.npz: no array 'ends'; re-import"):
            extras.next(0)
