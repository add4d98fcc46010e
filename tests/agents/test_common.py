"""The helper stack's fast paths give the numbers of the plain forms they replace: metrics read
per item on the CPU, one foreach Polyak step over several target pairs, frames converted once
per batch (either layout), BCQ's targets kept for the parts that are read, BCQ's and DMPO's
target passes in slices."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from torch import nn  # noqa: E402

from rlu.agents import bcq, common, make_agent  # noqa: E402
from rlu.agents import discrete_common as dc  # noqa: E402
from rlu.types import RluError  # noqa: E402
from tests.fakes import CONT_ACTION, LOWDIM_OBS, fake_transition  # noqa: E402


def test_metrics_read_per_item_equal_the_stacked_read():
    grad = torch.tensor(0.1234567, requires_grad=True) * 3.0
    metrics = {
        "a/third": torch.tensor(1.0) / 3.0,
        "a/grad": grad,
        "a/int": torch.tensor(7),
        "a/flag": torch.tensor(True),
        "a/tiny": torch.tensor(1e-30),
    }
    values = common.metrics_to_floats(metrics)
    stacked = torch.stack([v.detach().float() for v in metrics.values()]).tolist()
    assert list(values) == list(metrics)
    assert list(values.values()) == stacked  # the very same float32 values, in order
    assert all(type(v) is float for v in values.values())


def test_soft_updates_is_soft_update_of_every_pair():
    torch.manual_seed(0)
    sources = [nn.Linear(3, 4), nn.Sequential(nn.Linear(4, 2), nn.ReLU(), nn.Linear(2, 1))]
    targets = [common.frozen_copy(nn.Linear(3, 4)), common.frozen_copy(sources[1])]
    untouched = common.frozen_copy(nn.Linear(3, 4))
    expected = [common.frozen_copy(t) for t in targets]
    for t, s in zip(expected, sources, strict=True):
        common.soft_update(t, s, 0.25)
    before = [p.clone() for p in untouched.parameters()]
    common.soft_updates(dict(zip(targets, sources, strict=True)), 0.25)
    for t, e in zip(targets, expected, strict=True):
        for p, q in zip(t.parameters(), e.parameters(), strict=True):
            assert torch.equal(p, q)
    assert all(torch.equal(p, q) for p, q in zip(untouched.parameters(), before, strict=True))


def test_frames_scale_once_in_either_layout_and_the_torso_reads_both():
    rng = np.random.default_rng(0)
    # frame-major memory seen as (B, H, W, C), as the views give stacks
    stacks = rng.integers(0, 256, (3, 4, 84, 84), dtype=np.uint8).transpose(0, 2, 3, 1)
    expected = torch.from_numpy(np.ascontiguousarray(stacks.transpose(0, 3, 1, 2))) * (1 / 255)
    plain = dc.frames(stacks)
    last = dc.frames(stacks, channels_last=True)
    assert plain.dtype == last.dtype == torch.float32 and plain.shape == (3, 4, 84, 84)
    assert torch.equal(plain, expected) and torch.equal(last, expected)
    assert last.is_contiguous(memory_format=torch.channels_last)
    assert plain.is_contiguous()
    torso = dc.NatureTorso((84, 84, 4), dc.SMALL)
    with torch.no_grad():
        from_uint8 = torso(torch.from_numpy(stacks))
        assert torch.equal(from_uint8, torso(plain))
        torch.testing.assert_close(torso(last), from_uint8)


def test_frames_refuse_a_missing_batch_axis():
    with pytest.raises(dc.SpecError, match="batch axis"):
        dc.frames(np.zeros((84, 84, 4), np.uint8))


def test_bcq_targets_follow_the_parts_they_are_read_through():
    agent = make_agent(
        "bcq", LOWDIM_OBS, CONT_ACTION, "small", seed=0,
        actor_layers=(8,), critic_layers=(8,), vae_layers=(8,), target_update_period=0,
    )  # fmt: skip
    target, nets = agent.target, agent.nets
    vae_before = [p.clone() for p in target.vae.parameters()]
    read_before = {k: [p.clone() for p in m.parameters()]
                   for k, m in target.target_parts().items()}  # fmt: skip
    agent.update(fake_transition(LOWDIM_OBS, CONT_ACTION, batch=6, seed=1))
    tau = agent.config.tau
    for key, part in target.target_parts().items():
        source = nets.target_parts()[key]
        for p, b, s in zip(part.parameters(), read_before[key], source.parameters(), strict=True):
            torch.testing.assert_close(p, torch.lerp(b, s, tau), rtol=0, atol=1e-7)
    # the target VAE is never read (the target decodes with the online VAE): left as built
    assert all(torch.equal(p, b) for p, b in zip(target.vae.parameters(), vae_before, strict=True))
    s, a = torch.randn(5, 24), torch.rand(5, 3) * 2 - 1
    assert torch.equal(nets.q_first(s, a), nets.q(s, a)[0])
    assert set(bcq.BCQNets.target_parts(nets)) == {"actor_enc", "actor", "critic_enc", "q1", "q2"}


def test_bcq_target_pass_in_slices_gives_the_one_pass_values_and_random_stream():
    sizes = dict(actor_layers=(16,), critic_layers=(16,), vae_layers=(16,), num_samples=10)
    whole = make_agent("bcq", LOWDIM_OBS, CONT_ACTION, "small", cpu_slice_rows=0, **sizes)
    sliced = make_agent("bcq", LOWDIM_OBS, CONT_ACTION, "small", cpu_slice_rows=7, **sizes)
    sliced.load_state_dict(whole.state_dict())
    batch = fake_transition(LOWDIM_OBS, CONT_ACTION, batch=6, seed=2)
    calls = {"whole": 0, "sliced": 0}
    for key, agent in (("whole", whole), ("sliced", sliced)):
        agent.target.q1.register_forward_hook(lambda *_, k=key: calls.__setitem__(k, calls[k] + 1))
    with torch.no_grad():
        values = [a.next_value(common.to_torch(batch.next_observation)) for a in (whole, sliced)]
    assert calls == {"whole": 1, "sliced": 9}  # 60 rows: 8 slices of 7 and one of 4
    assert values[0].shape == (60,)
    torch.testing.assert_close(values[1], values[0], rtol=1e-6, atol=1e-6)
    # the latents are drawn for all rows at once: the generators stay in step
    assert torch.equal(whole.generator.get_state(), sliced.generator.get_state())
    whole.update(batch)
    sliced.update(batch)
    for p, q in zip(whole.nets.parameters(), sliced.nets.parameters(), strict=True):
        torch.testing.assert_close(q, p, rtol=1e-5, atol=1e-6)


def test_dmpo_target_critic_in_slices_of_whole_samples_gives_the_one_pass_logits():
    sizes = dict(policy_layers=(16,), critic_layers=(16,), num_samples=10)
    whole = make_agent("dmpo", LOWDIM_OBS, CONT_ACTION, "small", cpu_slice_rows=0, **sizes)
    sliced = make_agent("dmpo", LOWDIM_OBS, CONT_ACTION, "small", cpu_slice_rows=13, **sizes)
    sliced.load_state_dict(whole.state_dict())
    batch = fake_transition(LOWDIM_OBS, CONT_ACTION, batch=6, seed=3)
    calls = {"whole": [], "sliced": []}
    for key, agent in (("whole", whole), ("sliced", sliced)):
        agent.target_critic.head.register_forward_hook(
            lambda _m, args, _out, k=key: calls[k].append(tuple(args[0].shape))
        )
    next_obs = common.to_torch(batch.next_observation)
    actions = torch.randn(10, 6, 3)
    with torch.no_grad():
        logits = [a.sampled_logits(next_obs, actions) for a in (whole, sliced)]
    # 13 rows of 6 states: 2 whole samples a slice, 5 slices
    assert calls == {"whole": [(10, 6, 16)], "sliced": [(2, 6, 16)] * 5}
    assert logits[0].shape == (10, 6, whole.config.num_atoms)
    torch.testing.assert_close(logits[1], logits[0], rtol=1e-6, atol=1e-6)
    whole.update(batch)
    sliced.update(batch)
    for p, q in zip(whole.policy.parameters(), sliced.policy.parameters(), strict=True):
        torch.testing.assert_close(q, p, rtol=1e-5, atol=1e-6)
    for p, q in zip(whole.critic.parameters(), sliced.critic.parameters(), strict=True):
        torch.testing.assert_close(q, p, rtol=1e-5, atol=1e-6)


def test_passes_are_sliced_on_a_cpu_only():
    assert common.cpu_slices(torch.device("cpu"), 7, 60) == 7
    assert common.cpu_slices(torch.device("cpu"), 0, 60) == 60  # 0: one pass
    assert common.cpu_slices(torch.device("meta"), 7, 60) == 60  # any other device: one pass
    assert common.cpu_slices(torch.device("meta"), 7, 0) == 1  # an empty pass splits evenly


@pytest.mark.parametrize("agent", ["bcq", "dmpo"])
@pytest.mark.parametrize("rows", [-1, 2.5, True])
def test_a_slice_that_is_not_a_row_count_is_refused(agent, rows):
    with pytest.raises(RluError, match="cpu_slice_rows"):
        make_agent(agent, LOWDIM_OBS, CONT_ACTION, "small", cpu_slice_rows=rows)


def test_encoder_flatten_once_gives_the_features_of_every_dict_pass():
    from rlu.agents import networks as nets
    from rlu.types import ArraySpec

    spec = {"b": ArraySpec((3,), np.float32), "a": ArraySpec((2, 2), np.float32),
            "c": ArraySpec((), np.float64)}  # fmt: skip
    enc = nets.Encoder(spec)
    rng = np.random.default_rng(0)
    obs = {"b": torch.from_numpy(rng.standard_normal((5, 3)).astype(np.float32)),
           "a": torch.from_numpy(rng.standard_normal((5, 2, 2)).astype(np.float32)),
           "c": torch.from_numpy(rng.standard_normal(5))}  # fmt: skip
    flat = enc.flatten(obs)
    expected = torch.cat([obs["a"].reshape(5, 4), obs["b"], obs["c"].reshape(5, 1).float()], -1)
    assert flat.dtype == torch.float32 and torch.equal(flat, expected)  # sorted keys, float32
    assert torch.equal(enc(flat), enc(obs))
    seq = {k: v.unsqueeze(0).expand(2, *v.shape) for k, v in obs.items()}  # (T, B, ...) windows
    assert torch.equal(enc(enc.flatten(seq, batch_dims=2), batch_dims=2), enc(seq, batch_dims=2))
    frames = {"pixels": ArraySpec((8, 8, 3), np.uint8), "b": ArraySpec((3,), np.float32)}
    with_images = nets.Encoder(frames)
    batch = {"pixels": torch.zeros(5, 8, 8, 3, dtype=torch.uint8), "b": obs["b"]}
    assert with_images.flatten(batch) is batch  # the torso needs the frames: nothing to fold


def test_batches_of_one_kind_are_joined_and_mixed_kinds_refused():
    from rlu.agents.networks import cat_batches

    a, b = torch.zeros(2, 3), torch.ones(1, 3)
    assert cat_batches(a, b).tolist() == [[0.0] * 3, [0.0] * 3, [1.0] * 3]
    joined = cat_batches({"x": a}, {"x": b})
    assert set(joined) == {"x"} and joined["x"].shape == (3, 3)
    with pytest.raises(RluError, match="dicts and tensors"):
        cat_batches({"x": a}, b)


def test_bcq_decoding_without_latents_needs_the_agents_generator():
    vae = bcq.VAE(3, 2, (8,))
    s, g = torch.zeros(4, 3), torch.Generator().manual_seed(0)
    assert vae.decode(s, g).shape == (4, 2)
    with pytest.raises(RluError, match="give z or the generator"):
        vae.decode(s)  # torch's global generator would draw the latents
