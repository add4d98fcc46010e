"""Seed streams: every random stream of rlu derived from a run's seed and a key, with numpy's
``SeedSequence`` (no two different keys share a stream). Imports numpy only."""

from __future__ import annotations

import numpy as np

from rlu.types import RluError


def seed_stream(seed: int, *key: int) -> np.random.SeedSequence:
    """The random stream ``key`` of run ``seed``: ``SeedSequence(seed).spawn(...)`` indexed by
    ``key`` (``seed_stream(s, w, e)`` is ``SeedSequence(s).spawn(w + 1)[w].spawn(e + 1)[e]``).

    numpy spawns children by extending the spawn key and hashes (entropy, spawn key) together, so
    two different ``(seed, *key)`` never give the same stream, unlike ``seed + k`` (run 0's
    worker 1 would be run 1's worker 0). Every seed and key must be a non-negative int.
    """
    parts = (seed, *key)
    if any(isinstance(p, bool) or not isinstance(p, int | np.integer) or p < 0 for p in parts):
        raise RluError(f"seed {seed!r} with stream key {key!r}: seeds are non-negative integers")
    return np.random.SeedSequence(int(seed), spawn_key=tuple(int(k) for k in key))


def derive_seed(seed: int, *key: int) -> int:
    """A 31-bit int seed for stream ``key`` of ``seed`` (see ``seed_stream``), for APIs that take
    an int (``env.reset(seed=...)``, dm_control's ``random``, ALE's signed 32-bit seed)."""
    return int(seed_stream(seed, *key).generate_state(1, np.uint32)[0] >> 1)


RUN_STREAMS = 1 << 40
"""The first key of a training run's own streams (``stream_seed``). Evaluation at step ``k``
uses the key ``(k,)`` and steps stay far below ``2**40``, so the two never meet."""

STREAMS = ("learner", "act", "dropout", "sampler")
"""A training run's random streams besides initialisation: the learner's noise (target
smoothing, sampled actions in losses), acting, dropout, the batch sampler."""


def stream_seed(seed: int, name: str) -> int:
    """The int seed of stream ``name`` (one of ``STREAMS``) of run ``seed``: the key
    ``(RUN_STREAMS, index)`` of ``seed_stream``, so no stream is a transform of another.

    Initialisation is not among them: agents build their networks under torch's generator
    seeded with the run's seed itself (``torch.manual_seed(seed)``, a Mersenne Twister, not a
    ``SeedSequence`` child), which keeps the weights every earlier run and the bundled dataset's
    behaviour agent started from."""
    if name not in STREAMS:
        raise RluError(f"no random stream {name!r}: the streams are {', '.join(STREAMS)}")
    return derive_seed(seed, RUN_STREAMS, STREAMS.index(name))
