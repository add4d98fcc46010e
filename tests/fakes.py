"""Fake specs, episodes and batches for tests (Acme's fakes): small, seeded, in the real shapes."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from rlu.types import (
    ArraySpec,
    BoundedSpec,
    DiscreteSpec,
    ObservationSpec,
    Sequence,
    Transition,
)

# Low-dimensional dict observation (like control_suite/walker_walk).
LOWDIM_OBS: Mapping[str, ArraySpec] = {
    "orientations": ArraySpec((14,), "float32"),
    "velocity": ArraySpec((9,), "float32"),
    "height": ArraySpec((1,), "float32"),
}
# Features plus a small egocentric camera (like the locomotion tasks, 64x64x3 in the data).
IMAGE_OBS: Mapping[str, ArraySpec] = {
    "walker/joints_pos": ArraySpec((8,), "float32"),
    "walker/egocentric_camera": ArraySpec((64, 64, 3), "uint8"),
}
ATARI_OBS = ArraySpec((84, 84, 4), "uint8")
CONT_ACTION = BoundedSpec((3,), "float32", -1.0, 1.0)
ATARI_ACTION = DiscreteSpec((), "int64", 6)


def random_observation(spec: ObservationSpec, *leading: int, rng: np.random.Generator):
    def one(s: ArraySpec) -> np.ndarray:
        if np.dtype(s.dtype) == np.uint8:
            return rng.integers(0, 256, size=(*leading, *s.shape), dtype=np.uint8)
        return rng.standard_normal((*leading, *s.shape)).astype(s.dtype)

    if isinstance(spec, ArraySpec):
        return one(spec)
    return {k: one(v) for k, v in spec.items()}


def random_action(spec, *leading: int, rng: np.random.Generator) -> np.ndarray:
    if isinstance(spec, DiscreteSpec):
        return rng.integers(0, spec.num_values, size=leading).astype(np.int64)
    a = rng.uniform(spec.minimum, spec.maximum, size=(*leading, *spec.shape))
    return a.astype(spec.dtype)


def fake_transition(
    obs_spec: ObservationSpec, action_spec, batch: int = 8, seed: int = 0
) -> Transition:
    rng = np.random.default_rng(seed)
    return Transition(
        observation=random_observation(obs_spec, batch, rng=rng),
        action=random_action(action_spec, batch, rng=rng),
        reward=rng.standard_normal(batch).astype(np.float32),
        discount=(rng.random(batch) > 0.1).astype(np.float32),
        next_observation=random_observation(obs_spec, batch, rng=rng),
        next_action=random_action(action_spec, batch, rng=rng),
    )


def fake_sequence(
    obs_spec: ObservationSpec, action_spec, batch: int = 4, length: int = 5, seed: int = 0
) -> Sequence:
    rng = np.random.default_rng(seed)
    mask = np.ones((batch, length), bool)
    mask[0, length - 2 :] = False  # one padded window
    is_last = np.zeros((batch, length), bool)
    is_last[0, length - 3] = True
    observation = random_observation(obs_spec, batch, length, rng=rng)
    action = random_action(action_spec, batch, length, rng=rng)
    reward = rng.standard_normal((batch, length)).astype(np.float32) * mask
    # each window its own segment: returns to go summed to its end, timesteps from its start
    return_to_go = np.cumsum(reward[:, ::-1], axis=1)[:, ::-1].astype(np.float32) * mask
    return Sequence(
        observation=observation,
        action=action,
        reward=reward,
        discount=np.ones((batch, length), np.float32),
        is_first=np.zeros((batch, length), bool),
        is_last=is_last,
        mask=mask,
        return_to_go=np.ascontiguousarray(return_to_go),
        timestep=np.where(mask, np.arange(length), 0),
    )


def train_config(**kw):
    """An ``rlu.training.train.TrainConfig`` from flat keywords: the ``RunSettings`` fields
    (``steps``, ``eval_every``, ``runtime``, ...) go into its ``run``, the rest stay its own."""
    import dataclasses

    from rlu.training.config import RunSettings
    from rlu.training.train import TrainConfig

    names = {f.name for f in dataclasses.fields(RunSettings)}
    run = RunSettings(**{k: kw.pop(k) for k in list(kw) if k in names})
    return TrainConfig(**kw, run=run)


def sweep_config(**kw):
    """An ``rlu.training.sweep.SweepConfig`` from flat keywords, as :func:`train_config`."""
    import dataclasses

    from rlu.training.config import RunSettings
    from rlu.training.sweep import SweepConfig

    names = {f.name for f in dataclasses.fields(RunSettings)}
    run = RunSettings(**{k: kw.pop(k) for k in list(kw) if k in names})
    return SweepConfig(**kw, run=run)
