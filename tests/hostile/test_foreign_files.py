"""Hostile input, round two, for foreign files and kept behaviour policies (issue 30, classes 2,
4 and 5): HDF5 files that point outside themselves (external raw storage, external links, soft
links and their loops, virtual datasets), compressed bombs (HDF5 gzip datasets, .npz members and
policy .npz files that inflate to far more than they store), policy JSON of the wrong types or
absurd sizes. Each case is refused with one RluError naming the file and the field (exit 2 from
the CLI), reads nothing outside the file, leaves nothing at the destination, and holds a bounded
amount of memory (numpy's and Python's allocations, as ``tracemalloc`` counts them) whatever the
file declares. (`rlu import X.hdf5` without h5py: tests/hostile/test_missing_extras.py.)"""

from __future__ import annotations

import io
import json
import os
import tracemalloc
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from rlu.cli import main
from rlu.data import Schema, open_dataset
from rlu.data.d3rlpy_io import import_d3rlpy
from rlu.data.d4rl import import_d4rl, to_d4rl
from rlu.data.synthetic import write_synthetic
from rlu.tasks import get_task
from rlu.types import RluError

h5py = pytest.importorskip("h5py")

TASK = "control_suite/cartpole_swingup"
CARTPOLE = Schema.for_task(get_task(TASK))
PEAK = 96 << 20  # what an import may hold at once here; the bombs below declare 400 MB or more


def _d4rl(tmp: Path) -> dict[str, np.ndarray]:
    return to_d4rl(open_dataset(write_synthetic(tmp / "src", CARTPOLE, 3, 6, seed=1)))


def _write_d4rl(path: Path, d: dict, skip: tuple[str, ...] = ()) -> None:
    with h5py.File(path, "w") as f:
        for k, v in d.items():
            if k not in skip:
                f.create_dataset(k, data=v)


def _d3rlpy(path: Path, change: Callable[[object], None] | None = None, n: int = 5) -> None:
    """A one-episode d3rlpy dump (d3rlpy.dataset.io.dump's layout); ``change`` writes
    ``rewards_0`` (and whatever else it likes) instead of the plain one."""
    rng = np.random.default_rng(0)
    with h5py.File(path, "w") as h5:
        h5.create_dataset("columns", data=["observations", "actions", "rewards", "terminated"])
        h5.create_dataset("num_episodes", data=1)
        h5.create_dataset("observations_0", data=rng.standard_normal((n, 5)).astype(np.float32))
        h5.create_dataset("actions_0", data=rng.uniform(-1, 1, (n, 1)).astype(np.float32))
        h5.create_dataset("terminated_0", data=True)
        h5.create_dataset("version", data="2.1")
        if change is None:
            h5.create_dataset("rewards_0", data=np.ones((n, 1), np.float32))
        else:
            change(h5)


def _refused(run: Callable[[], object], *words: str, tmp: Path) -> str:
    with pytest.raises(RluError) as info:
        run()
    msg = str(info.value)
    assert "\n" not in msg and all(w in msg for w in words), msg
    out = tmp / "out"
    assert not out.exists() or os.listdir(out) == [], os.listdir(out)  # no partial, no lock
    return msg


def _dest(tmp: Path) -> Path:
    return tmp / "out" / "ds"


# --- class 2: no reads outside the file ---------------------------------------------------------
def _other(tmp: Path, name: str, shape: tuple) -> Path:
    """Another file holding dataset ``name``: what a link or a virtual dataset would read."""
    with h5py.File(tmp / "other.hdf5", "w") as f:
        f.create_dataset(name, data=np.full(shape, 7.0, np.float32))
    return tmp / "other.hdf5"


def _external_storage(f, name, shape):
    size = 4 * int(np.prod(shape))
    f.create_dataset(name, shape=shape, dtype="f4", external=[("/etc/passwd", 0, size)])


