"""Arrays out of files rlu did not write (D4RL ``.npz`` / ``.hdf5``, d3rlpy dumps, Minari's HDF5,
behaviour policies' ``.npz``), read warily.

Such files are input, and may be damaged or hostile. Nothing a file says makes rlu read another
file, allocate what the file does not hold, or hold more than a bounded amount at a time:

- HDF5: every link of the file is walked before anything is read; soft links (which may loop),
  external links and user-defined links are refused, and so are datasets whose values live
  outside the file (external raw storage, virtual datasets), filters other than HDF5's own and
  LZF, and chunks over ``MAX_CHUNK_BYTES`` (one chunk inflates whole);
- every array's declared size is checked against what the file really holds *before* it is
  allocated (an ``.npy`` header or an HDF5 dataset claiming 1e12 elements costs nothing);
- columns (:class:`Column`) are read in row blocks of about ``READ_BYTES``: a deflated ``.npz``
  member inflates in bounded steps as it is read, an HDF5 dataset chunk by chunk, so an importer
  that consumes the blocks as they come (rlu.data.d4rl) holds one block and one episode, however
  many gigabytes a small file inflates to; an episode is bounded by ``MAX_EPISODE_BYTES`` and by
  ``EPISODE_LENGTH_FACTOR`` times its task's episode length;
- object arrays are refused without being unpickled, and values are checked before import:
  numbers only (no strings, no complex), flags exactly 0 or 1, finite rewards.

Every refusal is a :class:`~rlu.types.FormatError` naming the file, the array and the fix.
"""

from __future__ import annotations

import dataclasses
import math
import os
import zipfile
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from rlu.segments import Segment
from rlu.system import install_hint
from rlu.types import FormatError, RluError

MAX_DEFLATE_RATIO = 1032
"""The most deflate can compress (RFC 1951: a 258-byte match in 2 bits): what a compressed
member or dataset of N stored bytes may inflate to, at most 1032 N."""
READ_BYTES = 32 << 20
"""About the most one read of a column returns (a block of rows)."""
MAX_CHUNK_BYTES = 64 << 20
"""The largest HDF5 chunk rlu inflates (h5py's automatic chunks are at most 1 MiB)."""
MAX_EPISODE_BYTES = 256 << 20
"""The most one imported episode may hold in memory (38,000 Atari frames; a 27,000-step episode,
Dopamine's time limit, takes 190 MB)."""
EPISODE_LENGTH_FACTOR = 4
"""An imported episode may be at most this many times its task's episode length (Atari's
original evaluation limit of 108,000 steps is 4 x the 27,000 of the data): longer means the file
lacks its episode ends."""
MAX_POLICY_BYTES = 256 << 20
"""The most a kept behaviour policy's arrays (``policies/**.npz``) may declare in all (a D4PG
256x3 policy in float16: 0.1 MB; Dopamine's DQN: 3.4 MB)."""
MAX_HDF5_LINKS = 1 << 20
HDF5_FILTERS = {
    1: "deflate (gzip)",
    2: "shuffle",
    3: "fletcher32",
    4: "szip",
    5: "nbit",
    6: "scaleoffset",
    32000: "lzf",
}
"""Filters rlu lets HDF5 run: HDF5's own and h5py's LZF. Any other id would make HDF5 load a
plugin library chosen by the file."""
_NPY_MAGIC = b"\x93NUMPY"


def _plausible(stored: int, declared: int) -> bool:
    return declared <= stored * MAX_DEFLATE_RATIO + (1 << 16)


def episode_limit(task: Any) -> int:
    """The most steps (transitions) an episode imported for ``task`` may have."""
    return EPISODE_LENGTH_FACTOR * int(task.episode_length)


