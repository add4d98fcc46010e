"""The data-generation recipe: online behaviour agents, the episode recorder, sub-sampling.

    from rlu.generate import generate
    generate("control_suite/cartpole_swingup", "data/cartpole", scale="small", seed=0)

Modules: ``recorder`` (env loop -> store segments), ``online`` (the D4PG / DQN actor-learner
runs), ``recipe`` (scales, success rule, selection, resumption, the final dataset). Heavy
dependencies (torch, the simulators) load only when a run starts.
"""

from __future__ import annotations

from rlu.generate.recipe import SCALES, generate, select_episodes, success_rule

__all__ = ["SCALES", "generate", "select_episodes", "success_rule"]
