"""Every command that needs an extra says, in one line, the pip line that installs it: torch
(agents), h5py (interop) and google-crc32c (release) hidden from a fresh interpreter."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

BLOCK = """
import sys
class _Block:
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in {hidden!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        return None
sys.meta_path.insert(0, _Block())
from rlu.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _rlu(hidden: set[str], *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-c", BLOCK.format(hidden=hidden), *args], cwd=ROOT,
                          env=env, capture_output=True, text=True)  # fmt: skip


def _bundled() -> str:
    from rlu.data.bundled import bundled_dataset

    return str(bundled_dataset())


@pytest.mark.parametrize(
    "args",
    [
        ["train", "--task", "control_suite/cartpole_swingup", "--agent", "bc", "--dataset",
         "{data}", "--out", "{tmp}/run", "--steps", "1"],
        ["evaluate", "{tmp}/nowhere"],
        ["generate", "control_suite/cartpole_swingup", "--scale", "tiny", "--out", "{tmp}/g"],
        ["evaluate-behaviour", "{data}", "--run", "0", "--checkpoint", "0", "--episodes", "1"],
        ["sweep", "--tasks", "control_suite/cartpole_swingup", "--agents", "bc", "--dataset",
         "control_suite/cartpole_swingup={data}", "--out", "{tmp}/s", "--steps", "1"],
    ],
    ids=["train", "evaluate", "generate", "evaluate-behaviour", "sweep"],
)  # fmt: skip
def test_commands_without_torch_name_the_agents_extra(args, tmp_path):
    argv = [a.format(data=_bundled(), tmp=tmp_path) for a in args]
    res = _rlu({"torch"}, *argv)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "rlu[agents]" in lines[0], res.stderr
    assert "Traceback" not in res.stderr


def test_hdf5_import_without_h5py_and_convert_without_crc32c_name_their_extras(tmp_path):
    (tmp_path / "d.hdf5").write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(100))
    res = _rlu({"h5py"}, "import", str(tmp_path / "d.hdf5"), "--format", "d4rl", "--task",
               "control_suite/cartpole_swingup", "--out", str(tmp_path / "out"))  # fmt: skip
    assert res.returncode == 2 and "rlu[interop]" in res.stderr, res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    (tmp_path / "shard.tfrecord").write_bytes(bytes(64))
    res = _rlu({"google_crc32c"}, "convert", "--family", "dm_control_suite", "--task",
               "control_suite/cartpole_swingup", "--out", str(tmp_path / "c"),
               str(tmp_path / "shard.tfrecord"))  # fmt: skip
    assert res.returncode == 2 and "rlu[release]" in res.stderr, res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
