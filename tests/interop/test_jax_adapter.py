"""The JAX adapter: device arrays named as the batch; the same stream with or without prefetch."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

jax = pytest.importorskip("jax")

from rlu.data import Schema, open_dataset, transition_sampler  # noqa: E402
from rlu.data.jax import JaxBatches, to_jax  # noqa: E402
from rlu.data.synthetic import write_synthetic  # noqa: E402
from rlu.tasks import get_task  # noqa: E402
from rlu.types import BatchSpec, Sequence, Transition  # noqa: E402

CARTPOLE = Schema.for_task(get_task("control_suite/cartpole_swingup"))


@pytest.fixture(scope="module")
def cartpole(tmp_path_factory):
    return write_synthetic(tmp_path_factory.mktemp("jax") / "ds", CARTPOLE, 3, 40, seed=2)


def test_to_jax_keeps_names_values_and_dtypes(tmp_path):
    path = write_synthetic(tmp_path / "ds", Schema.for_task(get_task("atari/Pong")), 2, 6)
    b = transition_sampler(open_dataset(path), 4, seed=0).sample()
    j = to_jax(b)
    assert isinstance(j, Transition)
    assert isinstance(j.observation, jax.Array) and j.observation.shape == (4, 84, 84, 4)
    assert j.observation.dtype == np.uint8 and j.reward.dtype == np.float32
    # int64 actions become jax's default integer (int32 unless jax_enable_x64), values kept
    assert j.action.dtype == jax.dtypes.canonicalize_dtype(np.int64)
    for x, y in zip(jax.tree_util.tree_leaves(j), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), y)
    assert j.observation.devices() == {jax.devices()[0]}


def test_dict_observations_and_sequences(cartpole):
    spec = BatchSpec(5, "sequence", sequence_length=7)
    with JaxBatches(str(cartpole), spec, seed=1, prefetch=0) as it:
        b = next(it)
    assert isinstance(b, Sequence)
    assert set(b.observation) == {"position", "velocity"}
    assert b.observation["position"].shape == (5, 7, 3) and b.mask.dtype == np.bool_


@pytest.mark.parametrize("prefetch", [0, 1, 3])
def test_prefetch_gives_the_samplers_stream(cartpole, prefetch):
    ref = transition_sampler(open_dataset(cartpole), 8, seed=9)
    with JaxBatches(str(cartpole), BatchSpec(8), seed=9, prefetch=prefetch) as it:
        for _ in range(6):
            got, want = next(it), ref.sample()
            np.testing.assert_array_equal(np.asarray(got.reward), want.reward)
            np.testing.assert_array_equal(
                np.asarray(got.next_observation["velocity"]), want.next_observation["velocity"]
            )
    assert it._thread is None  # closed


def test_a_jitted_update_consumes_the_batches(cartpole):
    import jax.numpy as jnp

    @jax.jit
    def td(b, w):
        q = b.observation["position"] @ w
        q2 = b.next_observation["position"] @ w
        return jnp.mean((b.reward + 0.99 * b.discount * q2 - q) ** 2)

    w = jnp.ones(3)
    with JaxBatches(str(cartpole), BatchSpec(16), seed=0, prefetch=2) as it:
        losses = [float(td(next(it), w)) for _ in range(3)]
    assert all(np.isfinite(losses))


def test_errors_in_the_prefetch_thread_reach_the_caller(tmp_path):
    path = write_synthetic(tmp_path / "ds", CARTPOLE, 1, 5)
    it = JaxBatches(str(path), BatchSpec(4), prefetch=2)
    (path / "steps" / "reward.bin").unlink()  # the column is mapped lazily, on the first sample
    with pytest.raises(Exception, match="reward.bin"):
        next(it)
    it.close()


def test_neither_adapter_is_imported_unless_used():
    code = (
        "import sys, rlu.data, rlu.data.minari, rlu.data.d3rlpy_io, rlu.data.d4rl;"
        "print([m for m in ('jax', 'torch', 'minari', 'd3rlpy', 'h5py', 'gymnasium')"
        " if m in sys.modules])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
