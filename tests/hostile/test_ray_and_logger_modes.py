"""Ray addresses and logger modes checked before Ray or the logger is called (issue 39, item 8):
a ``--ray-address`` that is none of auto, local, HOST:PORT, ray://HOST:PORT is one line
``rlu: error: ...`` (exit 2) naming the flag, the value and the forms, from ``rlu sweep``,
``rlu convert`` and ``rlu download``, before any output folder; a HOST:PORT nothing listens on
is refused by a TCP connect (no Ray started, no folder made) instead of ``ray.init`` retrying
for minutes; a WANDB_MODE wandb does not take is refused before the run folder exists.

No network: every address reached is on 127.0.0.1, a port bound then closed (nothing listens)
or a socket this test listens on."""

from __future__ import annotations

import importlib.util
import socket
from pathlib import Path

import pytest

from rlu.cli import main
from rlu.types import RluError
from rlu.workers import Backend, check_ray_address, reach_ray_address, run_jobs

MALFORMED = [
    "",
    " auto",
    "Local",
    "localhost",
    "10.0.0.5",
    "head:",
    ":6379",
    "head:0",
    "head:65536",
    "head:99999999",
    "head:63 79",
    "head:-1",
    "head:+80",
    "head:0x10",
    "http://head:6379",
    "ray://",
    "ray://head",
    "ray://:10001",
    "::1:6379",
    "[::1:6379",
    "[1.2.3.4]:6379",
    "[zz::1]:6379",
    "bad_host:6379",
    "bad!host:6379",
    "-head.example:6379",
    "head-.example:6379",
    "a..b:6379",
    "999.1.1.1:6379",
    "1.2.3:6379",
    "head name:6379",
    "head/path:6379",
    "head\n:6379",
    "x" * 64 + ".example:6379",
]


