"""Task names: TensorFlow Datasets' names for RL Unplugged resolve to rlu's tasks everywhere a
task id is taken, with the dataset (family, run, challenge, size) they name."""

from __future__ import annotations

import pytest

from rlu.cli import main
from rlu.data.release import catalog
from rlu.tasks import RWRL_SIZES, TASKS, TFDS_BUILDERS, get_task, resolve_task
from rlu.types import RluError

# TFDS's config names, built as tensorflow_datasets/rl_unplugged builds them: rlu_control_suite's
# and rlu_locomotion's configs are the task names; atari_utils.builder_configs() makes
# f"{game}_run_{run}" for runs 1..5; rlu_rwrl makes
# f"{domain}_{task}_combined_challenge_{str(challenge).lower()}_{dataset_size}" over SHARDS_MAPPING.
TFDS_CONTROL = [
    "cartpole_swingup", "cheetah_run", "finger_turn_hard", "fish_swim", "humanoid_run",
    "manipulator_insert_ball", "manipulator_insert_peg", "walker_stand", "walker_walk",
]  # fmt: skip
TFDS_LOCOMOTION = [
    "humanoid_corridor", "humanoid_gaps", "humanoid_walls", "rodent_bowl_escape", "rodent_gaps",
    "rodent_mazes", "rodent_two_touch",
]  # fmt: skip
TFDS_RWRL_TASKS = {"cartpole": "swingup", "quadruped": "walk", "walker": "walk", "humanoid": "walk"}
TFDS_RWRL_SIZES = ("1_percent", "5_percent", "20_percent", "40_percent", "100_percent")


def test_every_tfds_control_and_locomotion_config_names_its_task_and_episode_files():
    for name in TFDS_CONTROL:
        ref = resolve_task(f"rlu_control_suite/{name}")
        assert ref.task.id == f"control_suite/{name}"
        assert ref.family == "dm_control_suite_episodes"  # TFDS reads the whole-episode files
    for name in TFDS_LOCOMOTION:
        ref = resolve_task(f"rlu_locomotion/{name}")
        assert (ref.task.id, ref.family) == (f"locomotion/{name}", "dm_locomotion_episodes")


def test_every_tfds_atari_config_names_its_game_and_run():
    games = [t.name for t in TASKS.values() if t.domain == "atari"]
    assert len(games) == 46
    for builder in ("rlu_atari", "rlu_atari_checkpoints_ordered"):
        for game in games:
            for run in range(1, 6):
                ref = resolve_task(f"{builder}/{game}_run_{run}")
                assert (ref.task.id, ref.run) == (f"atari/{game}", f"run_{run}")
                assert ref.family == "atari_episodes_ordered"


def test_tfds_rwrl_configs_rlu_reads_resolve_and_the_others_say_which_it_has():
    accepted = 0
    for domain, task in TFDS_RWRL_TASKS.items():
        for challenge in ("none", "easy"):
            for size in TFDS_RWRL_SIZES:
                name = f"rlu_rwrl/{domain}_{task}_combined_challenge_{challenge}_{size}"
                paper = {v: k for k, v in RWRL_SIZES.items()}.get(size)
                if f"{challenge}/{paper}" in get_task(f"rwrl/{domain}_{task}").datasets:
                    ref = resolve_task(name)
                    assert ref.task.id == f"rwrl/{domain}_{task}"
                    assert (ref.family, ref.challenge, ref.size) == ("rwrl", challenge, paper)
                    accepted += 1
                else:
                    with pytest.raises(RluError, match="not one rlu reads.*easy_100_percent"):
                        resolve_task(name)
    assert accepted == 4 * 4  # none at 20/40/100 % and easy at 100 %, per task


def test_tfds_names_take_a_version_and_bad_ones_say_the_form():
    assert (
        resolve_task("rlu_control_suite/walker_walk:1.0.0").task.id == "control_suite/walker_walk"
    )
    cases = {
        "rlu_atari/Pong": "TFDS names read like rlu_atari/Pong_run_1",
        "rlu_atari/Pong_run_6": "no config 'Pong_run_6'",
        "rlu_control_suite": "names no config",
        "rlu_locomotion/rodent_run": "no config 'rodent_run'",
        "rlu_atari_checkpoints/Pong_run_1": "atari_episodes_v2 files, which rlu does not read",
        "rlu_dmlab_rooms_watermaze/snapshot_0_eps_0.0": "no config 'snapshot_0_eps_0.0'",
        "rlu_dmlab_seekavoid_arena_01/training_0": "rlu knows the TFDS builders",  # 'arena01'
        "rlu_nope/x": "rlu knows the TFDS builders rlu_control_suite",
    }
    for name, why in cases.items():
        with pytest.raises(RluError, match=why):
            get_task(name)
    assert set(TFDS_BUILDERS) >= {"rlu_control_suite", "rlu_locomotion", "rlu_atari", "rlu_rwrl"}