# --- columns ---------------------------------------------------------------------------------
class Column:
    """One array of a foreign file, read in row blocks: ``shape`` and ``dtype`` as declared
    (checked against the file), ``rows(a, b)`` the rows ``a .. b - 1``."""

    name: str
    shape: tuple[int, ...]
    dtype: np.dtype

    @property
    def row_bytes(self) -> int:
        return math.prod(self.shape[1:]) * self.dtype.itemsize

    @property
    def nbytes(self) -> int:
        return math.prod(self.shape) * self.dtype.itemsize

    def rows(self, a: int, b: int) -> np.ndarray:
        raise NotImplementedError

    def read(self, max_bytes: int | None = None, where: str = "") -> np.ndarray:
        """The whole array, refused beforehand when it declares more than ``max_bytes``."""
        if max_bytes is not None and self.nbytes > max_bytes:
            raise FormatError(
                f"{where}: {self.name!r} declares shape {self.shape} ({self.nbytes} bytes), more "
                f"than the {max_bytes} bytes such an array may hold; the file is damaged or not "
                "what it claims"
            )
        if not self.shape:
            return self.rows(0, 1)
        return self.rows(0, self.shape[0])


class ArrayColumn(Column):
    """An array already in memory (a dict handed to an importer)."""

    def __init__(self, value: Any, name: str, where: str):
        try:
            self.a = np.asarray(value)
        except (ValueError, TypeError) as e:
            raise FormatError(f"{where}: {name!r} is not an array ({e})") from None
        self.name, self.shape, self.dtype = name, self.a.shape, self.a.dtype

    def rows(self, a: int, b: int) -> np.ndarray:
        return self.a[a:b] if self.a.ndim else self.a


# --- .npz ------------------------------------------------------------------------------------
_NPZ_FIX = "write it with numpy.savez (numeric arrays only)"


@dataclasses.dataclass(frozen=True)
class NpyMember:
    """One ``.npy`` member of an ``.npz``: its header, read and checked, no data yet."""

    key: str
    info: zipfile.ZipInfo
    shape: tuple[int, ...]
    dtype: np.dtype
    fortran: bool
    header: int
    """Bytes before the data."""

    @property
    def nbytes(self) -> int:
        return math.prod(self.shape) * self.dtype.itemsize


class NpzFile:
    """An ``.npz`` archive opened for wary reading: ``members`` holds every ``.npy`` member's
    header, each checked against the zip entry's sizes; nothing else is read until asked.
    Object arrays (pickles) are refused, never unpickled."""

    def __init__(self, path: str | os.PathLike, fix: str = _NPZ_FIX):
        self.path, self.fix = Path(path), fix
        with open(self.path, "rb") as fh:
            head = fh.read(6)
        if head == _NPY_MAGIC:
            raise FormatError(
                f"{self.path}: a single .npy array, not an .npz archive of arrays; {fix}"
            )
        try:
            self.zf = zipfile.ZipFile(self.path)
        except (zipfile.BadZipFile, OSError, EOFError, ValueError) as e:
            raise FormatError(
                f"{self.path}: not an .npz archive of numeric arrays ({e}); rlu never unpickles "
                f"data: {fix}"
            ) from None
        self.infos = {
            i.filename[: -len(".npy")]: i for i in self.zf.infolist() if i.filename.endswith(".npy")
        }
        self._members: dict[str, NpyMember] = {}

    def __enter__(self) -> NpzFile:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.zf.close()

    def member(self, key: str) -> NpyMember:
        """The header of member ``key``, checked: numeric, and the zip entry holds exactly the
        declared bytes (and could, compressed as it is)."""
        if key not in self._members:
            self._members[key] = self._header(key)
        return self._members[key]

    def _header(self, key: str) -> NpyMember:
        fmt = np.lib.format
        info = self.infos[key]
        try:
            with self.zf.open(info) as fp:
                version = fmt.read_magic(fp)
                if version == (1, 0):
                    shape, fortran, dtype = fmt.read_array_header_1_0(fp)
                else:
                    shape, fortran, dtype = fmt.read_array_header_2_0(fp)
                header = fp.tell()
        except (ValueError, OSError, EOFError, zipfile.BadZipFile, RuntimeError) as e:
            raise FormatError(
                f"{self.path}: array {key!r} cannot be read ({e}); {self.fix}"
            ) from None
        if dtype.hasobject:
            raise FormatError(
                f"{self.path}: array {key!r} holds Python objects, which only a pickle can load; "
                "rlu never unpickles: save it as a numeric array"
            )
        m = NpyMember(key, info, tuple(int(x) for x in shape), dtype, bool(fortran), header)
        if info.file_size != header + m.nbytes or not _plausible(info.compress_size, m.nbytes):
            raise FormatError(
                f"{self.path}: array {key!r} declares shape {m.shape} {dtype} ({m.nbytes} bytes) "
                f"but its member holds {info.file_size} bytes ({info.compress_size} stored); the "
                f"file is damaged: {self.fix}"
            )
        return m

    def column(self, key: str) -> Column:
        m = self.member(key)
        if m.fortran and len(m.shape) > 1:  # rows are not contiguous: read whole, if small
            if m.nbytes > READ_BYTES:
                raise FormatError(
                    f"{self.path}: array {key!r} ({m.nbytes} bytes) is stored in Fortran order, "
                    f"which rlu reads whole only up to {READ_BYTES} bytes; save it C-ordered "
                    "(numpy.ascontiguousarray) with numpy.savez"
                )
            a = NpzColumn(self, m).read()
            return ArrayColumn(a.reshape(m.shape[::-1]).T, key, str(self.path))
        return NpzColumn(self, m)

    def read(self, key: str, max_bytes: int | None = None) -> np.ndarray:
        return self.column(key).read(max_bytes, str(self.path))


