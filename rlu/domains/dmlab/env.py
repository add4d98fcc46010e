"""DeepMind Lab: the env of the ``dmlab/`` tasks needs the ``deepmind_lab`` module.

DeepMind Lab is not on PyPI, so no rlu extra installs it: it is built from source with Bazel
(``rlu.domains.dmlab.ENV_INSTALL`` says how). Without it, ``make_env("dmlab/...")`` raises an
``RluError`` that says so; the datasets (download, convert, ``rlu list``, ``rlu info``, training
offline) need no env.

With ``deepmind_lab`` installed rlu still makes no env: the release documents neither the
recording R2D2 agent's 15 actions (which DeepMind Lab action vector each index is) nor its
action repeat, and an env with a guessed action set would evaluate a policy on a task it was
not trained on. ``make_env`` then raises an ``RluError`` naming what is missing.
"""

from __future__ import annotations

import importlib.util
from typing import Any, NoReturn

from rlu.domains import DOMAINS
from rlu.domains.envkit import Render
from rlu.domains.spec import TaskSpec
from rlu.types import RluError


def make(
    task: TaskSpec, seed: int | None = None, render: Render | None = None, **settings: Any
) -> NoReturn:
    """Refuses with what is missing (see the module docstring): ``deepmind_lab`` and how to
    build it, or, with it installed, the recording agent's action set."""
    domain = DOMAINS[task.domain]
    offline = (
        f"The {task.id} datasets need no env: `rlu download {task.id} --run "
        f"{task.datasets[0]}`, `rlu convert FILE --family dmlab --task {task.id} --out DATA`, "
        f"`rlu train --task {task.id} --dataset DATA --eval-every -1 ...`"
    )
    if importlib.util.find_spec("deepmind_lab") is None:
        raise RluError(
            f"{task.id}: {domain.data_only}. Its env would need the deepmind_lab module, which is "
            f"not installed: {domain.env_install}. {offline}"
        )
    raise RluError(
        f"{task.id}: rlu makes no DeepMind Lab env even with deepmind_lab installed: "
        f"{domain.data_only}, so evaluation in deepmind_lab would not be the task the data were "
        f"recorded on. {offline}"
    )