def test_dmlab_tfds_names_pick_the_level_and_run():
    ref = resolve_task("rlu_dmlab_seekavoid_arena01/training_2:1.1.0")
    assert (ref.task.id, ref.family, ref.run) == ("dmlab/seekavoid_arena_01", "dmlab", "training_2")
    sel = catalog.select("rlu_dmlab_rooms_watermaze/training_1")
    assert sel.binding == "training_1" and len(sel.objects) == 500
    assert sel.objects[-1] == "dmlab/rooms_watermaze/training_1/tfrecord-00499-of-00500"
    assert catalog.select("rlu_dmlab_rooms_watermaze/training_1", run="training_1").objects
    with pytest.raises(RluError, match="names run 'training_1', which contradicts run='train"):
        catalog.select("rlu_dmlab_rooms_watermaze/training_1", run="training_0")


def test_ids_and_bare_names_still_resolve_without_dataset_settings():
    ref = resolve_task("control_suite/cartpole_swingup")
    assert (ref.family, ref.run, ref.challenge, ref.size) == (None, None, None, None)
    assert get_task("Pong").id == "atari/Pong"
    with pytest.raises(RluError, match="unknown task id 'walker_walk'"):  # suite and RWRL
        get_task("walker_walk")


def test_release_selection_takes_the_name_s_dataset_and_refuses_a_contradiction():
    sel = catalog.select("rlu_atari/Pong_run_3")
    assert sel.family == "atari_episodes_ordered" and sel.binding == "run_3"
    assert sel.objects[0] == "atari_episodes_ordered/Pong/run_3-00000-of-00050"
    assert catalog.select("rlu_atari/Pong_run_3", run=3).binding == "run_3"  # agrees: fine
    with pytest.raises(RluError, match="names run 'run_3', which contradicts run=1"):
        catalog.select("rlu_atari/Pong_run_3", run=1)
    with pytest.raises(RluError, match="names family 'atari_episodes_ordered'"):
        catalog.select("rlu_atari/Pong_run_3", family="atari")
    rw = catalog.select("rlu_rwrl/walker_walk_combined_challenge_none_40_percent")
    assert rw.binding == "none/medium" and rw.objects[0].startswith(
        "rwrl/combined_challenge_none/walker/walk/40_percent/episodes.tfrecord-00000-of-00048"
    )
    cs = catalog.select("rlu_control_suite/fish_swim", shards="0")
    assert cs.objects == ("dm_control_suite_episodes/fish_swim/train-00000-of-00100",)


def test_an_rwrl_size_given_as_its_bucket_folder_agrees_with_the_name():
    """RWRL's sizes are the paper's words (large) and the bucket's folders (100_percent):
    either agrees with a name that picks the size; another size is a contradiction."""
    ref = resolve_task("rlu_rwrl/walker_walk_combined_challenge_none_100_percent")
    assert ref.size == "large"
    assert ref.dataset_settings(size="100_percent")[3] == "100_percent"
    assert ref.dataset_settings(size="large")[3] == "large"
    with pytest.raises(RluError, match="names size 'large', which contradicts size='20_percent'"):
        ref.dataset_settings(size="20_percent")


def test_cli_download_list_and_info_take_tfds_names(capsys):
    assert main(["download", "rlu_atari/Breakout_run_2", "--list", "--shards", "0"]) == 0
    assert (
        capsys.readouterr()
        .out.strip()
        .endswith("/atari_episodes_ordered/Breakout/run_2-00000-of-00050")
    )
    assert main(["info", "rlu_rwrl/cartpole_swingup_combined_challenge_easy_100_percent"]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0] == (
        'alias: "rlu_rwrl/cartpole_swingup_combined_challenge_easy_100_percent = '
        'rwrl/cartpole_swingup (family rwrl, challenge easy, size large)"'
    )
    assert main(["info", "rlu_atari/Pong"]) == 2
    err = capsys.readouterr().err
    assert "rlu_atari/Pong_run_1" in err and "dataset directory" not in err


def test_info_prints_a_single_dataset_s_counts_without_the_empty_key(capsys):
    assert main(["info", "control_suite/cartpole_swingup"]) == 0
    out = capsys.readouterr().out
    assert "episodes: 40\n" in out and '""' not in out and "datasets:" not in out
    assert "    shards: 100\n" in out
    assert main(["info", "rwrl/walker_walk"]) == 0
    out = capsys.readouterr().out
    assert 'episodes: {"none/small": 1000' in out and "datasets: [" in out
    assert main(["info", "atari/Pong"]) == 0
    assert 'episodes: "not a paper number' in capsys.readouterr().out
    assert main(["info", "control_suite/cartpole_swingup", "--json"]) == 0  # JSON as it was
    assert '"episodes": {\n  "": 40\n }' in capsys.readouterr().out


def test_make_env_takes_the_challenge_a_tfds_name_carries():
    pytest.importorskip("dm_control")
    import rlu

    env = rlu.make_env("rlu_rwrl/cartpole_swingup_combined_challenge_easy_100_percent", seed=0)
    assert env.spec.kwargs == {"task_id": "rwrl/cartpole_swingup", "seed": 0, "challenge": "easy"}
    assert "dummy-0" in env.observation_space.spaces
    env.close()
    plain = rlu.make_env("rlu_control_suite/cartpole_swingup")
    assert plain.spec.id == "rlu/control_suite-cartpole_swingup-v0"
    plain.close()
