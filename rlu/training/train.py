"""The one training loop: batch -> agent.update -> periodic evaluation in the env -> logs.
Three steps: ``rlu.training.prepare`` checks and resolves a ``TrainConfig`` (defined there, handed
on here; nothing written), ``rlu.training.loop`` builds the agent and runs the loop; this module
is the entry point, ``train``.

The agent declares its batches (``agent.batch_spec``) and the loop samples exactly those
(``rlu.data.make_sampler``); the run folder's layout and files belong to ``rlu.training.runs``; how
a run is run (preset, budget, evaluation, checkpoints, runtime) is one
``rlu.training.config.RunSettings``.

Resume is exact on the CPU: a checkpoint holds the agent's state, the sampler's generator, the
global torch and numpy generators and the step; on ``resume`` the logs are cut back to the
checkpoint's step and the loop goes on. Evaluation at step k uses env seeds derived from
(seed, k) only, so it needs no state.

Devices (``RunSettings.runtime``, docs/devices.md): the agent lives on the runtime's device;
batches come from the sampler in line (the CPU default), from a background prefetcher (CUDA's
default: pinned host batches copied on a side stream) or from the dataset held on the device;
every update runs in the runtime's precision. All three data paths give the same batches. The
runtime may differ between a run's sessions (train on a GPU, resume on a CPU): resume compares
the run's config without it, and checkpoints load on any device.

Agents are built by name through ``rlu.agents``; a dotted module path in a ``TrainConfig``
(``tests.train.fake_agent``: code or the command line named it) is imported and registered
(``rlu.agents.trust_agent``). Envs come from ``rlu.envs.make_env`` or from an env factory
``'module:function'`` given the same way. Names inside files are never imported.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rlu.training.prepare import TrainConfig, check_agent_config


def train(
    config: TrainConfig,
    out: str | os.PathLike,
    resume: bool = False,
    progress: bool | Any = False,
    loggers: Sequence[str] = (),
) -> dict[str, Any]:
    """Train ``config.agent`` on ``config.dataset``; returns the content of ``result.json``.
    ``loggers``: where the metrics go besides the run's own logs (``rlu.training.loggers.LOGGERS``).
    ``progress``: True shows the steps on stderr (``rlu.progress.Progress``); a
    ``rlu.progress.Relay`` sends them to the process that started this one (a sweep's run).

    One process per run folder: a second ``train`` into the same ``out`` fails with "in use by
    PID N" (:class:`rlu.locks.OutputLock`) while the first lives.
    """
    from rlu.locks import OutputLock
    from rlu.training.prepare import trust

    trust(config.agent, config.run.env)
    check_agent_config(config)  # before the lock file, its folder, the data
    with OutputLock(Path(out), "run folder"):
        return _train(config, out, resume, progress, tuple(loggers))


def _train(
    config: TrainConfig,
    out: str | os.PathLike,
    resume: bool,
    progress: bool | Any,
    logger_names: tuple[str, ...],
) -> dict[str, Any]:
    from rlu.training.loop import build, result_of, run_loop, start_folder
    from rlu.training.prepare import prepare

    prepared = prepare(config, Path(out), resume)
    if prepared.finished is not None:  # a finished run resumed: nothing left to do
        return prepared.finished
    built = build(prepared, logger_names)
    # everything that can fail before the first step has run: only now is the run folder written
    loggers = start_folder(prepared, built, logger_names)
    run_loop(prepared, built, loggers, progress)
    return result_of(prepared, built)


__all__ = ["TrainConfig", "train"]
