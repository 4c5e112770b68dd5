"""Robots and tasks shipped with jaxrobo; importing this package registers their ids."""
from __future__ import annotations

import os

from jaxrobo.registry import register

_CONFIGS = os.path.join(os.path.dirname(__file__), "configs")
_AGENT_CONFIGS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "agents", "configs")


def _cfg(name: str) -> str:
    return os.path.join(_CONFIGS, name)


def _register_builtin() -> None:
    from envs.cartpole_stay_up import CartPoleStayUp

    register("CartPoleStayUp-v0", CartPoleStayUp, 1000, config=_cfg("cartpole_stay_up.yaml"),
             agent_config="cartpole_stay_up.yaml", description="seed 001: keep the pole up, 4 actions")
    register("CartPoleStayUp-v1", CartPoleStayUp, 1000, config=_cfg("cartpole_stay_up.yaml"),
             agent_config="cartpole_stay_up.yaml", description="seed exercise 2.3: left/right only", n_actions=2)


_register_builtin()
