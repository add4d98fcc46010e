"""Where every registered task's release files live: object names, shard counts, URLs.

Built on ``TaskSpec.release`` (rlu.tasks), which carries each family's path pattern and its
per-dataset shard counts; this module binds the dataset (Atari run, RWRL challenge and size),
expands ``-%05d-of-%05d`` names, and finds already-downloaded shards under a bucket-shaped root.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from dataclasses import dataclass

from rlu.domains import DOMAINS
from rlu.tasks import (
    BASE_URL,
    RWRL_DATASETS,
    ReleaseDataset,
    TaskSpec,
    resolve_task,
)
from rlu.types import RluError

SHARD_RE = re.compile(r"-(\d{5})-of-(\d{5})$")


@dataclass(frozen=True)
class ReleaseSelection:
    """One dataset of one family for one task: its objects in the bucket."""

    task: TaskSpec
    release: ReleaseDataset
    binding: str
    objects: tuple[str, ...]

    @property
    def family(self) -> str:
        return self.release.family

    @property
    def num_shards(self) -> int:
        return self.release.shards[self.binding]

    def urls(self, base_url: str | None = None) -> list[str]:
        return [object_url(o, base_url) for o in self.objects]


def object_url(obj: str, base_url: str | None = None) -> str:
    return f"{(base_url or BASE_URL).rstrip('/')}/{obj}"


UNKNOWN_SHARD_BYTES = 16 << 30  # a name outside the release's families: no shard is larger


def shard_limit(obj: str) -> int:
    """The most bytes a file of ``obj`` may have: its family's ``max_shard_bytes`` (the top
    folder of the name), :data:`UNKNOWN_SHARD_BYTES` for a name of no known family."""
    from rlu.data.release.families import FAMILIES

    fam = FAMILIES.get(obj.split("/", 1)[0])
    return fam.max_shard_bytes if fam is not None else UNKNOWN_SHARD_BYTES


def dataset_binding(
    task: TaskSpec,
    run: str | int | None = None,
    challenge: str | None = None,
    size: str | None = None,
) -> str:
    """The key of ``ReleaseDataset.shards`` for a task's dataset (``run_1``, ``none/large``, '')."""
    kind = DOMAINS[task.domain].datasets
    if kind == "runs":
        r = run if run is not None else 1
        r = f"run_{r}" if not str(r).startswith("run_") else str(r)
        if r not in task.datasets:
            raise RluError(f"{task.id}: unknown run {run!r}; use one of {', '.join(task.datasets)}")
        return r
    if kind == "challenge_size":
        b = f"{challenge or 'none'}/{size or 'large'}"
        if b not in RWRL_DATASETS:
            raise RluError(
                f"{task.id}: no released dataset for challenge={challenge!r} size={size!r}; "
                f"released: {', '.join(RWRL_DATASETS)} (challenge/size)"
            )
        return b
    if kind in ("noise_run", "run_names"):  # bsuite's 0.1/3, DMLab's training_0
        b = str(run) if run is not None else task.datasets[0]
        if b not in task.datasets or challenge is not None or size is not None:
            some = task.datasets
            named = ", ".join(some) if len(some) <= 12 else f"{', '.join(some[:3])}, ... {some[-1]}"
            form = "NOISE/RUN" if kind == "noise_run" else "RUN"
            raise RluError(
                f"{task.id}: no released dataset run={run!r}; give --run {form}, one of {named}"
            )
        return b
    if run is not None or challenge is not None or size is not None:
        raise RluError(f"{task.id} has one dataset; drop --run/--challenge/--size")
    return ""


def parse_shards(spec: str | Sequence[int] | None, n: int) -> list[int]:
    """``"0-3,7"`` / [0, 7] / None (all) -> sorted shard indices, each checked against ``n``."""
    if spec is None:
        return list(range(n))
    out: set[int] = set()
    items = spec.split(",") if isinstance(spec, str) else [str(i) for i in spec]
    for item in items:
        item = item.strip()
        if not item:
            continue
        try:
            if "-" in item:
                a, b = item.split("-", 1)
                out.update(range(int(a), int(b) + 1))
            else:
                out.add(int(item))
        except ValueError:
            raise RluError(f"bad shard selection {item!r}; use e.g. 0-3,7") from None
    bad = sorted(i for i in out if not 0 <= i < n)
    if bad:
        raise RluError(f"shard indices {bad} are out of range: this dataset has {n} (0..{n - 1})")
    return sorted(out)