def _free_port() -> int:
    """A port on 127.0.0.1 nothing listens on: bound by the system, then closed."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _one_line(capsys, argv: list[str], *words: str) -> str:
    capsys.readouterr()
    code = main(argv)
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if not x.startswith("rlu train: ")]  # its device line
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("rlu: error: "), err
    assert "Traceback" not in err
    for w in words:
        assert w in lines[0], err
    return lines[0]


def _ray_started() -> bool:
    if importlib.util.find_spec("ray") is None:
        return False
    import ray

    return ray.is_initialized()


@pytest.mark.parametrize("address", MALFORMED)
def test_a_malformed_ray_address_is_refused_naming_the_forms(address):
    with pytest.raises(RluError) as e:
        check_ray_address(address)
    message = str(e.value)
    assert "--ray-address" in message and repr(address) in message
    assert "auto" in message and "local" in message and "ray://HOST:PORT" in message
    with pytest.raises(RluError, match="--ray-address"):
        Backend("ray", address=address)  # made from the command line or in code


@pytest.mark.parametrize(
    ("address", "target"),
    [
        ("auto", None),
        ("local", None),
        ("127.0.0.1:6379", ("127.0.0.1", 6379)),
        ("head-node.example.org:1", ("head-node.example.org", 1)),
        ("head:65535", ("head", 65535)),
        ("[::1]:6379", ("::1", 6379)),
        ("ray://10.0.0.5:10001", ("10.0.0.5", 10001)),
        ("ray://[fe80::1]:10001", ("fe80::1", 10001)),
    ],
)
def test_the_accepted_forms_pass_the_check(address, target):
    assert check_ray_address(address) == target
    assert Backend("ray", address=address).address == address


def test_auto_and_local_are_not_reached():
    reach_ray_address("local")  # left to Ray: no connection is tried
    reach_ray_address("auto")
    Backend("ray", address="local").reach()


def test_an_address_that_answers_passes():
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        reach_ray_address(f"127.0.0.1:{port}")
        reach_ray_address(f"ray://127.0.0.1:{port}")


@pytest.mark.parametrize("scheme", ["", "ray://"])
def test_a_port_nothing_listens_on_is_refused_without_ray(scheme):
    address = f"{scheme}127.0.0.1:{_free_port()}"
    with pytest.raises(RluError) as e:
        reach_ray_address(address)
    message = str(e.value)
    assert f"--ray-address {address}" in message and "refused the connection" in message
    assert "ray start --head" in message and "drop --ray-address" in message
    if importlib.util.find_spec("ray") is not None:
        # the runner itself reaches the address before ray.init
        with pytest.raises(RluError, match="refused the connection"):
            run_jobs(abs, [(-1,)], Backend("ray", address=address), lambda i, r: None)
    assert not _ray_started()


def _sweep_argv(out: Path, address: str) -> list[str]:
    return ["sweep", "--tasks", "test/pendulum", "--agents", "bc", "--seeds", "0",
            "--dataset", f"test/pendulum={out.parent / 'no-such-dataset'}", "--out", str(out),
            "--backend", "ray", f"--ray-address={address}"]  # fmt: skip


def _convert_argv(out: Path, address: str) -> list[str]:
    return ["convert", "--family", "dm_control_suite", "--task", "control_suite/cartpole_swingup",
            "--src", str(out.parent / "no-such-src"), "--out-root", str(out), "-q",
            "--backend", "ray", f"--ray-address={address}"]  # fmt: skip


def _download_argv(out: Path, address: str) -> list[str]:
    return ["download", "control_suite/cartpole_swingup", "--shards", "0", "--cache-dir",
            str(out), "--base-url", "http://127.0.0.1:9", "-q", "--backend", "ray",
            f"--ray-address={address}"]  # fmt: skip


COMMANDS = {"sweep": _sweep_argv, "convert": _convert_argv, "download": _download_argv}


@pytest.mark.parametrize("command", sorted(COMMANDS))
@pytest.mark.parametrize("address", MALFORMED)
def test_a_malformed_ray_address_is_one_line_before_any_folder(tmp_path, capsys, command, address):
    out = tmp_path / "out"
    argv = COMMANDS[command](out, address)
    _one_line(capsys, argv, "--ray-address", repr(address), "ray://HOST:PORT")
    assert list(tmp_path.iterdir()) == []  # no output folder, nothing else


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_an_unreachable_cluster_is_one_line_before_any_folder(tmp_path, capsys, command):
    out = tmp_path / "out"
    address = f"127.0.0.1:{_free_port()}"
    argv = COMMANDS[command](out, address)
    _one_line(capsys, argv, address, "refused the connection", "ray start --head")
    assert list(tmp_path.iterdir()) == []
    assert not _ray_started()


def test_the_library_entry_points_reach_the_cluster_before_any_output(tmp_path):
    """rlu.generate.generate and convert_release, called as a library (no command reached the
    address first), refuse a HOST:PORT nothing listens on with rlu's error before they write
    anything or read a shard (on main: only in the runner, after the work folder was made)."""
    from rlu.data.release.jobs import DatasetJob, convert_release
    from rlu.generate import GenerateConfig, generate

    address = f"127.0.0.1:{_free_port()}"
    backend = Backend("ray", address=address)
    config = GenerateConfig("control_suite/cartpole_swingup", scale="tiny", runs=1,
                            backend=backend, progress=False)  # fmt: skip
    with pytest.raises(RluError) as e:
        generate(config, tmp_path / "out")
    assert f"--ray-address {address}" in str(e.value) and "refused the connection" in str(e.value)
    job = DatasetJob("control_suite/cartpole_swingup", "dm_control_suite", str(tmp_path / "ds"),
                     (str(tmp_path / "no-such-shard"),))  # fmt: skip
    with pytest.raises(RluError, match="refused the connection"):  # not the missing shard
        convert_release([job], backend)
    assert list(tmp_path.iterdir()) == []  # no output folder, no work folder, no lock
    assert not _ray_started()


# --- W&B --------------------------------------------------------------------------------------
BAD_MODES = ["bogus", "Offline", "OFFLINE", "", "offline ", "off"]


@pytest.mark.parametrize("mode", BAD_MODES)
def test_an_unknown_wandb_mode_is_refused_naming_the_modes(monkeypatch, mode):
    from rlu.training.loggers import WANDB_MODES, check_logger_settings

    monkeypatch.setenv("WANDB_MODE", mode)
    monkeypatch.setenv("WANDB_API_KEY", "x" * 40)  # a key: the mode alone is at fault
    with pytest.raises(RluError) as e:
        check_logger_settings(["csv", "wandb"])
    assert f"WANDB_MODE is {mode!r}" in str(e.value)
    assert all(m in str(e.value) for m in WANDB_MODES)
    check_logger_settings(["csv"])  # W&B not asked for: its mode is not its business


def test_the_modes_are_wandbs_own():
    """WANDB_MODES is the installed wandb's list of its settings' modes, no more, no less."""
    pytest.importorskip("wandb")
    import typing

    from wandb.sdk.wandb_settings import Settings

    from rlu.training.loggers import WANDB_MODES

    hint = typing.get_type_hints(Settings)["mode"]
    assert set(typing.get_args(hint)) == set(WANDB_MODES)


@pytest.mark.parametrize("mode", ["online", "offline", "disabled", "dryrun", "run", "shared"])
def test_a_known_wandb_mode_passes(monkeypatch, mode):
    from rlu.training.loggers import check_logger_settings

    monkeypatch.setenv("WANDB_MODE", mode)
    monkeypatch.setenv("WANDB_API_KEY", "x" * 40)
    check_logger_settings(["wandb"])


@pytest.fixture(scope="module")
def pendulum(tmp_path_factory):
    pytest.importorskip("torch")
    pytest.importorskip("gymnasium")
    from tests.train.pendulum import write_dataset

    return write_dataset(tmp_path_factory.mktemp("modes") / "ds", "test/pendulum", episodes=3)


@pytest.mark.parametrize("mode", ["bogus", "Offline"])
def test_an_unknown_wandb_mode_is_one_line_before_the_run_folder(
    pendulum, tmp_path, capsys, monkeypatch, mode
):
    from tests.hostile.test_round3_links import _train_argv

    monkeypatch.setenv("WANDB_MODE", mode)
    monkeypatch.setenv("WANDB_API_KEY", "x" * 40)
    run = tmp_path / "run"
    _one_line(capsys, _train_argv(pendulum, run, "--log-to", "wandb"), "WANDB_MODE", repr(mode))
    assert not run.exists()


def test_an_unknown_wandb_mode_is_one_line_before_the_sweep_folder(
    pendulum, tmp_path, capsys, monkeypatch
):
    monkeypatch.setenv("WANDB_MODE", "bogus")
    monkeypatch.setenv("WANDB_API_KEY", "x" * 40)
    out = tmp_path / "sweep"
    argv = ["sweep", "--tasks", "test/pendulum", "--agents", "bc", "--seeds", "0",
            "--dataset", f"test/pendulum={pendulum}", "--out", str(out),
            "--log-to", "wandb"]  # fmt: skip
    _one_line(capsys, argv, "WANDB_MODE is 'bogus'")
    assert not out.exists()
