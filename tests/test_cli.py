"""The README's main job runs end to end."""

from __future__ import annotations

from rlu.cli import main


def test_quickstart_round_trip(tmp_path, capsys):
    assert main(["quickstart", "--out", str(tmp_path / "qs"), "--episodes", "3"]) == 0
    out = capsys.readouterr().out
    assert "validate: valid" in out and "rewards equal: True" in out
