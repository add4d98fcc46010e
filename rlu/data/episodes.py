"""Minari's episode API on rlu's datasets: ``sample_episodes``, ``filter_episodes``, ``split``,
``recover_environment``, with Minari 0.5's meanings (``minari.MinariDataset`` and
``minari.split_dataset``).

An episode is a stored segment, read as Minari returns one (:class:`EpisodeData`): ``T + 1``
observations (a dict observation nested by ``/``, as ``rlu export --format minari`` writes it;
Atari frames stacked, newest last) and ``T`` actions, rewards, terminations and truncations
(the last step terminated when the episode ends in a terminal state, truncated otherwise: a time
limit, or the end of a release window). ``filter_episodes`` and ``split`` return datasets of
some of the episodes (:class:`EpisodeSubset`, a :class:`~rlu.data.store.Dataset` over the same
files: every sampler and view takes it). ``sample_episodes`` draws without replacement from the
dataset's generator (``set_seed``), as Minari's does.

``recover_environment`` makes the env the data come from: for rlu's tasks the task's env with
the recorded settings (the spec ``rlu export --format minari`` writes); for a dataset imported
from Minari the ``env_spec`` (or ``eval_env_spec``) it recorded, time limit, kwargs and wrappers
included. Files are data, never code: a recorded spec is made only when its id is registered in
Gymnasium with that same entry point (or is rlu's own), and its wrappers are Gymnasium's own.
"""

from __future__ import annotations

import dataclasses
import json
import weakref
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np

from rlu.data.store import Dataset
from rlu.types import RluError

_GENERATORS: weakref.WeakKeyDictionary[Dataset, np.random.Generator] = weakref.WeakKeyDictionary()


@dataclasses.dataclass(frozen=True)
class EpisodeData:
    """One episode as ``minari.dataset.episode_data.EpisodeData`` holds it."""

    id: int
    observations: Any
    actions: np.ndarray
    rewards: np.ndarray
    terminations: np.ndarray
    truncations: np.ndarray
    infos: dict[str, Any]

    def __len__(self) -> int:
        return len(self.rewards)


