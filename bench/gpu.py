"""Accelerator figures and device checks (issue 16), one command on the GPU machine.

    .venv-bench/bin/python bench/gpu.py                    # on a GPU: every figure and check
    .venv-bench/bin/python bench/gpu.py --json $OUT/gpu.json
    .venv/bin/python bench/gpu.py --device cpu             # tiny sizes: proves the script runs
    .venv/bin/python bench/gpu.py --device cpu --size paper --agents dqn --variants fp32,bf16

For D4PG and BC (paper presets, on walker_walk-shaped synthetic data) and DQN and IQN (the
Nature torso, batch 256, on synthetic Atari frames) it prints updates/s of:

- rlu's full loop: ``rlu.training.train.train`` itself (sampling from the store, its data path, the
  update, logging), timed as the difference of two runs of N and N + K steps so that setup,
  the dataset upload and the final checkpoint cancel out; once with host batches prefetched by
  the background thread (CUDA's default), once with the dataset held on the device;
- the same agent on pre-sampled device batches (the agent alone, no data path) in fp32, TF32,
  bf16 autocast and ``torch.compile`` (fp32);
- the loop's share of the agent alone (the issue's target: at least 90 %);
- d3rlpy on the same device and widths, from host minibatches as its own loop feeds them
  (DoubleDQN; DQN with IQN heads, 16 quantiles; BC with a stochastic policy; DDPG for D4PG,
  which d3rlpy has not: same widths, no distributional critic). Skipped, with a line, where
  d3rlpy is not installed (it lives in the bench venv only, see bench/README.md);

and the projected wall time of the paper's Atari budget (2M learner steps) for one game.

Streamed (issue 36): DQN (the Nature torso; batch 256 at the paper size) and the Decision
Transformer ``dt`` (when the registry has it; a line says so when it does not) fed by
``rlu.data.StreamSampler`` from a cold run on disk (its files evicted from the page cache with
``posix_fadvise(DONTNEED)`` first; batches prefetched to the device by the background thread)
against the same agent on pre-sampled device batches (the target: at least 90 %). The run is
``--stream-data`` (a dataset folder of real frames: ``bench/stream_data.py``'s ``run``) or
synthetic Atari frames stored as rlu stores a release run (zlib frames, stack of 4).

Then the device checks (PASS/FAIL, exit status 1 on a FAIL): the on-device sampler and the
prefetcher give the host sampler's batches on this device; a checkpoint written on this device
loads into a CPU agent and back with equal weights, and the CPU agent acts; plus what is and
is not bit-identical on this device (two runs of the same seed), for docs/devices.md.
"""

from __future__ import annotations

import argparse
import io
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rlu.agents import make_agent  # noqa: E402
from rlu.data import Schema, make_sampler, open_dataset  # noqa: E402
from rlu.data.synthetic import write_synthetic  # noqa: E402
from rlu.data.torch import DeviceSampler, Prefetcher, device_batch  # noqa: E402
from rlu.devices import Runtime, compile_modules, numerics  # noqa: E402
from rlu.tasks import get_task  # noqa: E402
from rlu.training.config import RunSettings  # noqa: E402
from rlu.training.prepare import dataset_specs  # noqa: E402
from rlu.training.train import TrainConfig, train  # noqa: E402

TASKS = {"d4pg": "control_suite/walker_walk", "bc": "control_suite/walker_walk",
         "dqn": "atari/Pong", "iqn": "atari/Pong"}  # fmt: skip
ATARI_BUDGET = 2_000_000  # the paper's learner steps per game (appendix A.2)
TINY = {
    "d4pg": {"policy_layers": (32, 32), "critic_layers": (32, 32), "batch_size": 32},
    "bc": {"hidden_size": 32, "num_layers": 2, "batch_size": 32},
    "dqn": {"atari.channels": (8, 16, 16), "atari.hidden_size": 32, "atari.batch_size": 16},
    "iqn": {"atari.channels": (8, 16, 16), "atari.hidden_size": 32, "atari.batch_size": 16},
}
VARIANTS = {
    "fp32": Runtime(),
    "tf32": Runtime(tf32=True),
    "bf16": Runtime(precision="bf16"),
    "compile": Runtime(compile=True),
}


