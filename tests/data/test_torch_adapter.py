"""The PyTorch adapter: tensors of the right types, DataLoader workers with distinct seeds."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rlu.data import Schema, open_dataset, transition_sampler  # noqa: E402
from rlu.data.synthetic import write_synthetic  # noqa: E402
from rlu.data.torch import TorchSampler, to_torch  # noqa: E402
from rlu.tasks import get_task  # noqa: E402
from rlu.types import BatchSpec  # noqa: E402


def test_to_torch_keeps_names_and_dtypes(tmp_path):
    path = write_synthetic(tmp_path / "ds", Schema.for_task(get_task("atari/Pong")), 2, 6)
    b = to_torch(transition_sampler(open_dataset(path), 4, seed=0).sample())
    assert b.observation.dtype == torch.uint8 and b.observation.shape == (4, 84, 84, 4)
    assert b.action.dtype == torch.int64 and b.reward.dtype == torch.float32


def test_dataloader_workers_give_distinct_reproducible_streams(tmp_path):
    path = write_synthetic(
        tmp_path / "ds", Schema.for_task(get_task("control_suite/cartpole_swingup")), 3, 50
    )

    def draw(workers):
        loader = torch.utils.data.DataLoader(
            TorchSampler(str(path), BatchSpec(8), seed=5), batch_size=None, num_workers=workers
        )
        it = iter(loader)
        return [next(it).reward.numpy() for _ in range(4)]

    a, b = draw(2), draw(2)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a[0], a[1])  # workers 0 and 1 interleave with different seeds
    single = draw(0)
    np.testing.assert_array_equal(single[0], a[0])
