"""Hostile and unlucky foreign files: D4RL .npz / .hdf5, d3rlpy dumps, Minari folders and
release shards. Each must fail with an RluError naming the file and the field, leave nothing at
the destination (no partial folder, no lock), and allocate nothing it declares but does not
hold."""

from __future__ import annotations

import gzip
import io
import json
import os
import struct
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from rlu.codecs import example as E
from rlu.codecs.png import encode_png
from rlu.data import Schema, open_dataset
from rlu.data.d4rl import import_d4rl, to_d4rl
from rlu.data.release.convert import convert
from rlu.data.release.framing import frame, write_records
from rlu.data.synthetic import write_synthetic
from rlu.domains import records
from rlu.domains.atari import release as atari_release
from rlu.domains.rwrl import release as rwrl_release
from rlu.tasks import get_task
from rlu.types import RluError
from tests.release.test_families import atari_record, rwrl_record, window_record

h5py = pytest.importorskip("h5py")

CARTPOLE = Schema.for_task(get_task("control_suite/cartpole_swingup"))
TASK = "control_suite/cartpole_swingup"


@dataclass
class Case:
    run: Callable[[], object]
    file: str
    field: str


CASES: dict[str, Callable[[Path], Case]] = {}


def case(fn: Callable[[Path], Case]) -> Callable[[Path], Case]:
    CASES[fn.__name__] = fn
    return fn


def _dest(tmp: Path) -> Path:
    return tmp / "out" / "ds"


# --- D4RL .npz --------------------------------------------------------------------------------
def _d4rl(tmp: Path) -> dict[str, np.ndarray]:
    src = open_dataset(write_synthetic(tmp / "src", CARTPOLE, 3, 6, seed=1))
    return to_d4rl(src)


def _npz_case(name: str, change: Callable[[dict], None], field: str) -> None:
    def build(tmp: Path) -> Case:
        d = _d4rl(tmp)
        change(d)
        np.savez(tmp / "x.npz", **d)
        return Case(lambda: import_d4rl(tmp / "x.npz", _dest(tmp), TASK), "x.npz", field)

    CASES[name] = build


_npz_case("npz_missing_rewards", lambda d: d.pop("rewards"), "'rewards'")
_npz_case("npz_missing_actions", lambda d: d.pop("actions"), "'actions'")
_npz_case("npz_no_observations", lambda d: [d.pop(k) for k in list(d) if "obs" in k], "observ")
_npz_case("npz_short_actions", lambda d: d.update(actions=d["actions"][:-2]), "'actions'")
_npz_case("npz_short_terminals", lambda d: d.update(terminals=d["terminals"][:-1]), "terminals")
_npz_case(
    "npz_short_observations",
    lambda d: d.update({"observations/position": d["observations/position"][:-1]}),
    "observations/position",
)
_npz_case(
    "npz_action_width_0",
    lambda d: d.update(actions=np.zeros((len(d["actions"]), 0), np.float32)),
    "actions",
)
_npz_case(
    "npz_action_width_3",
    lambda d: d.update(actions=np.zeros((len(d["actions"]), 3), np.float32)),
    "actions",
)
_npz_case(
    "npz_string_rewards",
    lambda d: d.update(rewards=np.array(["1.0"] * len(d["rewards"]))),
    "'rewards'",
)
_npz_case(
    "npz_complex_rewards",
    lambda d: d.update(rewards=d["rewards"].astype(np.complex64) + 1j),
    "'rewards'",
)
_npz_case("npz_nan_reward", lambda d: d["rewards"].__setitem__(2, np.nan), "'rewards'")
_npz_case(
    "npz_terminals_half",
    lambda d: d.update(terminals=np.where(d["terminals"], 1.0, 0.5)),
    "'terminals'",
)
_npz_case(
    "npz_timeouts_strings",
    lambda d: d.update(timeouts=np.array(["no"] * len(d["timeouts"]))),
    "'timeouts'",
)
_npz_case(
    "npz_length_0",
    lambda d: d.update({k: v[:0] for k, v in d.items()}),
    "'rewards'",
)
_npz_case(
    "npz_rewards_2_columns",
    lambda d: d.update(rewards=np.stack([d["rewards"], d["rewards"]], 1)),
    "'rewards'",
)
_npz_case(
    "npz_action_outside_bounds",
    lambda d: d["actions"].__setitem__((1, 0), 7.0),
    "action space",
)
_npz_case(
    "npz_observation_width_4",
    lambda d: d.update(
        {
            k: np.zeros((len(d["rewards"]), 4), np.float32)
            for k in ("observations/position", "next_observations/position")
        }
    ),
    "observations/position",
)
_npz_case(
    "npz_next_observation_shape_differs",
    lambda d: d.update({"next_observations/velocity": np.zeros((len(d["rewards"]), 7))}),
    "next_observations",
)
_npz_case(
    "npz_unknown_observation_key",
    lambda d: d.update(
        {
            "observations/extra": np.zeros((len(d["rewards"]), 1)),
            "next_observations/extra": np.zeros((len(d["rewards"]), 1)),
        }
    ),
    "extra",
)
_npz_case(
    "npz_infinite_observation",
    lambda d: d["observations/position"].__setitem__((0, 0), np.inf),
    "observations/position",
)