def _virtual(f, name, shape, other):
    layout = h5py.VirtualLayout(shape=shape, dtype="f4")
    layout[:] = h5py.VirtualSource(str(other), name, shape=shape)
    f.create_virtual_dataset(name, layout)


def _outside(kind: str, tmp: Path, name: str, shape: tuple) -> Callable[[object], None]:
    other = _other(tmp, name, shape)

    def write(f) -> None:
        if kind == "external_storage":
            _external_storage(f, name, shape)
        elif kind == "external_link":
            f[name] = h5py.ExternalLink(str(other), f"/{name}")
        elif kind == "soft_link":
            f.create_dataset("elsewhere", data=np.ones(shape, np.float32))
            f[name] = h5py.SoftLink("/elsewhere")
        elif kind == "soft_link_loop":
            f[name] = h5py.SoftLink(f"/{name}_again")
            f[f"{name}_again"] = h5py.SoftLink(f"/{name}")
        elif kind == "virtual":
            _virtual(f, name, shape, other)

    return write


KINDS = {
    "external_storage": "external file '/etc/passwd'",
    "external_link": "external link",
    "soft_link": "soft link",
    "soft_link_loop": "soft link",
    "virtual": "virtual dataset",
}


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_d4rl_hdf5_pointing_outside_is_refused(kind, tmp_path):
    d = _d4rl(tmp_path)
    path = tmp_path / "x.hdf5"
    _write_d4rl(path, d, skip=("rewards",))
    with h5py.File(path, "a") as f:
        _outside(kind, tmp_path, "rewards", d["rewards"].shape)(f)
    _refused(lambda: import_d4rl(path, _dest(tmp_path), TASK), "x.hdf5", "'rewards'",
             KINDS[kind], tmp=tmp_path)  # fmt: skip
    argv = ["import", str(path), "--format", "d4rl", "--task", TASK, "--out", str(_dest(tmp_path))]
    assert main(argv) == 2


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_d3rlpy_dump_pointing_outside_is_refused(kind, tmp_path, capsys):
    path = tmp_path / "dump.h5"
    _d3rlpy(path, _outside(kind, tmp_path, "rewards_0", (5, 1)))
    _refused(lambda: import_d3rlpy(path, _dest(tmp_path), TASK), "dump.h5", "'rewards_0'",
             KINDS[kind], tmp=tmp_path)  # fmt: skip
    argv = [
        "import",
        str(path),
        "--format",
        "d3rlpy",
        "--task",
        TASK,
        "--out",
        str(_dest(tmp_path)),
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("rlu: error: ") and err.count("\n") == 1 and "Traceback" not in err


def test_a_soft_link_loop_to_a_group_is_one_line(tmp_path):
    """A group whose soft link names itself (every walk that follows links never ends)."""
    d = _d4rl(tmp_path)
    path = tmp_path / "x.hdf5"
    _write_d4rl(path, d)
    with h5py.File(path, "a") as f:
        f["infos/loop"] = h5py.SoftLink("/infos")
    _refused(lambda: import_d4rl(path, _dest(tmp_path), TASK), "x.hdf5", "'infos/loop'",
             "soft link", tmp=tmp_path)  # fmt: skip


def test_minari_episode_through_an_external_link_is_refused(tmp_path):
    pytest.importorskip("minari")
    from rlu.data.minari import export_minari, import_minari

    src = open_dataset(write_synthetic(tmp_path / "src", CARTPOLE, 2, 4, seed=2))
    data = export_minari(src, "rlu/outside-v0", root=tmp_path / "m") / "data"
    with h5py.File(data / "main_data.hdf5", "a") as f:
        n = f["episode_0/rewards"].shape
        with h5py.File(tmp_path / "other.hdf5", "w") as o:
            o.create_dataset("r", data=np.full(n, 7.0, np.float32))
        del f["episode_0/rewards"]
        f["episode_0/rewards"] = h5py.ExternalLink(str(tmp_path / "other.hdf5"), "/r")
    _refused(lambda: import_minari(data.parent, _dest(tmp_path), TASK), "main_data.hdf5",
             "'episode_0/rewards'", "external link", tmp=tmp_path)  # fmt: skip


# --- class 4: memory does not follow what a file declares ---------------------------------------
def _peak(run: Callable[[], object]) -> tuple[int, BaseException | None]:
    """Peak bytes numpy and Python allocated while ``run`` ran, and what it raised."""
    tracemalloc.start()
    err = None
    try:
        run()
    except Exception as e:  # noqa: BLE001 (returned to the test, which checks it)
        err = e
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak, err


def _gzip_zeros(f, name: str, shape: tuple, chunk_rows: int = 1 << 16) -> None:
    """A gzip dataset of zeros written chunk by chunk from one compressed chunk (a bomb: each
    chunk of 256 KiB or more stores a few hundred bytes)."""
    chunks = (chunk_rows, *shape[1:])
    ds = f.create_dataset(name, shape=shape, dtype="f4", chunks=chunks, compression="gzip")
    blob = zlib.compress(bytes(int(np.prod(chunks)) * 4), 9)
    for i in range(0, shape[0] - chunk_rows + 1, chunk_rows):
        ds.id.write_direct_chunk((i, *([0] * (len(shape) - 1))), blob)


def test_hdf5_gzip_bomb_in_one_array_is_refused_before_it_inflates(tmp_path):
    d = _d4rl(tmp_path)
    path = tmp_path / "bomb.hdf5"
    _write_d4rl(path, d, skip=("rewards",))
    with h5py.File(path, "a") as f:
        _gzip_zeros(f, "rewards", (10**8,), 1 << 18)  # 400 MB declared, 0.4 MB stored
    assert path.stat().st_size < 1 << 20
    peak, err = _peak(lambda: import_d4rl(path, _dest(tmp_path), TASK))
    assert isinstance(err, RluError) and "bomb.hdf5" in str(err), err
    assert peak < PEAK, f"{peak / 2**20:.0f} MiB"


def test_hdf5_gzip_bomb_of_consistent_arrays_stays_bounded(tmp_path):
    """Every step array declares the same 5,000,000 zero rows: a file of under a megabyte whose
    arrays inflate to 250 MB. Import reads it a block at a time and stops at the first episode
    longer than the task allows."""
    n = 5_000_000
    path = tmp_path / "bomb.hdf5"
    with h5py.File(path, "w") as f:
        for name, shape in (("observations", (n, 5)), ("next_observations", (n, 5)),
                            ("actions", (n, 1)), ("rewards", (n,)), ("terminals", (n,)),
                            ("timeouts", (n,))):  # fmt: skip
            _gzip_zeros(f, name, shape, 1 << 14)
    assert path.stat().st_size < 2 << 20
    peak, err = _peak(lambda: import_d4rl(path, _dest(tmp_path), TASK))
    assert isinstance(err, RluError) and "4000 steps" in str(err) and "bomb.hdf5" in str(err), err
    assert peak < PEAK, f"{peak / 2**20:.0f} MiB"
    assert not (tmp_path / "out").exists() or os.listdir(tmp_path / "out") == []


def test_d3rlpy_gzip_bomb_episode_is_refused_before_it_inflates(tmp_path):
    path = tmp_path / "bomb.h5"
    _d3rlpy(path, lambda h5: _gzip_zeros(h5, "rewards_0", (10**8, 1), 1 << 18))
    peak, err = _peak(lambda: import_d3rlpy(path, _dest(tmp_path), TASK))
    assert isinstance(err, RluError) and "bomb.h5: episode 0" in str(err), err
    assert peak < PEAK, f"{peak / 2**20:.0f} MiB"


def _deflated_npz(path: Path, members: dict[str, tuple[tuple, bytes | None]]) -> None:
    """An .npz whose members are deflated (np.savez_compressed's layout); a member given as
    (shape, None) is that many float32 zeros, written in pieces."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for name, (shape, data) in members.items():
            head = io.BytesIO()
            np.lib.format.write_array_header_1_0(
                head, {"descr": "<f4", "fortran_order": False, "shape": shape}
            )
            with z.open(f"{name}.npy", "w", force_zip64=True) as fh:
                fh.write(head.getvalue())
                if data is not None:
                    fh.write(data)
                    continue
                left = int(np.prod(shape)) * 4
                zeros = bytes(16 << 20)
                while left:
                    fh.write(zeros[: min(left, len(zeros))])
                    left -= min(left, len(zeros))


def test_npz_deflate_bomb_of_consistent_arrays_stays_bounded(tmp_path):
    n = 2_000_000  # 100 MB of rows in a file of about 100 KB
    path = tmp_path / "bomb.npz"
    _deflated_npz(path, {name: (shape, None) for name, shape in (
        ("observations", (n, 5)), ("next_observations", (n, 5)), ("actions", (n, 1)),
        ("rewards", (n,)), ("terminals", (n,)), ("timeouts", (n,)))})  # fmt: skip
    assert path.stat().st_size < 1 << 20
    peak, err = _peak(lambda: import_d4rl(path, _dest(tmp_path), TASK))
    assert isinstance(err, RluError) and "4000 steps" in str(err) and "bomb.npz" in str(err), err
    assert peak < PEAK // 2, f"{peak / 2**20:.0f} MiB"


# --- kept behaviour policies: a small dataset with one, built without running an env -------------
@pytest.fixture(scope="module")
def policy_ds(tmp_path_factory) -> Path:
    """A cartpole dataset keeping one D4PG behaviour policy (run 0, checkpoint 0), as
    ``rlu generate`` writes it."""
    pytest.importorskip("torch")
    from rlu.agents import make_agent
    from rlu.data import DatasetWriter
    from rlu.generate.online import OnlineConfig
    from rlu.generate.policies import policy_stem, save_snapshot
    from rlu.segments import make_episode

    tmp = tmp_path_factory.mktemp("policy")
    task = get_task(TASK)
    overrides = {"policy_layers": (32, 32), "critic_layers": (32, 32), "torso_hidden": 32}
    online = OnlineConfig("d4pg", episodes=1, agent_overrides=overrides, policy_dtype="float32")
    agent = make_agent("d4pg", task.observation_spec, task.action_spec, "small", 0, **overrides)
    save_snapshot(tmp / "work", agent, task, online, 0, 0, 0, 0, 0)
    rng = np.random.default_rng(0)
    obs = {k: rng.standard_normal((5, *s.shape)).astype(np.float32)
           for k, s in task.observation_spec.items()}  # fmt: skip
    seg = make_episode(obs, rng.uniform(-1, 1, (4, 1)).astype(np.float32), np.ones(4), False,
                       {"run": 0, "checkpoint": 0})  # fmt: skip
    with DatasetWriter(tmp / "ds", CARTPOLE) as w:
        w.append(seg)
        for suffix in (".npz", ".json"):
            w.attach(policy_stem(0, 0) + suffix, tmp / "work" / f"checkpoint_00000{suffix}")
    return tmp / "ds"


def _rewrite(ds: Path, rel: str, data: bytes) -> None:
    """Replace a file and record its new sha256 and size: a consistent (hostile) dataset."""
    import hashlib

    (ds / rel).write_bytes(data)
    m = json.loads((ds / "manifest.json").read_text())
    m["files"][rel] = {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}
    (ds / "manifest.json").write_text(json.dumps(m))


NPZ, JSON = "policies/run_000/checkpoint_00000.npz", "policies/run_000/checkpoint_00000.json"


@pytest.fixture
def copy(policy_ds, tmp_path) -> Path:
    import shutil

    shutil.copytree(policy_ds, tmp_path / "ds")
    return tmp_path / "ds"


def _meta(ds: Path) -> dict:
    return json.loads((ds / JSON).read_text())


def _load(ds: Path) -> Callable[[], object]:
    from rlu.generate.policies import load_behaviour_policy

    return lambda: load_behaviour_policy(ds, 0, 0)


def test_the_fixture_policy_loads_and_validates(policy_ds):
    from rlu.data.validate import validate

    policy = _load(policy_ds)()
    obs = {k: np.zeros((2, *s.shape), np.float32) for k, s in CARTPOLE.observation.items()}
    assert np.asarray(policy(obs, np.ones(2, bool))).shape == (2, 1)
    assert validate(policy_ds).ok


def test_policy_npz_declaring_1e12_elements_is_refused_unallocated(copy):
    member = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        member, {"descr": "<f4", "fortran_order": False, "shape": (10**12,)}
    )
    with np.load(copy / NPZ) as z:
        arrays = {k: z[k] for k in z.files}
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for k, v in arrays.items():
            if k == "out.weight":
                zf.writestr(f"{k}.npy", member.getvalue() + b"\0" * 4096)
            else:
                with zf.open(f"{k}.npy", "w") as fh:
                    np.lib.format.write_array(fh, v)
    _rewrite(copy, NPZ, buf.getvalue())
    peak, err = _peak(_load(copy))
    assert isinstance(err, RluError) and "checkpoint_00000.npz" in str(err), err
    assert "'out.weight'" in str(err) and "\n" not in str(err)
    assert peak < PEAK, f"{peak / 2**20:.0f} MiB"


def _bomb_policy(ds: Path, rows: int, json_agrees: bool) -> None:
    """The policy's ``out.weight`` replaced by ``rows`` x 32 deflated float32 zeros (a small
    file inflating to far more), its JSON declaring that shape or the original one."""
    with np.load(ds / NPZ) as z:
        arrays = {k: z[k] for k in z.files}
    members: dict[str, tuple[tuple, bytes | None]] = {}
    for k, v in arrays.items():
        bomb = ((rows, 32), None)
        members[k] = bomb if k == "out.weight" else (v.shape, v.astype("<f4").tobytes())
    _deflated_npz(ds / "bomb.npz", members)
    _rewrite(ds, NPZ, (ds / "bomb.npz").read_bytes())
    (ds / "bomb.npz").unlink()
    if json_agrees:
        meta = _meta(ds)
        meta["arrays"]["out.weight"]["shape"] = [rows, 32]
        _rewrite(ds, JSON, json.dumps(meta).encode())


@pytest.mark.parametrize("json_agrees", [False, True])
def test_policy_npz_inflating_to_gigabytes_is_refused_before_inflating(copy, json_agrees):
    rows = (320 << 20) // 128  # 320 MiB of float32 zeros (the limit is 256 MiB)
    _bomb_policy(copy, rows, json_agrees)
    assert (copy / NPZ).stat().st_size < 8 << 20
    peak, err = _peak(_load(copy))
    what = "field 'arrays' declares" if json_agrees else "array 'out.weight' is float32"
    assert isinstance(err, RluError) and what in str(err), err
    assert peak < PEAK, f"{peak / 2**20:.0f} MiB"


@pytest.mark.parametrize("json_agrees", [False, True])
def test_validate_reports_an_npz_that_does_not_match_its_json(copy, capsys, json_agrees):
    """Not as its JSON declares, or more than a kept policy may hold: a problem, found from the
    headers (nothing inflated)."""
    _bomb_policy(copy, (320 << 20) // 128, json_agrees=json_agrees)
    peak, _ = _peak(lambda: main(["validate", str(copy)]))
    out = capsys.readouterr().out
    what = "more than a kept policy" if json_agrees else "'out.weight' is float32[2621440, 32]"
    assert "FAIL" in out and what in out, out
    assert out.rstrip().endswith("1 problem(s)")
    assert main(["validate", str(copy)]) == 1
    assert peak < PEAK, f"{peak / 2**20:.0f} MiB"


# --- class 5: policy JSON of the wrong types or absurd sizes: one line, exit 2 ------------------
def _planted(task_id: str, **kw) -> None:
    Path(os.environ["RLU_PLANTED_MARKER"]).write_text("ran")
    raise RuntimeError("a planted env factory ran")


JSON_CASES: dict[str, tuple[Callable[[dict], object], str]] = {
    "layer_width_200000": (
        lambda m: m["agent_config"].update(policy_layers=[200000, 200000]),
        "agent_config.policy_layers[0]",
    ),
    "layer_width_negative": (
        lambda m: m["agent_config"].update(critic_layers=[-5]),
        "agent_config.critic_layers[0]",
    ),
    "layer_width_string": (
        lambda m: m["agent_config"].update(policy_layers=["256", "256"]),
        "agent_config.policy_layers[0]",
    ),
    "layers_a_string": (
        lambda m: m["agent_config"].update(policy_layers="256,256"),
        "agent_config.policy_layers",
    ),
    "gamma_a_string": (lambda m: m["agent_config"].update(gamma="0.99"), "agent_config.gamma"),
    "torso_1e9": (lambda m: m["agent_config"].update(torso_hidden=10**9), "torso_hidden"),
    "agent_config_a_list": (lambda m: m.update(agent_config=[1, 2]), "'agent_config'"),
    "agent_a_module_path": (lambda m: m.update(agent="http.server"), "'agent'"),
    "array_shape_negative": (
        lambda m: m["arrays"]["out.weight"].update(shape=[-1, 32]),
        "arrays.out.weight.shape[0]",
    ),
    "array_dtype_object": (
        lambda m: m["arrays"]["out.weight"].update(dtype="object"),
        "arrays.out.weight.dtype",
    ),
    "env_steps_negative": (lambda m: m.update(env_steps=-3), "'env_steps'"),
    "checkpoint_steps_0": (lambda m: m.update(checkpoint_steps=0), "'checkpoint_steps'"),
    "sigma_a_list": (lambda m: m["exploration"].update(sigma=[0.3]), "exploration.sigma"),
    "env_settings_make_env": (
        lambda m: m["env_settings"].update(make_env="tests.hostile.test_foreign_files:_planted"),
        "env_settings.make_env",
    ),
    "env_settings_a_list": (lambda m: m.update(env_settings=[]), "'env_settings'"),
    "deeply_nested": (lambda m: None, "nested"),  # the text is written below
}


@pytest.mark.parametrize("name", sorted(JSON_CASES))
def test_policy_json_of_the_wrong_type_or_size_is_one_line(name, copy, tmp_path, monkeypatch):
    from rlu.generate.policies import rollout_behaviour

    change, field = JSON_CASES[name]
    meta = _meta(copy)
    if name == "deeply_nested":
        text = json.dumps(meta)[:-1] + ', "agent_overrides": ' + "[" * 100_000 + "]" * 100_000
        text += "}"
        data = text.encode()
    else:
        change(meta)
        data = json.dumps(meta).encode()
    _rewrite(copy, JSON, data)
    marker = tmp_path / "PLANTED_RAN"
    monkeypatch.setenv("RLU_PLANTED_MARKER", str(marker))
    for run in (_load(copy), lambda: rollout_behaviour(copy, 0, 0, episodes=1, num_envs=1)):
        with pytest.raises(RluError) as info:
            run()
        msg = str(info.value)
        assert "checkpoint_00000.json" in msg and field in msg and "\n" not in msg, msg
    assert not marker.exists()


def test_cli_on_bad_policy_json_exits_2_with_one_line(copy, capsys):
    meta = _meta(copy)
    meta["agent_config"]["policy_layers"] = [200000, 200000]
    _rewrite(copy, JSON, json.dumps(meta).encode())
    argv = ["evaluate-behaviour", str(copy), "--run", "0", "--checkpoint", "0", "--episodes", "1"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("rlu: error: ") and err.count("\n") == 1, err
    assert "policy_layers" in err
