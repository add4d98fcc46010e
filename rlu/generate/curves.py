"""The behaviour runs' learning curves, read back from a generated dataset's manifest.

``rlu generate`` records every episode's return and length per run in the manifest's
provenance (``runs``), also the episodes selection dropped, so the curves of the runs behind a
dataset can be drawn from the dataset alone:

    rlu generate control_suite/cartpole_swingup --scale laptop --out data/cp --curves cp.png

``summarise`` gives per run the episodes, env steps, the best mean return over ``WINDOW``
consecutive episodes (the behaviour level a run reached, exploration noise included) and where
it got there, and the mean of its last ``WINDOW`` episodes; ``plot`` draws return against env
steps, one line per run (matplotlib, the ``report`` extra).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rlu.files import atomic_path
from rlu.types import RluError

WINDOW = 10
"""Episodes in the moving mean that defines a run's level (the laptop scale's targets)."""


@dataclass(frozen=True)
class RunCurve:
    run: int
    episode_return: np.ndarray
    """Every recorded episode's return, in the order played."""
    env_steps: np.ndarray
    """Env steps played by the end of each episode."""


@dataclass(frozen=True)
class RunSummary:
    run: int
    episodes: int
    env_steps: int
    best_mean: float
    """Best mean return over ``WINDOW`` consecutive episodes (over all when fewer)."""
    best_at_steps: int
    """Env steps at the end of that window."""
    final_mean: float
    """Mean return of the last ``WINDOW`` episodes."""


def read_curves(provenance: Mapping[str, Any], where: str = "manifest") -> list[RunCurve]:
    runs = provenance.get("runs")
    if not runs:
        raise RluError(
            f"{where}: provenance has no 'runs' (learning curves); only datasets written by "
            "rlu generate record them: regenerate it with its recorded command"
        )
    return [
        RunCurve(
            int(r["run"]),
            np.asarray(r["episode_return"], np.float64),
            np.cumsum(np.asarray(r["episode_steps"], np.int64)),
        )
        for r in runs
    ]


def dataset_curves(path: str | Path) -> tuple[list[RunCurve], Mapping[str, Any]]:
    """The curves and the provenance of the generated dataset at ``path``."""
    from rlu.data import open_dataset

    prov = open_dataset(path).manifest.get("provenance", {})
    return read_curves(prov, f"{Path(path) / 'manifest.json'}"), prov


def moving_mean(x: np.ndarray, window: int = WINDOW) -> np.ndarray:
    """Mean of each ``window`` consecutive values (one value, the mean, when fewer)."""
    if x.size == 0:
        return x
    if x.size < window:
        return np.array([x.mean()])
    c = np.concatenate([[0.0], np.cumsum(x)])
    return (c[window:] - c[:-window]) / window


def summarise(curves: Sequence[RunCurve], window: int = WINDOW) -> list[RunSummary]:
    out = []
    for c in curves:
        if c.episode_return.size == 0:
            out.append(RunSummary(c.run, 0, 0, float("nan"), 0, float("nan")))
            continue
        m = moving_mean(c.episode_return, window)
        i = int(np.argmax(m))
        end = min(i + window, c.env_steps.size) - 1
        out.append(
            RunSummary(
                c.run,
                int(c.episode_return.size),
                int(c.env_steps[-1]),
                float(m[i]),
                int(c.env_steps[end]),
                float(c.episode_return[-window:].mean()),
            )
        )
    return out


def markdown_table(summaries: Sequence[RunSummary], target: float | None = None) -> str:
    head = f"| run | episodes | env steps | best {WINDOW}-episode mean (at step) | last {WINDOW} |"
    sep = "|---:|---:|---:|---:|---:|"
    if target is not None:
        head += f" reached {target:g} |"
        sep += "---|"
    lines = [head, sep]
    for s in summaries:
        row = (
            f"| {s.run} | {s.episodes} | {s.env_steps:,} | {s.best_mean:.1f} "
            f"({s.best_at_steps:,}) | {s.final_mean:.1f} |"
        )
        if target is not None:
            row += f" {'yes' if s.best_mean >= target else 'no'} |"
        lines.append(row)
    return "\n".join(lines)


def plot(
    curves: Sequence[RunCurve], png: str | Path, title: str, target: float | None = None
) -> Path:
    """Return against env steps, one line per run: each episode faint, the ``WINDOW``-episode
    moving mean solid; a dashed line at ``target``."""
    try:
        import matplotlib
    except ImportError as e:
        raise RluError("--curves draws with matplotlib: bash scripts/install.sh report") from e
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    png = Path(png)
    png.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for c in curves:
        color = colors[c.run % len(colors)]
        ax.plot(c.env_steps, c.episode_return, color=color, alpha=0.25, linewidth=0.8)
        m = moving_mean(c.episode_return)
        if c.episode_return.size >= WINDOW:
            ax.plot(c.env_steps[WINDOW - 1 :], m, color=color, linewidth=1.8, label=f"run {c.run}")
        else:
            ax.plot(c.env_steps, c.episode_return, color=color, label=f"run {c.run}")
    if target is not None:
        ax.axhline(target, color="k", linestyle="--", linewidth=1, label=f"target {target:g}")
    ax.set_xlabel("env steps")
    ax.set_ylabel("episode return")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    try:
        with atomic_path(png) as tmp:
            fig.savefig(tmp, dpi=110, format="png", metadata={"Software": None})
    finally:
        plt.close(fig)
    return png
