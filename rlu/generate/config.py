"""One generation in one frozen value: what ``rlu generate`` records and how it runs.

:class:`GenerateConfig` is passed whole from ``rlu.generate.generate`` through the recipes to
every run; the command's flags, their help and range checks come from its fields
(``rlu.commands._options.add_options``). What is recorded (task, scale, runs, seed, policy) decides
the bytes; how it runs (device, backend, progress, the work folder) does not, except the device,
whose arithmetic the bytes follow. Standard library only.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from rlu.files import Checked, bounds
from rlu.workers import Backend

SCALES = ("tiny", "laptop", "paper")
"""The recipe's scales (``rlu.generate.scales``)."""


MAX_RUNS = 1000
"""Independent runs of one generation, at most (the paper's: 3 or 5)."""


@dataclass(frozen=True)
class GenerateConfig(Checked):
    """One ``rlu generate`` (see the module docstring); every field is checked when it is made
    (``rlu.files.Checked``: a ConfigError names the field, the value and the bound)."""

    task: str
    """Task id, e.g. control_suite/cartpole_swingup, atari/Pong or rwrl/cartpole_swingup (rwrl
    writes OUT/{none,easy}_{small,medium,large})."""
    scale: str = field(default="laptop", metadata=bounds(choices=SCALES))
    """laptop: behaviour runs that learn in minutes of CPU; tiny: seconds, for tests; paper: the
    paper's budgets (clusters)."""
    runs: int | None = field(
        default=None, metadata=bounds(min=1, max=MAX_RUNS, flag="--seeds", metavar="N")
    )
    """Independent runs (default: the scale's; the paper: 3 for the control suite, 5 for Atari)."""
    seed: int = field(default=0, metadata=bounds(min=0, max=2**63 - 1))
    """Base seed of every run; the same seed gives the same bytes."""
    policy: str | None = field(default=None, metadata=bounds(metavar="MODULE:FACTORY"))
    """Record this policy instead of training D4PG / DQN (required for locomotion):
    factory(task_id, seed) -> policy(observation) -> action; imported because you typed it."""
    device: str = field(default="cpu", metadata=bounds(cli_default="auto", metavar="DEVICE"))
    """auto, cpu, cuda or cuda:N: where the behaviour agents learn (the bytes follow the
    device's arithmetic; the command line's default is auto)."""
    backend: Backend = field(default_factory=Backend)
    """Where the runs play: this process, local worker processes or a Ray cluster (the bytes do
    not depend on it)."""
    keep_work: bool = False
    """Keep the work folder (each run's parts and state) after the dataset is written."""
    progress: bool = True
    """A progress bar on stderr."""

    def command(self, runs: int) -> str:
        """The command recorded in the manifest (``--out`` left out: it does not change the
        data; nor do the device and the backend, or only as arithmetic does)."""
        line = f"rlu generate {self.task} --scale {self.scale} --seeds {runs} --seed {self.seed}"
        return line if self.policy is None else f"{line} --policy {self.policy}"


__all__ = ["MAX_RUNS", "SCALES", "GenerateConfig"]
