"""The README's main job runs end to end."""

from __future__ import annotations

import json

import pytest

from rlu.cli import main


def test_quickstart_end_to_end_at_tiny_cost(tmp_path, capsys):
    pytest.importorskip("torch")
    pytest.importorskip("dm_control")
    out = tmp_path / "qs"
    argv = ["quickstart", "--out", str(out), "--steps", "5", "--eval-episodes", "1"]
    assert main([*argv, "--agents", "bc"]) == 0
    text = capsys.readouterr().out
    assert "validate: valid" in text and "| bc |" in text and "| random |" in text
    result = json.loads((out / "results.json").read_text())
    assert [r["policy"] for r in result["policies"]] == ["random", "bc"]
    assert result["dataset_returns"]["episodes"] == 40
    assert (out / "bc" / "result.json").exists() and (out / "report.md").exists()
    if __import__("importlib").util.find_spec("matplotlib") is not None:
        png = (out / "quickstart.png").read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
        assert "![policies beside the dataset's returns](quickstart.png)" in text


def test_info_json_lists_every_episode_return(capsys):
    import numpy as np

    from rlu.data import open_dataset
    from rlu.generate.recipe import bundled_dataset

    path = bundled_dataset()
    assert main(["info", str(path), "--json"]) == 0
    returns = json.loads(capsys.readouterr().out)["returns"]
    per_episode = returns["per_episode"]
    assert per_episode == open_dataset(path).episode_returns().tolist() and len(per_episode) == 40
    assert returns["mean"] == np.mean(per_episode) and returns["max"] == max(per_episode)
    assert main(["info", str(path)]) == 0
    assert "per_episode" not in capsys.readouterr().out  # the tree print stays short
