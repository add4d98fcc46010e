from __future__ import annotations

import pytest

from tests.train.pendulum import write_dataset


@pytest.fixture(scope="session")
def pendulum_datasets(tmp_path_factory):
    pytest.importorskip("gymnasium")
    pytest.importorskip("torch")
    root = tmp_path_factory.mktemp("datasets")
    return {
        t: str(write_dataset(root / t.split("/")[-1], t, seed=i))
        for i, t in enumerate(["test/pendulum", "test/pendulum_heavy"])
    }
