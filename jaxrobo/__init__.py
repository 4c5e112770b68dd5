"""jaxrobo: the openai_ros training structure (task → robot → sim → env) as functional JAX on MuJoCo MJX.

>>> import jax, jaxrobo
>>> env = jaxrobo.make("CartPoleStayUp-v0", control_type="position")
>>> state = env.reset(jax.random.key(0))
>>> state = env.step(state, 1)
"""
from __future__ import annotations

__version__ = "0.1.0"

from jaxrobo.render import select_gl_backend as _select_gl

_select_gl()  # before anything imports mujoco: MUJOCO_GL may only name a backend whose library loads

from jaxrobo.config import ConfigError
from jaxrobo.env import EnvState, TaskEnv
from jaxrobo.registry import make, register, registered, spec
from jaxrobo import gym_adapter as _gym_adapter  # noqa: E402,F401  (registers "jaxrobo/<id>" with Gymnasium)

__all__ = ["ConfigError", "EnvState", "TaskEnv", "make", "register", "registered", "spec", "__version__"]
