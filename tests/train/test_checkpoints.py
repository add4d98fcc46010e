"""State files (``rlu.training.checkpoints``): their bytes depend on the values only."""

from __future__ import annotations

from collections import OrderedDict

import pytest

from rlu.training.checkpoints import load_state, save_state

torch = pytest.importorskip("torch")


def _state(key: str, betas: tuple) -> dict:
    weights = OrderedDict(w=torch.arange(3.0))
    weights._metadata = OrderedDict({"": {"version": 1}})  # a module state dict's
    return {
        "step": 4,
        "opt": {"state": {0: {key: torch.tensor(4.0)}}, "groups": [betas, betas]},
        "net": weights,
    }


def test_equal_states_shared_differently_save_the_same_bytes(tmp_path):
    betas = (0.9, 0.999)
    shared = _state("step", betas)  # the top-level key's own string, one tuple twice
    fresh = _state("".join(["st", "ep"]), (0.9, 0.999))  # a string and a tuple of their own
    fresh["opt"]["groups"][1] = (0.9, 0.999)
    assert fresh["opt"]["state"][0].keys() == shared["opt"]["state"][0].keys()
    a, b = save_state(tmp_path / "a.pt", shared), save_state(tmp_path / "b.pt", fresh)
    assert a.read_bytes() == b.read_bytes()
    back = load_state(a, ("step", "opt", "net"))
    assert type(back["net"]) is OrderedDict and back["net"]._metadata == {"": {"version": 1}}
    assert back["opt"]["groups"] == [betas, betas] and torch.equal(
        back["net"]["w"], torch.arange(3.0)
    )
