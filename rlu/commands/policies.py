"""``rlu policies`` and ``rlu evaluate-behaviour``: the behaviour policies a generated dataset
keeps (rlu.generate.policies), listed, rolled out, and valued by FQE (an off-policy evaluation
study)."""

from __future__ import annotations

import argparse
import json
import math

from rlu.commands._options import checked
from rlu.commands.train import add_device_option


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "policies",
        help="list the behaviour policies a generated dataset keeps (one per run and checkpoint)",
        description="Each row: a kept behaviour policy, the env steps of its run when it was "
        "taken, and the returns of its checkpoint's episodes (recorded by the run, and kept in "
        "the dataset).",
    )
    p.add_argument(
        "dataset",
        help="a dataset rlu generate wrote, as rlu.load_dataset names it (a folder, or a task id: "
        "control_suite/cartpole_swingup is the one rlu ships)",
    )
    p.add_argument("--json", action="store_true", help="print the list as JSON")
    p.set_defaults(func=_list)

    p = sub.add_parser(
        "evaluate-behaviour",
        help="roll out a dataset's behaviour policies in the env; --fqe: an OPE study",
        description="Rolls out the behaviour policy of --run/--checkpoint (default: every kept "
        "one) and prints its mean return. --fqe also estimates each policy's value from the "
        "data alone by Fitted Q Evaluation and prints the Spearman rank correlation of the "
        "estimates with the rolled-out returns (FQE values the discounted return; the "
        "roll-outs are undiscounted: compare ranks).",
    )
    p.add_argument(
        "dataset",
        help="a dataset rlu generate wrote, as rlu.load_dataset names it (a folder, or a task id: "
        "control_suite/cartpole_swingup is the one rlu ships)",
    )
    p.add_argument("--run", type=_index, default=None, help="run (default: every kept policy)")
    p.add_argument("--checkpoint", type=_index, default=None, help="checkpoint id (with --run)")
    p.add_argument("--episodes", type=_count, default=10, help="episodes rolled out per policy")
    p.add_argument("--seed", type=_index, default=0, help="seeds the env resets (and the noise)")
    p.add_argument("--envs", type=_count, default=4, help="envs stepped in lockstep")
    p.add_argument(
        "--exploration",
        action="store_true",
        help="act with the behaviour noise (D4PG: sigma; DQN: the schedule's epsilon), as the "
        "data was recorded; default: deterministic",
    )
    p.add_argument("--fqe", action="store_true", help="also the FQE estimate of each policy")
    # measured on a laptop-scale cartpole swingup run's 6 checkpoints (docs/behaviour_policies.md):
    # FQE's own defaults (2000 steps, target copied every 100) bootstrap only ~20 times, too few
    # to reach the swing-up's rewards from the first observations (estimates all near 0,
    # Spearman -0.2); 20000 steps with a copy every 20 ranked the 6 policies exactly (1.0)
    p.add_argument("--fqe-steps", type=_count, default=20_000, help="FQE gradient steps")
    p.add_argument(
        "--fqe-target-period",
        type=_count,
        default=20,
        help="FQE steps between target-network copies",
    )
    p.add_argument("--threads", type=_count, default=1, help="torch threads (default 1)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress of the FQE steps (stderr)")
    add_device_option(p)
    p.set_defaults(func=_evaluate)


_count = checked(int, {"min": 1}, "this option")
_index = checked(int, {"min": 0}, "this option")


def _fmt(x: float) -> str:
    return "-" if math.isnan(x) else f"{x:.1f}"


def _list(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from rlu.data import load_dataset
    from rlu.generate.policies import list_policies

    rows = list_policies(load_dataset(args.dataset))
    if args.json:
        # NaN (no recorded episodes) is not JSON: null
        print(json.dumps([{k: None if isinstance(v, float) and math.isnan(v) else v
                           for k, v in asdict(r).items()} for r in rows]))  # fmt: skip
        return 0
    if not rows:
        print(f"{args.dataset}: no behaviour policies (made before rlu kept them, or by "
              "--policy / rwrl generation)")  # fmt: skip
        return 0
    print("| run | checkpoint | env steps | recorded episodes | recorded mean return "
          "| kept episodes | kept mean return |")  # fmt: skip
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r.run} | {r.checkpoint} | {r.env_steps:,} | {r.recorded_episodes} | "
              f"{_fmt(r.recorded_mean)} | {r.kept_episodes} | {_fmt(r.kept_mean)} |")  # fmt: skip
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    from rlu.types import RluError

    if (args.run is None) != (args.checkpoint is None):
        raise RluError("give --run and --checkpoint together (or neither: every kept policy)")
    if args.episodes < 1:
        raise RluError(f"--episodes {args.episodes}; roll out at least 1")
    if args.threads < 1:
        raise RluError(f"--threads {args.threads}; use 1 or more")
    import torch

    from rlu.data import load_dataset
    from rlu.generate.policies import behaviour_ope, list_policies, rollout_behaviour

    torch.set_num_threads(args.threads)
    device = args.device
    ds = load_dataset(args.dataset)
    which = None if args.run is None else [(args.run, args.checkpoint)]
    if args.fqe:
        if args.exploration:
            raise RluError("--fqe values the deterministic policies; drop --exploration")
        from rlu.evaluation.fqe import FQEConfig

        fqe = FQEConfig(steps=args.fqe_steps, target_period=args.fqe_target_period)
        res = behaviour_ope(ds, which, args.episodes, fqe, args.seed, args.envs, device,
                            quiet=args.quiet)  # fmt: skip
        if args.json:
            rho = res["spearman"]
            print(json.dumps({**res, "spearman": None if math.isnan(rho) else rho}))
            return 0
        print("| run | checkpoint | env steps | FQE estimate | return (rolled out) "
              "| recorded mean return |")  # fmt: skip
        print("|---:|---:|---:|---:|---:|---:|")
        for r in res["policies"]:
            print(f"| {r['run']} | {r['checkpoint']} | {r['env_steps']:,} | "
                  f"{r['fqe_estimate']:.2f} | {r['return']:.1f} | "
                  f"{_fmt(r['recorded_mean'])} |")  # fmt: skip
        print(f"Spearman rank correlation (FQE estimate vs return): {res['spearman']:.3f}"
              if not math.isnan(res["spearman"]) else
              "Spearman rank correlation: undefined (fewer than 2 policies, or ties)")  # fmt: skip
        return 0
    pairs = which or [(p.run, p.checkpoint) for p in list_policies(ds)]
    if not pairs:
        raise RluError(f"{args.dataset}: keeps no behaviour policy; nothing to roll out")
    out = []
    for run, checkpoint in pairs:
        res = rollout_behaviour(ds, run, checkpoint, args.episodes, args.seed, args.exploration,
                                args.envs, device)  # fmt: skip
        out.append({"run": run, "checkpoint": checkpoint, **res.to_json()})
        if not args.json:
            print(
                f"run {run} checkpoint {checkpoint}: {len(res.returns)} episodes, mean return "
                f"{res.mean:.1f} (" + ", ".join(f"{x:.1f}" for x in res.returns) + ")"
            )
    if args.json:
        print(json.dumps(out))
    return 0
