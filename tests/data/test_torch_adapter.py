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
    """The keys rlu spawns streams from (rlu.seeds.seed_stream): 20 runs x 9 lanes x 20 epochs,
    the first 4 draws of each stream, all distinct."""
    from rlu.seeds import seed_stream
    from rlu.types import RluError

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


# --- the training loop's data path: DeviceSampler and Prefetcher ------------------------------
def _equal_batches(host, device_batch):
    for x, y in zip(host, device_batch, strict=True):
        if isinstance(x, dict):
            assert x.keys() == y.keys()
            for k in x:
                np.testing.assert_array_equal(x[k], y[k].numpy())
        else:
            assert isinstance(y, torch.Tensor)
            np.testing.assert_array_equal(x, y.numpy())


@pytest.mark.parametrize(
    ("task", "encoding"),
    [("atari/Pong", "raw"), ("atari/Pong", "zlib"), ("control_suite/cartpole_swingup", "raw"),
     ("locomotion/rodent_gaps", "zlib")],
)  # fmt: skip
@pytest.mark.parametrize(
    "spec", [BatchSpec(16), BatchSpec(16, n_step=3, gamma=0.9, reward_clip=0.5)]
)
def test_device_sampler_gives_the_host_samplers_batches(task, encoding, spec, tmp_path):
    from rlu.data import make_sampler
    from rlu.data.torch import DeviceSampler

    schema = Schema.for_task(get_task(task), image_encoding=encoding)
    ds = open_dataset(write_synthetic(tmp_path / "ds", schema, 4, 12, vary_length=True))
    host, dev = make_sampler(ds, spec, seed=3), DeviceSampler(ds, spec, seed=3, device="cpu")
    for _ in range(4):
        _equal_batches(host.sample(), dev.sample())
    state = host.get_state()
    assert dev.get_state() == state
    expected = host.sample()
    dev.set_state(state)
    _equal_batches(expected, dev.sample())
    if schema.frame_stack > 1:  # frames are held once, as stored: the stacks are made by index
        assert dev.columns[""].shape == (ds.num_frames, 84, 84)
        assert dev.columns[""].dtype == torch.uint8


def test_device_sampler_refuses_a_dataset_that_does_not_fit_and_sequences(tmp_path, monkeypatch):
    import rlu.data.torch as adapter

    path = write_synthetic(tmp_path / "ds", Schema.for_task(get_task("atari/Pong")), 2, 10)
    monkeypatch.setattr(adapter, "_free_bytes", lambda device: 100_000)
    with pytest.raises(adapter.RluError, match=r"GiB free on cpu; drop --data-on-device"):
        adapter.DeviceSampler(path, BatchSpec(4), device="cpu")
    monkeypatch.undo()
    with pytest.raises(adapter.RluError, match="transition batches"):
        adapter.DeviceSampler(path, BatchSpec(4, "sequence", sequence_length=3), device="cpu")


class _Counting:
    """A sampler stand-in handing out numbered batches (its state: how many were drawn), failing
    at draw ``fail_at``."""

    def __init__(self, fail_at: int = 0):
        self.n, self.fail_at = 0, fail_at

    def sample(self):
        self.n += 1
        if self.n == self.fail_at:
            raise ValueError(f"draw {self.n} failed")
        return (np.full(3, self.n),)

    def get_state(self):
        return {"drawn": self.n}


def _prefetch_threads():
    import threading

    return [t for t in threading.enumerate() if t.name == "rlu-prefetch"]


def test_prefetcher_hands_out_the_samplers_batches_in_order_with_their_state(cartpole):
    from rlu.data import make_sampler
    from rlu.data.torch import Prefetcher

    ds = open_dataset(cartpole)
    reference = make_sampler(ds, BatchSpec(8, n_step=2, gamma=0.9), seed=4)
    with Prefetcher(make_sampler(ds, BatchSpec(8, n_step=2, gamma=0.9), seed=4), "cpu") as p:
        for _ in range(6):
            got, want = p.sample(), reference.sample()
            np.testing.assert_array_equal(got.reward, want.reward)
            np.testing.assert_array_equal(got.observation["position"], want.observation["position"])
            assert p.get_state() == reference.get_state()  # the last batch handed out's
    assert not _prefetch_threads()


def test_prefetcher_raises_the_threads_error_in_order_and_stops():
    from rlu.data.torch import Prefetcher

    p = Prefetcher(_Counting(fail_at=4), "cpu", depth=2)
    assert [int(p.sample()[0][0]) for _ in range(3)] == [1, 2, 3]
    assert p.get_state() == {"drawn": 3}
    with pytest.raises(ValueError, match="draw 4 failed"):
        p.sample()
    assert not _prefetch_threads()


def test_prefetcher_closes_while_its_thread_waits_on_a_full_queue():
    from rlu.data.torch import Prefetcher, prefetched

    sampler = _Counting()
    with Prefetcher(sampler, "cpu", depth=1) as p:
        assert int(p.sample()[0][0]) == 1
        assert _prefetch_threads()
    assert not _prefetch_threads()
    with prefetched(sampler, "cpu", 0) as same:
        assert same is sampler  # depth 0: sampled in line, no thread
