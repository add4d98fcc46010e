"""Where one update's time goes, for rlu, its minimal loop and d3rlpy: the evidence behind the
ratios of bench/agents_continuous.py and bench/agents_discrete.py.

    .venv-bench/bin/python bench/agents_profile.py bcq double_dqn --updates 5
    .venv-bench/bin/python bench/agents_profile.py bc --ops 12      # the 12 costliest ops too

Each contestant is built exactly as in those benches (same data, sizes, batch), warmed up, then
``--updates`` updates on pre-drawn batches run under ``torch.profiler``. The time is split into
the dense kernels (matrix products and convolutions, forward and backward: the arithmetic both
libraries ask of the same oneDNN / MKL), Adam and the target updates (fused or foreach kernels),
every other aten op (elementwise, reductions, copies, layout changes) and what is left of the
update's wall time outside aten ops (Python, dispatch, the profiler's own bookkeeping). Where
d3rlpy has the algorithm, a last line gives the ratio's ceiling: d3rlpy's update time over rlu's
dense kernels and optimizer alone, the most any loop doing rlu's arithmetic could reach. The
profiler clocks ops on the wall, so the shares are of wall time: on a loaded machine they stay
meaningful as long as the load hits every op alike. It also counts aten ops per update, a figure
the machine's load does not move, and each contestant's floating-point operations per update
(``torch.utils.flop_counter``: matrix products and convolutions, forward and backward), which
shows whether two libraries ask for the same arithmetic.

The profiled ceiling is a ratio of two profiled runs taken one after the other, which a shared
machine's load can move a lot (on 2026-12-01 one contestant's elementwise ops ran up to 10x
slower in one run and not in the next, most likely a neighbour's memory traffic). ``--replay``
measures it interleaved instead: one rlu update is recorded below autograd (a
``TorchDispatchMode``) and its dense kernels and optimizer ops are replayed on copies of their
real arguments, the same shapes, strides and values; that replay and d3rlpy's update are timed
in alternation (bench/agents_timing.py), and the ceiling is d3rlpy's update over the replay.
Names: a continuous agent as in agents_continuous.py (``bc``, ``bcq``, ``d4pg``, ...), a
discrete one as in agents_discrete.py (``dqn``, ``double_dqn``, ``iqn``, ...; ``--batch`` sets
its batch).
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_map
from torch.utils.flop_counter import FlopCounterMode

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import agents_continuous as cont  # noqa: E402
import agents_discrete as disc  # noqa: E402
from agents_timing import Contestant, cpu_line, load_line, time_contestants  # noqa: E402

from rlu.agents import make_agent  # noqa: E402
from rlu.data import make_sampler  # noqa: E402

DENSE = (
    "aten::addmm", "aten::mm", "aten::bmm", "aten::baddbmm", "aten::mkldnn_convolution",
    "aten::convolution_backward", "aten::_convolution", "aten::linear", "aten::matmul",
)  # fmt: skip
# what the replay keeps, as seen below autograd: the dense kernels, Adam, the target updates
REPLAYED = {"addmm", "mm", "bmm", "baddbmm", "convolution", "convolution_backward"}
OPTIMIZER = ("_fused_adam", "_foreach_")


def contestants(name: str, ds_c, ds_d, batch: int, d3rlpy: bool, same_network: bool = False):
    """{label: (update, batch)} built as the benches build them; ``same_network``: the benches'
    same-network rows (BC and CRR with one Gaussian, d3rlpy on rlu's networks; IQN in d3rlpy
    on rlu's network)."""
    out = {}
    if name in cont.SETTINGS:
        one = {"mixture_components": 1} if same_network else {}
        agent = make_agent(
            name, cont.OBS, cont.ACTION, "paper", 0, **{**cont.SETTINGS[name], **one}
        )
        spec, ds = agent.batch_spec, ds_c
        out["rlu"] = (agent.update, make_sampler(ds, spec, 0).sample())
        if name in cont.MINIMAL:
            update, _ = cont.MINIMAL[name](agent.config)
            mini = cont.MinimalSampler(ds, spec.batch_size, spec.n_step, spec.gamma)
            out["minimal loop"] = (update, mini.sample())
        if d3rlpy:
            buffer = cont.d3rlpy_buffer(ds)
            d3 = cont.d3rlpy_contestant(name, agent.config, buffer, same_network)
            if d3 is not None:
                out["d3rlpy"] = (d3.update, d3.sample())
        return out
    agent_name, overrides = disc.AGENT_SETTINGS[name]
    agent = make_agent(agent_name, disc.OBS, disc.ACTION, "paper", 0,
                       **overrides, **{"atari.batch_size": batch})  # fmt: skip
    out["rlu"] = (agent.update, make_sampler(ds_d, agent.batch_spec, 0).sample())
    update, _ = disc.MINIMAL[name](agent.config)
    mini = disc.MinimalSampler(ds_d, batch, agent.config.atari.reward_clip)
    out["minimal loop"] = (update, mini.sample())
    if d3rlpy:
        if same_network and name == "iqn":
            config = disc.d3rlpy_iqn_same_network(agent.config)
        else:
            config = disc.d3rlpy_algo(name, agent.config)
        if config is not None:
            buffer = disc.d3rlpy_buffer(ds_d)
            algo = config.create(device="cpu:0")
            algo.build_with_dataset(buffer)
            out["d3rlpy"] = (algo.update, buffer.sample_transition_batch(batch))
    return out


def breakdown(update, batch, updates: int, ops: int) -> tuple[float, float]:
    """Print where one update's wall time goes; return (wall, dense kernels + optimizer) in ms."""
    for _ in range(3):
        update(batch)
    w0, c0 = time.perf_counter(), time.process_time()
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(updates):
            update(batch)
    # the profiler times ops on the wall clock, so the shares are of the wall time
    wall = (time.perf_counter() - w0) / updates * 1e3
    cpu = (time.process_time() - c0) / updates * 1e3
    aten = [e for e in prof.key_averages() if e.key.startswith("aten::")]
    ms = {e.key: e.self_cpu_time_total / updates / 1e3 for e in aten}
    count = sum(e.count for e in aten) / updates
    dense = sum(v for k, v in ms.items() if k in DENSE)
    # Adam (fused, or foreach as d3rlpy's) and foreach target updates
    optim = sum(v for k, v in ms.items() if k.startswith(("aten::_foreach", "aten::_fused")))
    other = sum(ms.values()) - dense - optim
    rest = max(wall - dense - optim - other, 0.0)
    print(
        f"    {cpu:7.2f} ms CPU, {wall:7.2f} ms wall per update (profiled); of the wall: dense "
        f"kernels {dense / wall:4.0%}, Adam and target updates {optim / wall:4.0%}, other aten "
        f"ops {other / wall:4.0%}, outside aten ops {rest / wall:4.0%}; {count:.0f} aten ops"
    )
    for key, value in sorted(ms.items(), key=lambda kv: -kv[1])[:ops]:
        print(f"      {key:40s} {value:8.3f} ms")
    return wall, dense + optim


def gflop(update, batch) -> float:
    """Floating-point operations of one update (products and convolutions), in GFLOP."""
    with FlopCounterMode(display=False) as counter:
        update(batch)
    return counter.get_total_flops() / 1e9


class Recorder(TorchDispatchMode):
    """Keeps every dense kernel and optimizer op that one update dispatches, each with a copy
    of its arguments taken before it runs (strides kept: ``clone`` preserves a dense layout)."""

    def __init__(self):
        super().__init__()
        self.calls: list = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = func.overloadpacket.__name__
        if name in REPLAYED or name.startswith(OPTIMIZER):
            self.calls.append((func, tree_map(_copy, args), tree_map(_copy, kwargs)))
        return func(*args, **kwargs)


def _copy(x):
    return x.detach().clone() if isinstance(x, torch.Tensor) else x


def dense_replay(update, batch):
    """(replay, kernels): a function running one update's dense kernels and optimizer ops alone,
    on copies of their recorded arguments, and how many there are."""
    with Recorder() as recorder:
        update(batch)
    calls = recorder.calls

    def replay(_batch):
        for func, args, kwargs in calls:
            func(*args, **kwargs)

    return replay, len(calls)


def replay_ceiling(update, batch, d3_update, d3_batch, rounds: int) -> None:
    """rlu's update, d3rlpy's and the replay of rlu's dense kernels, timed in alternation."""
    replay, kernels = dense_replay(update, batch)
    timed = {
        "rlu": Contestant(lambda: batch, update),
        "d3rlpy": Contestant(lambda: d3_batch, d3_update),
        "rlu dense replay": Contestant(lambda: batch, replay),
    }
    rates = time_contestants(timed, rounds, block=0.25, warmup=2, pool=1)
    ms = {k: 1e3 / v["update only"][1] for k, v in rates.items()}
    print(
        f"  interleaved ({rounds} rounds, CPU time, median update): rlu {ms['rlu']:.2f} ms, "
        f"d3rlpy {ms['d3rlpy']:.2f} ms, replay of rlu's {kernels} dense kernels and optimizer "
        f"ops {ms['rlu dense replay']:.2f} ms\n"
        f"  rlu / d3rlpy {ms['d3rlpy'] / ms['rlu']:.2f}x; ceiling "
        f"{ms['d3rlpy'] / ms['rlu dense replay']:.2f}x (d3rlpy's update over the replay); "
        f"the dense kernels are {ms['rlu dense replay'] / ms['rlu']:.0%} of rlu's update"
    )


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("agents", nargs="+", choices=[*cont.SETTINGS, *disc.AGENT_SETTINGS])
    p.add_argument("--updates", type=int, default=5, help="profiled updates per contestant")
    p.add_argument("--batch", type=int, default=32, help="batch of the discrete agents")
    p.add_argument("--ops", type=int, default=0, help="print the costliest aten ops too")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--no-d3rlpy", action="store_true")
    p.add_argument(
        "--same-network",
        action="store_true",
        help="the same-network rows of bc, crr (one Gaussian) and iqn (d3rlpy on rlu's network)",
    )
    p.add_argument(
        "--replay",
        type=int,
        default=0,
        metavar="ROUNDS",
        help="measure the ceiling interleaved, over this many rounds (bench/README)",
    )
    args = p.parse_args(argv)
    sys.stdout.reconfigure(line_buffering=True)
    torch.set_num_threads(args.threads)
    have_d3rlpy = not args.no_d3rlpy
    if have_d3rlpy:
        try:
            import structlog

            structlog.configure(
                wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING)
            )
        except ImportError:
            have_d3rlpy = False
    threads = torch.get_num_threads()
    print(f"torch {torch.__version__}, {threads} thread(s); {load_line()}; {cpu_line()}")
    with tempfile.TemporaryDirectory() as tmp:
        ds_c = cont.make_data(f"{tmp}/c", episodes=10, length=1000)
        ds_d = disc.make_data(f"{tmp}/d", episodes=4, length=1000)
        for name in args.agents:
            print(f"\n{name}")
            times = {}
            built = contestants(name, ds_c, ds_d, args.batch, have_d3rlpy, args.same_network)
            for label, (update, batch) in built.items():
                print(f"  {label}")
                times[label] = breakdown(update, batch, args.updates, args.ops)
                print(f"    {gflop(update, batch):.3f} GFLOP per update")
            if "d3rlpy" in times:
                # the same arithmetic can go no faster than its dense kernels and optimizer
                wall, floor = times["rlu"][0], times["rlu"][1]
                print(
                    f"  rlu / d3rlpy {times['d3rlpy'][0] / wall:.2f}x profiled; ceiling "
                    f"{times['d3rlpy'][0] / floor:.2f}x (d3rlpy's update over rlu's dense kernels "
                    f"and optimizer alone: the ratio if rlu spent nothing else)"
                )
                if args.replay:
                    replay_ceiling(*built["rlu"], *built["d3rlpy"], args.replay)
    print(f"\n{load_line()}")


if __name__ == "__main__":
    main()
