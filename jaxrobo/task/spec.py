"""What an id's registration records, :class:`EnvSpec`: in a module of its own, which imports nothing, so that the
registry (and with it ``import jaxrobo``, which registers every id with Gymnasium) needs no JAX while every env
(:class:`jaxrobo.task.env.Env`) carries the spec it was made with."""
from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class EnvSpec:
    """How an environment was registered: id, step limit and the default overrides it was made with."""

    id: str
    #: None in a registration that leaves the step limit to its task's Params default (``jaxrobo.spec`` and
    #: ``make`` fill it in).
    max_episode_steps: int | None
    description: str = ""
    config: str | None = None  # YAML with the env parameters (the seed's split)
    agent_config: str | None = None  # YAML with the learner parameters