def select(
    task_id: str,
    family: str | None = None,
    run: str | int | None = None,
    challenge: str | None = None,
    size: str | None = None,
    shards: str | Sequence[int] | None = None,
) -> ReleaseSelection:
    """The release objects of a task's dataset (all shards unless ``shards`` picks some); a TFDS
    name (``rlu_atari/Pong_run_1``) fills in the family, run, challenge and size it carries."""
    ref = resolve_task(task_id)
    task = ref.task
    family, run, challenge, size = ref.dataset_settings(family, run, challenge, size)
    rel = task.release_dataset(family)
    binding = dataset_binding(task, run, challenge, size)
    names = rel.shard_names(binding)
    picked = parse_shards(shards, len(names))
    return ReleaseSelection(task, rel, binding, tuple(names[i] for i in picked))


def expand_tasks(patterns: str | Sequence[str]) -> list[str]:
    """Task names as typed: comma-separated lists and shell patterns over the registry's ids
    (``atari/*``: every Atari game) expanded, in the order given, each name once. A name without
    a pattern is kept as it is (a TFDS name too); a pattern that matches nothing is an error."""
    import fnmatch

    from rlu.tasks import TASKS

    items = [patterns] if isinstance(patterns, str) else list(patterns)
    out: list[str] = []
    for item in items:
        for name in (n.strip() for n in item.split(",")):
            if not name:
                continue
            if any(c in name for c in "*?["):
                hits = [t for t in TASKS if fnmatch.fnmatchcase(t, name)]
                if not hits:
                    raise RluError(
                        f"no registered task matches {name!r}; see `rlu list` (patterns use "
                        "* and ?, e.g. 'atari/*')"
                    )
            else:
                hits = [name]
            out.extend(h for h in hits if h not in out)
    if not out:
        raise RluError("no task given; name one or more, e.g. atari/Pong or 'atari/*'")
    return out


def catalog() -> list[dict]:
    """Every registered task's release datasets: family, binding, shard count, first object."""
    from rlu.tasks import TASKS

    rows = []
    for t in TASKS.values():
        for rel in t.release:
            for binding, n in rel.shards.items():
                rows.append(
                    {
                        "task": t.id,
                        "family": rel.family,
                        "dataset": binding,
                        "shards": n,
                        "first": rel.shard_names(binding)[0],
                    }
                )
    return rows


def find_shards(
    root: str | os.PathLike, selection: ReleaseSelection, shards: str | Sequence[int] | None = None
) -> list[str]:
    """The dataset's shard files under a bucket-shaped ``root``, in shard order.

    Files are found by name, ``<prefix>-%05d-of-%05d``, so a copy renumbered as the README does
    (``...-00000-of-00001``) is found too; all N shards of the count in the names must be there.
    """
    root = os.fspath(root)
    prefix = selection.release.prefix(selection.binding)
    folder = os.path.join(root, *prefix.split("/")[:-1])
    base = prefix.split("/")[-1]
    pat = re.compile(re.escape(base) + r"-(\d{5})-of-(\d{5})$")
    found: dict[int, dict[int, str]] = {}
    names = os.listdir(folder) if os.path.isdir(folder) else []
    for name in names:
        m = pat.match(name)
        if m:
            found.setdefault(int(m.group(2)), {})[int(m.group(1))] = os.path.join(folder, name)
    hint = (
        f"Fetch them with `rlu download {selection.task.id} --family {selection.family}` "
        f"or pass the files themselves"
    )
    if not found:
        raise RluError(
            f"no shards {base}-NNNNN-of-NNNNN of {selection.task.id} in {folder}. {hint}"
        )
    if len(found) > 1:
        raise RluError(f"{folder} mixes shard counts {sorted(found)} for {base}; keep one set")
    ((n, by_index),) = found.items()
    missing = [i for i in range(n) if i not in by_index]
    picked = parse_shards(shards, n)
    gone = [i for i in picked if i not in by_index]
    if gone:
        raise RluError(
            f"{len(missing)} of {n} shards of {base} are missing in {folder} (first: "
            f"{base}-{missing[0]:05d}-of-{n:05d}). {hint}"
        )
    return [by_index[i] for i in picked]
