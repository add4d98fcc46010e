"""Every ``paper`` preset trains on the release's own files, for each domain's default release
family and each agent the paper runs in that domain (RL Unplugged's tables: control suite BC,
D4PG, BCQ, BRAC, RABM; locomotion BC, D4PG, RABM, recurrent on the sequence tasks; Atari BC,
DQN, IQN, BCQ, REM).

The shards are TF-written where a fixture exists (``../shared/fixtures/rlu_release``: the control
suite's 2-step windows and one Atari transition shard, whose random actions span 18 values, so
it is converted as an 18-action game) and written with the release writer of these tests
(``rlu.data.release.families.write_shard``) for locomotion, then converted with ``rlu convert``.

Two checks: every case samples a batch of the paper preset's ``batch_spec`` from the converted
data (what D4PG's 5-step preset failed on the control suite's 2-step windows), and, marked slow
(the paper's networks at the paper's batch sizes on a CPU), ``rlu train --preset paper`` runs
10 updates (3 on locomotion, whose every update runs the camera ResNet over 1,024 frames, or
5,120 in 40-step windows, once per network: over 40 minutes for recurrent RABM's 10 on a shared
2-core machine) and one evaluation episode of at most 10 steps in the real env. BRAC's
300k-update behaviour phase and 20k-update warm start are cut to 3 updates each.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("torch")

from rlu.agents import make_agent  # noqa: E402
from rlu.cli import main  # noqa: E402
from rlu.data.release import families as Fm  # noqa: E402
from rlu.data.store import open_dataset  # noqa: E402
from rlu.data.views import make_sampler  # noqa: E402
from rlu.tasks import get_task  # noqa: E402
from tests.release.conftest import FIXTURES  # noqa: E402
from tests.release.test_convert import _windows  # noqa: E402

CONTROL = "control_suite/cartpole_swingup"
ATARI = "atari/Zaxxon"  # 18 actions: the TF fixture's a_t span 0..17
LOCOMOTION = "locomotion/humanoid_corridor"  # seq2 windows
SEQUENCE = "locomotion/rodent_two_touch"  # seq40 windows, a recurrent task of the paper

# (task, agent, preset): the paper's agents per domain
CASES = [
    *((CONTROL, a, "paper") for a in ("bc", "d4pg", "bcq", "brac", "rabm")),
    *((LOCOMOTION, a, "paper") for a in ("bc", "d4pg", "rabm")),
    *((SEQUENCE, a, "paper_recurrent") for a in ("bc", "rabm")),
    *((ATARI, a, "paper") for a in ("bc", "dqn", "iqn", "bcq", "rem")),
]
IDS = [f"{t.split('/')[0]}-{a}-{p}" for t, a, p in CASES]
SHORT_PHASES = {"brac": ["behaviour_steps=3", "warm_start_steps=3"]}
STEPS = {CONTROL: 10, ATARI: 10, LOCOMOTION: 3, SEQUENCE: 3}


@pytest.fixture(scope="module")
def release_datasets(tmp_path_factory):
    """task -> a dataset converted with ``rlu convert`` from a shard of its default family."""
    if not (FIXTURES / "data").is_dir():  # the conftest's ``fixtures``, once per module
        pytest.skip(f"release fixtures not found at {FIXTURES} (set RLU_SHARED)")
    fixtures = FIXTURES
    root = tmp_path_factory.mktemp("release")
    shards = {
        CONTROL: fixtures / "data" / "dm_control_suite/cartpole_swingup/train-00000-of-00001",
        ATARI: fixtures / "data" / "atari/Pong/run_1-00000-of-00001",
    }
    for task, (n, t) in {LOCOMOTION: (9, 2), SEQUENCE: (3, 40)}.items():
        family = get_task(task).release_dataset().family
        shards[task] = root / "shards" / task.split("/")[1] / "train-00000-of-00001"
        shards[task].parent.mkdir(parents=True)
        Fm.write_shard(shards[task], family, _windows(task, n=n, t=t))
    out = {}
    for task, shard in shards.items():
        family = get_task(task).release_dataset().family  # the domain's default family
        dest = root / task.replace("/", "_")
        args = ["convert", "--family", family, "--task", task, "--out", str(dest), str(shard)]
        assert main(args) == 0
        out[task] = dest
    return out


@pytest.mark.parametrize(("task", "agent", "preset"), CASES, ids=IDS)
def test_paper_preset_batches_come_from_the_default_release_family(
    release_datasets, task, agent, preset
):
    spec = get_task(task)
    built = make_agent(agent, spec.observation_spec, spec.action_spec, preset=preset)
    ds = open_dataset(release_datasets[task])
    batch = make_sampler(ds, built.batch_spec, seed=0).sample()
    assert len(batch.action) == built.batch_spec.batch_size
    if built.batch_spec.kind == "sequence":
        assert batch.mask.shape[1] == built.batch_spec.sequence_length and batch.mask.any()


@pytest.mark.slow
@pytest.mark.parametrize(("task", "agent", "preset"), CASES, ids=IDS)
def test_rlu_train_paper_preset_on_the_release(release_datasets, tmp_path, task, agent, preset):
    out = tmp_path / "run"
    args = ["train", "--task", task, "--agent", agent, "--dataset", str(release_datasets[task])]
    args += ["--out", str(out), "--preset", preset, "--steps", str(STEPS[task]), "--device", "cpu"]
    args += ["--eval-every", "0", "--eval-episodes", "1", "--eval-envs", "1"]
    args += ["--eval-max-steps", "10", "--no-progress", *SHORT_PHASES.get(agent, [])]
    assert main(args) == 0
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert rows and rows[-1]["step"] >= STEPS[task]
    assert all(np.isfinite(v) for row in rows for k, v in row.items() if k != "step")
    result = json.loads((out / "result.json").read_text())
    assert result["steps"] == STEPS[task] and np.isfinite(result["final_eval"]["mean"])
    assert 1 <= result["final_eval"]["lengths"][0] <= 10