class NpzColumn(Column):
    """A C-ordered ``.npy`` member, inflated front to back as its rows are asked for (a row
    block behind the position is read again from the start; the last row read is kept, since
    readers look one row ahead)."""

    def __init__(self, npz: NpzFile, m: NpyMember):
        self.npz, self.m = npz, m
        self.name, self.shape, self.dtype = m.key, m.shape, m.dtype
        self._fp: Any = None
        self._pos = 0
        self._last: np.ndarray | None = None

    def _fail(self, e: Exception) -> FormatError:
        return FormatError(
            f"{self.npz.path}: array {self.name!r} cannot be read ({e}); {self.npz.fix}"
        )

    def _open(self) -> None:
        if self._fp is not None:
            self._fp.close()
        self._fp = self.npz.zf.open(self.m.info)
        self._fp.read(self.m.header)
        self._pos, self._last = 0, None

    def _bytes(self, n: int) -> bytes:
        out = []
        while n > 0:
            block = self._fp.read(min(n, READ_BYTES))
            if not block:
                raise EOFError(f"{n} bytes short of its declared shape {self.shape}")
            out.append(block)
            n -= len(block)
        return b"".join(out)

    def rows(self, a: int, b: int) -> np.ndarray:
        row = self.row_bytes
        count = self.shape[0] if self.shape else 1
        b = min(b, count)
        try:
            keep = None
            if self._fp is None or a < self._pos - (self._last is not None):
                self._open()
            if a == self._pos - 1 and self._last is not None and b > a:
                keep, a = self._last, self._pos
            while self._pos < a:  # skip forward in bounded steps
                step = min(a - self._pos, max(1, READ_BYTES // max(row, 1)))
                self._bytes(step * row)
                self._pos += step
            data = self._bytes(max(b - a, 0) * row)
            self._pos = max(self._pos, b)
        except (ValueError, OSError, EOFError, zipfile.BadZipFile, RuntimeError) as e:
            raise self._fail(e) from None
        out = np.frombuffer(data, self.dtype).reshape(max(b - a, 0), *self.shape[1:])
        if keep is not None:
            out = np.concatenate([keep, out])
        if len(out):
            self._last = out[-1:].copy()
        return out if self.shape else out.reshape(())


def read_npz(path: str | os.PathLike, max_bytes: int | None = None) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` file; object arrays (pickles) are refused, never unpickled,
    and so is an archive declaring more than ``max_bytes`` in all (before a byte is inflated)."""
    with NpzFile(path) as z:
        members = [z.member(k) for k in z.infos]
        total = sum(m.nbytes for m in members)
        if max_bytes is not None and total > max_bytes:
            raise FormatError(
                f"{path}: its arrays declare {total} bytes, more than the {max_bytes} it may "
                f"hold; {z.fix}"
            )
        return {m.key: z.read(m.key) for m in members}


# --- HDF5 ------------------------------------------------------------------------------------
def _require_h5py() -> Any:
    try:
        import h5py
    except ImportError:
        raise RluError(f"reading HDF5 files needs h5py: {install_hint('interop')}") from None
    return h5py


def open_hdf5(path: str | os.PathLike, what: str) -> Any:
    """An open ``h5py.File`` whose structure passed :func:`hdf5_datasets`; ``what`` names the
    writer for the error (d3rlpy's dump, D4RL...)."""
    h5py = _require_h5py()
    try:
        f = h5py.File(path, "r")
    except (OSError, ValueError) as e:
        raise FormatError(f"{path}: not an HDF5 file ({e}); give {what}") from None
    try:
        hdf5_datasets(f, Path(path), what)
    except BaseException:
        f.close()
        raise
    return f


def hdf5_datasets(f: Any, path: Path, what: str) -> list[str]:
    """The name of every dataset of open file ``f`` (hard links, all names of each), after
    refusing whatever could make a read leave the file or run unbounded (module docstring)."""
    import h5py
    from h5py import h5l

    links: list[tuple[bytes, int]] = []

    def visit(name: bytes, info: Any) -> Any:  # never raises: h5py cannot pass it through
        links.append((name, info.type))
        return True if len(links) > MAX_HDF5_LINKS else None

    fix = f"re-write it with plain datasets inside the file; give {what}"
    try:
        f.id.links.visit(visit, info=True)
    except (RuntimeError, OSError, ValueError, KeyError, SystemError) as e:
        raise FormatError(f"{path}: damaged HDF5 structure ({e}); {fix}") from None
    if len(links) > MAX_HDF5_LINKS:
        raise FormatError(f"{path}: more than {MAX_HDF5_LINKS} HDF5 objects; {fix}")
    names = []
    for raw, kind in links:
        name = raw.decode("utf-8", "replace")
        if kind != h5l.TYPE_HARD:
            try:
                target = f.id.links.get_val(raw)
            except (RuntimeError, OSError, ValueError, KeyError, TypeError):
                target = "?"
            if kind == h5l.TYPE_SOFT:
                kind_name = f"a soft link to {target.decode('utf-8', 'replace')!r}"
            elif kind == h5l.TYPE_EXTERNAL:
                file, obj = (t.decode("utf-8", "replace") for t in target)
                kind_name = f"an external link to {file}:{obj}"
            else:
                kind_name = f"a user-defined link (type {kind})"
            raise FormatError(
                f"{path}: {name!r} is {kind_name}; rlu follows no links in a foreign file "
                f"(they can loop or point outside it): {fix}"
            )
        try:
            obj = f[raw]
        except (RuntimeError, OSError, ValueError, KeyError, TypeError) as e:
            raise FormatError(f"{path}: {name!r} cannot be opened ({e}); {fix}") from None
        if isinstance(obj, h5py.Dataset):
            _check_storage(obj, path, name, fix)
            names.append(name)
    return names


def _check_storage(obj: Any, path: Path, name: str, fix: str) -> None:
    """Refuse a dataset whose values live outside the file, or that inflates unbounded."""
    if obj.is_virtual:
        raise FormatError(
            f"{path}: dataset {name!r} is a virtual dataset (its values are in other files); "
            f"rlu reads nothing outside the file: {fix}"
        )
    dcpl = obj.id.get_create_plist()
    if dcpl.get_external_count():
        other = dcpl.get_external(0)[0].decode("utf-8", "replace")
        raise FormatError(
            f"{path}: dataset {name!r} keeps its values in external file {other!r}; rlu reads "
            f"nothing outside the file: {fix}"
        )
    for i in range(dcpl.get_nfilters()):
        code = dcpl.get_filter(i)[0]
        if code not in HDF5_FILTERS:
            raise FormatError(
                f"{path}: dataset {name!r} uses HDF5 filter {code}; rlu runs only "
                f"{', '.join(HDF5_FILTERS.values())}: {fix}"
            )
    if obj.chunks is not None:
        chunk = math.prod(obj.chunks) * obj.dtype.itemsize
        if chunk > MAX_CHUNK_BYTES:
            raise FormatError(
                f"{path}: dataset {name!r} has chunks of {chunk} bytes (shape {obj.chunks}), "
                f"more than the {MAX_CHUNK_BYTES} rlu inflates at once: {fix}"
            )


def h5_check(obj: Any, path: Path, name: str, numeric: bool = True) -> None:
    """Refuse an HDF5 dataset whose declared size the file does not store (nothing is read)."""
    import h5py

    if not isinstance(obj, h5py.Dataset):
        raise FormatError(f"{path}: {name!r} is a {type(obj).__name__}, not an array")
    dtype = obj.dtype
    if numeric and (dtype.hasobject or dtype.kind not in "biuf" or dtype.fields is not None):
        raise FormatError(
            f"{path}: dataset {name!r} holds {dtype} values; rlu imports numeric arrays only"
        )
    if dtype.kind == "O":  # variable-length strings (Minari infos): sized by their heap, not here
        return
    shape = obj.shape if obj.shape is not None else ()
    nbytes = math.prod(shape) * dtype.itemsize
    stored = obj.id.get_storage_size()
    file_size = os.path.getsize(path)
    if nbytes and (stored == 0 or stored > file_size or not _plausible(stored, nbytes)):
        raise FormatError(
            f"{path}: dataset {name!r} declares shape {shape} ({nbytes} bytes) but the file "
            f"stores {stored} bytes of it; the file is damaged or not what it claims"
        )


class H5Column(Column):
    """An HDF5 dataset (checked by :func:`h5_check`), read a hyperslab of rows at a time."""

    def __init__(self, obj: Any, path: Path, name: str, numeric: bool = True):
        h5_check(obj, path, name, numeric)
        self.obj, self.path, self.name = obj, path, name
        self.shape = tuple(int(x) for x in (obj.shape or ()))
        self.dtype = obj.dtype

    def rows(self, a: int, b: int) -> np.ndarray:
        try:
            return np.asarray(self.obj[a:b] if self.shape else self.obj[()])
        except (OSError, ValueError, TypeError, RuntimeError) as e:
            raise FormatError(f"{self.path}: dataset {self.name!r} cannot be read ({e})") from None


def h5_array(obj: Any, path: Path, name: str, max_bytes: int | None = None) -> np.ndarray:
    """One HDF5 dataset as an array, after checking that the file really stores its bytes and
    that it declares at most ``max_bytes``."""
    return H5Column(obj, path, name).read(max_bytes, str(path))


def hdf5_columns(f: Any, path: Path, want: Callable[[str], bool], what: str) -> dict[str, Column]:
    """The datasets of open file ``f`` whose names ``want`` accepts, as columns (others are
    never read)."""
    return {n: H5Column(f[n], path, n) for n in hdf5_datasets(f, path, what) if want(n)}


# --- values ----------------------------------------------------------------------------------
def real_array(v: Any, name: str, where: str) -> np.ndarray:
    """``v`` as a numeric array (bool, int or float); strings, objects and complex are refused."""
    try:
        a = np.asarray(v)
    except (ValueError, TypeError) as e:
        raise FormatError(f"{where}: {name!r} is not an array ({e})") from None
    real_dtype(a.dtype, name, where)
    return a


def real_dtype(dtype: np.dtype, name: str, where: str) -> None:
    if dtype.kind not in "biuf" or dtype.fields is not None:
        raise FormatError(
            f"{where}: {name!r} holds {dtype} values; rlu imports real numbers only "
            "(no strings, objects or complex numbers)"
        )


def rows(a: np.ndarray, name: str, where: str, n: int) -> np.ndarray:
    """``a`` with one row per step (``n`` of them)."""
    if a.ndim == 0 or len(a) != n:
        raise FormatError(
            f"{where}: {name!r} has {0 if a.ndim == 0 else len(a)} rows where the other arrays "
            f"have {n}; every array needs one row per step"
        )
    return a


def flag_array(v: Any, name: str, where: str) -> np.ndarray:
    """Booleans stored as bool, int or float: every value exactly 0 or 1 (0.5 is refused)."""
    a = real_array(v, name, where).reshape(-1)
    if a.dtype != np.bool_ and not np.isin(a, (0, 1)).all():
        bad = a[~np.isin(a, (0, 1))][0]
        raise FormatError(f"{where}: {name!r} holds {bad!r}; a flag is 0 or 1")
    return a.astype(bool)


def finite_array(v: Any, name: str, where: str, dtype: str = "float32") -> np.ndarray:
    a = real_array(v, name, where)
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        raise FormatError(f"{where}: {name!r} holds NaN or inf; rlu imports finite values only")
    return a.astype(dtype, copy=False)


def fits(a: np.ndarray, dtype: str, name: str, where: str) -> np.ndarray:
    """``a`` cast to ``dtype`` only where every value survives (300.0 does not fit uint8)."""
    a = real_array(a, name, where)
    target = np.dtype(dtype)
    if target.kind in "iu" and a.dtype.kind in "fiub" and a.size:
        if a.dtype.kind == "f" and not (np.isfinite(a) & (a == np.round(a))).all():
            raise FormatError(f"{where}: {name!r} holds non-integers; the task stores {dtype}")
        info = np.iinfo(target)
        if float(a.min()) < info.min or float(a.max()) > info.max:
            raise FormatError(
                f"{where}: {name!r} holds values outside [{info.min}, {info.max}] ({dtype})"
            )
    elif target.kind == "b" and a.dtype.kind != "b":
        return flag_array(a, name, where).reshape(a.shape)
    out = a.astype(target, copy=False)
    if target.kind == "f" and not np.isfinite(out).all():
        raise FormatError(f"{where}: {name!r} holds NaN or inf (or values beyond {dtype})")
    return out


def keyed(d: Mapping[str, Any], key: str, where: str, fix: str) -> Any:
    if key not in d:
        raise FormatError(f"{where}: no {key!r} array; {fix}")
    return d[key]


def with_final_step(seg: Segment, action: np.ndarray, reward: float) -> Segment:
    """``seg`` with its final step holding ``action`` and ``reward``: the last row of a
    truncated episode in d3rlpy's and D4RL's files (no next observation, so no transition; d3rlpy
    counts the reward in the return and the returns-to-go), kept instead of dropped. The stored
    episode return counts it too, as those libraries' returns do."""
    act = np.array(seg.action)
    act[-1] = action
    rew = np.array(seg.reward)
    rew[-1] = reward
    meta = dict(seg.metadata)
    if "episode_return" in meta:
        meta["episode_return"] = float(np.asarray(rew, np.float64).sum())
    return dataclasses.replace(seg, action=act, reward=rew, metadata=meta)


def iter_blocks(n: int, row_bytes: int) -> Iterator[tuple[int, int]]:
    """Row ranges ``[a, b)`` of about ``READ_BYTES`` each, covering ``n`` rows."""
    step = max(1, READ_BYTES // max(1, row_bytes))
    for a in range(0, n, step):
        yield a, min(n, a + step)
