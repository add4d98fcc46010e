"""Nothing rlu writes or reads for its own state uses pickle.

Two checks: a scan of the package's source (ast) for pickle and for loaders that can unpickle,
and pickle payloads planted where rlu expects its files, each refused with an error that names
the file, without the payload ever running.
"""

from __future__ import annotations

import ast
import pickle
from pathlib import Path

import numpy as np
import pytest

from rlu.cli import main
from rlu.data import Schema, open_dataset
from rlu.data.d3rlpy_io import import_d3rlpy
from rlu.data.d4rl import export_d4rl, import_d4rl
from rlu.data.synthetic import write_synthetic
from rlu.tasks import get_task
from rlu.types import FormatError

PKG = Path(__file__).resolve().parents[2] / "rlu"
PICKLE_MODULES = {"pickle", "_pickle", "cPickle", "dill", "cloudpickle", "joblib", "shelve"}
CARTPOLE = Schema.for_task(get_task("control_suite/cartpole_swingup"))


def _const(call: ast.Call, name: str):
    for kw in call.keywords:
        if kw.arg == name and isinstance(kw.value, ast.Constant):
            return kw.value.value
    return None


def pickle_uses(source: str, filename: str = "<src>") -> list[str]:
    """Lines of ``source`` that import a pickle module, call np.load without
    ``allow_pickle=False``, torch.load without ``weights_only=True``, or read a pickle by name."""
    problems = []
    for node in ast.walk(ast.parse(source)):
        where = f"{filename}:{getattr(node, 'lineno', '?')}"
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] in PICKLE_MODULES:
                    problems.append(f"{where}: imports {a.name}")
        elif isinstance(node, ast.ImportFrom) and node.module:
            root = node.module.split(".")[0]
            if root in PICKLE_MODULES:
                problems.append(f"{where}: imports from {node.module}")
            if root in ("numpy", "torch") and any(a.name == "load" for a in node.names):
                problems.append(f"{where}: 'from {node.module} import load' hides the loader")
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            f = node.func
            owner = f.value.id if isinstance(f.value, ast.Name) else None
            if (
                f.attr == "load"
                and owner in ("np", "numpy")
                and _const(node, "allow_pickle") is not False
            ):
                problems.append(f"{where}: np.load without allow_pickle=False")
            if f.attr == "load" and owner == "torch" and _const(node, "weights_only") is not True:
                problems.append(f"{where}: torch.load without weights_only=True")
            if f.attr in ("read_pickle", "to_pickle", "from_pickle"):
                problems.append(f"{where}: {f.attr}")
    return problems


def test_the_package_never_unpickles():
    problems = []
    for path in sorted(PKG.rglob("*.py")):
        problems += pickle_uses(path.read_text(), str(path.relative_to(PKG.parent)))
    assert not problems, "\n".join(problems)


def test_the_scan_finds_each_kind_of_use():
    bad = """
import pickle
from joblib import load
from numpy import load
import numpy as np, torch
np.load("a.npy")
np.load("a.npy", allow_pickle=True)
torch.load("ckpt.pt")
torch.load("ckpt.pt", weights_only=False)
df.read_pickle("x")
"""
    assert len(pickle_uses(bad)) == 8
    good = (
        "import numpy as np, torch\n"
        'np.load("a", allow_pickle=False)\n'
        'torch.load("c", weights_only=True)\n'
    )
    assert pickle_uses(good) == []


