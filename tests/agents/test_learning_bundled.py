"""Learning checks (long) of TD3+BC and ReBRAC on the bundled control_suite/cartpole_swingup
data (40 episodes made by ``rlu generate``, mean return 500.2), through the training loop, so
the dataset statistics reach the agents as in every run: each ``small`` preset for its 20,000
updates, seed 0, one torch thread, then 10 greedy episodes in dm_control's cartpole swingup.
Bar: the return beats BC's (its small preset, trained the same way here) or the data's mean.
About half an hour of one core for the three runs; run with ``-s`` to see the numbers.

Measured on the bundled data as regenerated on 2026-12-02 (docs/agents.md, "Learning on the
bundled data"): BC 347.1; ReBRAC 356.9 (passes); TD3+BC 206.8, and with seeds 1 and 2 287.0 and
171.2: on this data TD3+BC's 20,000 updates stay below BC's return and the data's mean (on the
earlier bytes, mean 435.6, they gave 286.7, 437.9, 266.7 against BC's 130). Its case is a strict
xfail: it says so until TD3+BC passes, and then fails so that the mark is removed.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("dm_control")

TASK = "control_suite/cartpole_swingup"
EPISODES = 10


def small_preset_return(name: str, folder) -> float:
    from rlu.generate.recipe import bundled_dataset
    from rlu.training.train import train
    from tests.fakes import train_config

    cfg = train_config(
        task=TASK, agent=name, dataset=str(bundled_dataset(TASK)), preset="small", seed=0,
        eval_every=0, eval_episodes=EPISODES, torch_threads=1, log_every=1000,
    )  # fmt: skip
    return float(train(cfg, folder / name, progress=False)["score"])


@pytest.fixture(scope="module")
def bars(tmp_path_factory):
    from rlu.data import open_dataset
    from rlu.generate.recipe import bundled_dataset

    data_mean = float(np.mean(open_dataset(bundled_dataset(TASK)).episode_returns()))
    return small_preset_return("bc", tmp_path_factory.mktemp("bc")), data_mean


@pytest.mark.slow
@pytest.mark.long  # outside CI: RLU_SLOW=2
@pytest.mark.parametrize(
    "name",
    [
        pytest.param("td3bc", marks=pytest.mark.xfail(strict=True, raises=AssertionError, reason=(
            "TD3+BC's small preset returns 171-287 on the regenerated bundled data (3 seeds), "
            "below BC's 347 and the data's 500 (module docstring)"))),
        "rebrac",
    ],
)  # fmt: skip
def test_small_preset_beats_bc_or_the_data_on_the_bundled_cartpole(name, bars, tmp_path):
    bc, data_mean = bars
    score = small_preset_return(name, tmp_path)
    print(f"\n{name}: return {score:.1f} (bc {bc:.1f}, data mean {data_mean:.1f})")
    assert score > bc or score > data_mean
