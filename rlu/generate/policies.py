"""Behaviour policies kept with generated data: saved at each checkpoint id, loaded without pickle.

Users of D4RL long asked for the data-generating checkpoints, and the DOPE benchmark (Fu et al.
2021, "Benchmarks for Deep Off-Policy Evaluation") shipped RL Unplugged policies for off-policy
evaluation. ``rlu generate`` (the D4PG / DQN recipe) keeps, per run, the acting part of the
behaviour agent at the start of the first episode of every checkpoint id (the ``checkpoint``
metadata: ``env_steps // checkpoint_steps`` when the episode starts). The dataset holds those of
every (run, checkpoint) that its kept episodes name::

    policies/run_000/checkpoint_00003.npz   the acting network's weights: D4PG's policy network,
                                            (Dopamine's) DQN's Q network; one plain array per
                                            state-dict entry
    policies/run_000/checkpoint_00003.json  agent, preset, overrides, resolved config, task, env
                                            steps, the behaviour noise: enough to rebuild it

Both are listed in the manifest with their sha256 (``rlu validate`` checks them). The ``.npz`` is
read with ``np.load(allow_pickle=False)``: rlu never unpickles a policy. Floating arrays are stored
as ``OnlineConfig.policy_dtype`` (float16 by default: the bundled cartpole dataset's 18 D4PG
policies of 256x256 MLPs take 2.5 MB instead of 4.9 MB; an array with values beyond float16's
range stays float32) and acted with in float32. The bytes are deterministic: the zip's entries
carry a fixed date and no compression, so the same seed gives the same files.

A checkpoint's policy is the agent at the first episode of that checkpoint id; the recorded
episodes of the checkpoint come from it and from the updates that follow within the checkpoint,
so their mean return is near, not equal to, the snapshot's. With ``exploration=True`` the policy
acts as the behaviour did (D4PG: Gaussian noise ``sigma``, clipped to the bounds; DMPO: a sample
of its Gaussian, clipped; DQN: epsilon-greedy with the schedule's epsilon at the snapshot); by
default it acts deterministically (D4PG's ``pi(s)``, DMPO's mean, DQN's evaluation epsilon), the
policy an off-policy evaluation study values.
"""

from __future__ import annotations

import io
import json
import math
import os
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rlu.data.foreign import MAX_POLICY_BYTES
from rlu.files import (
    AnyJSON,
    Bool,
    Float,
    Int,
    ListOf,
    MapOf,
    Record,
    Shape,
    Str,
    check_value,
    read_json,
    shape_of,
    write_atomic,
)
from rlu.types import Policy, RluError

FORMAT = "rlu-behaviour-policy"
VERSION = 1
ACTING_MODULE = {"d4pg": "policy", "dmpo": "policy", "dqn": "network", "dopamine_dqn": "network"}
"""The agent's module that acts (``agent.modules[name]``): what a behaviour policy keeps."""
POLICY_DTYPES = ("float16", "float32")
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)  # the zip format's earliest date: no clock in the bytes
_FLOAT16_MAX = float(np.finfo(np.float16).max)


def policy_stem(run: int, checkpoint: int) -> str:
    """The dataset-relative path of a policy's files, without the suffix."""
    return f"policies/run_{int(run):03d}/checkpoint_{int(checkpoint):05d}"


