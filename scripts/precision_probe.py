"""How far one bf16 update's gradients are from fp32's, next to how far another batch's are.

    python scripts/precision_probe.py AGENT DATASET_DIR [--preset small] [--at 0 2000 10000]
                                      [--pairs 8] [--seed 0]

The agent (built with ``rlu.agents.make_agent``) trains in fp32 on the dataset. At each step
of ``--at`` it is copied through its own checkpoint (``state_dict`` / ``load_state_dict``: the
same weights, optimiser states and generators) and, for ``--pairs`` pairs of batches (b, b'),
three copies each take one update: on b in fp32, on b under the bf16 autocast that
``--precision bf16`` trains with (``rlu.devices.numerics``), and on b' in fp32. Per optimiser,
the gradients each copy's update left on its parameters are compared:

- ``bf16``: ||g_bf16(b) - g_fp32(b)|| / ||g_fp32(b)|| and their cosine: what bf16 changes;
- ``batch``: ||g_fp32(b') - g_fp32(b)|| / ||g_fp32(b)|| and their cosine: what drawing another
  minibatch changes, the noise every SGD step already has.

A bf16 error well under the batch noise perturbs each step by less than sampling does; one
near it or above is a change to what the agent learns. Rounding that pushes every step the same
way would add up where sampling noise averages out, so each kind of difference also gets its
coherence over the pairs: ||mean of the differences|| / mean of their norms, about
1 / sqrt(pairs) for differences in unrelated directions and 1 for the same one every time.
docs/devices.md has the figures.
"""

from __future__ import annotations

import argparse
import functools
import math

import numpy as np
import torch

from rlu.agents import make_agent
from rlu.data import make_sampler, open_dataset
from rlu.devices import Runtime, numerics
from rlu.types import RluError


def gradients(agent) -> dict[str, torch.Tensor]:
    """Per optimiser, its parameters' gradients after an update, flattened into one vector
    (parameters the update left without a gradient are skipped; an optimiser none of whose
    parameters has one is left out)."""
    out = {}
    for name, opt in agent.optimizers.items():
        grads = [p.grad.reshape(-1) for g in opt.param_groups for p in g["params"]
                 if p.grad is not None]  # fmt: skip
        if grads:
            out[name] = torch.cat(grads).double()
    return out


def compare(reference: torch.Tensor, other: torch.Tensor) -> tuple[float, float]:
    """(||other - reference|| / ||reference||, cosine(reference, other))."""
    norm = reference.norm().item()
    if norm == 0.0:
        return math.nan, math.nan
    rel = (other - reference).norm().item() / norm
    cos = torch.nn.functional.cosine_similarity(reference, other, dim=0).item()
    return rel, cos


def coherence(differences: list[torch.Tensor]) -> float:
    """||mean of the vectors|| / mean of their norms: 1 when they all point the same way, about
    1 / sqrt(n) for n vectors of similar size in unrelated directions."""
    mean_norm = float(np.mean([d.norm().item() for d in differences]))
    return torch.stack(differences).mean(0).norm().item() / mean_norm if mean_norm else math.nan


def probe(agent_name, ds, preset, at, pairs, seed) -> list[dict]:
    """Rows of {step, optimizer, bf16_rel, bf16_cos, batch_rel, batch_cos} (each the median over
    ``pairs`` batch pairs at one step of fp32 training) and {bf16_coherence,
    batch_coherence} (of the differences over the pairs)."""
    spec = ds.schema
    build = functools.partial(make_agent, agent_name, spec.observation, spec.action, preset, seed)
    agent = build()
    train = make_sampler(ds, agent.batch_spec, seed=seed)
    probes = make_sampler(ds, agent.batch_spec, seed=seed + 1)
    bf16 = Runtime(precision="bf16").resolve()
    rows = []
    for target in sorted(set(at)):
        while agent.step < target:
            agent.update(train.sample())
        state = agent.state_dict()
        cells: dict[str, list[tuple[float, float, float, float]]] = {}
        diffs: dict[str, tuple[list[torch.Tensor], list[torch.Tensor]]] = {}
        for i in range(pairs):
            b, b2 = probes.sample(), probes.sample()
            runs = []
            # the first pair also reruns fp32 on b: the copies must be exact for the rest to
            # mean anything (same weights, optimiser states and generators)
            plan = ((b, False), (b, True), (b2, False)) + (((b, False),) if i == 0 else ())
            for batch, low in plan:
                twin = build()
                twin.load_state_dict(state)
                if low:
                    with numerics(bf16) as context, context():
                        twin.update(batch)
                else:
                    twin.update(batch)
                runs.append(gradients(twin))
            ref, low, other = runs[:3]
            if i == 0 and any(not torch.equal(ref[k], runs[3][k]) for k in ref):
                raise RluError(
                    f"{agent_name}: two fp32 updates of the same copy on the same batch gave "
                    "other gradients, so the copies are not exact; run with one torch thread "
                    "and check the agent's state_dict holds all it draws from"
                )
            for name in ref:
                if name in low and name in other:
                    cells.setdefault(name, []).append(
                        compare(ref[name], low[name]) + compare(ref[name], other[name])
                    )
                    low_diffs, batch_diffs = diffs.setdefault(name, ([], []))
                    low_diffs.append(low[name] - ref[name])
                    batch_diffs.append(other[name] - ref[name])
        for name, values in cells.items():
            med = np.median(np.array(values), axis=0)
            rows.append({"step": agent.step, "optimizer": name, "bf16_rel": med[0],
                         "bf16_cos": med[1], "batch_rel": med[2], "batch_cos": med[3],
                         "bf16_coherence": coherence(diffs[name][0]),
                         "batch_coherence": coherence(diffs[name][1])})  # fmt: skip
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("agent")
    p.add_argument("dataset")
    p.add_argument("--preset", default="small")
    p.add_argument("--at", type=int, nargs="+", default=[0, 2000, 10000])
    p.add_argument("--pairs", type=int, default=8)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    if args.pairs < 1 or min(args.at) < 0:
        raise SystemExit("error: --pairs must be 1 or more and every --at step 0 or more")
    torch.set_num_threads(1)
    try:
        ds = open_dataset(args.dataset)
        rows = probe(args.agent, ds, args.preset, args.at, args.pairs, args.seed)
    except RluError as e:
        raise SystemExit(f"error: {e}") from None
    print(f"{args.agent} ({args.preset}) on {args.dataset}; median of {args.pairs} batch pairs; "
          f"coherence of unrelated differences ~ {1 / math.sqrt(args.pairs):.2f}")  # fmt: skip
    print("| step | optimiser | bf16: rel. error | bf16: cosine | other batch: rel. change "
          "| other batch: cosine | bf16 / batch | coherence: bf16 "
          "| coherence: batch |")  # fmt: skip
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['step']} | {r['optimizer']} | {r['bf16_rel']:.4f} | {r['bf16_cos']:.4f} "
              f"| {r['batch_rel']:.4f} | {r['batch_cos']:.4f} "
              f"| {r['bf16_rel'] / r['batch_rel']:.3f} | {r['bf16_coherence']:.2f} "
              f"| {r['batch_coherence']:.2f} |")  # fmt: skip


if __name__ == "__main__":
    main()
