"""Environments by id, with their step limit and config files: ``jaxrobo.make("CartPoleStayUp-v0", **overrides)``;
and the tabular learners by name.

This is the one place ``jaxrobo`` reaches the built-in environments (the ``envs`` package) and the learners (the
``agents`` package): by the module names :data:`BUILTIN_ENVS` and :data:`LEARNERS_MODULE`, imported with
importlib on first use, so neither package is a static import of jaxrobo (``tests/test_structure.py``).

Public surface:

* :func:`make` - build an env by id with keyword overrides of its options and parameters (``jaxrobo.make``);
* :func:`register` - add an id: a :class:`jaxrobo.task.env.TaskEnv` subclass or ``"module:Class"``, its step limit
  and optional YAML files (a relative path is relative to the directory of the module that calls ``register``,
  so a user's task finds the YAML files beside it); :func:`deprecated_alias` keeps an old id working;
* ids from a user's own module: every function taking an id also takes Gymnasium's ``"module:Id"`` form, which
  imports ``module`` (from ``sys.path``, then the current directory) so that its ``register`` calls run, then looks
  up ``Id``; :func:`qualified_id` is the form a run records so that ``--resume`` can import the module again;
* :func:`registered`, :func:`spec`, :func:`registration`, :func:`env_config` - what is registered (an id's
  :class:`Registration`: its spec, its class, its registered defaults) and with which values;
* :func:`learners`, :func:`learner` - the tabular learners by name (``qlearn``, ``sarsa``, ...).

Private: ``_REGISTRY``, ``_lookup`` and the loading of the built-in packages.
"""
from __future__ import annotations

import dataclasses
import importlib
import os
import sys
from typing import TYPE_CHECKING, Any, Callable

from jaxrobo.core.config import ConfigError, check_relations, coerce, load_yaml, split_and_validate, unknown_key
from jaxrobo.core.precision import check_precision
from jaxrobo.core.struct import rules
from jaxrobo.task.spec import EnvSpec

if TYPE_CHECKING:
    from jaxrobo.task.env import Env

#: The package whose import registers the built-in robots and tasks.
BUILTIN_ENVS = "envs"
#: The package holding the tabular learners: its ``LEARNERS`` maps each name to its learner.
LEARNERS_MODULE = "agents"


@dataclasses.dataclass(frozen=True)
class Registration:
    spec: EnvSpec
    entry_point: str | type  # a class, or "module:Class" imported on first use (keeps `import envs` light)
    defaults: dict[str, Any]
    #: The module whose ``register`` call added the id (``None``: the built-in package, or no importable module,
    #: e.g. a script run as ``__main__``): ``"module:Id"`` imports it again.
    module: str | None = None

    def env_class(self) -> type:
        return load_entry_point(self.entry_point) if isinstance(self.entry_point, str) else self.entry_point


def load_entry_point(entry_point: str) -> Any:
    """What a ``"module:Name"`` entry point names, its module imported on first use: how jaxrobo reaches a task's
    code in ``envs`` (its env class; its native-MuJoCo port, for the ROS nodes)."""
    module, _, name = entry_point.partition(":")
    return getattr(importlib.import_module(module), name)


_REGISTRY: dict[str, Registration] = {}
#: Called with each id :func:`register` adds (the Gymnasium adapter registers ``jaxrobo/<id>`` this way, so an id
#: a user's module registers after ``import jaxrobo`` is a Gymnasium id too; the registry never imports it).
REGISTER_HOOKS: list[Callable[[str], None]] = []
#: Old ids that still work in jaxrobo (with a FutureWarning) but are not registered ids of their own, nor
#: Gymnasium ids: ``{old: new}``.
ALIASES: dict[str, str] = {}


def deprecated_alias(old: str, new: str) -> None:
    """Keep ``old`` working as a deprecated name of the registered id ``new``."""
    ALIASES[old] = new


def register(id: str, entry_point: str | type, max_episode_steps: int | None = None, *, config: str | None = None,
             agent_config: str | None = None, description: str = "", **defaults: Any) -> None:
    """Register an environment class (or ``"module:Class"``) under ``id``; ``defaults`` override its defaults.

    The step limit's home is the task's ``Params.max_episode_steps`` default: give ``max_episode_steps`` (or put
    it in the env YAML) only for an id whose limit differs from it; it is then one more default override.

    ``config`` (the env YAML) and ``agent_config`` (the agent presets) may be absolute, or relative to the
    directory of the module calling ``register`` (the built-in package's agent YAML names are relative to
    ``agents/configs``).
    """
    if not isinstance(id, str) or not id or ":" in id:
        raise ValueError(f"environment id {id!r}: expected a non-empty string without ':' (':' separates a module "
                         "from an id in 'module:Id')")
    if id in _REGISTRY:
        raise ValueError(f"environment id {id!r} is already registered")
    if max_episode_steps is not None:
        defaults["max_episode_steps"] = max_episode_steps
    module, directory = _caller()
    builtin = module is not None and (module == BUILTIN_ENVS or module.startswith(BUILTIN_ENVS + "."))
    if not builtin:
        config, agent_config = (_beside(directory, path) for path in (config, agent_config))
    spec = EnvSpec(id, None, description, config, agent_config)
    _REGISTRY[id] = Registration(spec, entry_point, dict(defaults),
                                 None if builtin or module in (None, "__main__") else module)
    for hook in REGISTER_HOOKS:
        hook(id)


