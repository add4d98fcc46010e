"""Where every registered task's release files live: object names, shard counts, URLs.

Built on ``TaskSpec.release`` (rlu.tasks), which carries each family's path pattern and its
per-dataset shard counts; this module binds the dataset (Atari run, RWRL challenge and size),
expands ``-%05d-of-%05d`` names, and finds already-downloaded shards under a bucket-shaped root.
bsuite and DMLab are not registry tasks; their object names are built here from the facts file.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from dataclasses import dataclass

from rlu.tasks import BASE_URL, RWRL_DATASETS, ReleaseDataset, TaskSpec, get_task
from rlu.types import RluError

SHARD_RE = re.compile(r"-(\d{5})-of-(\d{5})$")
DMLAB_SHARDS = 500


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


def dataset_binding(
    task: TaskSpec, run: str | int | None = None, challenge: str | None = None,
    size: str | None = None,
) -> str:  # fmt: skip
    """The key of ``ReleaseDataset.shards`` for a task's dataset (``run_1``, ``none/large``, '')."""
    if task.domain == "atari":
        r = run if run is not None else 1
        r = f"run_{r}" if not str(r).startswith("run_") else str(r)
        if r not in task.datasets:
            raise RluError(f"{task.id}: unknown run {run!r}; use one of {', '.join(task.datasets)}")
        return r
    if task.domain == "rwrl":
        b = f"{challenge or 'none'}/{size or 'large'}"
        if b not in RWRL_DATASETS:
            raise RluError(
                f"{task.id}: no released dataset for challenge={challenge!r} size={size!r}; "
                f"released: {', '.join(RWRL_DATASETS)} (challenge/size)"
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
    """The release objects of a task's dataset (all shards unless ``shards`` picks some)."""
    task = get_task(task_id)
    rel = task.release_dataset(family)
    binding = dataset_binding(task, run, challenge, size)
    names = rel.shard_names(binding)
    picked = parse_shards(shards, len(names))
    return ReleaseSelection(task, rel, binding, tuple(names[i] for i in picked))


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


def find_shards(root: str | os.PathLike, selection: ReleaseSelection) -> list[str]:
    """The selection's shard files under a bucket-shaped ``root`` (all must exist)."""
    root = os.fspath(root)
    paths = [os.path.join(root, *o.split("/")) for o in selection.objects]
    missing = [p for p in paths if not os.path.isfile(p)]
    if missing:
        more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
        raise RluError(
            f"{len(missing)} of {len(paths)} shards of {selection.task.id} "
            f"({selection.family}) are not under {root}: first missing {missing[0]}{more}. "
            f"Fetch them with `rlu download {selection.task.id} --family {selection.family}`"
        )
    return paths


def bsuite_objects(env: str, noise: float, k: int = 0, split: str = "full") -> list[str]:
    """bsuite shards (one each): ``bsuite/{env}/0_{noise}/{k}_{split}-00000-of-00001``."""
    if env not in ("cartpole", "catch", "mountain_car"):
        raise RluError(f"unknown bsuite environment {env!r}; use cartpole, catch or mountain_car")
    return [f"bsuite/{env}/0_{noise:.1f}/{k}_{split}-00000-of-00001"]


def dmlab_objects(level: str, run: str) -> list[str]:
    """DMLab shards: ``dmlab/{level}/{run}/tfrecord-{i}-of-00500``."""
    return [f"dmlab/{level}/{run}/tfrecord-{i:05d}-of-{DMLAB_SHARDS:05d}" for i in range(DMLAB_SHARDS)]
