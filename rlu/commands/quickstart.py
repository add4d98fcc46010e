"""``rlu quickstart``: the README's main job.

For now an end-to-end round trip of the data layer on a synthetic dataset in the exact schema of
control_suite/cartpole_swingup: write it atomically, validate it, sample SARSA / n-step / sequence
batches, export it to the D4RL layout and import it back.
"""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("quickstart", help="run the small end-to-end job (see README)")
    p.add_argument("--out", default="runs/quickstart", help="working directory")
    p.add_argument("--episodes", type=int, default=40)
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    import shutil
    import time
    from pathlib import Path

    import numpy as np

    from rlu.data import Schema, TransitionView, open_dataset, sequence_sampler, transition_sampler
    from rlu.data.d4rl import export_d4rl, import_d4rl
    from rlu.data.synthetic import write_synthetic
    from rlu.data.validate import validate
    from rlu.tasks import get_task

    task = get_task("control_suite/cartpole_swingup")
    out = Path(args.out)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    t0 = time.perf_counter()
    path = write_synthetic(
        out / "synthetic", Schema.for_task(task), args.episodes, task.episode_length, args.seed
    )
    ds = open_dataset(path)
    print(f"1. wrote {ds.num_steps} steps in {len(ds)} synthetic episodes of {task.id} -> {path}")
    report = validate(path)
    print(
        f"2. validate: {'valid' if report.ok else report.problems} ({len(report.checked)} checks)"
    )
    b = transition_sampler(ds, 256, seed=args.seed).sample()
    nb = transition_sampler(ds, 256, seed=args.seed, n_step=5, gamma=0.99).sample()
    sb = sequence_sampler(ds, 16, length=40, seed=args.seed).sample()
    print(
        f"3. sampled SARSA {b.action.shape[0]}x(obs {sorted(b.observation)}), 5-step batch "
        f"(mean reward {nb.reward.mean():.3f}), sequences {sb.mask.shape}"
    )
    npz = export_d4rl(ds, out / "synthetic_d4rl.npz")
    back = open_dataset(import_d4rl(npz, out / "reimported", task.id))
    same = np.array_equal(TransitionView(back).all().reward, TransitionView(ds).all().reward)
    print(f"4. D4RL export -> {npz.name} -> import: {len(back)} episodes, rewards equal: {same}")
    print(f"done in {time.perf_counter() - t0:.1f}s; files under {out}")
    return 0 if report.ok and same else 1