def _caller() -> tuple[str | None, str]:
    """The module (name, directory) of the first caller outside jaxrobo: the module whose ``register`` call this
    is, also when it goes through ``jaxrobo.register``. The directory is the current one without a file."""
    frame = sys._getframe(1)
    while frame is not None and str(frame.f_globals.get("__name__", "")).split(".")[0] == "jaxrobo":
        frame = frame.f_back
    if frame is None:
        return None, os.getcwd()
    name, path = frame.f_globals.get("__name__"), frame.f_globals.get("__file__")
    return name, os.path.dirname(os.path.abspath(path)) if path else os.getcwd()


def _beside(directory: str, path: str | None) -> str | None:
    if path is None or os.path.isabs(path):
        return path
    return os.path.normpath(os.path.join(directory, os.path.expanduser(path)))


def _import_user_module(module: str, where: str) -> None:
    """Import ``module`` (its import registers its ids), from ``sys.path`` or else the current directory, which
    then stays on ``sys.path`` (a console script's ``sys.path`` lacks it; a later import, e.g. of the task class
    by its entry point, must find the module again)."""
    def missing(err: ModuleNotFoundError) -> bool:  # the module itself, not something it imports
        return err.name is not None and (module == err.name or module.startswith(err.name + "."))

    try:
        importlib.import_module(module)
        return
    except ModuleNotFoundError as err:
        if not missing(err):
            raise ConfigError(f"{where}: importing module {module!r} failed: {err}") from err
    cwd = os.getcwd()
    if cwd in sys.path or "" in sys.path:
        raise ConfigError(f"{where}: no module named {module!r} (looked in the current directory {cwd} and "
                          "sys.path; in 'module:Id' the module is a Python module that registers Id)")
    sys.path.insert(0, cwd)
    try:
        importlib.import_module(module)
    except ModuleNotFoundError as err:
        sys.path.remove(cwd)
        if missing(err):
            raise ConfigError(f"{where}: no module named {module!r} (looked in the current directory {cwd} and "
                              "sys.path; in 'module:Id' the module is a Python module that registers Id)") from err
        raise ConfigError(f"{where}: importing module {module!r} failed: {err}") from err
    except Exception as err:
        sys.path.remove(cwd)
        raise ConfigError(f"{where}: importing module {module!r} failed: {type(err).__name__}: {err}") from err


def find(id: str, where: str | None = None, *, may_import: bool = True) -> Registration:
    """The registration of ``id`` or ``"module:Id"`` (importing ``module`` first); for a missing module or id, a
    :class:`ConfigError` that starts with ``where`` (e.g. ``"--env ID"``), then ``environment id``.

    ``may_import=False`` (an id read from a file: a run directory's ``config.yaml``) imports nothing: a
    ``module:Id`` whose module is not imported yet is refused (the caller says which flag would allow it)."""
    where = "environment id" if where is None else f"{where}: environment id"
    if not isinstance(id, str):
        raise ConfigError(f"{where}: expected an environment id string, got {type(id).__name__} {id!r}")
    if ":" in id:
        module, _, name = id.partition(":")
        if not module or not name:
            raise ConfigError(f"{where}: {id!r}: expected 'module:Id' (e.g. my_task:MyTask-v0) or a registered id")
        if not may_import and (module not in sys.modules or name not in _REGISTRY):
            raise ConfigError(f"{where}: {id!r} names the Python module {module!r}, which a file read back never "
                              f"imports (it would run its code); if you trust it, pass --env {id} explicitly")
        try:
            _import_user_module(module, where)
        except ConfigError:
            raise
        except Exception as err:  # an error inside the user's module: name it, at the boundary
            raise ConfigError(f"{where}: importing module {module!r} failed: {type(err).__name__}: {err}") from err
        if name not in _REGISTRY and name not in ALIASES:
            _load_builtin()
            mine = sorted(k for k, r in _REGISTRY.items() if r.module == module)
            raise ConfigError(f"{where}: module {module!r} does not register {name!r}; it registers "
                              f"{', '.join(mine) or 'no environment id'}")
        id = name
    return _lookup(id, where)


