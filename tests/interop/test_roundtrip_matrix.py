"""Every export round-trips rlu's own datasets exactly (issue 39 item 7): each family rlu stores
(control-suite episodes, seq2 windows, RWRL, Atari episodes, locomotion), made by rlu's converter
from release records, exported to each format (D4RL .hdf5 and .npz, Minari, d3rlpy) and imported
back, is the same dataset: every step column row by row (the last row of every episode, episodes
of 1, 2, 5 and 9 steps, terminal and truncated), the segment index, every metadata column, the
episode returns, schema and provenance. Where a format cannot hold a family, the export refuses
with the reason and writes nothing. The matrix is in docs/interop.md."""

from __future__ import annotations

import pytest

pytest.importorskip("h5py")
pytest.importorskip("minari")

from rlu.data import open_dataset  # noqa: E402
from rlu.data.d3rlpy_io import export_d3rlpy, import_d3rlpy  # noqa: E402
from rlu.data.d4rl import export_d4rl, import_d4rl  # noqa: E402
from rlu.data.minari import export_minari, import_minari  # noqa: E402
from rlu.types import RluError  # noqa: E402

from .families import FAMILIES, make_family  # noqa: E402
from .helpers import assert_same_dataset  # noqa: E402

FORMATS = ("d4rl.hdf5", "d4rl.npz", "minari", "d3rlpy")
REFUSED = {
    ("seq2_windows", "d4rl.hdf5"): "release windows",
    ("seq2_windows", "d4rl.npz"): "release windows",
    ("seq2_windows", "d3rlpy"): "release windows",
}
"""The cells a format cannot hold, and the reason its export gives; every other cell is exact."""


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    root = tmp_path_factory.mktemp("families")
    return {
        (name, outside): make_family(name, root / f"{name}_{outside}", outside=outside)
        for name in FAMILIES
        for outside in (False, True)
        if not (outside and name == "atari_episodes")  # Atari actions are always legal
    }


def round_trip(src, fmt, tmp_path):
    out = tmp_path / "out"
    if fmt.startswith("d4rl"):
        path = export_d4rl(src, tmp_path / f"x.{fmt.split('.')[1]}")
        return open_dataset(import_d4rl(path, out))
    if fmt == "d3rlpy":
        return open_dataset(import_d3rlpy(export_d3rlpy(src, tmp_path / "x.h5"), out))
    path = export_minari(src, "rlu/matrix-v0", root=tmp_path / "minari")
    return open_dataset(import_minari(path, out))


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("family", FAMILIES)
def test_export_then_import_is_exact_or_refused(made, family, fmt, tmp_path):
    src = open_dataset(made[(family, False)])
    if (family, fmt) in REFUSED:
        with pytest.raises(RluError, match=REFUSED[(family, fmt)]):
            round_trip(src, fmt, tmp_path)
        assert not [p.name for p in tmp_path.iterdir() if p.name != "minari"]
        return
    back = round_trip(src, fmt, tmp_path)
    n = assert_same_dataset(src, back)
    assert n["rows"] and n["segments"] == len(src) and 1 in src.length.tolist()


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("family", [f for f in FAMILIES if f != "atari_episodes"])
def test_actions_outside_the_space_are_refused_by_every_format(made, family, fmt, tmp_path):
    """The release's control-suite actions may lie outside [-1, 1] (D4PG's noise before the env
    clips it); rlu's import and the formats' readers take actions inside the space only, so the
    export refuses, naming the step, instead of writing a file rlu would not read back."""
    src = open_dataset(made[(family, True)])
    with pytest.raises(RluError) as info:
        round_trip(src, fmt, tmp_path)
    msg = str(info.value)
    assert ("outside the action space" in msg and "step " in msg) or "release windows" in msg
    assert not [p.name for p in tmp_path.iterdir() if p.name != "minari"]
