"""rlu's own files: written atomically, opened without following planted links, read back checked.

Writing. Every file rlu writes goes through :func:`atomic_path` (:func:`write_atomic`,
:func:`write_json` for bytes and JSON; ``with atomic_path(p, suffix=True) as tmp`` for a library
that writes to a path itself: ``torch.save``, ``np.savez``, h5py, matplotlib, ffmpeg): the target
is checked first (:func:`check_target`: not a symbolic link, not a file with another hard link,
no symlinked folder between the folder the command was given and the file), a temporary with an
unpredictable name is created exclusively (``O_EXCL | O_NOFOLLOW``) beside it, synced, renamed
over the target, the folder synced. A kill leaves the old file or the new one, never half of
one. A temporary or staging folder written some other way is renamed into place by
:func:`move_into_place`, which checks the target the same way. A folder rlu hands to a library
that owns it (TensorBoard, W&B) is made by :func:`make_folder`. A file rlu opens again and
again (a lock, a log it appends to, a cache entry, a partial download) goes through
:func:`open_private`: never a symbolic link, a hard link or a non-file.
``tests/hostile/test_writers_walk.py`` walks the package's syntax trees and fails on a write
site outside this module (``open`` in a write mode, ``savefig``, ``torch.save``, ...) that
neither writes what these functions produced nor is listed there with its reason, and on any
rename outside this module (``os.replace``, ``os.rename``, ``Path.rename``, ``Path.replace``).

Reading. A JSON file rlu reads is checked at the boundary, once, against a *shape* of its own
(:class:`Shape`: types, ranges, sizes, nesting depth) before any value is used; a shape is written
as data (``Record({"step": Int(min=0)})``) or derived from a frozen config dataclass
(:func:`shape_of`: type hints, plus ``min`` / ``max`` / ``choices`` in a field's metadata). A bad
file is a :class:`rlu.types.FormatError` naming the file, the field and the fix. The same
shapes check a config dataclass deriving from :class:`Checked` whenever one is made
(:func:`check_fields`: a :class:`rlu.types.ConfigError`), so a value is held to one set of
bounds whether it came from a file, an override or Python. The file must be
a regular file no larger than ``max_bytes``: a FIFO, a device or a runaway file is refused before
it is read.

Outputs. :func:`check_output` is the one rule for a folder a command may replace: never an input
or a folder holding an input, and never an existing folder that is not an rlu output of the
same kind (its marker file says which).

Standard library only.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import functools
import json
import math
import numbers
import os
import secrets
import stat
import types
import typing
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from rlu.types import ConfigError, FormatError, RluError

MAX_JSON_BYTES = 64 << 20
"""Largest JSON file rlu reads for its own state (a results.jsonl of 100k runs is ~50 MB)."""
MAX_DEPTH = 32
"""Deepest nesting a JSON value rlu reads may have (its own files nest 5 levels or fewer)."""
MAX_ITEMS = 1_000_000
"""Most items in one JSON list or object rlu reads."""
MAX_STR = 1 << 20
"""Longest string in a JSON file rlu reads."""
MAX_STEPS = 10**9
"""Most learner steps a run may be given (the paper's longest budget is 2M; 1e9 is weeks on a
GPU): a larger number is a mistake, not a budget."""
MAX_BATCH = 1 << 20
"""Most rows in one batch a config may ask for (the paper's largest is 1,024)."""
MAX_WIDTH = 1 << 16
"""Widest layer a config may ask for (the paper's widest is 1,024 units)."""
MAX_LAYERS = 64
"""Most layers in one network a config may ask for (the paper's deepest MLP has 8)."""
MAX_LR = 10.0
"""Largest learning rate a config may ask for (the paper's largest is 1e-3); every learning
rate is also > 0."""


# --- writing --------------------------------------------------------------------------------
def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def open_new(path: str | os.PathLike, mode: int = 0o644) -> int:
    """A new file's descriptor, write-only: ``O_CREAT | O_EXCL | O_NOFOLLOW``, so an existing
    file or a planted symlink at ``path`` is refused (``FileExistsError``), never followed."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
    return os.open(path, flags, mode)


def open_private(path: str | os.PathLike, flags: int, what: str = "file") -> int:
    """``os.open`` of a file rlu keeps reopening (a lock, a cache entry, a partial download),
    never through a link: a symbolic link (``O_NOFOLLOW``), anything but a regular file, or a file
    with a second hard link is refused with an :class:`~rlu.types.RluError` naming it. ``O_TRUNC``
    is applied only after these checks, so a planted hard link is never truncated either. Other
    ``OSError`` (a missing file, permissions) propagate."""
    trunc = flags & os.O_TRUNC
    try:
        fd = os.open(path, (flags & ~os.O_TRUNC) | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise RluError(
                f"{path}: the {what} is a symbolic link; rlu does not write through it (nor read "
                "its own files through one): remove it and run again"
            ) from None
        raise
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode) or st.st_nlink > 1:
        os.close(fd)
        raise RluError(
            f"{path}: the {what} is not a plain file of its own (a hard link or a device); "
            "remove it and run again"
        )
    if trunc:
        os.ftruncate(fd, 0)
    return fd


TEMPORARY = ".tmp"
"""Every temporary rlu writes has a name ``.<name>.<random>.tmp`` (plus the target's suffix
when a library needs it: ``.video.<random>.tmp.mp4``); :func:`clear_temporaries` finds them."""


def _refuse(path: Path, why: str) -> RluError:
    return RluError(
        f"{path}: {why}; rlu does not write through it: remove it or choose another path"
    )


def check_target(path: str | os.PathLike, root: str | os.PathLike | None = None) -> Path:
    """Refuse to write ``path`` (an :class:`~rlu.types.RluError` naming it) when it is a symbolic
    link, exists and is not a regular file, or is a regular file with another hard link; or when
    a folder between ``root`` (the folder the command was given, itself included) and ``path``
    is a symbolic link, so the write would land outside where it was named. Without ``root``,
    ``path``'s own folder is checked. Folders above ``root`` are the user's (a symlinked home is
    fine). Returns ``path``."""
    path = Path(path)
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        st = None
    if st is not None:
        if stat.S_ISLNK(st.st_mode):
            raise _refuse(path, "is a symbolic link")
        if not stat.S_ISREG(st.st_mode):
            raise _refuse(path, "exists and is not a plain file (a folder, FIFO or device)")
        if st.st_nlink > 1:
            raise _refuse(path, "has another hard link (writing it would change that file too)")
    _check_folders(path, root)
    return path


def _check_folders(path: Path, root: str | os.PathLike | None) -> None:
    """Refuse ``path`` when it lies outside ``root`` or a folder between ``root`` (itself
    included; default: ``path``'s own folder) and ``path`` is a symbolic link."""
    parent = Path(os.path.abspath(path.parent))
    top = parent if root is None else Path(os.path.abspath(root))
    if not _inside(parent, top):
        raise RluError(f"{path}: lies outside the output folder {top}; choose a path inside it")
    folder = parent
    while True:
        if folder.is_symlink():
            raise _refuse(folder, "is a symbolic link (the write would land where it points)")
        if folder == top:
            break
        folder = folder.parent


def move_into_place(
    source: str | os.PathLike, target: str | os.PathLike, root: str | os.PathLike | None = None
) -> Path:
    """Rename ``source`` (a temporary file or staging folder rlu wrote) onto ``target``, then
    sync ``target``'s folder: the one rename into place outside :func:`atomic_path`. The target
    is checked first: a file's as :func:`check_target` does (with ``root``); a folder's must not
    be a symbolic link or a non-folder, and no folder between ``root`` and it may be a link. A
    planted link at ``source`` is refused too. An existing non-empty target folder makes the
    rename fail (``OSError`` ENOTEMPTY or EEXIST, for the caller: another writer finished
    first). Returns ``target``."""
    source, target = Path(source), Path(target)
    st = os.lstat(source)
    if stat.S_ISLNK(st.st_mode):
        raise _refuse(source, "is a symbolic link, not the temporary rlu wrote")
    if stat.S_ISDIR(st.st_mode):
        try:
            mode = os.lstat(target).st_mode
        except FileNotFoundError:
            mode = None
        if mode is not None and stat.S_ISLNK(mode):
            raise _refuse(target, "is a symbolic link")
        if mode is not None and not stat.S_ISDIR(mode):
            raise _refuse(target, "exists and is not a folder")
        _check_folders(target, root)
    else:
        check_target(target, root)
    os.replace(source, target)
    _fsync_dir(target.parent)
    return target


def check_targets(folder: str | os.PathLike, patterns: Sequence[str]) -> None:
    """:func:`check_target` (root ``folder``) of every entry of ``folder`` a command is about to
    replace (``patterns``: names or globs relative to it, ``"figures/*.png"``), before the first
    one is written, so a link planted at the last of them does not leave the others replaced."""
    folder = Path(folder)
    if not folder.is_dir() or folder.is_symlink():
        return  # check_output / make_folder say what is wrong with the folder itself
    for pattern in patterns:
        head = pattern.rpartition("/")[0]
        if head:
            check_target(folder / head / ".probe", folder)  # a linked subfolder
        matches = folder.glob(pattern) if any(c in pattern for c in "*?[") else [folder / pattern]
        for path in matches:
            check_target(path, folder)


def make_folder(path: str | os.PathLike, root: str | os.PathLike | None = None) -> Path:
    """Create folder ``path`` (and its parents) for rlu's output, or accept it if it is already a
    real folder; a symbolic link there, or between ``root`` and ``path``, is refused (an
    :class:`~rlu.types.RluError`). Loggers that own a folder (TensorBoard, W&B) get one made
    here. Returns ``path``."""
    path = Path(path)
    if path.is_symlink():
        raise _refuse(path, "is a symbolic link, not a folder rlu made")
    if path.exists() and not path.is_dir():
        raise RluError(f"{path}: exists and is not a folder; choose another path")
    path.mkdir(parents=True, exist_ok=True)
    check_target(path / ".probe", root if root is not None else path)
    return path


def clear_temporaries(folder: str | os.PathLike) -> None:
    """Remove the temporaries a killed writer left under ``folder`` (links removed, never
    followed)."""
    for tmp in Path(folder).rglob(f".*{TEMPORARY}*"):
        if tmp.is_symlink() or tmp.is_file():
            name = tmp.name
            if name.endswith(TEMPORARY) or f"{TEMPORARY}." in name:
                tmp.unlink()


@contextlib.contextmanager
def atomic_path(
    path: str | os.PathLike, suffix: bool = False, root: str | os.PathLike | None = None
) -> Iterator[Path]:
    """``with atomic_path(p) as tmp: write tmp`` -> ``tmp`` synced and renamed to ``p`` when the
    block succeeds, removed when it fails. The target is checked first (:func:`check_target`,
    with ``root``); ``tmp`` is a new file with an unpredictable name in ``p``'s folder, created
    exclusively without following links, and exists (empty) when the block starts; the writer
    may replace its content. ``suffix=True`` ends ``tmp``'s name with ``p``'s suffix, for
    libraries that choose a format by it (``np.savez`` adds ``.npz``, ffmpeg reads ``.mp4``)."""
    path = check_target(path, root)
    end = path.suffix if suffix else ""
    base = path.stem if suffix else path.name
    while True:
        tmp = path.with_name(f".{base}.{secrets.token_hex(6)}{TEMPORARY}{end}")
        try:
            os.close(open_new(tmp))
            break
        except FileExistsError:
            continue  # 48 random bits taken: draw again
        except OSError as e:
            raise RluError(
                f"{tmp}: cannot be created ({e.strerror}); check {path.parent}"
            ) from None
    try:
        yield tmp
        fd = os.open(tmp, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
        try:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                raise _refuse(tmp, "was replaced by something that is not a plain file")
            os.fsync(fd)
        finally:
            os.close(fd)
        check_target(path, root)  # again: a link planted while the file was written
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    _fsync_dir(path.parent)


def write_atomic(
    path: str | os.PathLike, data: str | bytes, root: str | os.PathLike | None = None
) -> None:
    """Write ``data`` (text as UTF-8) to ``path`` atomically (see :func:`atomic_path`)."""
    raw = data.encode() if isinstance(data, str) else data
    with atomic_path(path, root=root) as tmp:
        fd = os.open(tmp, os.O_WRONLY | os.O_TRUNC | os.O_NOFOLLOW | os.O_CLOEXEC)
        try:
            view = memoryview(raw)
            while view:
                view = view[os.write(fd, view) :]
        finally:
            os.close(fd)


def write_json(
    path: str | os.PathLike,
    data: Any,
    indent: int | None = 2,
    root: str | os.PathLike | None = None,
) -> None:
    """``data`` as JSON, atomically; NaN and infinities are refused (JSON has none: write None
    for a value that is not a number)."""
    try:
        text = json.dumps(data, indent=indent, allow_nan=False)
    except ValueError:
        raise RluError(f"{path}: a value to write is NaN or infinite, which JSON cannot hold "
                       "(a bug in rlu: report it)") from None  # fmt: skip
    write_atomic(path, text + "\n", root)


# --- shapes ---------------------------------------------------------------------------------
class Bad(Exception):
    """A value that does not fit its shape: where (a field path) and what is wrong."""

    def __init__(self, where: str, what: str):
        super().__init__(where, what)
        self.where, self.what = where, what


def _name(value: Any) -> str:
    names = {
        bool: "a boolean",
        int: "an integer",
        float: "a number",
        str: "a string",
        list: "a list",
        dict: "an object",
        type(None): "null",
    }
    return names.get(type(value), type(value).__name__)


class Shape:
    """What a JSON value must look like; ``check(value, where)`` returns it (lists of a tuple
    shape as tuples) or raises :class:`Bad`."""

    def check(self, value: Any, where: str) -> Any:
        raise NotImplementedError

    def describe(self) -> str:
        raise NotImplementedError


@dataclasses.dataclass(frozen=True)
class Int(Shape):
    min: int | None = None
    max: int | None = None

    def check(self, value: Any, where: str) -> Any:
        if isinstance(value, float) and value.is_integer() and abs(value) < 2**53:
            value = int(value)  # 1e3 written by hand
        elif isinstance(value, numbers.Integral) and not isinstance(value, bool | int):
            value = int(value)  # a numpy integer, from code
        if isinstance(value, bool) or not isinstance(value, int):
            raise Bad(where, f"is {_name(value)} ({_short(value)}); expected {self.describe()}")
        if (self.min is not None and value < self.min) or (
            self.max is not None and value > self.max
        ):
            raise Bad(where, f"is {value}; expected {self.describe()}")
        return value

    def describe(self) -> str:
        return "an integer" + _range(self.min, self.max)


@dataclasses.dataclass(frozen=True)
class Float(Shape):
    """A finite number in [min, max]; ``gt`` / ``lt``: strictly above / below it (a learning
    rate > 0, Adam's betas < 1)."""

    min: float | None = None
    max: float | None = None
    gt: float | None = None
    lt: float | None = None

    def check(self, value: Any, where: str) -> Any:
        if isinstance(value, numbers.Real) and not isinstance(value, bool | int | float):
            value = float(value)  # a numpy float32, from code
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise Bad(where, f"is {_name(value)} ({_short(value)}); expected {self.describe()}")
        if not math.isfinite(value):
            finite = self.describe().replace("a number", "a finite number", 1)
            raise Bad(where, f"is {value}; expected {finite}")
        if (
            (self.min is not None and value < self.min)
            or (self.max is not None and value > self.max)
            or (self.gt is not None and value <= self.gt)
            or (self.lt is not None and value >= self.lt)
        ):
            raise Bad(where, f"is {value}; expected {self.describe()}")
        return value

    def describe(self) -> str:
        if self.gt is None and self.lt is None:
            return "a number" + _range(self.min, self.max)
        parts = [
            f"{op} {bound}"
            for op, bound in (("> ", self.gt), (">=", self.min), ("<", self.lt), ("<=", self.max))
            if bound is not None
        ]
        return "a number " + " and ".join(p.replace("  ", " ") for p in parts)


@dataclasses.dataclass(frozen=True)
class Str(Shape):
    choices: tuple[str, ...] | None = None
    max_len: int = 4096

    def check(self, value: Any, where: str) -> Any:
        if not isinstance(value, str):
            raise Bad(where, f"is {_name(value)} ({_short(value)}); expected {self.describe()}")
        if len(value) > self.max_len:
            raise Bad(where, f"is a string of {len(value)} characters; at most {self.max_len}")
        if self.choices is not None and value not in self.choices:
            raise Bad(where, f"is {value!r}; expected {self.describe()}")
        return value

    def describe(self) -> str:
        if self.choices is not None:
            return "one of " + ", ".join(repr(c) for c in self.choices)
        return "a string"


@dataclasses.dataclass(frozen=True)
class Bool(Shape):
    def check(self, value: Any, where: str) -> Any:
        if not isinstance(value, bool):
            raise Bad(where, f"is {_name(value)} ({_short(value)}); expected true or false")
        return value

    def describe(self) -> str:
        return "true or false"


@dataclasses.dataclass(frozen=True)
class Optional(Shape):
    inner: Shape

    def check(self, value: Any, where: str) -> Any:
        return None if value is None else self.inner.check(value, where)

    def describe(self) -> str:
        return f"{self.inner.describe()} or null"


@dataclasses.dataclass(frozen=True)
class ListOf(Shape):
    item: Shape
    max_len: int = MAX_ITEMS
    min_len: int = 0
    as_tuple: bool = False

    def check(self, value: Any, where: str) -> Any:
        if not isinstance(value, list | tuple):
            raise Bad(where, f"is {_name(value)} ({_short(value)}); expected {self.describe()}")
        if not self.min_len <= len(value) <= self.max_len:
            want = (
                f"exactly {self.min_len}"
                if self.min_len == self.max_len
                else f"{self.min_len} to {self.max_len}"
            )
            raise Bad(where, f"has {len(value)} items; expected {want}")
        out = [self.item.check(v, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(out) if self.as_tuple else out

    def describe(self) -> str:
        return f"a list of {self.item.describe()}"


@dataclasses.dataclass(frozen=True)
class MapOf(Shape):
    """An object with any string keys, every value of one shape."""

    value: Shape
    max_len: int = MAX_ITEMS

    def check(self, value: Any, where: str) -> Any:
        if not isinstance(value, Mapping):
            raise Bad(where, f"is {_name(value)} ({_short(value)}); expected an object")
        if len(value) > self.max_len:
            raise Bad(where, f"has {len(value)} keys; at most {self.max_len}")
        return {
            str(k): self.value.check(v, f"{where}.{k}" if where else str(k))
            for k, v in value.items()
        }

    def describe(self) -> str:
        return f"an object of {self.value.describe()}"


@dataclasses.dataclass(frozen=True)
class Record(Shape):
    """An object with known fields: ``required`` must be present, ``optional`` may be;
    ``extra=False`` refuses any other key."""

    required: Mapping[str, Shape]
    optional: Mapping[str, Shape] = dataclasses.field(default_factory=dict)
    extra: bool = True

    def check(self, value: Any, where: str) -> Any:
        if not isinstance(value, Mapping):
            raise Bad(
                where,
                f"is {_name(value)} ({_short(value)}); expected an object with "
                f"{', '.join(self.required) or 'fields'}",
            )
        out = dict(value) if self.extra else {}
        for key, shape in self.required.items():
            if key not in value:
                raise Bad(_join(where, key), "is missing")
            out[key] = shape.check(value[key], _join(where, key))
        for key, shape in self.optional.items():
            if key in value:
                out[key] = shape.check(value[key], _join(where, key))
        if not self.extra:
            unknown = sorted(set(value) - set(self.required) - set(self.optional))
            if unknown:
                raise Bad(_join(where, str(unknown[0])), "is not a known field")
        return out

    def describe(self) -> str:
        return "an object"


@dataclasses.dataclass(frozen=True)
class AnyJSON(Shape):
    """Any JSON value no deeper than ``depth`` and with no string longer than ``max_str``."""

    depth: int = MAX_DEPTH
    max_str: int = MAX_STR
    finite: bool = True

    def check(self, value: Any, where: str) -> Any:
        stack = [(value, 0)]
        while stack:
            v, d = stack.pop()
            if d > self.depth:
                raise Bad(where, f"nests deeper than {self.depth} levels")
            if isinstance(v, Mapping):
                stack.extend((x, d + 1) for x in v.values())
            elif isinstance(v, list | tuple):
                stack.extend((x, d + 1) for x in v)
            elif isinstance(v, str) and len(v) > self.max_str:
                raise Bad(where, f"holds a string of {len(v)} characters")
            elif self.finite and isinstance(v, float) and not math.isfinite(v):
                raise Bad(where, f"holds {v}; JSON numbers must be finite")
        return value

    def describe(self) -> str:
        return "a JSON value"


def _join(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


def _range(lo: Any, hi: Any) -> str:
    if lo is not None and hi is not None:
        return f" from {lo} to {hi}"
    if lo is not None:
        return f" >= {lo}"
    if hi is not None:
        return f" <= {hi}"
    return ""


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


# --- shapes of config dataclasses -----------------------------------------------------------
def bounds(
    min: float | None = None,
    max: float | None = None,
    *,
    gt: float | None = None,
    lt: float | None = None,
    min_len: int | None = None,
    max_len: int | None = None,
    **more: Any,
) -> dict[str, Any]:
    """A field's metadata for :func:`shape_of`, :class:`Checked` and the CLI: ``field(default=1,
    metadata=bounds(min=1, max=64))``. ``gt`` / ``lt``: strictly above / below (a learning rate:
    ``gt=0``); on a tuple field ``min`` / ``max`` / ``gt`` / ``lt`` bound each item and
    ``min_len`` / ``max_len`` its length."""
    given = {
        "min": min,
        "max": max,
        "gt": gt,
        "lt": lt,
        "min_len": min_len,
        "max_len": max_len,
        **more,
    }
    return {k: v for k, v in given.items() if v is not None}


# The bounds most config fields share, named once (``field(default=3e-4, metadata=LEARNING_RATE)``).
LEARNING_RATE = bounds(gt=0.0, max=MAX_LR)
"""A learning rate: > 0 and at most ``MAX_LR``."""
FRACTION = bounds(min=0.0, max=1.0)
"""A number in [0, 1]: a discount, a Polyak rate, a probability."""
STEPS = bounds(min=1, max=MAX_STEPS)
"""A count of learner steps."""
WIDTH = bounds(min=1, max=MAX_WIDTH)
"""A layer's width (units, channels, embedding size)."""
LAYERS = bounds(min=1, max=MAX_WIDTH, min_len=1, max_len=MAX_LAYERS)
"""A network's hidden sizes: one to ``MAX_LAYERS`` widths."""
BATCH = bounds(min=1, max=MAX_BATCH)
"""Rows (or windows) in one batch."""


def _shape_of_hint(hint: Any, meta: Mapping[str, Any]) -> Shape:
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        rest = [a for a in args if a is not type(None)]
        inner = _shape_of_hint(rest[0], meta) if len(rest) == 1 else AnyJSON()
        return Optional(inner) if type(None) in args else inner
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):  # a hint is a class
        return shape_of(hint)
    if hint is bool:
        return Bool()
    if hint is int:
        return Int(meta.get("min"), meta.get("max"))
    if hint is float:
        return Float(meta.get("min"), meta.get("max"), meta.get("gt"), meta.get("lt"))
    if hint is str:
        choices = meta.get("choices")
        return Str(tuple(choices) if choices is not None else None)
    if origin is typing.Literal:
        return Str(tuple(args))
    if origin in (tuple, list, Sequence, typing.Sequence):
        item = args[0] if args else Any
        fixed = origin is tuple and bool(args) and args[-1] is not Ellipsis
        if fixed and len(set(args)) > 1:
            return AnyJSON()  # a tuple of mixed items: no config field has one
        lo = len(args) if fixed else meta.get("min_len", 0)
        hi = len(args) if fixed else meta.get("max_len", MAX_ITEMS)
        shape = AnyJSON() if item is Any else _shape_of_hint(item, meta)
        return ListOf(shape, max_len=hi, min_len=lo, as_tuple=origin is tuple)
    if origin in (dict, Mapping, typing.Mapping):
        value = args[1] if len(args) == 2 else Any
        return MapOf(AnyJSON() if value is Any else _shape_of_hint(value, {}))
    return AnyJSON()


def field_shape(cls: type, name: str) -> Shape:
    """The shape of one field of config dataclass ``cls`` (its hint and metadata)."""
    hints = typing.get_type_hints(cls)
    meta = next(f.metadata for f in dataclasses.fields(cls) if f.name == name)
    return _shape_of_hint(hints[name], meta)


def shape_of(cls: type) -> Record:
    """The shape of a config dataclass's JSON form (``dataclasses.asdict``): every field,
    typed by its hint, ranged by its metadata (:func:`bounds`), no unknown keys."""
    hints = typing.get_type_hints(cls)
    required: dict[str, Shape] = {}
    optional: dict[str, Shape] = {}
    for f in dataclasses.fields(cls):
        shape = _shape_of_hint(hints[f.name], f.metadata)
        has_default = (
            f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING
        )
        (optional if has_default else required)[f.name] = shape
    return Record(required, optional, extra=False)


@functools.cache
def _field_checks(cls: type) -> tuple[tuple[str, Shape | type, bool], ...]:
    """Per field of dataclass ``cls``: (name, its shape, False), or for a composed dataclass
    (name, its class, whether None is allowed); derived once per class."""
    hints = typing.get_type_hints(cls)
    out: list[tuple[str, Shape | type, bool]] = []
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        args = typing.get_args(hint)
        union = typing.get_origin(hint) in (typing.Union, types.UnionType)
        rest = [a for a in args if a is not type(None)] if union else [hint]
        if len(rest) == 1 and isinstance(rest[0], type) and dataclasses.is_dataclass(rest[0]):
            out.append((f.name, rest[0], union))
        else:
            out.append((f.name, _shape_of_hint(hint, f.metadata), False))
    return tuple(out)


def check_fields(config: Any) -> None:
    """Check every field of config dataclass instance ``config`` against its declared type and
    its :func:`bounds` (the shapes :func:`shape_of` reads files with): a
    :class:`rlu.types.ConfigError` names the config, the field, the value and the bound. A
    whole number given as a float (or a numpy integer) becomes an int, a numpy float a float, a
    list for a tuple field a tuple; a composed
    dataclass must be an instance of its class (which checked itself)."""
    cls: type = type(config)
    for name, check, optional in _field_checks(cls):
        value = getattr(config, name)
        if isinstance(check, type):
            if not (isinstance(value, check) or (optional and value is None)):
                raise ConfigError(
                    f"{cls.__name__} field {name!r} is {_name(value)} ({_short(value)}); "
                    f"expected a {check.__name__}"
                )
            continue
        try:
            out = check.check(value, name)
        except Bad as e:
            raise ConfigError(f"{cls.__name__} field {e.where!r} {e.what}") from None
        if type(out) is not type(value) and isinstance(out, tuple | int | float):
            object.__setattr__(config, name, out)  # 1e3 -> 1000, [256, 256] -> (256, 256)


class Checked:
    """Base of a frozen config dataclass whose every field is checked when it is made (from
    Python, a file, an override, ``dataclasses.replace``): :func:`check_fields`. A subclass with
    its own ``__post_init__`` calls ``super().__post_init__()`` first."""

    __slots__ = ()

    def __post_init__(self) -> None:
        check_fields(self)


def check_value(shape: Shape, value: Any, what: str, fix: str) -> Any:
    """``shape.check`` with a :class:`Bad` turned into a FormatError naming ``what`` (a file),
    the field and ``fix``."""
    try:
        return shape.check(value, "")
    except Bad as e:
        if not e.where:  # the value as a whole
            raise FormatError(f"{what} {e.what}; {fix}") from None
        raise FormatError(f"{what}: field '{e.where}' {e.what}; {fix}") from None


# --- reading --------------------------------------------------------------------------------
def read_bytes(path: str | os.PathLike, max_bytes: int, fix: str) -> bytes:
    """A regular file's bytes, at most ``max_bytes`` (a FIFO, a device or a larger file is a
    FormatError naming it and ``fix``)."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC | os.O_NONBLOCK)
    except FileNotFoundError:
        raise RluError(f"{path} is missing; {fix}") from None
    except OSError as e:
        raise RluError(f"{path}: cannot be read ({e.strerror}); {fix}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise FormatError(f"{path}: not a regular file; {fix}")
        if st.st_size > max_bytes:
            raise FormatError(
                f"{path}: {st.st_size:,} bytes, more than the {max_bytes:,} such a file may hold; "
                f"{fix}"
            )
        chunks, left = [], max_bytes + 1
        while left > 0:
            chunk = os.read(fd, min(left, 1 << 20))
            if not chunk:
                break
            chunks.append(chunk)
            left -= len(chunk)
        if left <= 0:
            raise FormatError(f"{path}: grew past {max_bytes:,} bytes while read; {fix}")
        return b"".join(chunks)
    except OSError as e:
        raise RluError(f"{path}: cannot be read ({e.strerror}); {fix}") from None
    finally:
        os.close(fd)


def parse_json(text: str | bytes, what: str, fix: str, allow_nan: bool = False) -> Any:
    """JSON text -> value; malformed or too deep JSON is a FormatError, and so are NaN and
    Infinity unless ``allow_nan`` (a diverged run logs NaN losses)."""
    try:
        if allow_nan:
            value = json.loads(text)
        else:
            value = json.loads(text, parse_constant=_refuse_constant)
    except RecursionError:
        raise FormatError(f"{what}: JSON nested too deep; {fix}") from None
    except (ValueError, UnicodeDecodeError) as e:
        raise FormatError(f"{what}: not valid JSON ({type(e).__name__}: {e}); {fix}") from None
    return value


def _refuse_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a JSON number")


def read_json(
    path: str | os.PathLike,
    shape: Shape | None = None,
    fix: str = "restore it or rerun the command that wrote it",
    max_bytes: int = MAX_JSON_BYTES,
) -> Any:
    """A JSON file checked against ``shape`` (default: any JSON of bounded depth)."""
    raw = read_bytes(path, max_bytes, fix)
    value = parse_json(raw, str(path), fix)
    return check_value(shape or AnyJSON(), value, str(path), fix)


def read_jsonl(
    path: str | os.PathLike,
    shape: Shape | None = None,
    fix: str = "restore it or rerun the command that wrote it",
    torn: str = "drop",
    max_bytes: int = MAX_JSON_BYTES,
    allow_nan: bool = False,
) -> list[Any]:
    """The records of a JSON-lines file, each checked against ``shape``. A line that is not
    JSON: ``torn="drop"`` skips it when it is the last line (a kill mid-append) and refuses it
    elsewhere; ``torn="refuse"`` refuses every such line. A missing file has no records."""
    if not Path(path).exists():
        return []
    lines = read_bytes(path, max_bytes, fix).decode("utf-8", "replace").splitlines()
    out = []
    for i, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            value = parse_json(line, f"{path}: line {i}", fix, allow_nan)
        except FormatError:
            if torn == "drop" and i == len(lines):
                continue
            raise
        out.append(check_value(shape or AnyJSON(), value, f"{path}: line {i}", fix))
    return out


# --- outputs --------------------------------------------------------------------------------
def _inside(a: Path, b: Path) -> bool:
    return a == b or b in a.parents


def check_output(
    out: str | os.PathLike,
    inputs: Sequence[str | os.PathLike] = (),
    marker: str | None = None,
    what: str = "output folder",
    flag: str = "--out",
) -> Path:
    """Refuse an output folder a command would replace or write into when it is, holds or lies
    inside one of ``inputs``, or when it exists, is not empty and lacks ``marker`` (the file every
    output of this kind holds; None: an existing non-empty folder is refused). Call it before
    anything is touched. Returns ``out``."""
    if not str(out).strip():
        raise RluError(f"{flag} is empty; give the {what}'s path")
    out = Path(out)
    real = Path(os.path.realpath(out))
    for item in inputs:
        src = Path(os.path.realpath(item))
        if _inside(real, src) or _inside(src, real):
            raise RluError(
                f"{flag} {out} is or contains the input {item}; writing there could destroy it: "
                f"choose an {what} outside it"
            )
    if out.is_symlink() or (out.exists() and not out.is_dir()):
        raise RluError(f"{flag} {out} exists and is not a folder; choose another {what}")
    if out.is_dir() and any(out.iterdir()) and (marker is None or not (out / marker).is_file()):
        kind = f" (it has no {marker})" if marker else ""
        raise RluError(
            f"{flag} {out} exists and is not an rlu {what}{kind}; rlu replaces only its own "
            f"outputs: choose a new {flag} or empty that folder yourself"
        )
    return out


def check_output_file(
    out: str | os.PathLike,
    inputs: Sequence[str | os.PathLike] = (),
    overwrite: bool = False,
    ours: typing.Callable[[Path], bool] | None = None,
    what: str = "output file",
    flag: str = "-o",
) -> Path:
    """Refuse an output file a command would write before any work: an empty name; a file
    that is, or lies inside, one of ``inputs``; an existing file without ``overwrite``, or with
    it when ``ours(path)`` says rlu did not write it (a file of the same format that some other
    tool wrote is never replaced); a link or anything :func:`check_target` refuses. Returns
    ``out``."""
    if not str(out).strip():
        raise RluError(f"{flag} is empty; give the {what}'s path")
    out = Path(out)
    real = Path(os.path.realpath(out))
    for item in inputs:
        src = Path(os.path.realpath(item))
        if _inside(real, src):
            raise RluError(
                f"{flag} {out} is or lies inside the input {item}; writing there could destroy "
                f"it: choose an {what} outside it"
            )
    check_target(out)
    if os.path.lexists(out):
        if not overwrite:
            raise RluError(
                f"{flag} {out} exists; pass --overwrite to replace it, or choose another {what}"
            )
        if ours is not None and not ours(out):
            raise RluError(
                f"{flag} {out} exists and was not written by rlu; rlu replaces only its own "
                f"outputs, even with --overwrite: choose another {what} or remove it yourself"
            )
    return out


@contextlib.contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Hold Ctrl-C (SIGINT) for the duration of a block that must not be cut (closing an HDF5
    file: an interrupt inside h5py's close is swallowed as "Exception ignored", and the command
    would go on and exit 0), then raise it at the block's end. Main thread only (elsewhere the
    block runs as it is)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if caught:
        raise KeyboardInterrupt
