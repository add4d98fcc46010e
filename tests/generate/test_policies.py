"""Behaviour policies kept with generated data: deterministic, resumable, loaded without pickle,
checked by validate, and handed to roll-outs and FQE (rlu.generate.policies)."""

from __future__ import annotations

import hashlib
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("dm_control")

TASK = "control_suite/cartpole_swingup"


def _config():
    from rlu.generate import GenerateConfig

    return GenerateConfig(TASK, scale="tiny", runs=2, seed=7, progress=False)


def _files(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """Two tiny D4PG runs of two 1000-step episodes: checkpoints 0 and 1 of each run."""
    from rlu.generate import generate

    return generate(_config(), tmp_path_factory.mktemp("policies") / "ds")


@pytest.fixture
def copy(tiny, tmp_path) -> Path:
    dst = tmp_path / "copy"
    shutil.copytree(tiny, dst)
    return dst


def _rewrite(ds: Path, rel: str, data: bytes) -> None:
    """Replace a file and record its new sha256 and size, as a consistent (hostile) dataset."""
    (ds / rel).write_bytes(data)
    mpath = ds / "manifest.json"
    manifest = json.loads(mpath.read_text())
    manifest["files"][rel] = {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}
    mpath.write_text(json.dumps(manifest))


def test_every_named_checkpoint_keeps_its_policy_listed_in_the_manifest(tiny):
    from rlu.data import open_dataset
    from rlu.data.validate import validate
    from rlu.generate.policies import list_policies

    ds = open_dataset(tiny)
    named = {
        (int(r), int(c)) for r, c in zip(ds.metadata("run"), ds.metadata("checkpoint"), strict=True)
    }
    assert named == {(0, 0), (0, 1), (1, 0), (1, 1)}
    rels = sorted(r for r in ds.manifest["files"] if r.startswith("policies/"))
    assert rels == sorted(
        f"policies/run_{r:03d}/checkpoint_{c:05d}{s}" for r, c in named for s in (".npz", ".json")
    )
    prov = ds.manifest["provenance"]["policies"]
    assert prov["dtype"] == "float16" and prov["count"] == 4
    report = validate(tiny)
    assert report.ok, report.problems
    assert any("8 attached file(s) under policies/" in c for c in report.checked), report.checked
    meta = json.loads((tiny / "policies/run_001/checkpoint_00001.json").read_text())
    assert meta["agent"] == "d4pg" and meta["module"] == "policy" and meta["env_steps"] == 1000
    assert meta["agent_config"]["policy_layers"] == [32, 32]  # the tiny scale's override
    with np.load(tiny / "policies/run_001/checkpoint_00001.npz", allow_pickle=False) as z:
        assert {z[k].dtype for k in z.files} == {np.dtype(np.float16)}
    rows = list_policies(tiny)
    assert [
        (p.run, p.checkpoint, p.env_steps, p.recorded_episodes, p.kept_episodes) for p in rows
    ] == [(0, 0, 0, 1, 1), (0, 1, 1000, 1, 1), (1, 0, 0, 1, 1), (1, 1, 1000, 1, 1)]
    kept = np.asarray(ds.metadata("episode_return"))
    assert rows[1].kept_mean == pytest.approx(float(kept[1]))
    assert rows[1].recorded_mean == pytest.approx(float(kept[1]), abs=1e-3)


def test_same_seed_same_policy_bytes_and_a_crashed_run_resumes_to_them(tiny, tmp_path):
    from rlu.generate import generate

    class Crash(Exception):
        pass

    def crash(run: int, chunk: int) -> None:
        if (run, chunk) == (0, 0):  # run 0's checkpoint 0 policy and first chunk are saved
            raise Crash

    out = tmp_path / "crashed"
    with pytest.raises(Crash):
        generate(_config(), out, on_chunk=crash)
    work = tmp_path / ".crashed.generate"
    assert (work / "run_000/policies/checkpoint_00000.npz").exists()
    assert not (work / "run_000/policies/checkpoint_00001.npz").exists()
    generate(_config(), out)
    got, want = _files(out), _files(tiny)
    assert [k for k in want if k.startswith("policies/")] and got.keys() == want.keys()
    assert [k for k in want if got[k] != want[k]] == []


def test_loaded_policy_acts_as_the_behaviour_agent_did(tiny):
    """Checkpoint 0 is the agent before any update: rebuilt from its seed, it must act as the
    loaded policy (float16 weights: within rounding)."""
    from rlu.data import open_dataset
    from rlu.generate.common import AGENT, run_seed
    from rlu.generate.online import make_behaviour_agent
    from rlu.generate.policies import load_behaviour_policy
    from rlu.generate.scales import get_scale
    from rlu.tasks import get_task

    task = get_task(TASK)
    ds = open_dataset(tiny)
    obs = {k: np.asarray(v) for k, v in ds.segment(0).observation.items()}
    for run in (0, 1):
        agent = make_behaviour_agent(task, get_scale(task, "tiny").online, run_seed(7, run, AGENT))
        want = agent.act(obs)
        got = load_behaviour_policy(tiny, run, 0)(obs, np.zeros(len(want), bool))
        assert got.shape == want.shape == (1001, 1)
        np.testing.assert_allclose(got, want, atol=5e-7, rtol=1e-2)
    first = load_behaviour_policy(tiny, 0, 0)(obs, np.zeros(1001, bool))
    other = load_behaviour_policy(tiny, 1, 0)(obs, np.zeros(1001, bool))
    assert np.abs(other - first).max() > 1e-6  # run 1's policy is not run 0's
    noisy = load_behaviour_policy(tiny, 1, 0, exploration=True)(obs, np.zeros(1001, bool))
    assert 0.1 < np.std(noisy - other) < 0.5  # sigma 0.3, clipped at the bounds
    assert np.abs(noisy).max() <= 1.0


def test_a_pickle_inside_the_npz_is_refused(copy):
    from rlu.data.validate import validate
    from rlu.generate.policies import load_behaviour_policy
    from rlu.types import RluError

    rel = "policies/run_000/checkpoint_00001.npz"
    with np.load(copy / rel) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["out.bias"] = np.array([{"payload": 1}], dtype=object)  # only pickle can store it
    bad = copy / "bad.npz"
    np.savez(bad, **arrays)
    _rewrite(copy, rel, bad.read_bytes())
    with pytest.raises(RluError, match="holds Python objects, which only a pickle can load"):
        load_behaviour_policy(copy, 0, 1)
    report = validate(copy)
    assert not report.ok
    assert any(rel in p and "only a pickle can load" in p for p in report.problems), report.problems


def test_validate_and_load_catch_a_changed_byte(copy):
    from rlu.data.validate import validate
    from rlu.generate.policies import load_behaviour_policy
    from rlu.types import RluError

    path = copy / "policies/run_001/checkpoint_00000.npz"
    data = bytearray(path.read_bytes())
    data[-100] ^= 1  # inside the last array's values: still a readable .npz
    path.write_bytes(bytes(data))
    report = validate(copy)
    assert not report.ok
    assert any(str(path) in p and "sha256" in p for p in report.problems), report.problems
    with pytest.raises(RluError, match="sha256 differs"):
        load_behaviour_policy(copy, 1, 0)
    load_behaviour_policy(copy, 1, 1)  # the others still load


def test_bad_policies_are_refused_with_the_file_and_the_fix(copy, tiny):
    from rlu.data import DatasetWriter, open_dataset
    from rlu.generate.policies import load_behaviour_policy
    from rlu.types import RluError

    with pytest.raises(RluError, match=r"run 0 checkpoint 7 .*rlu policies .* lists the 4"):
        load_behaviour_policy(tiny, 0, 7)

    rel = "policies/run_000/checkpoint_00000.npz"
    with np.load(copy / rel) as z:
        arrays = {k: z[k] for k in z.files}
    _rewrite(copy, rel, (copy / rel).read_bytes()[:200])  # truncated, manifest agreeing
    with pytest.raises(RluError, match=f"{rel}: not an .npz archive"):
        load_behaviour_policy(copy, 0, 0)

    from rlu.generate.policies import write_npz

    # wrong shapes, the JSON agreeing with the npz: the network as configured refuses them
    arrays["out.weight"] = np.zeros((1, 16), np.float16)
    write_npz(copy / "w.npz", arrays)
    _rewrite(copy, rel, (copy / "w.npz").read_bytes())
    jrel = rel.replace(".npz", ".json")
    meta = json.loads((copy / jrel).read_text())
    meta["arrays"]["out.weight"]["shape"] = [1, 16]
    _rewrite(copy, jrel, json.dumps(meta).encode())
    with pytest.raises(RluError, match=r"checkpoint_00000.npz: arrays do not fit .*out.weight"):
        load_behaviour_policy(copy, 0, 0)
    # and an npz whose arrays disagree with its JSON
    meta["arrays"]["out.weight"]["shape"] = [1, 32]
    _rewrite(copy, jrel, json.dumps(meta).encode())
    with pytest.raises(RluError, match=r"array 'out.weight' is float16\[1, 16\]"):
        load_behaviour_policy(copy, 0, 0)

    # a dataset without policies says why and what to do
    src = open_dataset(tiny)
    with DatasetWriter(copy.parent / "plain", src.schema) as w:
        w.append(src.segment(0))
    with pytest.raises(RluError, match="keeps none"):
        load_behaviour_policy(copy.parent / "plain", 0, 0)


def test_attachments_stay_under_policies(tiny, tmp_path):
    from rlu.data import DatasetWriter, open_dataset
    from rlu.types import FormatError, RluError

    src = open_dataset(tiny)
    with pytest.raises(RluError, match="under policies/"):
        with DatasetWriter(tmp_path / "x", src.schema) as w:
            w.attach("steps/evil.bin", tiny / "manifest.json")
    assert not (tmp_path / "x").exists()
    # a manifest listing a file outside policies/ is still refused
    ds = tmp_path / "y"
    shutil.copytree(tiny, ds)
    (ds / "extra.bin").write_bytes(b"x")
    _rewrite(ds, "extra.bin", b"x")
    with pytest.raises(FormatError, match="unexpected \\['extra.bin'\\]"):
        open_dataset(ds)


def test_fqe_values_behaviour_policies_against_their_rollouts(tiny, capsys):
    """The OPE study's plumbing on tiny data: FQE estimates and rolled-out returns of two
    different policies, finite; the rank correlation is the study, not asserted."""
    from rlu.cli import main
    from rlu.evaluation.fqe import FQEConfig
    from rlu.generate.policies import behaviour_ope, rollout_behaviour

    res = behaviour_ope(tiny, [(0, 1), (1, 1)], episodes=1, fqe=FQEConfig(steps=50))
    rows = res["policies"]
    assert [(r["run"], r["checkpoint"]) for r in rows] == [(0, 1), (1, 1)]
    for r in rows:
        assert math.isfinite(r["fqe_estimate"]) and math.isfinite(r["return"])
        assert len(r["returns"]) == 1
    assert rows[0]["fqe_estimate"] != rows[1]["fqe_estimate"]
    assert math.isnan(res["spearman"]) or -1.0 <= res["spearman"] <= 1.0
    again = rollout_behaviour(tiny, 1, 1, episodes=1)
    assert again.returns == tuple(rows[1]["returns"])

    assert main(["policies", str(tiny)]) == 0
    out = capsys.readouterr().out
    assert "| run | checkpoint | env steps |" in out and "| 1 | 1 | 1,000 | 1 |" in out
    one = ["evaluate-behaviour", str(tiny), "--run", "1", "--checkpoint", "1", "--episodes", "1"]
    assert main([*one, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)[0]["returns"] == rows[1]["returns"]
    assert main([*one, "--fqe", "--fqe-steps", "50", "--fqe-target-period", "100"]) == 0
    out = capsys.readouterr().out
    assert f"| 1 | 1 | 1,000 | {rows[1]['fqe_estimate']:.2f} |" in out  # same FQE seed, same value
    assert "Spearman rank correlation: undefined" in out
    assert main(["evaluate-behaviour", str(tiny), "--run", "1"]) == 2
    assert "--run and --checkpoint together" in capsys.readouterr().err


def test_dqn_keeps_its_q_network_and_rolls_out_under_its_env_settings(tmp_path):
    """Atari's recipe: DQN's Q network is the policy; the roll-out uses the recorded env settings
    (the tiny scale's 100-step episodes)."""
    pytest.importorskip("ale_py")
    from rlu.data import open_dataset
    from rlu.data.validate import validate
    from rlu.generate import GenerateConfig, generate
    from rlu.generate.policies import list_policies, load_behaviour_policy, rollout_behaviour

    config = GenerateConfig("atari/Pong", scale="tiny", seed=1, progress=False)
    out = generate(config, tmp_path / "pong")
    assert validate(out).ok
    rows = list_policies(out)
    assert rows and rows[0].run == 0 and rows[0].checkpoint == 0
    meta = json.loads((out / "policies/run_000/checkpoint_00000.json").read_text())
    from rlu.generate.scales import get_scale
    from rlu.tasks import get_task

    assert meta["agent"] == get_scale(get_task("atari/Pong"), "tiny").online.agent
    assert meta["module"] == "network"
    assert meta["exploration"] == {"epsilon": 1.0}  # the schedule's start
    assert meta["env_settings"] == {"max_episode_steps": 100}
    ds = open_dataset(out)
    from rlu.data.views import DatasetView

    obs = DatasetView(ds).observation(np.zeros(3, np.int64), np.arange(3))
    actions = load_behaviour_policy(out, 0, 0)(obs, np.ones(3, bool))
    assert actions.shape == (3,) and actions.dtype.kind == "i" and (actions < 6).all()
    res = rollout_behaviour(out, 0, 0, episodes=1, num_envs=1)
    assert res.lengths == (100,)
