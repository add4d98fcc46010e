"""Arrays out of files rlu did not write (D4RL ``.npz`` / ``.hdf5``, d3rlpy dumps), read warily.

Such files are input, and may be damaged or hostile. Every array's declared size is checked
against what the file really holds *before* it is allocated (an ``.npy`` header or an HDF5
dataset claiming 1e12 elements costs nothing), object arrays are refused without being
unpickled, and values are checked before import: numbers only (no strings, no complex), flags
exactly 0 or 1, finite rewards. Every refusal is a :class:`~rlu.types.FormatError` naming the
file, the array and the fix.
"""

from __future__ import annotations

import math
import os
import zipfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from rlu.types import FormatError, RluError, install_hint

MAX_DEFLATE_RATIO = 1032
"""The most deflate can compress (RFC 1951: a 258-byte match in 2 bits): what a compressed
member or dataset of N stored bytes may inflate to, at most 1032 N."""
_NPY_MAGIC = b"\x93NUMPY"


def _plausible(stored: int, declared: int) -> bool:
    return declared <= stored * MAX_DEFLATE_RATIO + (1 << 16)


# --- .npz ------------------------------------------------------------------------------------
def read_npz(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` file; object arrays (pickles) are refused, never unpickled."""
    path = Path(path)
    fix = "write it with numpy.savez (numeric arrays only)"
    with open(path, "rb") as fh:
        head = fh.read(6)
    if head == _NPY_MAGIC:
        raise FormatError(f"{path}: a single .npy array, not an .npz archive of arrays; {fix}")
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as e:
        raise FormatError(
            f"{path}: not an .npz archive of numeric arrays ({e}); rlu never unpickles data: {fix}"
        ) from None
    out: dict[str, np.ndarray] = {}
    with zf:
        for info in zf.infolist():
            if not info.filename.endswith(".npy"):
                continue
            key = info.filename[: -len(".npy")]
            out[key] = _npz_member(zf, info, path, key, fix)
    return out


def _npz_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, path: Path, key: str, fix: str):
    fmt = np.lib.format
    try:
        with zf.open(info) as fp:
            version = fmt.read_magic(fp)
            if version == (1, 0):
                shape, fortran, dtype = fmt.read_array_header_1_0(fp)
            else:
                shape, fortran, dtype = fmt.read_array_header_2_0(fp)
            header = fp.tell()
            if dtype.hasobject:
                raise FormatError(
                    f"{path}: array {key!r} holds Python objects, which only a pickle can load; "
                    "rlu never unpickles: save it as a numeric array"
                )
            nbytes = math.prod(shape) * dtype.itemsize
            if info.file_size != header + nbytes or not _plausible(info.compress_size, nbytes):
                raise FormatError(
                    f"{path}: array {key!r} declares shape {shape} {dtype} ({nbytes} bytes) but "
                    f"its member holds {info.file_size} bytes ({info.compress_size} stored); the "
                    f"file is damaged: {fix}"
                )
        with zf.open(info) as fp:  # from the start again: read_array parses the header itself
            return fmt.read_array(fp, allow_pickle=False)
    except FormatError:
        raise
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, RuntimeError) as e:
        raise FormatError(f"{path}: array {key!r} cannot be read ({e}); {fix}") from None


# --- HDF5 ------------------------------------------------------------------------------------
def open_hdf5(path: str | os.PathLike, what: str) -> Any:
    """An open ``h5py.File``; ``what`` names the writer for the error (d3rlpy's dump, D4RL...)."""
    try:
        import h5py
    except ImportError:
        raise RluError(f"reading HDF5 files needs h5py: {install_hint('interop')}") from None
    try:
        return h5py.File(path, "r")
    except (OSError, ValueError) as e:
        raise FormatError(f"{path}: not an HDF5 file ({e}); give {what}") from None


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


def h5_array(obj: Any, path: Path, name: str) -> np.ndarray:
    """One HDF5 dataset as an array, after checking that the file really stores its bytes."""
    h5_check(obj, path, name)
    try:
        return np.asarray(obj[()])
    except (OSError, ValueError, TypeError) as e:
        raise FormatError(f"{path}: dataset {name!r} cannot be read ({e})") from None


def read_hdf5(path: str | os.PathLike, want: Callable[[str], bool], what: str) -> dict:
    """The datasets of an HDF5 file whose names ``want`` accepts (others are never read)."""
    import h5py

    path = Path(path)
    out: dict[str, np.ndarray] = {}
    with open_hdf5(path, what) as f:
        names: list[str] = []

        def visit(name: str, obj: Any) -> None:
            if isinstance(obj, h5py.Dataset) and want(name):
                names.append(name)

        try:
            f.visititems(visit)
        except (OSError, RuntimeError, ValueError) as e:
            raise FormatError(f"{path}: damaged HDF5 structure ({e}); give {what}") from None
        for name in names:
            out[name] = h5_array(f[name], path, name)
    return out


# --- values ----------------------------------------------------------------------------------
def real_array(v: Any, name: str, where: str) -> np.ndarray:
    """``v`` as a numeric array (bool, int or float); strings, objects and complex are refused."""
    try:
        a = np.asarray(v)
    except (ValueError, TypeError) as e:
        raise FormatError(f"{where}: {name!r} is not an array ({e})") from None
    if a.dtype.kind not in "biuf":
        raise FormatError(
            f"{where}: {name!r} holds {a.dtype} values; rlu imports real numbers only "
            "(no strings, objects or complex numbers)"
        )
    return a


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
