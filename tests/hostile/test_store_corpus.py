"""Hostile and unlucky datasets in the store's own format: every one gets a clear error.

Each case damages a small valid dataset in one way. ``validate`` must report it, naming the file
and the field; opening and sampling the dataset must raise an RluError naming them too (or, for
values that sampling does not trip on, run through without a raw error). A secret file sits
beside every dataset, and the audit log of opened files proves it is never read, whatever the
manifest or a symlink says.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from rlu.data import Schema, open_dataset
from rlu.data.synthetic import write_synthetic
from rlu.data.validate import validate
from rlu.data.views import make_sampler
from rlu.tasks import get_task
from rlu.types import BatchSpec, RluError

ROOT = Path(__file__).resolve().parents[2]
CARTPOLE = Schema.for_task(get_task("control_suite/cartpole_swingup"))
PONG = Schema.for_task(get_task("atari/Pong"), image_encoding="zlib")
SECRET = b"the secret beside the dataset"


@dataclass
class Case:
    ds: Path
    file: str
    """What the messages must name: the file (a path fragment)."""
    field: str
    """... and the field or property that is wrong."""
    trips: bool = True
    """Whether opening or sampling must raise (else only validate reports it)."""


CASES: dict[str, Callable[[Path], Case]] = {}


def case(fn: Callable[[Path], Case]) -> Callable[[Path], Case]:
    CASES[fn.__name__] = fn
    return fn


# --- building blocks ---------------------------------------------------------------------------
def _ds(tmp: Path, schema: Schema = CARTPOLE) -> Path:
    (tmp / "secret.bin").write_bytes(SECRET)
    n = 2 if schema.frame_stack > 1 else 3
    return write_synthetic(tmp / "ds", schema, n, 5, seed=0, terminal_prob=0.0)


def _pong(tmp: Path) -> Path:
    return _ds(tmp, PONG)


def _edit(ds: Path, fn: Callable[[dict], object]) -> None:
    m = json.loads((ds / "manifest.json").read_text())
    fn(m)
    (ds / "manifest.json").write_text(json.dumps(m))


def _put(ds: Path, rel: str, data: bytes) -> None:
    """Replace a file and record its new size and sha256, as a careful forger would."""
    import hashlib

    (ds / rel).write_bytes(data)
    sha = hashlib.sha256(data).hexdigest()
    _edit(ds, lambda m: m["files"][rel].update(bytes=len(data), sha256=sha))


def _put_array(ds: Path, rel: str, arr: np.ndarray) -> None:
    _put(ds, rel, np.ascontiguousarray(arr).astype(arr.dtype.newbyteorder("<")).tobytes())


def _read(ds: Path, rel: str, dtype: str) -> np.ndarray:
    return np.fromfile(ds / rel, dtype=np.dtype(dtype).newbyteorder("<")).copy()


def _set(path: list[str], value: object) -> Callable[[dict], None]:
    def fn(m: dict) -> None:
        node = m
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = value

    return fn


def _drop(path: list[str]) -> Callable[[dict], None]:
    def fn(m: dict) -> None:
        node = m
        for k in path[:-1]:
            node = node[k]
        del node[path[-1]]

    return fn


def _manifest_case(name: str, edit: Callable[[dict], None], field: str, pong: bool = False):
    def build(tmp: Path) -> Case:
        ds = _pong(tmp) if pong else _ds(tmp)
        _edit(ds, edit)
        return Case(ds, "manifest.json", field)

    build.__name__ = name
    CASES[name] = build


# --- the manifest file itself -------------------------------------------------------------------
@case
def manifest_missing(tmp: Path) -> Case:
    ds = _ds(tmp)
    (ds / "manifest.json").unlink()
    return Case(ds, "manifest.json", "no manifest")


@case
def manifest_is_a_directory(tmp: Path) -> Case:
    ds = _ds(tmp)
    (ds / "manifest.json").unlink()
    (ds / "manifest.json").mkdir()
    return Case(ds, "manifest.json", "not a regular file")


@case
def manifest_is_a_fifo(tmp: Path) -> Case:
    ds = _ds(tmp)
    (ds / "manifest.json").unlink()
    os.mkfifo(ds / "manifest.json")  # opening it would block forever
    return Case(ds, "manifest.json", "not a regular file")


@case
def manifest_symlinked_outside(tmp: Path) -> Case:
    ds = _ds(tmp)
    shutil.copy(ds / "manifest.json", tmp / "secret.bin")
    (ds / "manifest.json").unlink()
    (ds / "manifest.json").symlink_to(tmp / "secret.bin")
    return Case(ds, "manifest.json", "outside the dataset folder")


@case
def manifest_empty(tmp: Path) -> Case:
    ds = _ds(tmp)
    (ds / "manifest.json").write_bytes(b"")
    return Case(ds, "manifest.json", "corrupt JSON")


@case
def manifest_binary(tmp: Path) -> Case:
    ds = _ds(tmp)
    (ds / "manifest.json").write_bytes(bytes(range(256)))
    return Case(ds, "manifest.json", "corrupt JSON")


@case
def manifest_a_list(tmp: Path) -> Case:
    ds = _ds(tmp)
    (ds / "manifest.json").write_text("[1, 2]")
    return Case(ds, "manifest.json", "'format'")


@case
def manifest_nested_deeply(tmp: Path) -> Case:
    ds = _ds(tmp)
    (ds / "manifest.json").write_text("[" * 200_000 + "]" * 200_000)
    return Case(ds, "manifest.json", "nested too deeply")


@case
def manifest_gigantic(tmp: Path) -> Case:
    ds = _ds(tmp)
    with open(ds / "manifest.json", "r+b") as f:
        f.truncate(80 << 20)  # sparse: refused by its size before a byte is read
    return Case(ds, "manifest.json", "at most")


_manifest_case("format_other", _set(["format"], "hdf5"), "'format'")
_manifest_case("version_2", _set(["version"], 2), "'version'")
_manifest_case("version_a_string", _set(["version"], "1"), "'version'")
for _key in ("schema", "counts", "files", "provenance"):
    _manifest_case(f"no_{_key}", _drop([_key]), f"'{_key}'")
_manifest_case("steps_1e300", _set(["counts", "steps"], 1e300), "counts.steps")
_manifest_case("steps_a_string", _set(["counts", "steps"], "15"), "counts.steps")
_manifest_case("steps_negative", _set(["counts", "steps"], -1), "counts.steps")
_manifest_case("steps_boolean", _set(["counts", "steps"], True), "counts.steps")
_manifest_case("segments_2_to_60", _set(["counts", "segments"], 2**60), "counts.segments")
_manifest_case("segments_missing", _drop(["counts", "segments"]), "counts.segments")
_manifest_case("counts_a_list", _set(["counts"], [3, 15, 0, 3]), "'counts'")
_manifest_case("files_a_list", _set(["files"], ["steps/action.bin"]), "'files'")
_manifest_case("files_entry_missing", _drop(["files", "steps/reward.bin"]), "steps/reward.bin")
_manifest_case(
    "files_absolute_path",
    lambda m: m["files"].update({"/etc/passwd": {"sha256": "0" * 64, "bytes": 1}}),
    "/etc/passwd",
)
_manifest_case(
    "files_dotdot_path",
    lambda m: m["files"].update({"../secret.bin": {"sha256": "0" * 64, "bytes": len(SECRET)}}),
    "../secret.bin",
)
_manifest_case("files_entry_a_string", _set(["files", "steps/reward.bin"], "abc"), "reward.bin")
_manifest_case("sha256_short", _set(["files", "steps/reward.bin", "sha256"], "abc"), "sha256")
_manifest_case("bytes_a_string", _set(["files", "steps/reward.bin", "bytes"], "60"), "bytes")
_manifest_case("bytes_negative", _set(["files", "steps/reward.bin", "bytes"], -60), "bytes")
_manifest_case("schema_a_list", _set(["schema"], [1]), "'schema'")
_manifest_case(
    "dtype_object", _set(["schema", "observation", "position", "dtype"], "object"), "dtype"
)
_manifest_case(
    "dtype_complex", _set(["schema", "observation", "position", "dtype"], "complex64"), "dtype"
)
_manifest_case("dtype_unknown", _set(["schema", "action", "dtype"], "float128x"), "dtype")
_manifest_case(
    "shape_negative", _set(["schema", "observation", "position", "shape"], [-3]), "shape"
)
_manifest_case(
    "shape_huge", _set(["schema", "observation", "position", "shape"], [10**9, 10**9]), "shape"
)
_manifest_case("shape_a_string", _set(["schema", "observation", "position", "shape"], "3"), "shape")
_manifest_case("shape_floats", _set(["schema", "observation", "position", "shape"], [3.0]), "shape")
_manifest_case(
    "shape_rank_20", _set(["schema", "observation", "position", "shape"], [1] * 20), "shape"
)
_manifest_case(
    "observation_key_dotdot",
    lambda m: m["schema"]["observation"].update({"../../secret": {"shape": [1], "dtype": "uint8"}}),
    "../../secret",
)
_manifest_case(
    "observation_key_absolute",
    lambda m: m["schema"]["observation"].update({"/etc/passwd": {"shape": [1], "dtype": "uint8"}}),
    "/etc/passwd",
)
_manifest_case("observation_empty", _set(["schema", "observation"], {}), "schema.observation")
_manifest_case("action_unbounded", _drop(["schema", "action", "minimum"]), "schema.action")
_manifest_case("action_min_above_max", _set(["schema", "action", "minimum"], 5.0), "minimum")
_manifest_case("action_min_nan", _set(["schema", "action", "minimum"], float("nan")), "minimum")
_manifest_case("num_values_0", _set(["schema", "action", "num_values"], 0), "num_values", True)
_manifest_case(
    "discrete_float_action", _set(["schema", "action", "dtype"], "float32"), "action", True
)
_manifest_case("frame_stack_1e9", _set(["schema", "frame_stack"], 10**9), "frame_stack", True)
_manifest_case("frame_stack_0", _set(["schema", "frame_stack"], 0), "frame_stack", True)
_manifest_case("frame_stack_a_string", _set(["schema", "frame_stack"], "4"), "frame_stack", True)
_manifest_case("image_encoding_gzip", _set(["schema", "image_encoding"], "gzip"), "image_encoding")
_manifest_case("task_id_a_number", _set(["schema", "task_id"], 7), "task_id")
_manifest_case("provenance_a_list", _set(["provenance"], [1]), "provenance")
_manifest_case("frames_with_no_stacking", _set(["counts", "frames"], 5), "counts.frames")

for _name, _edit_fn, _file, _field in (
    ("frames_count_wrong", _set(["counts", "frames"], 11), "frame_start.bin", "counts.frames"),
    ("steps_count_wrong", _set(["counts", "steps"], 16), "length.bin", "counts.steps"),
    ("segments_count_wrong", _set(["counts", "segments"], 4), "start.bin", "bytes"),
):

    def _build(tmp: Path, edit=_edit_fn, file=_file, field=_field) -> Case:
        ds = _pong(tmp) if "frames" in field else _ds(tmp)
        _edit(ds, edit)
        return Case(ds, file, field)

    CASES[_name] = _build


# --- column files ------------------------------------------------------------------------------
@case
def column_truncated(tmp: Path) -> Case:
    ds = _ds(tmp)
    f = ds / "steps" / "reward.bin"
    f.write_bytes(f.read_bytes()[:-4])
    return Case(ds, "reward.bin", "bytes")


@case
def column_longer(tmp: Path) -> Case:
    ds = _ds(tmp)
    with open(ds / "steps" / "reward.bin", "ab") as f:
        f.write(b"\0" * 4)
    return Case(ds, "reward.bin", "bytes")


@case
def column_longer_with_forged_manifest(tmp: Path) -> Case:
    ds = _ds(tmp)
    _put(ds, "steps/reward.bin", (ds / "steps" / "reward.bin").read_bytes() + b"\0" * 4)
    return Case(ds, "reward.bin", "bytes")


@case
def column_missing(tmp: Path) -> Case:
    ds = _ds(tmp)
    (ds / "steps" / "discount.bin").unlink()
    return Case(ds, "discount.bin", "missing")


@case
def column_is_a_directory(tmp: Path) -> Case:
    ds = _ds(tmp)
    (ds / "steps" / "discount.bin").unlink()
    (ds / "steps" / "discount.bin").mkdir()
    return Case(ds, "discount.bin", "not a regular file")


@case
def column_is_a_fifo(tmp: Path) -> Case:
    ds = _ds(tmp)
    (ds / "steps" / "discount.bin").unlink()
    os.mkfifo(ds / "steps" / "discount.bin")
    return Case(ds, "discount.bin", "not a regular file")


@case
def column_symlinked_outside(tmp: Path) -> Case:
    ds = _ds(tmp)
    col = ds / "steps" / "reward.bin"
    (tmp / "secret.bin").write_bytes(col.read_bytes())  # same size and hash: only the path tells
    col.unlink()
    col.symlink_to(tmp / "secret.bin")
    return Case(ds, "reward.bin", "outside the dataset folder")


@case
def steps_folder_symlinked_outside(tmp: Path) -> Case:
    ds = _ds(tmp)
    shutil.copytree(ds / "steps", tmp / "elsewhere")
    shutil.rmtree(ds / "steps")
    (ds / "steps").symlink_to(tmp / "elsewhere")
    return Case(ds, "steps", "outside the dataset folder")


@case
def segments_folder_symlinked_outside(tmp: Path) -> Case:
    ds = _ds(tmp)
    shutil.copytree(ds / "segments", tmp / "elsewhere")
    shutil.rmtree(ds / "segments")
    (ds / "segments").symlink_to(tmp / "elsewhere")
    return Case(ds, "segments", "outside the dataset folder")


@case
def dataset_root_has_dotdot_symlink(tmp: Path) -> Case:
    ds = _ds(tmp)
    col = ds / "steps" / "action.bin"
    shutil.copy(col, tmp / "secret.bin")
    col.unlink()
    col.symlink_to(Path("..") / ".." / "secret.bin")  # relative, and still outside
    return Case(ds, "action.bin", "outside the dataset folder")


@case
def column_corrupt_bytes(tmp: Path) -> Case:
    ds = _ds(tmp)
    f = ds / "steps" / "observation" / "position.bin"
    data = bytearray(f.read_bytes())
    data[3] ^= 0xFF
    f.write_bytes(bytes(data))
    return Case(ds, "position.bin", "sha256", trips=False)


# --- the segment index --------------------------------------------------------------------------
@case
def start_out_of_range(tmp: Path) -> Case:
    ds = _ds(tmp)
    start = _read(ds, "segments/start.bin", "int64")
    start[1] = 10**12
    _put_array(ds, "segments/start.bin", start)
    return Case(ds, "start.bin", "starts at step")


@case
def start_negative(tmp: Path) -> Case:
    ds = _ds(tmp)
    start = _read(ds, "segments/start.bin", "int64")
    start[2] = -4
    _put_array(ds, "segments/start.bin", start)
    return Case(ds, "start.bin", "starts at step")


@case
def length_zero(tmp: Path) -> Case:
    ds = _ds(tmp)
    length = _read(ds, "segments/length.bin", "int64")
    length[0] = 0
    _put_array(ds, "segments/length.bin", length)
    return Case(ds, "length.bin", "length 0")


@case
def length_huge(tmp: Path) -> Case:
    ds = _ds(tmp)
    length = _read(ds, "segments/length.bin", "int64")
    length[0] = 2**62
    _put_array(ds, "segments/length.bin", length)
    return Case(ds, "length.bin", "length")


@case
def lengths_not_adding_up(tmp: Path) -> Case:
    ds = _ds(tmp)
    length = _read(ds, "segments/length.bin", "int64")
    length[2] = 3
    _put_array(ds, "segments/length.bin", length)
    return Case(ds, "length.bin", "add up")


@case
def frame_start_wrong(tmp: Path) -> Case:
    ds = _pong(tmp)
    fs = _read(ds, "segments/frame_start.bin", "int64")
    fs[1] = 10**9
    _put_array(ds, "segments/frame_start.bin", fs)
    return Case(ds, "frame_start.bin", "frame start")


# --- compressed frames -------------------------------------------------------------------------
@case
def zlib_offsets_descending(tmp: Path) -> Case:
    ds = _pong(tmp)
    off = _read(ds, "steps/observation.offsets.bin", "int64")
    off[2], off[3] = off[3], off[2]
    _put_array(ds, "steps/observation.offsets.bin", off)
    return Case(ds, "observation.offsets.bin", "frame 2")


@case
def zlib_offsets_start_not_0(tmp: Path) -> Case:
    ds = _pong(tmp)
    off = _read(ds, "steps/observation.offsets.bin", "int64")
    off[0] = 5
    _put_array(ds, "steps/observation.offsets.bin", off)
    return Case(ds, "observation.offsets.bin", "offsets run from 5")


@case
def zlib_offsets_2_to_40(tmp: Path) -> Case:
    ds = _pong(tmp)
    off = _read(ds, "steps/observation.offsets.bin", "int64")
    off[-1] = 2**40
    _put_array(ds, "steps/observation.offsets.bin", off)
    return Case(ds, "observation.offsets.bin", "stream file holds")


def _replace_frame(ds: Path, row: int, blob: bytes) -> None:
    off = _read(ds, "steps/observation.offsets.bin", "int64")
    data = (ds / "steps" / "observation.zlib").read_bytes()
    new = data[: off[row]] + blob + data[off[row + 1] :]
    off[row + 1 :] += len(blob) - (off[row + 1] - off[row])
    _put(ds, "steps/observation.zlib", new)
    _put_array(ds, "steps/observation.offsets.bin", off)


@case
def zlib_frame_garbage(tmp: Path) -> Case:
    ds = _pong(tmp)
    _replace_frame(ds, 4, b"definitely not a zlib stream")
    return Case(ds, "observation.zlib", "frame 4")


@case
def zlib_frame_bomb(tmp: Path) -> Case:
    ds = _pong(tmp)
    blob = zlib.compress(b"\0" * (6 << 20), 9)  # 6 MiB where 7 KB belong, in a frame-sized stream
    assert len(blob) <= 84 * 84
    _replace_frame(ds, 5, blob)
    return Case(ds, "observation.zlib", "frame 5")


@case
def zlib_frame_stream_too_long(tmp: Path) -> Case:
    ds = _pong(tmp)
    _replace_frame(ds, 5, zlib.compress(b"\0" * (64 << 20), 9))  # no frame's stream is 64 KB
    return Case(ds, "observation.offsets.bin", "frame 5")


@case
def zlib_frame_short(tmp: Path) -> Case:
    ds = _pong(tmp)
    _replace_frame(ds, 3, zlib.compress(b"\0" * 100))
    return Case(ds, "observation.zlib", "frame 3")


@case
def zlib_frame_with_trailing_bytes(tmp: Path) -> Case:
    ds = _pong(tmp)
    _replace_frame(ds, 2, zlib.compress(b"\0" * (84 * 84)) + b"tail")
    return Case(ds, "observation.zlib", "frame 2")


@case
def zlib_stream_file_truncated(tmp: Path) -> Case:
    ds = _pong(tmp)
    f = ds / "steps" / "observation.zlib"
    f.write_bytes(f.read_bytes()[:-10])
    return Case(ds, "observation.zlib", "bytes")


# --- values a dataset must not hold -------------------------------------------------------------
@case
def terminal_flag_byte_2(tmp: Path) -> Case:
    ds = _ds(tmp)
    flags = _read(ds, "steps/is_terminal.bin", "uint8")
    flags[3] = 2
    _put_array(ds, "steps/is_terminal.bin", flags)
    return Case(ds, "is_terminal.bin", "flag", trips=False)


@case
def first_flag_byte_255(tmp: Path) -> Case:
    ds = _ds(tmp)
    flags = _read(ds, "steps/is_first.bin", "uint8")
    flags[0] = 255
    _put_array(ds, "steps/is_first.bin", flags)
    return Case(ds, "is_first.bin", "flag", trips=False)


@case
def discrete_action_out_of_range(tmp: Path) -> Case:
    ds = _pong(tmp)
    a = _read(ds, "steps/action.bin", "int64")
    a[1] = 17
    _put_array(ds, "steps/action.bin", a)
    return Case(ds, "action.bin", "action space", trips=False)


@case
def discrete_action_negative(tmp: Path) -> Case:
    ds = _pong(tmp)
    a = _read(ds, "steps/action.bin", "int64")
    a[0] = -1
    _put_array(ds, "steps/action.bin", a)
    return Case(ds, "action.bin", "action space", trips=False)


@case
def continuous_action_outside_bounds(tmp: Path) -> Case:
    ds = _ds(tmp)
    a = _read(ds, "steps/action.bin", "float32")
    a[2] = 3.5
    _put_array(ds, "steps/action.bin", a)
    return Case(ds, "action.bin", "action space", trips=False)


@case
def action_nan(tmp: Path) -> Case:
    ds = _ds(tmp)
    a = _read(ds, "steps/action.bin", "float32")
    a[1] = np.nan
    _put_array(ds, "steps/action.bin", a)
    return Case(ds, "action.bin", "action", trips=False)


@case
def reward_nan(tmp: Path) -> Case:
    ds = _ds(tmp)
    r = _read(ds, "steps/reward.bin", "float32")
    r[0] = np.nan
    _put_array(ds, "steps/reward.bin", r)
    return Case(ds, "reward.bin", "NaN", trips=False)


@case
def discount_2(tmp: Path) -> Case:
    ds = _ds(tmp)
    d = _read(ds, "steps/discount.bin", "float32")
    d[1] = 2.0
    _put_array(ds, "steps/discount.bin", d)
    return Case(ds, "discount.bin", "[0, 1]", trips=False)


@case
def discount_inf(tmp: Path) -> Case:
    ds = _ds(tmp)
    d = _read(ds, "steps/discount.bin", "float32")
    d[1] = np.inf
    _put_array(ds, "steps/discount.bin", d)
    return Case(ds, "discount.bin", "[0, 1]", trips=False)


@case
def stored_return_lies(tmp: Path) -> Case:
    ds = _ds(tmp)
    r = _read(ds, "segments/meta_episode_return.bin", "float64")
    r[0] += 100
    _put_array(ds, "segments/meta_episode_return.bin", r)
    return Case(ds, "meta_episode_return.bin", "stores return", trips=False)


@case
def schema_of_another_task(tmp: Path) -> Case:
    ds = _ds(tmp)
    _edit(ds, _set(["schema", "task_id"], "control_suite/cheetah_run"))
    return Case(ds, "manifest.json", "schema does not match task", trips=False)


# --- the test ------------------------------------------------------------------------------------
def _use(ds: Path) -> None:
    """What a user does with a dataset: open, read every segment, sample both views."""
    d = open_dataset(ds)
    for i in range(len(d)):
        d.segment(i)
    make_sampler(d, BatchSpec(8), seed=0).sample()
    make_sampler(d, BatchSpec(8, n_step=3, gamma=0.9), seed=0).sample()
    make_sampler(d, BatchSpec(4, kind="sequence", sequence_length=3), seed=0).sample()
    d.info()


def _check(name: str, tmp_path: Path, opened) -> None:
    c = CASES[name](tmp_path)
    opened.log.clear()  # from here on: what reading the dataset opens
    report = validate(c.ds)
    text = "\n".join(report.problems)
    assert report.problems, f"{name}: validate found nothing"
    assert c.file in text and c.field in text, text
    if c.trips:
        with pytest.raises(RluError) as info:
            _use(c.ds)
        assert c.file in str(info.value) and c.field in str(info.value), str(info.value)
    else:
        try:
            _use(c.ds)
        except RluError as e:  # a clear error is fine too; a raw one is not
            assert c.file in str(e), str(e)
    secret = os.path.realpath(c.ds.parent / "secret.bin")
    assert secret not in opened.log, f"{name}: the file beside the dataset was read"
    inside = os.path.realpath(c.ds) + os.sep
    outside = [p for p in opened.under(tmp_path) if not p.startswith(inside)]
    assert not outside, f"{name}: opened beside the dataset: {outside}"


FIFO = {"manifest_is_a_fifo", "column_is_a_fifo"}


@pytest.mark.parametrize("name", sorted(set(CASES) - FIFO))
def test_hostile_dataset(name, tmp_path, opened):
    _check(name, tmp_path, opened)


@pytest.mark.parametrize("name", sorted(FIFO))
def test_fifo_never_hangs(name, tmp_path):
    """In a child with a deadline: a FIFO opened for reading would block forever."""
    code = (
        "import sys; from pathlib import Path; from tests.hostile import test_store_corpus as T;"
        f"c = T.CASES[{name!r}](Path(sys.argv[1])); r = T.validate(c.ds);"
        "assert any(c.field in p for p in r.problems), r.problems;"
        "from rlu.cli import main; sys.exit(main(['validate', str(c.ds)]))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 1, out.stderr
    assert "not a regular file" in out.stdout and "Traceback" not in out.stderr


def test_symlinks_inside_the_folder_are_followed(tmp_path, opened):
    ds = _ds(tmp_path)
    col = ds / "steps" / "reward.bin"
    shutil.move(col, ds / "reward-copy.bin")
    col.symlink_to(Path("..") / "reward-copy.bin")  # inside: allowed
    opened.log.clear()
    assert validate(ds).ok
    _use(ds)
    assert os.path.realpath(tmp_path / "secret.bin") not in opened.log


def test_the_corpus_is_large():
    assert len(CASES) >= 90
