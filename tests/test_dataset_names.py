"""One way to name data (issue 37 item 2, issue 39 item 6): whatever takes a dataset (``rlu
train --dataset``, ``rlu sweep --dataset``, ``rlu quickstart --dataset``, config files,
``TrainConfig``) takes what ``rlu.load_dataset`` takes, through that one resolver, and the
resolver is as strict as the command line: unknown keywords, cache entries of another task and
links out of the cache are refused."""

from __future__ import annotations

import json
import os

import pytest

import rlu
from rlu.cli import main
from rlu.data.release import catalog
from rlu.data.release.load import release_dataset_path
from rlu.data.store import Schema
from rlu.data.synthetic import write_synthetic
from rlu.tasks import get_task
from rlu.types import RluError

CARTPOLE = "control_suite/cartpole_swingup"
TFDS = "rlu_control_suite/cartpole_swingup"


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("RLU_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache"


def _release_entry(task: str, **pick) -> str:
    """A converted release dataset of ``task`` where the cache keeps it (synthetic episodes)."""
    sel = catalog.select(task, **pick)
    dest = release_dataset_path(sel, None, all_shards=True)
    write_synthetic(dest, Schema.for_task(get_task(task)), num_episodes=3, episode_length=6)
    return dest


def _train(tmp_path, dataset: str, name: str = "run") -> list[str]:
    return ["train", "--task", CARTPOLE, "--agent", "bc", "--dataset", dataset, "--out",
            str(tmp_path / name), "--steps", "2", "--eval-every", "-1", "--quiet",
            "batch_size=4"]  # fmt: skip


def test_train_takes_a_task_id_and_a_tfds_name(tmp_path, cache, capsys):
    pytest.importorskip("torch")
    from rlu.data.bundled import bundled_dataset

    assert main(_train(tmp_path, CARTPOLE)) == 0  # the dataset rlu ships
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert config["dataset"]["path"] == str(bundled_dataset().resolve())
    assert config["train"]["dataset"] == CARTPOLE  # as typed: resume compares it
    # the TFDS name asks for the release's episodes: not here yet, so the exact download command
    assert main(_train(tmp_path, TFDS, "tfds")) == 2
    err = capsys.readouterr().err
    assert f"`rlu download {CARTPOLE} --family dm_control_suite_episodes`" in err
    assert not (tmp_path / "tfds").exists() and not cache.exists()
    # converted into the cache, the same name resolves to it
    dest = _release_entry(CARTPOLE, family="dm_control_suite_episodes")
    assert main(_train(tmp_path, TFDS, "tfds")) == 0
    config = json.loads((tmp_path / "tfds" / "config.json").read_text())
    assert config["dataset"]["path"] == str(os.path.realpath(dest))


def test_a_name_that_is_nothing_says_what_was_tried(tmp_path, capsys):
    assert main(_train(tmp_path, "control_suite/cartpol")) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("rlu: error: dataset 'control_suite/cartpol': no such folder (")
    assert "not a task id or TFDS name" in err and f"Closest: {CARTPOLE}" in err
    assert main(_train(tmp_path, "runs/nothing/here")) == 2
    assert "no such folder" in capsys.readouterr().err


def test_a_sweep_takes_bare_names_and_defaults_to_each_tasks_own_data(tmp_path):
    from rlu.commands.train import _datasets
    from rlu.data.bundled import bundled_dataset
    from rlu.training.sweep import SweepConfig, resolve_datasets

    assert _datasets([CARTPOLE]) == {CARTPOLE: CARTPOLE}
    assert _datasets([f"{CARTPOLE}={bundled_dataset()}"]) == {CARTPOLE: str(bundled_dataset())}
    assert _datasets([str(bundled_dataset())]) == {CARTPOLE: str(bundled_dataset())}  # manifest
    with pytest.raises(RluError, match="two datasets for"):
        _datasets([CARTPOLE, f"{CARTPOLE}=x"])
    config = SweepConfig(tasks=(CARTPOLE,), agents=("bc",), datasets={})
    assert resolve_datasets(config) == {CARTPOLE: str(bundled_dataset().resolve())}
    typo = SweepConfig(tasks=(CARTPOLE,), agents=("bc",), datasets={"control/cartpole": "x"})
    with pytest.raises(RluError, match="not one of the sweep's tasks"):
        resolve_datasets(typo)


def test_config_files_build_their_configs(tmp_path):
    pytest.importorskip("yaml")
    from rlu.training.config import RunSettings
    from rlu.training.sweep import SweepConfig
    from rlu.training.train import TrainConfig

    path = tmp_path / "bc.yaml"
    path.write_text(
        f"task: {CARTPOLE}\nagent: bc\ndataset: {TFDS}\nseed: 3\noverrides:\n  batch_size: 8\n"
        "run:\n  steps: 6\n  eval_every: -1\n  runtime:\n    device: cpu\n"
    )
    config = TrainConfig.from_file(path)
    assert config == TrainConfig(
        task=CARTPOLE, agent="bc", dataset=TFDS, seed=3, overrides={"batch_size": 8},
        run=RunSettings(steps=6, eval_every=-1),
    )  # fmt: skip
    assert TrainConfig.from_file(path, seed=4).seed == 4
    # a run folder's config.json reads back as the config that made it
    resolved = {"train": config.to_json(), "agent_config": {}}
    (tmp_path / "config.json").write_text(json.dumps(resolved))
    assert TrainConfig.from_file(tmp_path / "config.json") == config
    (tmp_path / "partial.json").write_text(json.dumps({"task": CARTPOLE, "agent": "bc"}))
    with pytest.raises(RluError, match="partial.json: field 'dataset' is missing"):
        TrainConfig.from_file(tmp_path / "partial.json")
    assert TrainConfig.from_file(tmp_path / "partial.json", dataset=CARTPOLE).dataset == CARTPOLE
    (tmp_path / "module.json").write_text(json.dumps({**config.to_json(), "agent": "os.path"}))
    with pytest.raises(RluError, match="names the agent module 'os.path'"):
        TrainConfig.from_file(tmp_path / "module.json")
    env = {**config.to_json(), "run": {"env": "os:system"}}
    (tmp_path / "env.json").write_text(json.dumps(env))
    with pytest.raises(RluError, match="names the env factory 'os:system'"):
        TrainConfig.from_file(tmp_path / "env.json")

    sweep = tmp_path / "sweep.yaml"
    sweep.write_text(
        f"tasks: [{CARTPOLE}]\nagents: [bc, d4pg]\ndatasets: {{{CARTPOLE}: {TFDS}}}\n"
        "seeds: [0, 1]\ngrid: {learning_rate: [0.001, 0.0003]}\nrun: {steps: 10}\n"
    )
    assert SweepConfig.from_file(sweep) == SweepConfig(
        tasks=(CARTPOLE,), agents=("bc", "d4pg"), datasets={CARTPOLE: TFDS}, seeds=(0, 1),
        grid={"learning_rate": [0.001, 0.0003]}, run=RunSettings(steps=10),
    )  # fmt: skip


def test_load_dataset_refuses_unknown_keywords_with_the_closest():
    with pytest.raises(RluError, match="no keyword 'familly'; did you mean 'family'?"):
        rlu.load_dataset(CARTPOLE, familly="dm_control_suite_episodes")
    with pytest.raises(RluError, match="no keyword 'zzz'. It takes base_url, cache_dir"):
        rlu.load_dataset(CARTPOLE, zzz=1)
    from rlu.data.bundled import bundled_dataset

    with pytest.raises(RluError, match="a dataset folder is one dataset, and family, run pick"):
        rlu.load_dataset(str(bundled_dataset()), family="x", run=1)
    with pytest.raises(RluError, match="base_url applies to source='release'"):
        rlu.load_dataset(CARTPOLE, base_url="http://127.0.0.1:9")


def test_a_cache_entry_of_another_task_is_refused(cache):
    dest = release_dataset_path(catalog.select("control_suite/walker_walk"), None, True)
    write_synthetic(dest, Schema.for_task(get_task(CARTPOLE)), 2, 4)  # cartpole's episodes
    with pytest.raises(RluError) as e:
        rlu.load_dataset("control_suite/walker_walk")
    msg = str(e.value)
    assert "holds a dataset of 'control_suite/cartpole_swingup'" in msg
    assert "not of control_suite/walker_walk" in msg and f"rm -r {dest}" in msg


def test_the_cache_is_never_followed_out_of_itself(cache, tmp_path):
    elsewhere = tmp_path / "elsewhere"
    write_synthetic(elsewhere, Schema.for_task(get_task("control_suite/walker_walk")), 2, 4)
    dest = release_dataset_path(catalog.select("control_suite/walker_walk"), None, True)
    os.makedirs(os.path.dirname(dest))
    os.symlink(elsewhere, dest)  # the entry itself a link
    with pytest.raises(RluError, match="a symbolic link in rlu's dataset cache"):
        rlu.load_dataset("control_suite/walker_walk")
    os.unlink(dest)
    # a folder on the way a link: datasets/control_suite -> a folder holding walker_walk/...
    outside = tmp_path / "outside"
    write_synthetic(
        outside / os.path.relpath(dest, cache / "datasets" / "control_suite"),
        Schema.for_task(get_task("control_suite/walker_walk")), 2, 4,
    )  # fmt: skip
    os.rmdir(os.path.dirname(dest))
    os.rmdir(cache / "datasets" / "control_suite")
    os.symlink(outside, cache / "datasets" / "control_suite")
    with pytest.raises(RluError, match="datasets/control_suite: a symbolic link"):
        rlu.load_dataset("control_suite/walker_walk")
    assert len(rlu.load_dataset(str(outside / "walker_walk" / "dm_control_suite"))) == 2
