"""The Gymnasium ids ``jaxrobo/<id>``: registered on ``import jaxrobo`` with string entry points into
:mod:`jaxrobo.interop.gym_adapter`, which (with JAX) is imported only when Gymnasium makes an env.

* :func:`register_gymnasium_envs` - every jaxrobo id as ``jaxrobo/<id>`` for ``gymnasium.make`` and
  ``gymnasium.make_vec``. It runs on ``import jaxrobo`` and records strings only (no env is built, no task module
  imported); an id registered later (a user's module) becomes a Gymnasium id at once, through
  :data:`jaxrobo.task.registry.REGISTER_HOOKS`, also under its bare name for Gymnasium's
  ``gymnasium.make("my_mod:MyEnv-v0")``.
* :class:`JaxroboSpec` - such a registration: its ``max_episode_steps`` is the id's step limit, read when first asked.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import gymnasium
from gymnasium.envs.registration import EnvSpec

NAMESPACE = "jaxrobo"
#: The module holding the single and vector env classes the registrations name.
ADAPTER = "jaxrobo.interop.gym_adapter"


class _Unread:
    """A step limit not read yet (a class, so that a copy or a pickle of a spec keeps it as it is)."""


class JaxroboSpec(EnvSpec):
    """Gymnasium's spec of a jaxrobo id. ``max_episode_steps`` is the id's step limit (:func:`jaxrobo.spec`: its
    env YAML's, else its task's ``Params`` default), read when first asked rather than at registration: the
    default's one home is the task module, and importing it imports JAX and MuJoCo, which ``import jaxrobo`` does
    not. ``gymnasium.make`` asks after building the env, so its ``TimeLimit`` ends episodes at the task's limit."""

    def __init__(self, *args: Any, jaxrobo_id: str | None = None, **fields: Any):
        # The id apart from ``kwargs``, which ``gymnasium.make_vec`` empties on its copy before it reads the limit.
        self.jaxrobo_id = jaxrobo_id
        super().__init__(*args, **fields)

    @property
    def max_episode_steps(self) -> int | None:
        if self._max_episode_steps is _Unread:
            from jaxrobo.task.registry import spec

            self._max_episode_steps = spec(self.jaxrobo_id).max_episode_steps
        return self._max_episode_steps

    @max_episode_steps.setter
    def max_episode_steps(self, value: int | None) -> None:
        self._max_episode_steps = value


def gym_id(env_id: str) -> str:
    """The Gymnasium id of a jaxrobo id: ``jaxrobo/<id>``."""
    return f"{NAMESPACE}/{env_id}"


def register_gymnasium_envs() -> list[str]:
    """Register every jaxrobo id with Gymnasium as ``jaxrobo/<id>`` (idempotent). :func:`jaxrobo.register` calls
    :func:`register_gymnasium_id` for each id it adds after ``import jaxrobo``, so ``gymnasium.make("jaxrobo/<id>")``
    works after importing the user's module that registers it."""
    from jaxrobo.task.registry import registered

    return [gid for gid in (register_gymnasium_id(env_id) for env_id in registered()) if gid]


def register_gymnasium_id(env_id: str) -> str | None:
    """Register ``jaxrobo/<env_id>`` with Gymnasium; its id, or ``None`` if it was already registered.

    An id a user's module registers (``jaxrobo.register`` called from ``my_mod``) is also registered under its bare
    name, unless Gymnasium already has that name: Gymnasium's own ``gymnasium.make("my_mod:MyEnv-v0")`` imports
    ``my_mod`` and looks up ``MyEnv-v0``, so that form works like ``"my_mod:jaxrobo/MyEnv-v0"``."""
    from jaxrobo.task.registry import registration

    gid = gym_id(env_id)
    if gid in gymnasium.registry:
        return None
    names = [gid]
    if registration(env_id).module is not None and env_id not in gymnasium.registry:
        names.append(env_id)
    for name in names:
        # Gymnasium's own register (its checks of the id), then the same spec as one that reads the step limit later
        gymnasium.register(id=name, entry_point=f"{ADAPTER}:JaxroboEnv",
                           vector_entry_point=f"{ADAPTER}:JaxroboVectorEnv", kwargs={"env_id": env_id})
        plain = gymnasium.registry[name]
        fields = {f.name: getattr(plain, f.name) for f in dataclasses.fields(plain) if f.init}
        gymnasium.registry[name] = JaxroboSpec(**{**fields, "max_episode_steps": _Unread}, jaxrobo_id=env_id)
    return gid


register_gymnasium_envs()


def _install_hook() -> None:
    from jaxrobo.task.registry import REGISTER_HOOKS

    if register_gymnasium_id not in REGISTER_HOOKS:
        REGISTER_HOOKS.append(register_gymnasium_id)


_install_hook()  # after the built-in ids: every id registered from now on becomes a Gymnasium id at once
