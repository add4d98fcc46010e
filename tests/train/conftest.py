from __future__ import annotations

import pytest

from tests.train.pendulum import write_dataset

TASKS = ("test/pendulum", "test/pendulum_heavy")
AGENTS = ("tests.train.fake_agent", "tests.train.fake_agent_mlp")


@pytest.fixture(scope="session")
def pendulum_datasets(tmp_path_factory):
    pytest.importorskip("gymnasium")
    pytest.importorskip("torch")
    root = tmp_path_factory.mktemp("datasets")
    return {t: str(write_dataset(root / t.split("/")[-1], t, seed=i)) for i, t in enumerate(TASKS)}


def sweep_config(datasets):
    """2 tasks x 2 agents x 2 configurations (each agent's GRID) x 2 seeds, small and short."""
    from tests.fakes import sweep_config as make

    return make(
        tasks=TASKS,
        agents=AGENTS,
        datasets=datasets,
        seeds=(0, 1),
        steps=30,
        eval_episodes=2,
        eval_envs=2,
        eval_max_steps=20,
        log_every=10,
        checkpoint_every=30,
        env="tests.train.pendulum:make_env",
    )


@pytest.fixture(scope="session")
def local_sweep(pendulum_datasets, tmp_path_factory):
    from rlu.training.sweep import sweep

    out = tmp_path_factory.mktemp("sweep_local")
    from rlu.workers import Backend

    records = sweep(sweep_config(pendulum_datasets), out, Backend("local", 2))
    return out, records