def _nest(flat: Mapping[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, v in flat.items():
        *parents, leaf = key.split("/")
        node = out
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = v
    return out


def episode(ds: Dataset, i: int) -> EpisodeData:
    """Segment ``i`` of ``ds`` as Minari's episode (module docstring)."""
    seg = ds.segment(i)
    n = len(seg) - 1
    if ds.schema.frame_stack > 1:
        from rlu.data.views import DatasetView

        steps = int(ds.start[i]) + np.arange(len(seg))
        obs: Any = DatasetView(ds).observation(np.full(len(seg), i), steps)
    elif isinstance(seg.observation, Mapping):
        obs = _nest(seg.observation)
    else:
        obs = seg.observation
    terminal = bool(seg.is_terminal[-1])
    terminations = np.zeros(n, bool)
    truncations = np.zeros(n, bool)
    if n:
        terminations[-1], truncations[-1] = terminal, not terminal
    return EpisodeData(
        id=int(ds.indices[i]) if isinstance(ds, EpisodeSubset) else i,
        observations=obs,
        actions=seg.action[:n],
        rewards=seg.reward[:n],
        terminations=terminations,
        truncations=truncations,
        infos={},
    )


def iterate_episodes(ds: Dataset, indices: Iterable[int] | None = None) -> Iterator[EpisodeData]:
    """The episodes at ``indices`` (positions in ``ds``; default: all), in order."""
    for i in range(len(ds)) if indices is None else indices:
        yield episode(ds, int(i))


def set_seed(ds: Dataset, seed: int | None) -> None:
    """Seed ``ds``'s generator of :func:`sample_episodes` (``MinariDataset.set_seed``)."""
    _GENERATORS[ds] = np.random.default_rng(seed)


def sample_episodes(ds: Dataset, n_episodes: int) -> list[EpisodeData]:
    """``n_episodes`` distinct episodes drawn at random (``MinariDataset.sample_episodes``:
    ``generator.choice(indices, size=n, replace=False)``)."""
    if not isinstance(n_episodes, int | np.integer) or not 0 <= n_episodes <= len(ds):
        raise RluError(
            f"sample_episodes({n_episodes!r}): the dataset holds {len(ds)} episodes; ask for a "
            f"whole number from 0 to {len(ds)}"
        )
    rng = _GENERATORS.setdefault(ds, np.random.default_rng())
    picks = rng.choice(np.arange(len(ds)), size=int(n_episodes), replace=False)
    return [episode(ds, int(i)) for i in picks]


def filter_episodes(ds: Dataset, condition: Callable[[EpisodeData], bool]) -> EpisodeSubset:
    """The dataset of the episodes for which ``condition(episode)`` is true, in order
    (``MinariDataset.filter_episodes``)."""
    keep = [i for i in range(len(ds)) if bool(condition(episode(ds, i)))]
    return subset(ds, keep)


def split(
    ds: Dataset, sizes: Sequence[float | int], seed: int | None = None
) -> list[EpisodeSubset]:
    """Disjoint datasets of randomly chosen episodes (``minari.split_dataset``: one permutation
    of the episodes by ``numpy.random.default_rng(seed)``, cut in consecutive slices). ``sizes``
    are episode counts (Minari's) or fractions of the episodes (floats summing to at most 1: the
    counts are rounded down, and fractions summing to 1 give the last slice the remainder)."""
    n = len(ds)
    if not sizes:
        raise RluError("split: give the sizes of the parts (episode counts or fractions)")
    if all(isinstance(s, int | np.integer) and not isinstance(s, bool) for s in sizes):
        counts = [int(s) for s in sizes]
        if min(counts) < 0 or sum(counts) > n:
            raise RluError(
                f"split({list(sizes)}): the sizes sum to {sum(counts)}, more than the dataset's "
                f"{n} episodes (or one is negative)"
            )
    elif all(isinstance(s, float | int) and not isinstance(s, bool) for s in sizes):
        fractions = [float(s) for s in sizes]
        total = sum(fractions)
        if min(fractions) < 0 or total > 1 + 1e-9:
            raise RluError(f"split({list(sizes)}): fractions must be >= 0 and sum to at most 1")
        counts = [int(np.floor(f * n + 1e-9)) for f in fractions]
        if abs(total - 1) <= 1e-9:
            counts[-1] = n - sum(counts[:-1])
    else:
        raise RluError(f"split({list(sizes)!r}): give episode counts or fractions")
    order = np.random.default_rng(seed).permutation(np.arange(n))
    out, start = [], 0
    for c in counts:
        out.append(subset(ds, order[start : start + c]))
        start += c
    return out


class EpisodeSubset(Dataset):
    """Some of a dataset's episodes, in a given order, over the same files: a
    :class:`~rlu.data.store.Dataset` to every sampler, view and adapter. ``indices`` are the
    episodes' positions in the original dataset (``parent``)."""

    parent: Dataset
    indices: np.ndarray

    def __init__(self, parent: Dataset, indices: Any):
        root = parent.parent if isinstance(parent, EpisodeSubset) else parent
        idx = np.asarray(indices, np.int64).reshape(-1)
        if isinstance(parent, EpisodeSubset):
            idx = parent.indices[idx]
        if idx.size and (idx.min() < 0 or idx.max() >= len(root)):
            raise RluError(f"episodes {idx.tolist()[:5]}...: the dataset holds {len(root)}")
        self.__dict__.update(root.__dict__)  # the same manifest, schema, mapped columns
        self.parent, self.indices = root, idx
        self.start = np.asarray(root.start)[idx]
        self.length = np.asarray(root.length)[idx]
        self.frame_start = np.asarray(root.frame_start)[idx]
        self.num_segments = len(idx)

    def __repr__(self) -> str:
        return f"EpisodeSubset({self.parent!r}, episodes={len(self)})"

    @property
    def total_steps(self) -> int:
        """Steps of its episodes (``num_steps`` stays the files' count, as the columns hold)."""
        return int(self.length.sum())

    def metadata(self, key: str) -> np.ndarray:
        return self.parent.metadata(key)[self.indices]

    def episode_returns(self) -> np.ndarray:
        reward = np.concatenate([[0.0], np.cumsum(self.column("reward"), dtype=np.float64)])
        end = self.start + self.length
        first = np.asarray(self.column("is_first"))[self.start]
        last = np.asarray(self.column("is_last"))[end - 1]
        return (reward[end] - reward[self.start])[first & last]


def subset(ds: Dataset, indices: Any) -> EpisodeSubset:
    """The episodes of ``ds`` at ``indices`` (positions in ``ds``) as a dataset."""
    return EpisodeSubset(ds, indices)


# --- the environment ----------------------------------------------------------------------------
def recover_environment(ds: Dataset, eval_env: bool = False, **kwargs: Any) -> Any:
    """The Gymnasium env the data come from (``MinariDataset.recover_environment``): with
    ``eval_env`` the evaluation env the dataset names, if any (else the same). ``kwargs`` go to
    ``gymnasium.make``. See the module docstring for which recorded specs are made."""
    import gymnasium as gym

    spec = _recorded_spec(ds, eval_env)
    if spec is None:
        from rlu.data.minari import env_spec_for

        spec = env_spec_for(ds.schema, ds.manifest.get("provenance", {}))
    if spec is None:
        raise RluError(
            f"{ds.path}: the dataset names no registered task and records no env spec, so there "
            "is no environment to recover"
        )
    _check_spec(spec, ds)
    return gym.make(spec, **kwargs)


_GYM_1_0_KEYS = (  # keys of a spec's JSON that gymnasium 1.0's EnvSpec no longer takes
    '"order_enforce": true,',
    '"apply_api_compatibility": false,',
    '"autoreset": false, ',
)


def _recorded_spec(ds: Dataset, eval_env: bool) -> Any:
    """The ``env_spec`` (or ``eval_env_spec``) a Minari dataset recorded, kept by its import."""
    from gymnasium.envs.registration import EnvSpec

    from rlu.data.roundtrip import read_source

    src = read_source(ds, "minari")
    if src is None:
        return None
    src[1].__exit__()
    meta = src[0].get("metadata") or {}
    text = meta.get("eval_env_spec") if eval_env and meta.get("eval_env_spec") else None
    text = text or meta.get("env_spec")
    if not isinstance(text, str):
        return None
    for old in _GYM_1_0_KEYS:
        text = text.replace(old, "")  # as Minari does, for gymnasium 1.0
    try:
        return EnvSpec.from_json(text)
    except (ValueError, TypeError, KeyError, json.JSONDecodeError) as e:
        raise RluError(f"{ds.path}: the recorded env_spec cannot be read ({e})") from None


def _check_spec(spec: Any, ds: Dataset) -> None:
    """Make only what rlu or Gymnasium registered: the recorded entry point must be rlu's, or
    the one Gymnasium's registry holds for the id; wrappers must be Gymnasium's."""
    import gymnasium as gym

    from rlu.tasks import GYM_ENTRY_POINT, TASKS

    if spec.entry_point == GYM_ENTRY_POINT:
        task = (spec.kwargs or {}).get("task_id")
        if task not in TASKS:
            raise RluError(f"{ds.path}: the env spec names task {task!r}, which rlu does not know")
        return
    registered = gym.registry.get(spec.id)
    if registered is None or registered.entry_point != spec.entry_point:
        raise RluError(
            f"{ds.path}: the recorded env {spec.id!r} (entry point {spec.entry_point!r}) is not "
            "registered in Gymnasium with that entry point; rlu makes only registered envs "
            "(files are data, never code): register it, or make it yourself from "
            "dataset.manifest / source/minari.json"
        )
    for w in spec.additional_wrappers or ():
        if not str(w.entry_point).startswith("gymnasium.wrappers"):
            raise RluError(
                f"{ds.path}: the recorded env spec wraps {w.name} ({w.entry_point}); rlu applies "
                "only Gymnasium's own wrappers"
            )