def log(*parts) -> None:
    print(*parts, flush=True)


# --- data -------------------------------------------------------------------------------------
def make_datasets(root: Path, atari_steps: int, control_steps: int) -> dict[str, str]:
    out = {}
    for task, steps, length in [("atari/Pong", atari_steps, 1000),
                                ("control_suite/walker_walk", control_steps, 1000)]:  # fmt: skip
        length = min(length, steps)
        t0 = time.perf_counter()
        path = write_synthetic(root / task.replace("/", "_"), Schema.for_task(get_task(task)),
                               max(1, steps // length), length)  # fmt: skip
        log(f"  data {task}: {steps} steps, {time.perf_counter() - t0:.0f}s")
        out[task] = str(path)
    return out


# --- timing -----------------------------------------------------------------------------------
def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def rate(step, seconds: float, device: torch.device, warmup: int = 3) -> float:
    """Updates/s of ``step()``: warm up (compilation happens here), calibrate on 3 calls, then
    time enough calls to fill ``seconds``."""
    for _ in range(warmup):
        step()
    sync(device)
    t0 = time.perf_counter()
    for _ in range(3):
        step()
    sync(device)
    n = max(5, int(3 * seconds / max(time.perf_counter() - t0, 1e-6)))
    t0 = time.perf_counter()
    for _ in range(n):
        step()
    sync(device)
    return n / (time.perf_counter() - t0)


def presampled_rate(name, path, overrides, preset, runtime, seconds) -> float:
    """The agent alone: updates on 8 batches sampled and put on the device beforehand."""
    runtime = runtime.resolve()
    device = torch.device(runtime.device)
    ds = open_dataset(path)
    obs, act = dataset_specs(ds)
    agent = make_agent(name, obs, act, preset, seed=0, device=device, **overrides)
    sampler = make_sampler(ds, agent.batch_spec, seed=0)
    batches = [device_batch(sampler.sample(), device) for _ in range(8)]
    if runtime.compile:
        compile_modules(agent.modules)
    i = [0]

    def step():
        with update_context():
            agent.update(batches[i[0] % len(batches)])
        i[0] += 1

    with numerics(runtime) as update_context:
        return rate(step, seconds, device, warmup=10 if runtime.compile else 3)


def loop_rate(name, task, path, overrides, preset, runtime, k, work: Path) -> float:
    """rlu's full loop: ``train()`` for N and N + K steps; K / (difference of wall times). The
    runs use the process's torch thread count (``train`` sets it from ``torch_threads``), so the
    loop and the agent alone are timed on the same threads."""
    times = []
    for steps in (20, 20 + k):
        run = RunSettings(
            preset=preset,
            steps=steps,
            eval_every=-1,
            log_every=10**9,
            checkpoint_every=10**9,
            keep_checkpoints=1,
            runtime=runtime,
            torch_threads=torch.get_num_threads(),
        )
        cfg = TrainConfig(task=task, agent=name, dataset=path, overrides=overrides, run=run)
        out = work / f"{name}_{steps}"
        t0 = time.perf_counter()
        train(cfg, out)
        times.append(time.perf_counter() - t0)
        shutil.rmtree(out)
    return k / max(times[1] - times[0], 1e-6)


# --- d3rlpy -----------------------------------------------------------------------------------
def d3rlpy_rate(name, path, overrides, preset, device, seconds) -> float | None:
    try:
        import d3rlpy
        from d3rlpy.dataset import TransitionMiniBatch
        from d3rlpy.models.encoders import VectorEncoderFactory
    except ImportError:
        return None
    ds = open_dataset(path)
    obs_spec, act_spec = dataset_specs(ds)
    agent = make_agent(name, obs_spec, act_spec, preset, **overrides)  # for the widths only
    c, size = agent.config, agent.batch_spec.batch_size
    b = make_sampler(ds, agent.batch_spec, seed=0).sample()
    if name in ("dqn", "iqn"):
        a = c.atari
        filters = [list(f) for f in zip(a.channels, a.kernel_sizes, a.strides, strict=True)]
        kw = dict(batch_size=size, learning_rate=c.learning_rate, gamma=a.gamma,
                  target_update_interval=a.target_update_period,
                  observation_scaler=d3rlpy.preprocessing.PixelObservationScaler(),
                  optim_factory=d3rlpy.optimizers.AdamFactory(eps=a.adam_eps),
                  encoder_factory=d3rlpy.models.encoders.PixelEncoderFactory(
                      filters=filters, feature_size=a.hidden_size))  # fmt: skip
        if name == "dqn":
            config = d3rlpy.algos.DoubleDQNConfig(**kw)
        else:
            q = d3rlpy.models.IQNQFunctionFactory(n_quantiles=c.num_tau_samples,
                                                  n_greedy_quantiles=c.num_quantile_samples,
                                                  embed_size=c.embedding_size)  # fmt: skip
            config = d3rlpy.algos.DQNConfig(q_func_factory=q, **kw)
        shape, actions = (obs_spec.shape[-1], *obs_spec.shape[:2]), act_spec.num_values

        def observation(x):  # channels first, float32: what d3rlpy's samplers hand its update
            return np.ascontiguousarray(np.moveaxis(x, -1, 1)).astype(np.float32)

        act = b.action.astype(np.float32)[:, None]
        next_act = b.next_action.astype(np.float32)[:, None]
    else:
        if name == "bc":
            enc = VectorEncoderFactory([c.hidden_size] * c.num_layers, use_layer_norm=True)
            config = d3rlpy.algos.BCConfig(
                batch_size=size, learning_rate=c.learning_rate, policy_type="stochastic",
                encoder_factory=enc,
            )  # fmt: skip
        else:
            config = d3rlpy.algos.DDPGConfig(
                batch_size=size, gamma=c.gamma,
                actor_encoder_factory=VectorEncoderFactory(list(c.policy_layers),
                                                           use_layer_norm=True),
                critic_encoder_factory=VectorEncoderFactory(list(c.critic_layers),
                                                            use_layer_norm=True),
            )  # fmt: skip
        shape, actions = (sum(s.size for s in obs_spec.values()),), act_spec.size

        def observation(x):
            return np.concatenate([x[k].reshape(size, -1) for k in sorted(x)], 1)

        act, next_act = b.action, b.next_action
    algo = config.create(device=str(device) if device.type == "cuda" else "cpu:0")
    algo.create_impl(shape, actions)
    mini = TransitionMiniBatch(
        observations=observation(b.observation), actions=act,
        rewards=b.reward[:, None].astype(np.float32),
        next_observations=observation(b.next_observation), next_actions=next_act,
        terminals=(1.0 - b.discount)[:, None].astype(np.float32),
        intervals=np.ones((size, 1), np.float32), transitions=[],
    )  # fmt: skip
    return rate(lambda: algo.update(mini), seconds, device)


# --- fed by the stream sampler from a cold disk (issue 36) ----------------------------------
STREAM_AGENTS = {"dqn": {"atari.batch_size": 256}, "dt": {}}
"""Agents of the streamed figure and their paper-size overrides (DQN: the batch of 256)."""


def evict(path: Path) -> None:
    """Drop every file of a dataset from the page cache (a cold run on disk)."""
    import os

    for f in sorted(Path(path).rglob("*")):
        if f.is_file():
            fd = os.open(f, os.O_RDONLY)
            try:
                os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
            finally:
                os.close(fd)


def stream_figures(name, path, overrides, preset, device, seconds, memory, reuse) -> dict | None:
    """Updates/s of ``name`` fed by the stream sampler from ``path`` evicted from the page cache,
    and of the same agent on pre-sampled device batches; None when the registry has no such
    agent."""
    from rlu.agents import AGENTS
    from rlu.data import StreamSampler

    if (name, True) not in AGENTS:
        return None
    ds = open_dataset(path)
    obs, act = dataset_specs(ds)
    agent = make_agent(name, obs, act, preset, seed=0, device=device, **overrides)
    out: dict = {"batch": agent.batch_spec.batch_size, "kind": agent.batch_spec.kind}
    out["alone"] = presampled_rate(name, path, overrides, preset, Runtime(device=str(device)),
                                   seconds)  # fmt: skip
    evict(path)
    t0 = time.perf_counter()
    sampler = StreamSampler(path, agent.batch_spec, seed=0, memory=memory, reuse=reuse)
    with Prefetcher(sampler, device, depth=4) as batches:
        agent.update(batches.sample())
        sync(device)
        out["first_s"] = time.perf_counter() - t0
        out["streamed"] = rate(lambda: agent.update(batches.sample()), seconds, device)
    sampler.close()
    out["share"] = out["streamed"] / out["alone"]
    return out


def stream_data(root: Path, steps: int) -> Path:
    """Synthetic Atari frames stored as a converted release run (zlib frames, a stack of 4)."""
    task = get_task("atari/Pong")
    length = min(1000, steps)
    return write_synthetic(root / "stream_atari", Schema.for_task(task, image_encoding="zlib"),
                           max(1, steps // length), length)  # fmt: skip


# --- device checks ----------------------------------------------------------------------------
def checks(device: torch.device, data: dict[str, str]) -> list[tuple[str, bool | None, str]]:
    from rlu.types import BatchSpec

    out: list[tuple[str, bool | None, str]] = []

    def same(host, dev) -> bool:
        for x, y in zip(host, dev, strict=True):
            xs, ys = (x, y) if isinstance(x, dict) else ({"": x}, {"": y})
            for k in xs:
                got = ys[k]
                if isinstance(got, np.ndarray):  # the CPU prefetcher hands numpy on
                    got = torch.from_numpy(got)
                if got.device != device or not np.array_equal(xs[k], got.cpu().numpy()):
                    return False
        return True

    for task, path in data.items():
        spec = BatchSpec(64, n_step=3, gamma=0.99, reward_clip=1.0)
        host = make_sampler(path, spec, seed=1)
        dev = DeviceSampler(path, spec, seed=1, device=device)
        ok = all(same(host.sample(), dev.sample()) for _ in range(5))
        out.append((f"on-device sampler = host sampler ({task})", ok, ""))
        ref = make_sampler(path, spec, seed=2)
        with Prefetcher(make_sampler(path, spec, seed=2), device, depth=2) as p:
            ok = all(same(ref.sample(), p.sample()) and p.get_state() == ref.get_state()
                     for _ in range(5))  # fmt: skip
        out.append((f"prefetcher = host sampler ({task})", ok, ""))

    ds = open_dataset(data["atari/Pong"])
    obs, act = dataset_specs(ds)
    tiny = TINY["dqn"]
    batches = [make_sampler(ds, make_agent("dqn", obs, act, **tiny).batch_spec, seed=3).sample()
               for _ in range(1)] * 4  # fmt: skip

    def trained(dev):
        agent = make_agent("dqn", obs, act, seed=0, device=dev, **tiny)
        return agent, [agent.update(b) for b in batches]

    gpu_agent, metrics = trained(device)
    buffer = io.BytesIO()
    torch.save(gpu_agent.state_dict(), buffer)
    buffer.seek(0)
    state = torch.load(
        buffer, weights_only=True, map_location="cpu"
    )  # as rlu.training.runs loads it
    cpu_agent = make_agent("dqn", obs, act, seed=9, device="cpu", **tiny)
    cpu_agent.load_state_dict(state)
    equal = all(torch.equal(v.cpu(), cpu_agent.network.state_dict()[k])
                for k, v in gpu_agent.network.state_dict().items())  # fmt: skip
    acted = cpu_agent.act(batches[0].observation[:4]).shape == (4,)
    out.append(("checkpoint from this device -> CPU agent: weights equal, acts", equal and acted,
                ""))  # fmt: skip
    back = make_agent("dqn", obs, act, seed=9, device=device, **tiny)
    back.load_state_dict(cpu_agent.state_dict())
    equal = all(torch.equal(v.cpu(), cpu_agent.network.state_dict()[k])
                for k, v in back.network.state_dict().items())  # fmt: skip
    out.append(("checkpoint from the CPU -> agent on this device: weights equal", equal, ""))
    again = trained(device)[1]
    out.append(("two runs, same seed, same batches: bit-identical metrics", None,
                "yes" if again == metrics else f"no: {metrics[-1]} vs {again[-1]}"))  # fmt: skip
    return out


# --- main -------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    p.add_argument("--size", choices=["tiny", "paper"], default=None,
                   help="network sizes (default: paper on CUDA, tiny on the CPU)")  # fmt: skip
    p.add_argument("--agents", default="d4pg,bc,dqn,iqn")
    p.add_argument("--variants", default=None,
                   help="agent-alone variants (default: fp32,tf32,bf16,compile on CUDA; "
                        "fp32,bf16 on the CPU)")  # fmt: skip
    p.add_argument("--seconds", type=float, default=None, help="per measurement")
    p.add_argument("--atari-steps", type=int, default=None, help="default 50k (CUDA), 2k (CPU)")
    p.add_argument("--control-steps", type=int, default=None, help="default 100k / 2k")
    p.add_argument("--no-loop", action="store_true", help="skip the full-loop figures")
    p.add_argument("--no-checks", action="store_true")
    p.add_argument("--threads", type=int, default=RunSettings().torch_threads,
                   help="torch threads of every figure (default: a run's, RunSettings."
                        "torch_threads; the agent alone and the loop use the same)")  # fmt: skip
    p.add_argument("--json", default=None, help="also write the figures here")
    p.add_argument("--stream-agents", default=",".join(STREAM_AGENTS),
                   help="agents fed by the stream sampler (empty: none)")  # fmt: skip
    p.add_argument("--stream-data", default=None,
                   help="dataset folder of Atari frames for them (default: synthetic frames, "
                        "--atari-steps of them)")  # fmt: skip
    p.add_argument(
        "--stream-memory",
        type=int,
        default=None,
        help="the stream sampler's buffer in MB (default 2048 on CUDA, 64 on the CPU)",
    )
    p.add_argument("--stream-reuse", type=int, default=8)
    args = p.parse_args(argv)
    device = Runtime(device=args.device).resolve().device
    dev = torch.device(device)
    cuda = dev.type == "cuda"
    torch.set_num_threads(args.threads)
    size = args.size or ("paper" if cuda else "tiny")
    variants = (args.variants or ("fp32,tf32,bf16,compile" if cuda else "fp32,bf16")).split(",")
    seconds = args.seconds or (3.0 if cuda else 1.0)
    name = torch.cuda.get_device_name(dev) if cuda else "CPU"
    log(f"rlu bench/gpu.py: {name} ({device}), torch {torch.__version__}, size {size}, "
        f"{torch.get_num_threads()} CPU threads, variants {variants}")  # fmt: skip
    work = Path(tempfile.mkdtemp(prefix="rlu_gpu_bench_"))
    report: dict = {"device": device, "name": name, "torch": torch.__version__, "size": size,
                    "agents": {}, "checks": []}  # fmt: skip
    failed = False
    try:
        data = make_datasets(work / "data", args.atari_steps or (50_000 if cuda else 2_000),
                             args.control_steps or (100_000 if cuda else 2_000))  # fmt: skip
        for agent in args.agents.split(","):
            task, preset = TASKS[agent], "paper"
            overrides = TINY[agent] if size == "tiny" else {}
            path = data[task]
            fig: dict = {}
            for v in variants:
                rt = VARIANTS[v]
                if (rt.tf32 and not cuda) or (rt.precision == "bf16" and cuda
                                              and not torch.cuda.is_bf16_supported()):  # fmt: skip
                    continue
                fig[f"alone {v}"] = presampled_rate(
                    agent, path, overrides, preset,
                    Runtime(device=device, precision=rt.precision, tf32=rt.tf32,
                            compile=rt.compile), seconds)  # fmt: skip
                log(f"  {agent:5s} agent alone, {v:8s} {fig[f'alone {v}']:9.1f} updates/s")
            if not args.no_loop:
                k = int(min(max(fig["alone fp32"] * 2 * seconds, 50), 20_000))
                for label, rt in [("loop prefetch", Runtime(device=device)),
                                  ("loop on-device", Runtime(device=device,
                                                             data_on_device=True))]:  # fmt: skip
                    fig[label] = loop_rate(agent, task, path, overrides, preset, rt, k, work)
                    share = fig[label] / fig["alone fp32"]
                    log(f"  {agent:5s} {label:22s} {fig[label]:9.1f} updates/s = {share:.0%} "
                        "of the agent alone (fp32)")  # fmt: skip
            d3 = d3rlpy_rate(agent, path, overrides, preset, dev, seconds)
            if d3 is None:
                log(f"  {agent:5s} d3rlpy: not installed here (bench venv only)")
            else:
                fig["d3rlpy"] = d3
                log(f"  {agent:5s} d3rlpy                 {d3:9.1f} updates/s; rlu agent alone "
                    f"fp32 / d3rlpy = {fig['alone fp32'] / d3:.2f}x")  # fmt: skip
            if agent in ("dqn", "iqn"):
                for label in ("loop prefetch", "loop on-device", "alone fp32"):
                    if label in fig:
                        hours = ATARI_BUDGET / fig[label] / 3600
                        fig[f"atari budget hours ({label})"] = hours
                        log(f"  {agent:5s} 2M learner steps ({label}): {hours:.1f} h per game")
            report["agents"][agent] = fig
        names = [a for a in args.stream_agents.split(",") if a]
        if names:
            path = Path(args.stream_data) if args.stream_data else stream_data(
                work / "data", args.atari_steps or (50_000 if cuda else 2_000))  # fmt: skip
            memory = (args.stream_memory or (2048 if cuda else 64)) << 20
            report["stream"] = {}
            for agent in names:
                overrides = TINY.get(agent, {}) if size == "tiny" else STREAM_AGENTS.get(agent, {})
                fig = stream_figures(agent, path, overrides, "paper" if size == "paper" else
                                     "small", dev, seconds, memory, args.stream_reuse)  # fmt: skip
                if fig is None:
                    log(f"  {agent:5s} streamed: no agent {agent!r} in rlu.agents.AGENTS yet; "
                        "skipped")  # fmt: skip
                    continue
                report["stream"][agent] = fig
                log(f"  {agent:5s} streamed from a cold disk ({fig['kind']}s of "
                    f"{fig['batch']}): {fig['streamed']:9.1f} updates/s = {fig['share']:.0%} of "
                    f"the agent on pre-sampled batches ({fig['alone']:.1f}/s; target >= 90%), "
                    f"first batch after {fig['first_s']:.1f} s")  # fmt: skip
        if not args.no_checks:
            log("device checks:")
            for what, ok, note in checks(dev, data):
                mark = "INFO" if ok is None else ("PASS" if ok else "FAIL")
                failed |= ok is False
                log(f"  {mark} {what}{': ' + note if note else ''}")
                report["checks"].append({"check": what, "ok": ok, "note": note})
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