def _npz_raw(name: str, data: bytes, field: str) -> None:
    def build(tmp: Path) -> Case:
        (tmp / "x.npz").write_bytes(data)
        return Case(lambda: import_d4rl(tmp / "x.npz", _dest(tmp), TASK), "x.npz", field)

    CASES[name] = build


_npz_raw("npz_empty_file", b"", "not an .npz archive")
_npz_raw("npz_text_file", b"observations,actions\n1,2\n", "not an .npz archive")
_npz_raw("npz_half_a_zip", b"PK\x03\x04" + b"\0" * 40, "not an .npz archive")
_buf = io.BytesIO()
np.save(_buf, np.zeros(3))
_npz_raw("npy_named_npz", _buf.getvalue(), "single .npy array")


def _zip_with_member(members: dict[str, bytes], compress: int = zipfile.ZIP_STORED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compress) as z:
        for name, data in members.items():
            z.writestr(name, data)
    return buf.getvalue()


def _npy_header(shape: tuple, dtype: str = "<f4") -> bytes:
    """The magic and header of an .npy file declaring ``shape`` (what numpy writes)."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf, {"descr": dtype, "fortran_order": False, "shape": shape}
    )
    return buf.getvalue()


@case
def npz_header_claims_1e12_elements(tmp: Path) -> Case:
    member = _npy_header((10**12,)) + b"\0" * 400
    (tmp / "x.npz").write_bytes(_zip_with_member({"rewards.npy": member}))
    return Case(lambda: import_d4rl(tmp / "x.npz", _dest(tmp), TASK), "x.npz", "rewards")


@case
def npz_zip_bomb_member(tmp: Path) -> Case:
    """A deflated member that inflates far beyond anything its header allows."""
    big = _npy_header((4,)) + b"\0" * (50 << 20)
    (tmp / "x.npz").write_bytes(_zip_with_member({"rewards.npy": big}, zipfile.ZIP_DEFLATED))
    return Case(lambda: import_d4rl(tmp / "x.npz", _dest(tmp), TASK), "x.npz", "rewards")


@case
def npz_object_array(tmp: Path) -> Case:
    d = _d4rl(tmp)
    d["rewards"] = np.array([{"r": 1}] * len(d["rewards"]), dtype=object)
    np.savez(tmp / "x.npz", **d)
    return Case(lambda: import_d4rl(tmp / "x.npz", _dest(tmp), TASK), "x.npz", "Python objects")


@case
def npz_is_a_directory(tmp: Path) -> Case:
    (tmp / "x.npz").mkdir()
    return Case(lambda: import_d4rl(tmp / "x.npz", _dest(tmp), TASK), "x.npz", "no such file")


@case
def d4rl_unknown_suffix(tmp: Path) -> Case:
    (tmp / "x.csv").write_text("1,2,3")
    return Case(lambda: import_d4rl(tmp / "x.csv", _dest(tmp), TASK), "x.csv", "file type")


# --- D4RL .hdf5 -------------------------------------------------------------------------------
def _hdf5_case(name: str, write: Callable[[object, dict], None], field: str) -> None:
    def build(tmp: Path) -> Case:
        d = _d4rl(tmp)
        with h5py.File(tmp / "x.hdf5", "w") as f:
            write(f, d)
        return Case(lambda: import_d4rl(tmp / "x.hdf5", _dest(tmp), TASK), "x.hdf5", field)

    CASES[name] = build


def _all_but(*skip: str) -> Callable[[object, dict], None]:
    def write(f, d):
        for k, v in d.items():
            if k not in skip:
                f.create_dataset(k, data=v)

    return write


def _with(key: str, **kw) -> Callable[[object, dict], None]:
    def write(f, d):
        _all_but(key)(f, d)
        f.create_dataset(key, **kw)

    return write


_hdf5_case("hdf5_missing_timeouts", _all_but("timeouts"), "'timeouts'")
_hdf5_case(
    "hdf5_rewards_declare_1e12",
    _with("rewards", shape=(10**12,), dtype="f4", chunks=(1024,)),
    "'rewards'",
)


def _one_chunk(f, d):
    _all_but("rewards")(f, d)
    ds = f.create_dataset("rewards", shape=(10**9,), dtype="f4", chunks=(4096,))
    ds[:4096] = 1.0  # one chunk stored, a billion values declared


_hdf5_case("hdf5_rewards_mostly_unstored", _one_chunk, "'rewards'")
_hdf5_case("hdf5_string_rewards", _with("rewards", data=np.array([b"x"] * 18)), "'rewards'")


def _rewards_group(f, d):
    _all_but("rewards")(f, d)
    f.create_group("rewards")


_hdf5_case("hdf5_rewards_a_group", _rewards_group, "'rewards'")
_hdf5_case(
    "hdf5_terminals_half", _with("terminals", data=np.full(18, 0.5, np.float32)), "'terminals'"
)


def _hdf5_raw(name: str, data: bytes, field: str) -> None:
    def build(tmp: Path) -> Case:
        (tmp / "x.hdf5").write_bytes(data)
        return Case(lambda: import_d4rl(tmp / "x.hdf5", _dest(tmp), TASK), "x.hdf5", field)

    CASES[name] = build


_hdf5_raw("hdf5_empty_file", b"", "not an HDF5 file")
_hdf5_raw("hdf5_html_page", b"<html><body>404</body></html>", "not an HDF5 file")
_hdf5_raw("hdf5_signature_only", b"\x89HDF\r\n\x1a\n" + b"\0" * 64, "not an HDF5 file")


# --- d3rlpy dumps ----------------------------------------------------------------------------
def _dump(path: Path, episodes, version="2.1", num=None, columns=None) -> None:
    keys = ["observations", "actions", "rewards", "terminated"]
    with h5py.File(path, "w") as h5:
        h5.create_dataset("columns", data=columns if columns is not None else keys)
        h5.create_dataset("num_episodes", data=len(episodes) if num is None else num)
        for i, ep in enumerate(episodes):
            for key, value in zip(keys, ep, strict=True):
                if value is not None:
                    h5.create_dataset(f"{key}_{i}", data=value)
        if version is not None:
            h5.create_dataset("version", data=version)


def _ep(n=5, terminated=True):
    rng = np.random.default_rng(n)
    return [
        rng.standard_normal((n, 5)).astype(np.float32),
        rng.uniform(-1, 1, (n, 1)).astype(np.float32),
        rng.random((n, 1), dtype=np.float32),
        terminated,
    ]


def _d3_case(name: str, make: Callable[[Path], None], field: str) -> None:
    def build(tmp: Path) -> Case:
        from rlu.data.d3rlpy_io import import_d3rlpy

        make(tmp / "dump.h5")
        return Case(lambda: import_d3rlpy(tmp / "dump.h5", _dest(tmp), TASK), "dump.h5", field)

    CASES[name] = build


def _changed(i: int, value) -> list:
    ep = _ep()
    ep[i] = value
    return ep


_d3_case("d3rlpy_no_version", lambda p: _dump(p, [_ep()], version=None), "'version'")
_d3_case("d3rlpy_version_1", lambda p: _dump(p, [_ep()], version="1.0"), "'version'")
_d3_case("d3rlpy_num_episodes_1e15", lambda p: _dump(p, [_ep()], num=10**15), "num_episodes")
_d3_case("d3rlpy_num_episodes_string", lambda p: _dump(p, [_ep()], num="3"), "num_episodes")
_d3_case("d3rlpy_more_episodes_claimed", lambda p: _dump(p, [_ep()], num=2), "observations_1")
_d3_case("d3rlpy_no_observations", lambda p: _dump(p, [_changed(0, None)]), "observations_0")
_d3_case("d3rlpy_terminated_half", lambda p: _dump(p, [_changed(3, 0.5)]), "'terminated'")
_d3_case(
    "d3rlpy_short_actions",
    lambda p: _dump(p, [_changed(1, np.zeros((3, 1), np.float32))]),
    "actions",
)
_d3_case(
    "d3rlpy_string_rewards", lambda p: _dump(p, [_changed(2, np.array([b"a"] * 5))]), "rewards"
)
_d3_case(
    "d3rlpy_observation_width_9",
    lambda p: _dump(p, [_changed(0, np.zeros((5, 9), np.float32))]),
    "observations",
)
_d3_case("d3rlpy_columns_missing", lambda p: _dump(p, [_ep()], columns=["x"]), "'observations'")


# --- Minari folders ---------------------------------------------------------------------------
minari = pytest.importorskip("minari")


def _minari(tmp: Path) -> Path:
    from rlu.data.minari import export_minari

    src = open_dataset(write_synthetic(tmp / "src", CARTPOLE, 2, 4, seed=2))
    return export_minari(src, "rlu/hostile-v0", root=tmp / "m") / "data"


def _minari_meta(name: str, change: Callable[[dict], object], field: str) -> None:
    def build(tmp: Path) -> Case:
        from rlu.data.minari import import_minari

        data = _minari(tmp)
        meta = json.loads((data / "metadata.json").read_text())
        out = change(meta)
        (data / "metadata.json").write_text(json.dumps(meta if out is None else out))
        return Case(lambda: import_minari(data.parent, _dest(tmp), TASK), "metadata.json", field)

    CASES[name] = build


def _space(meta: dict, key: str, value: dict) -> None:
    meta[key] = json.dumps(value)


_minari_meta("minari_metadata_a_list", lambda m: [m], "not an object")
_minari_meta(
    "minari_no_spaces_env_spec_only", lambda m: m.pop("observation_space") and None, "env_spec"
)
_minari_meta(
    "minari_unknown_space", lambda m: _space(m, "observation_space", {"type": "Weird"}), "Weird"
)
_minari_meta(
    "minari_box_1e18_values",
    lambda m: _space(
        m,
        "action_space",
        {"type": "Box", "shape": [10**9, 10**9], "dtype": "float32", "low": 0, "high": 1},
    ),
    "action_space.shape",
)
_minari_meta(
    "minari_total_episodes_1e15", lambda m: m.update(total_episodes=10**15), "total_episodes"
)
_minari_meta(
    "minari_total_episodes_string", lambda m: m.update(total_episodes="2"), "total_episodes"
)
_minari_meta("minari_data_format_pickle", lambda m: m.update(data_format="pickle"), "data_format")


@case
def minari_metadata_empty(tmp: Path) -> Case:
    from rlu.data.minari import import_minari

    data = _minari(tmp)
    (data / "metadata.json").write_bytes(b"")
    return Case(lambda: import_minari(data.parent, _dest(tmp), TASK), "metadata.json", "JSON")


def _minari_h5(name: str, change: Callable[[object], None], field: str) -> None:
    def build(tmp: Path) -> Case:
        from rlu.data.minari import import_minari

        data = _minari(tmp)
        with h5py.File(data / "main_data.hdf5", "a") as f:
            change(f)
        return Case(lambda: import_minari(data.parent, _dest(tmp), TASK), "", field)

    CASES[name] = build


def _replace(key: str, **kw) -> Callable[[object], None]:
    def change(f) -> None:
        del f[f"episode_0/{key}"]
        f.create_dataset(f"episode_0/{key}", **kw)

    return change


_minari_h5(
    "minari_episode_without_actions", lambda f: f.__delitem__("episode_0/actions"), "actions"
)
_minari_h5(
    "minari_terminations_half",
    _replace("terminations", data=np.array([0, 0, 0.5], np.float32)),
    "'terminations'",
)
_minari_h5("minari_rewards_strings", _replace("rewards", data=np.array([b"a"] * 3)), "rewards")
_minari_h5(
    "minari_rewards_declare_1e12",
    _replace("rewards", shape=(10**12,), dtype="f4", chunks=(1024,)),
    "rewards",
)
_minari_h5(
    "minari_actions_outside_bounds",
    _replace("actions", data=np.full((4, 1), 9.0, np.float32)),
    "action space",
)


# --- release shards ---------------------------------------------------------------------------
def _convert_case(
    name: str, make: Callable[[Path], Path], family: str, task: str, field: str, **kw
) -> None:
    def build(tmp: Path) -> Case:
        path = make(tmp)
        return Case(
            lambda: convert([path], family, task, _dest(tmp), workers=1, **kw), path.name, field
        )

    CASES[name] = build


def _raw_file(data: bytes, name: str = "train-00000-of-00001") -> Callable[[Path], Path]:
    def make(tmp: Path) -> Path:
        (tmp / name).write_bytes(data)
        return tmp / name

    return make


def _records(payloads: list[bytes], gz: bool = True) -> Callable[[Path], Path]:
    def make(tmp: Path) -> Path:
        path = tmp / "train-00000-of-00001"
        write_records(path, payloads, compression="gzip" if gz else None)
        return path

    return make


def _window(**change) -> bytes:
    rec = window_record(np.random.default_rng(0), 2, {"position": 3, "velocity": 2})
    rec["action"] = rec["action"][:, :1]
    feats = E.decode_example(records.encode_sequence(rec))
    feats.update(change)
    for k, v in change.items():
        if v is None:
            feats.pop(k)
    return E.encode_example(feats)


def _atari(**change) -> bytes:
    feats = E.decode_example(
        atari_release.encode_atari_transition(atari_record(np.random.default_rng(0)))
    )
    feats.update(change)
    return E.encode_example(feats)


CS = ("dm_control_suite", TASK)
PONG = ("atari", "atari/Pong")
_convert_case("shard_empty_file", _raw_file(b""), *CS, "no records")
_convert_case("shard_html_page", _raw_file(b"<!doctype html><title>Sign in</title>"), *CS, "CRC")
_convert_case("shard_gzip_of_garbage", _raw_file(gzip.compress(os.urandom(5000))), *CS, "CRC")
_convert_case(
    "shard_gzip_cut",
    _raw_file(gzip.compress(b"".join(frame(_window()) for _ in range(50)))[:-40]),
    *CS,
    "truncated",
)
_convert_case(
    "shard_gzip_then_garbage", _raw_file(gzip.compress(frame(_window())) + b"junk"), *CS, "garbage"
)
_convert_case(
    "shard_record_length_2_to_40",
    _raw_file(struct.pack("<Q", 2**40) + b"\0" * 20),
    *CS,
    "byte offset 0",
)
_convert_case("record_without_action", _records([_window(action=None)]), *CS, "'action'")
_convert_case("record_without_discount", _records([_window(discount=None)]), *CS, "'discount'")
_convert_case(
    "record_zero_steps",
    _records([_window(discount=np.zeros(0, np.float32))]),
    *CS,
    "T=0",
)
_convert_case(
    "record_step_type_as_bytes", _records([_window(step_type=[b"FIRST", b"MID"])]), *CS, "step_type"
)
_convert_case(
    "record_reward_3_values", _records([_window(reward=np.ones(3, np.float32))]), *CS, "'reward'"
)
_convert_case("record_garbage_payload", _records([b"\xff" * 64]), *CS, "record 0 at byte offset 0")
_convert_case(
    "atari_empty_episode_id",
    _records([_atari(episode_id=np.zeros(0, np.int64))]),
    *PONG,
    "episode_id",
)
_convert_case(
    "atari_png_32x32",
    _records([_atari(o_t=[encode_png(np.zeros((32, 32), np.uint8))] * 4)]),
    *PONG,
    "32x32",
)


def _png_claiming(w: int, h: int) -> bytes:
    png = encode_png(np.zeros((84, 84), np.uint8))
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    import zlib as _z

    chunk = struct.pack(">I", 13) + b"IHDR" + ihdr + struct.pack(">I", _z.crc32(b"IHDR" + ihdr))
    return png[:8] + chunk + png[33:]


_convert_case(
    "atari_png_claims_65535_square",
    _records([_atari(o_tp1=[_png_claiming(65535, 65535)] * 4)]),
    *PONG,
    "65535x65535",
)
_convert_case(
    "atari_three_frames",
    _records([_atari(o_t=[encode_png(np.zeros((84, 84), np.uint8))] * 3)]),
    *PONG,
    "'o_t'",
)
_convert_case("atari_action_as_float", _records([_atari(a_t=np.float32([1.5]))]), *PONG, "'a_t'")
_convert_case(
    "rwrl_header_beyond_the_file",
    _raw_file(
        (frame(rwrl_release.encode_rwrl(rwrl_record(np.random.default_rng(0), 5))) * 2)[:-30],
        "episodes.tfrecord-00000-of-00001",
    ),
    "rwrl",
    "rwrl/cartpole_swingup",
    "truncated record",
    challenge="none",
)


@case
def shard_is_a_directory(tmp: Path) -> Case:
    (tmp / "shard").mkdir()
    return Case(lambda: convert([tmp / "shard"], *CS, _dest(tmp), workers=1), "shard", "no such")


# --- the test -----------------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(CASES))
def test_hostile_file(name, tmp_path):
    c = CASES[name](tmp_path)
    with pytest.raises(RluError) as info:
        c.run()
    msg = str(info.value)
    assert c.file in msg and c.field in msg, msg
    out = tmp_path / "out"
    assert not out.exists() or os.listdir(out) == [], os.listdir(out)  # no partial, no lock


def test_a_planted_env_spec_never_runs(tmp_path):
    """Minari builds an env from ``env_spec`` (gym.make: any entry point) when the spaces are
    missing; rlu refuses such metadata before Minari sees it."""
    from rlu.data.minari import import_minari

    data = _minari(tmp_path)
    meta = json.loads((data / "metadata.json").read_text())
    del meta["observation_space"]
    marker = tmp_path / "ENV_SPEC_RAN"
    meta["env_spec"] = json.dumps(
        {
            "id": "Planted-v0",
            "entry_point": "tests.hostile.test_import_corpus:_planted",
            "kwargs": {"marker": str(marker)},
        }
    )
    (data / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(RluError, match="never builds an env from env_spec"):
        import_minari(data.parent, _dest(tmp_path), TASK)
    assert not marker.exists()


def _planted(marker: str, **kw):
    Path(marker).write_text("ran")
    raise RuntimeError("a planted entry point ran")


def test_the_corpus_is_large():
    assert len(CASES) >= 60