# --- planted payloads ---------------------------------------------------------------------------
class Payload:
    """Unpickling this creates ``marker`` (by calling open(marker, 'w')): proof that it ran."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (open, (str(self.marker), "w"))


@pytest.fixture
def payload(tmp_path):
    marker = tmp_path / "PAYLOAD_RAN"
    data = pickle.dumps(Payload(marker))
    yield data
    assert not marker.exists(), "a planted pickle was unpickled"


def test_pickled_manifest_is_refused(tmp_path, payload, capsys):
    path = write_synthetic(tmp_path / "ds", CARTPOLE, 2, 4)
    (path / "manifest.json").write_bytes(payload)
    with pytest.raises(FormatError, match=r"manifest\.json: corrupt JSON"):
        open_dataset(path)
    assert main(["validate", str(path)]) == 1
    assert "manifest.json" in capsys.readouterr().out


def test_pickled_column_is_refused(tmp_path, payload):
    path = write_synthetic(tmp_path / "ds", CARTPOLE, 2, 4)
    col = path / "steps" / "reward.bin"
    size = col.stat().st_size
    col.write_bytes(payload)
    with pytest.raises(FormatError, match=r"reward\.bin: \d+ bytes, the manifest says"):
        open_dataset(path)
    # the same size as the real column: still raw bytes to rlu, and its checksum gives it away
    col.write_bytes((payload * (size // len(payload) + 1))[:size])
    with pytest.raises(FormatError, match=r"reward\.bin: sha256 differs"):
        open_dataset(path, verify=True)
    np.asarray(open_dataset(path).column("reward"))  # read as numbers, never unpickled


def test_npz_with_object_arrays_is_refused(tmp_path, payload):
    src = open_dataset(write_synthetic(tmp_path / "src", CARTPOLE, 2, 4))
    good = export_d4rl(src, tmp_path / "good.npz")
    with np.load(good, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    rewards = np.array([_Unpicklable(payload)] * len(arrays["rewards"]), dtype=object)
    np.savez(tmp_path / "evil.npz", **{**arrays, "rewards": rewards})  # numpy pickles it
    with pytest.raises(FormatError, match=r"evil\.npz: array 'rewards' holds Python objects"):
        import_d4rl(tmp_path / "evil.npz", tmp_path / "out", CARTPOLE.task_id)
    assert not (tmp_path / "out").exists()


class _Unpicklable:
    """Pickles to the planted payload's bytes (so the .npz holds exactly that pickle)."""

    def __init__(self, data: bytes):
        self.data = data

    def __reduce__(self):
        return (pickle.loads, (self.data,))


def test_a_pickle_named_npz_is_refused(tmp_path, payload, capsys):
    (tmp_path / "x.npz").write_bytes(payload)
    with pytest.raises(FormatError, match=r"x\.npz: not an \.npz archive"):
        import_d4rl(tmp_path / "x.npz", tmp_path / "out", CARTPOLE.task_id)
    assert (
        main(
            [
                "import",
                "--format",
                "d4rl",
                str(tmp_path / "x.npz"),
                "--task",
                CARTPOLE.task_id,
                "--out",
                str(tmp_path / "out"),
            ]
        )
        == 2
    )
    assert "never unpickles" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("name", ["dump.h5", "file.hdf5"])
def test_a_pickle_instead_of_hdf5_is_refused(tmp_path, payload, name):
    pytest.importorskip("h5py")
    (tmp_path / name).write_bytes(payload)
    with pytest.raises(FormatError, match=rf"{name}: not an HDF5 file"):
        if name == "dump.h5":
            import_d3rlpy(tmp_path / name, tmp_path / "out", "control_suite/walker_walk")
        else:
            import_d4rl(tmp_path / name, tmp_path / "out", CARTPOLE.task_id)
    assert not (tmp_path / "out").exists()


def test_a_pickled_minari_metadata_is_refused(tmp_path, payload):
    pytest.importorskip("minari")
    from rlu.data.minari import export_minari, import_minari

    src = open_dataset(write_synthetic(tmp_path / "src", CARTPOLE, 1, 3))
    path = export_minari(src, "rlu/evil-v0", root=tmp_path / "m")
    (path / "data" / "metadata.json").write_bytes(payload)
    with pytest.raises(FormatError, match=r"metadata\.json: not a Minari metadata JSON"):
        import_minari(path, tmp_path / "out", CARTPOLE.task_id)
    assert not (tmp_path / "out").exists()
