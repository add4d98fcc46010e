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


def _first_batches(path, seed, workers, passes, generator_seed=0):
    """The first two batches' rewards of every worker on each of ``passes`` iterations of one
    DataLoader (workers' batches interleave: batch j comes from worker j % workers)."""
    loader = torch.utils.data.DataLoader(
        TorchSampler(str(path), BatchSpec(8), seed=seed),
        batch_size=None,
        num_workers=workers,
        generator=torch.Generator().manual_seed(generator_seed),
    )
    out = []
    for _ in range(passes):
        it = iter(loader)
        out.append([next(it).reward.numpy() for _ in range(2 * max(workers, 1))])
    return out


@pytest.fixture(scope="module")
def cartpole(tmp_path_factory):
    schema = Schema.for_task(get_task("control_suite/cartpole_swingup"))
    return write_synthetic(tmp_path_factory.mktemp("torch") / "ds", schema, 3, 50)


def test_no_two_run_worker_pass_streams_coincide(cartpole):
    """Runs 0-2 x (no worker, workers 0 and 1) x 3 passes over the loader: 27 streams, no two
    alike. With ``seed + worker`` run 0's worker 1 was run 1's worker 0, and every pass over a
    loader replayed the first."""
    streams = {}
    for seed in range(3):
        for workers in (0, 2):
            for p, batches in enumerate(_first_batches(cartpole, seed, workers, 3)):
                for w in range(max(workers, 1)):
                    own = batches[w :: max(workers, 1)]  # this worker's two batches
                    streams[(seed, workers, w, p)] = np.concatenate(own).tobytes()
    assert len(streams) == 27
    by_value = {}
    for key, value in streams.items():
        by_value.setdefault(value, []).append(key)
    clashes = [keys for keys in by_value.values() if len(keys) > 1]
    assert not clashes, f"streams replayed: {clashes}"


def test_seed_streams_are_distinct_over_runs_workers_and_epochs():
    """The keys rlu spawns streams from (rlu.types.seed_stream): 20 runs x 9 lanes x 20 epochs,
    the first 4 draws of each stream, all distinct."""
    from rlu.types import RluError, seed_stream

    draws = {
        np.random.default_rng(seed_stream(r, w, e)).integers(0, 2**63, 4).tobytes()
        for r in range(20)
        for w in range(9)
        for e in range(20)
    }
    assert len(draws) == 20 * 9 * 20
    with pytest.raises(RluError, match="non-negative"):
        seed_stream(-1, 0)


def test_dataloader_passes_are_reproducible_under_a_seeded_generator(cartpole):
    a = _first_batches(cartpole, 5, 2, 2, generator_seed=1)
    b = _first_batches(cartpole, 5, 2, 2, generator_seed=1)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(np.stack(x), np.stack(y))
    single = _first_batches(cartpole, 5, 0, 2)
    again = _first_batches(cartpole, 5, 0, 2)
    np.testing.assert_array_equal(np.stack(single[1]), np.stack(again[1]))
    assert not np.array_equal(single[0][0], single[1][0])  # a second pass is a new stream