# ----------------------------------------------------------------------------------- writing
def write_npz(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    """A ``.npz`` of plain arrays with deterministic bytes (sorted entries, a fixed date, stored
    uncompressed), written atomically. ``np.savez`` stamps the clock into every entry."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        for name in sorted(arrays):
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_DATE)
            info.create_system = 3  # unix: the same bytes whichever system writes them
            info.external_attr = 0o644 << 16
            arr = np.ascontiguousarray(arrays[name])
            with zf.open(info, "w") as fh:
                np.lib.format.write_array(fh, arr, allow_pickle=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, buf.getvalue())


def _stored(value: np.ndarray, dtype: str) -> np.ndarray:
    if value.dtype.kind != "f" or dtype == "float32":
        return value
    if np.abs(value).max(initial=0.0) > _FLOAT16_MAX:  # would overflow to inf: keep float32
        return value
    return value.astype(np.float16)


def save_snapshot(
    folder: Path,
    agent: Any,
    task: Any,
    online: Any,
    seed: int,
    run: int,
    checkpoint: int,
    env_steps: int,
    episode: int,
) -> None:
    """Write ``folder/checkpoint_{checkpoint}.npz`` and ``.json``: the acting module of
    ``agent`` (a behaviour agent of ``online``, an ``OnlineConfig``) at ``env_steps``."""
    if online.agent not in ACTING_MODULE:
        raise RluError(
            f"behaviour agent {online.agent!r}: rlu keeps the policies of "
            f"{', '.join(ACTING_MODULE)} only"
        )
    if online.policy_dtype not in POLICY_DTYPES:
        raise RluError(
            f"OnlineConfig.policy_dtype {online.policy_dtype!r}; use one of "
            f"{', '.join(POLICY_DTYPES)}"
        )
    from rlu.agents import make_config

    module = ACTING_MODULE[online.agent]
    state = agent.modules[module].state_dict()
    arrays = {k: _stored(v.detach().cpu().numpy(), online.policy_dtype) for k, v in state.items()}
    config = make_config(online.agent, task.discrete, online.preset, **online.agent_overrides)
    if task.discrete:  # DQN's linearly decayed epsilon (rlu.generate.online)
        frac = min(1.0, env_steps / max(1, online.epsilon_decay_steps))
        exploration = {"epsilon": 1.0 + frac * (online.epsilon_end - 1.0)}
    elif online.sigma is None:  # a stochastic policy (DMPO) explores by sampling itself
        exploration = {"sample": True}
    else:
        exploration = {"sigma": float(online.sigma)}
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "task": task.id,
        "agent": online.agent,
        "preset": online.preset,
        "agent_overrides": dict(online.agent_overrides),
        "agent_config": asdict(config),
        "module": module,
        "env_settings": dict(online.env_settings),
        "seed": int(seed),
        "run": int(run),
        "checkpoint": int(checkpoint),
        "checkpoint_steps": int(online.checkpoint_steps),
        "env_steps": int(env_steps),
        "episode_index": int(episode),
        "exploration": exploration,
        "arrays": {k: {"shape": list(v.shape), "dtype": str(v.dtype)} for k, v in arrays.items()},
    }
    name = f"checkpoint_{int(checkpoint):05d}"
    write_npz(folder / f"{name}.npz", arrays)
    text = json.dumps(json.loads(json.dumps(meta)), indent=1, sort_keys=True) + "\n"
    write_atomic(folder / f"{name}.json", text)


def snapshot_files(work: Path, kept: Sequence[tuple[int, int]]) -> dict[str, Path]:
    """{dataset-relative path: file in the work folder} of every (run, checkpoint) in ``kept``."""
    out = {}
    for run, checkpoint in sorted(set(kept)):
        for suffix in (".npz", ".json"):
            src = work / f"run_{run:03d}" / "policies" / f"checkpoint_{checkpoint:05d}{suffix}"
            if not src.exists():
                raise RluError(
                    f"{src} is missing: the behaviour policy of run {run} checkpoint "
                    f"{checkpoint}; remove {work} and re-run the command"
                )
            out[policy_stem(run, checkpoint) + suffix] = src
    return out


# ----------------------------------------------------------------- the files' shapes (reading)
# Every field of a policy's ``.json`` rlu reads, with its type and range, in one place, written as
# rlu.files shapes: checked before anything is built from the file (the network, the env), so a
# value of the wrong type or an absurd size is a one-line error naming the file and the field.
_WIDTH = Int(1, 4096)
_LAYERS = ListOf(_WIDTH, max_len=16, min_len=1, as_tuple=True)
ENV_SETTINGS = Record(
    {},
    {
        "camera": Bool(),
        "max_episode_steps": Int(1, 10**7),
        "clip_rewards": Bool(),
        "sticky_action_prob": Float(0, 1),
        "frame_skip": Int(1, 64),
        "challenge": Str(("none", "easy", "medium", "hard")),
        "safety": Bool(),
        "safety_coeff": Float(0, 1),
        "multiobj_reward": Bool(),
        "multiobj_coeff": Float(0, 1),
        "multiobj_observed": Bool(),
    },
    extra=False,
)
"""The env settings a policy may name (``rlu.envs.make_env``'s keyword arguments): a file never
hands anything else to the env factory."""
POLICY_ARRAY_DTYPES = ("float16", "float32", "float64", "int64", "int32", "uint8", "bool")
_U63, _STEPS = 2**63 - 1, 2**53
POLICY_SHAPE = Record(
    {
        "format": Str((FORMAT,)),
        "version": Int(VERSION, VERSION),
        "task": Str(max_len=200),
        "agent": Str(tuple(ACTING_MODULE)),
        "module": Str(tuple(sorted(set(ACTING_MODULE.values())))),
        "agent_config": MapOf(AnyJSON(depth=8), max_len=256),  # + AGENT_CONFIG_RANGES, below
        "env_settings": ENV_SETTINGS,
        "checkpoint_steps": Int(1, _STEPS),
        "env_steps": Int(0, _STEPS),
        "exploration": Record(
            {}, {"epsilon": Float(0, 1), "sigma": Float(0, 100), "sample": Bool()}, extra=False
        ),
        "arrays": MapOf(
            Record(
                {
                    "shape": ListOf(Int(0, 2**31), max_len=8),
                    "dtype": Str(POLICY_ARRAY_DTYPES),
                },
                extra=False,
            ),
            max_len=256,
        ),
    },
    {
        "preset": Str(max_len=64),
        "agent_overrides": MapOf(AnyJSON(depth=8), max_len=64),
        "seed": Int(0, _U63),
        "run": Int(0, 2**31),
        "checkpoint": Int(0, 2**40),
        "episode_index": Int(0, _STEPS),
    },
    extra=False,
)
"""A policy's ``.json`` (written by ``save_snapshot``)."""
AGENT_CONFIG_RANGES: Mapping[str, Shape] = {
    "policy_layers": _LAYERS,
    "critic_layers": _LAYERS,
    "torso_hidden": _WIDTH,
    "num_atoms": Int(1, 1001),
    "num_samples": Int(1, 1024),
    "cpu_slice_rows": Int(1, 1 << 20),
    "atari.channels": ListOf(Int(1, 1024), max_len=8, min_len=1, as_tuple=True),
    "atari.kernel_sizes": ListOf(Int(1, 16), max_len=8, min_len=1, as_tuple=True),
    "atari.strides": ListOf(Int(1, 8), max_len=8, min_len=1, as_tuple=True),
    "atari.hidden_size": Int(1, 8192),
}
"""Ranges of the ``agent_config`` fields that size what building the agent allocates (its
networks; the paper's widest behaviour network is 1024 units). Every other field is typed by the
agent's config dataclass (``rlu.files.shape_of``): :func:`agent_config_shape`."""
MAX_POLICY_JSON_BYTES = 1 << 20


def agent_config_shape(cls: type) -> Record:
    """The shape of ``agent_config`` for config dataclass ``cls``: ``shape_of(cls)`` with the
    fields of ``AGENT_CONFIG_RANGES`` (dotted paths into composed configs) ranged."""

    def ranged(record: Record, prefix: str) -> Record:
        parts = []
        for fields in (record.required, record.optional):
            out = {}
            for name, shape in fields.items():
                path = prefix + name
                if path in AGENT_CONFIG_RANGES:
                    shape = AGENT_CONFIG_RANGES[path]
                elif isinstance(shape, Record):
                    shape = ranged(shape, path + ".")
                out[name] = shape
            parts.append(out)
        return Record(parts[0], parts[1], extra=record.extra)

    return ranged(shape_of(cls), "")


# ----------------------------------------------------------------------------------- reading
@dataclass(frozen=True)
class PolicyInfo:
    """One kept behaviour policy and the episodes of its checkpoint."""

    run: int
    checkpoint: int
    env_steps: int
    """Env steps of its run when the snapshot was taken."""
    recorded_episodes: int
    """Episodes the run recorded under this checkpoint id (before the selection)."""
    recorded_mean: float
    """Their mean return (NaN if the provenance keeps no per-episode returns)."""
    kept_episodes: int
    """Episodes of this (run, checkpoint) in the dataset."""
    kept_mean: float


def _open(dataset: Any) -> Any:
    from rlu.data import open_dataset

    return open_dataset(dataset) if isinstance(dataset, (str, os.PathLike)) else dataset


def _policy_stems(ds: Any) -> list[tuple[int, int]]:
    out = []
    for rel in ds.manifest["files"]:
        if rel.startswith("policies/run_") and rel.endswith(".json"):
            run_part, _, ckpt_part = rel.removeprefix("policies/run_").partition("/checkpoint_")
            out.append((int(run_part), int(ckpt_part.removesuffix(".json"))))
    return sorted(out)


def list_policies(dataset: Any) -> list[PolicyInfo]:
    """The behaviour policies ``dataset`` (a path or an open dataset) keeps, with the returns of
    their checkpoints' episodes (recorded, from the provenance's per-run curves, and kept)."""
    ds = _open(dataset)
    prov = ds.manifest["provenance"]
    curves = {int(c["run"]): c for c in prov.get("runs", [])}
    runs = np.asarray(ds.metadata("run"))
    ckpts = np.asarray(ds.metadata("checkpoint"))
    rets = np.asarray(ds.metadata("episode_return"), np.float64)
    out = []
    for run, checkpoint in _policy_stems(ds):
        meta = _read_meta(ds, run, checkpoint)
        rec = np.zeros(0)
        curve = curves.get(run)
        if curve is not None:
            steps = np.asarray(curve["episode_steps"], np.int64)
            start = np.cumsum(steps) - steps
            of = start // int(meta["checkpoint_steps"]) == checkpoint
            rec = np.asarray(curve["episode_return"], np.float64)[of]
        kept = rets[(runs == run) & (ckpts == checkpoint)]
        out.append(PolicyInfo(
            run, checkpoint, int(meta["env_steps"]),
            int(rec.size), float(rec.mean()) if rec.size else math.nan,
            int(kept.size), float(kept.mean()) if kept.size else math.nan,
        ))  # fmt: skip
    return out


def _checked_file(ds: Any, rel: str, run: int, checkpoint: int) -> Path:
    from rlu.data.store import file_sha256

    files = ds.manifest["files"]
    if rel not in files:
        have = _policy_stems(ds)
        hint = (
            f"`rlu policies {ds.path}` lists the {len(have)} it keeps"
            if have
            else "it keeps none (made before rlu kept behaviour policies, or by --policy / rwrl "
            "generation): re-generate it with rlu generate"
        )
        raise RluError(
            f"{ds.path}: no behaviour policy for run {run} checkpoint {checkpoint} ({rel} is not "
            f"in manifest.json's files); {hint}"
        )
    path = ds.path / rel
    if not path.is_file():
        raise RluError(f"{path}: missing; the dataset is incomplete, re-generate or re-copy it")
    if file_sha256(path) != files[rel]["sha256"]:
        raise RluError(
            f"{path}: sha256 differs from manifest.json (a damaged or changed file); "
            "re-generate or re-copy the dataset"
        )
    return path


def _read_meta(ds: Any, run: int, checkpoint: int) -> dict[str, Any]:
    path = _checked_file(ds, policy_stem(run, checkpoint) + ".json", run, checkpoint)
    fix = "re-generate the dataset"
    meta = read_json(path, AnyJSON(depth=16), fix, max_bytes=MAX_POLICY_JSON_BYTES)
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise RluError(f"{path}: field 'format' is not {FORMAT!r}; not an rlu behaviour policy")
    if meta.get("version") != VERSION:
        raise RluError(
            f"{path}: field 'version' is {meta.get('version')!r}; this rlu reads version "
            f"{VERSION}: upgrade rlu"
        )
    agent = meta.get("agent")
    if isinstance(agent, str) and agent not in ACTING_MODULE:
        raise RluError(
            f"{path}: field 'agent' is {agent[:80]!r}, not one of rlu's behaviour agents "
            f"({', '.join(ACTING_MODULE)}); a name read from a file is looked up, never "
            f"imported: {fix}"
        )
    return check_value(POLICY_SHAPE, meta, str(path), fix)


def _read_arrays(path: Path, meta: Mapping[str, Any], json_path: Path) -> dict[str, np.ndarray]:
    """The arrays of a policy's ``.npz``, each member's header checked against the ``arrays``
    field of its JSON (and the total against ``MAX_POLICY_BYTES``) before a byte is inflated."""
    from rlu.data.foreign import NpzFile

    want = meta["arrays"]
    declared = sum(math.prod(a["shape"]) * np.dtype(a["dtype"]).itemsize for a in want.values())
    if declared > MAX_POLICY_BYTES:
        raise RluError(
            f"{json_path}: field 'arrays' declares {declared} bytes of weights, more than a "
            f"behaviour policy holds ({MAX_POLICY_BYTES}); re-generate the dataset"
        )
    fix = "a plain-array .npz is what rlu generate writes: re-generate the dataset"
    with NpzFile(path, fix) as z:
        if set(z.infos) != set(want):
            raise RluError(
                f"{path}: arrays {sorted(z.infos)[:8]} differ from {json_path.name}'s field "
                f"'arrays' {sorted(want)[:8]}; re-generate the dataset"
            )
        for k in sorted(want):
            m = z.member(k)
            if list(m.shape) != list(want[k]["shape"]) or m.dtype != np.dtype(want[k]["dtype"]):
                raise RluError(
                    f"{path}: array {k!r} is {m.dtype}{list(m.shape)}; {json_path.name} field "
                    f"'arrays.{k}' says {want[k]['dtype']}{want[k]['shape']}; re-generate the "
                    "dataset"
                )
        arrays = {k: z.read(k, MAX_POLICY_BYTES) for k in sorted(want)}
    for k, v in arrays.items():
        if v.dtype.kind == "f" and not np.isfinite(v).all():
            raise RluError(f"{path}: array {k!r} holds NaN or inf; re-generate the dataset")
    return arrays


def _load_weights(
    net: Any, arrays: Mapping[str, Any], npz: Path, json_path: Path, meta: Mapping[str, Any]
) -> None:
    """Load a snapshot's arrays into the network its json names (shapes checked), in eval
    mode; float16 weights act in the network's own dtype (float32)."""
    import torch

    want = {k: tuple(v.shape) for k, v in net.state_dict().items()}
    have = {k: tuple(v.shape) for k, v in arrays.items()}
    if want != have:
        diff = sorted(k for k in want.keys() | have.keys() if want.get(k) != have.get(k))
        raise RluError(
            f"{npz}: arrays do not fit {meta['agent']}'s {meta['module']} network as "
            f"{json_path.name} configures it (wrong or missing: {', '.join(diff[:5])}); "
            "re-generate the dataset"
        )
    ref = net.state_dict()
    net.load_state_dict(
        {k: torch.from_numpy(np.array(v)).to(ref[k].dtype) for k, v in arrays.items()}
    )
    net.eval()


def load_behaviour_policy(
    dataset: Any,
    run: int,
    checkpoint: int,
    exploration: bool = False,
    seed: int = 0,
    device: Any = "cpu",
) -> Policy:
    """The behaviour policy of ``run`` at ``checkpoint`` that ``dataset`` (a path or an open
    dataset) keeps, as an evaluation ``Policy``: ``(observation, is_first, reward) -> action``
    on batched observations (the behaviour agents are memoryless: ``is_first`` and ``reward``
    are ignored). ``exploration``: act with the behaviour noise (module docstring);
    ``seed`` seeds that noise and DQN's evaluation epsilon."""
    from rlu.agents import agent_module, config_from_json
    from rlu.tasks import get_task

    ds = _open(dataset)
    meta = _read_meta(ds, run, checkpoint)
    stem = policy_stem(run, checkpoint)
    npz = _checked_file(ds, stem + ".npz", run, checkpoint)
    json_path = ds.path / (stem + ".json")
    arrays = _read_arrays(npz, meta, json_path)
    task = get_task(meta["task"])
    if ds.schema.task_id and ds.schema.task_id != task.id:
        raise RluError(
            f"{json_path}: field 'task' is {task.id!r} but the dataset is {ds.schema.task_id!r}; "
            "re-generate the dataset"
        )
    module = agent_module(meta["agent"], task.discrete)
    shape = Record({"agent_config": agent_config_shape(module.Config)})
    data = check_value(shape, meta, str(json_path), "re-generate the dataset")["agent_config"]
    config = config_from_json(module.Config, data)
    agent = module.Agent(task.observation_spec, task.action_spec, config, seed=seed,
                         device=device)  # fmt: skip
    if meta["module"] not in agent.modules:
        raise RluError(
            f"{json_path}: field 'module' is {meta['module']!r}; agent {meta['agent']!r} has "
            f"{', '.join(agent.modules)}"
        )
    _load_weights(agent.modules[meta["module"]], arrays, npz, json_path, meta)
    rng = np.random.default_rng([int(seed), 8])
    noise = meta["exploration"]
    if task.discrete:
        eps, n = float(noise.get("epsilon", 0.0)), task.action_dim

        def discrete_policy(
            observation: Any, is_first: np.ndarray | None = None, reward: np.ndarray | None = None
        ) -> np.ndarray:
            if not exploration:
                return agent.act(observation, greedy=True)
            a = np.asarray(agent.act(observation, greedy=False))
            explore = rng.random(a.shape[0]) < eps
            return np.where(explore, rng.integers(n, size=a.shape[0]), a).astype(a.dtype)

        return discrete_policy
    sigma = float(noise.get("sigma", 0.0))
    sample = bool(noise.get("sample", False))  # DMPO: its own Gaussian, not added noise
    lo = np.asarray(task.action_spec.minimum, np.float32)  # type: ignore[union-attr]
    hi = np.asarray(task.action_spec.maximum, np.float32)  # type: ignore[union-attr]

    def continuous_policy(
        observation: Any, is_first: np.ndarray | None = None, reward: np.ndarray | None = None
    ) -> np.ndarray:
        if exploration and sample:
            return np.clip(np.asarray(agent.act(observation, greedy=False), np.float32), lo, hi)
        a = np.asarray(agent.act(observation), np.float32)
        if exploration:
            a = np.clip(a + sigma * rng.standard_normal(a.shape).astype(np.float32), lo, hi)
        return a

    return continuous_policy


# ---------------------------------------------------------------------------- roll-outs, OPE
def rollout_behaviour(
    dataset: Any,
    run: int,
    checkpoint: int,
    episodes: int = 10,
    seed: int = 0,
    exploration: bool = False,
    num_envs: int = 4,
    device: Any = "cpu",
) -> Any:
    """Roll out a kept behaviour policy in its task's env (the env settings it was recorded
    with); returns an ``rlu.evaluation.EvalResult`` (undiscounted returns)."""
    from rlu.evaluation.rollout import evaluate, task_env_factory

    ds = _open(dataset)
    meta = _read_meta(ds, run, checkpoint)
    policy = load_behaviour_policy(ds, run, checkpoint, exploration, seed, device)
    env_fn = task_env_factory(meta["task"], **meta["env_settings"])
    return evaluate(policy, env_fn, episodes, seed, num_envs)


def behaviour_ope(
    dataset: Any,
    which: Sequence[tuple[int, int]] | None = None,
    episodes: int = 10,
    fqe: Any = None,
    seed: int = 0,
    num_envs: int = 4,
    device: Any = "cpu",
    quiet: bool = False,
) -> dict[str, Any]:
    """An off-policy evaluation study on the dataset's own behaviour policies: per policy (all
    kept, or the (run, checkpoint) pairs ``which``), the FQE estimate from the data alone
    (``rlu.evaluation.fqe``; the discounted value at the episodes' first observations) and the
    true return rolled out in the env (undiscounted, ``episodes`` episodes), then their Spearman
    rank correlation across policies (NaN with fewer than two, or when either side ties)."""
    from rlu.evaluation.fqe import FQEConfig, dataset_fqe_inputs, fqe_estimate
    from rlu.evaluation.protocols import spearman
    from rlu.tasks import get_task

    ds = _open(dataset)
    config = FQEConfig() if fqe is None else fqe
    infos = {(p.run, p.checkpoint): p for p in list_policies(ds)}
    pairs = sorted(infos) if which is None else [(int(r), int(c)) for r, c in which]
    if not pairs:
        raise RluError(f"{ds.path}: keeps no behaviour policy; `rlu policies {ds.path}` lists them")
    for pair in pairs:
        if pair not in infos:
            _checked_file(ds, policy_stem(*pair) + ".npz", *pair)  # raises, naming what is kept
    transitions, init = dataset_fqe_inputs(ds)
    action_spec = get_task(ds.schema.task_id).action_spec
    from rlu.progress import Progress

    rows = []
    # FQE's gradient steps are the cost; each policy's roll-outs come after its steps
    with Progress(len(pairs) * config.steps, "FQE", "steps", quiet=quiet) as bar:
        for run, checkpoint in pairs:
            policy = load_behaviour_policy(ds, run, checkpoint, seed=seed, device=device)
            estimate = fqe_estimate(transitions, init, policy, action_spec, config, device,
                                    progress=bar)  # fmt: skip
            result = rollout_behaviour(ds, run, checkpoint, episodes, seed, False, num_envs,
                                       device)  # fmt: skip
            info = infos[(run, checkpoint)]
            rows.append({**asdict(info), "fqe_estimate": float(estimate), "return": result.mean,
                         "returns": list(result.returns)})  # fmt: skip
            bar.note(f"run {run} checkpoint {checkpoint}: FQE {estimate:.2f}, return "
                     f"{result.mean:.1f}")  # fmt: skip
    rho = math.nan
    if len(rows) >= 2:
        rho = spearman([r["fqe_estimate"] for r in rows], [r["return"] for r in rows])
    return {"dataset": str(ds.path), "fqe": asdict(config), "episodes": episodes,
            "policies": rows, "spearman": rho}  # fmt: skip


__all__ = [
    "ACTING_MODULE",
    "PolicyInfo",
    "behaviour_ope",
    "list_policies",
    "load_behaviour_policy",
    "rollout_behaviour",
    "save_snapshot",
    "write_npz",
]