def qualified_id(id: str) -> str:
    """``"module:Id"`` for an id a user's module registered (so a saved run can import it again), else the id."""
    reg = find(id)
    return f"{reg.module}:{reg.spec.id}" if reg.module else reg.spec.id


def registered() -> list[str]:
    """All registered ids."""
    _load_builtin()
    return sorted(_REGISTRY)


def spec(id: str) -> EnvSpec:
    """How ``id`` was registered, with the step limit ``make(id)`` gives (:func:`max_episode_steps`). A broken env
    YAML is reported when the env is made, not here (``import jaxrobo`` registers every id with Gymnasium): the
    step limit is then the task's default."""
    try:
        steps = max_episode_steps(id)
    except ConfigError:
        steps = max_episode_steps(id, with_yaml=False)
    return dataclasses.replace(_lookup(id).spec, max_episode_steps=steps)


def registration(id: str) -> Registration:
    """The registration of ``id`` (a deprecated alias resolves, with a FutureWarning)."""
    return _lookup(id)


def _load_builtin() -> None:
    importlib.import_module(BUILTIN_ENVS).register_builtin()  # the built-in robots and tasks (once: it caches)


def _lookup(id: str, where: str = "environment id") -> Registration:
    if isinstance(id, str) and ":" in id:
        return find(id)
    _load_builtin()
    if id in ALIASES and id not in _REGISTRY:
        import warnings

        warnings.warn(f"environment id {id!r} is deprecated: it is {ALIASES[id]!r}", FutureWarning, stacklevel=3)
        id = ALIASES[id]
    if not isinstance(id, str) or id not in _REGISTRY:
        raise unknown_key(id, _REGISTRY, where=where)
    return _REGISTRY[id]


def env_config(id: str, with_yaml: bool = True) -> dict[str, Any]:
    """The env options and parameters the id sets (its env YAML over its registration's overrides): only what
    differs from the task's ``Options``/``Params`` defaults, which are every default's one home."""
    reg = _lookup(id)
    values = dict(reg.defaults)
    if reg.spec.config and with_yaml:
        env = load_yaml(reg.spec.config).get("env", {}) or {}
        if not isinstance(env, dict):
            raise ConfigError(f"{reg.spec.config}: env: expected a mapping of key: value, got {type(env).__name__}")
        values.update(env)
    return values


def max_episode_steps(id: str, with_yaml: bool = True) -> int:
    """The step limit of ``id``: its task's ``Params.max_episode_steps`` default unless the id's registration or
    env YAML sets another (validated; :class:`ConfigError` otherwise). The same value as ``make(id).spec``."""
    params = _lookup(id).env_class().Params
    values = env_config(id, with_yaml)
    if "max_episode_steps" not in values:
        return int(next(f.default for f in dataclasses.fields(params) if f.name == "max_episode_steps"))
    return int(coerce("max_episode_steps", values["max_episode_steps"], rules(params)["max_episode_steps"], id))


def make(id: str, **overrides: Any) -> Env:
    """Create the environment ``id``; keyword overrides may name any option or parameter of the task.

    Options (static: control type, backend, number of actions, ...) select the model and code path; parameters
    (limits, gains, goals) become ``env.default_params`` and can later be changed, or vmapped, per call.
    """
    if not isinstance(id, str):
        raise ConfigError(f"jaxrobo.make(id={id!r}): expected an environment id string (see jaxrobo.registered()), "
                          f"got {type(id).__name__}")
    check_precision(f"jaxrobo.make({id!r})")  # before any model is built or code is traced
    reg = _lookup(id)
    cls = reg.env_class()
    values = env_config(id)
    values.update(overrides)
    where = f"{id}"
    options, params = split_and_validate(values, cls.Options, cls.Params, where=where)
    try:
        env = cls(cls.Options(**options), cls.Params(**params))
    except ConfigError:
        raise
    except (TypeError, ValueError) as err:  # e.g. a running_step that is not a multiple of the timestep
        raise ConfigError(f"{id}: {err}") from err
    check_relations(env.options, where)  # min <= max pairs, a start inside its bounds: what no single field sees
    check_relations(env.default_params, where)
    env.spec = dataclasses.replace(reg.spec, max_episode_steps=int(env.default_params.max_episode_steps))
    return env


def learners() -> dict[str, Any]:
    """The tabular learners, ``{name: jaxrobo.tabular.learner.Learner}``, in their listed order."""
    return importlib.import_module(LEARNERS_MODULE).LEARNERS


def learner(name: str) -> Any:
    """The tabular learner called ``name`` (a ValueError naming the allowed ones otherwise)."""
    return importlib.import_module(LEARNERS_MODULE).get(name)
