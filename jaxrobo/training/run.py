"""Resolve a training run from the shipped YAML files and user overrides, validated before anything compiles.

A task's agent YAML (``agents/configs/<name>.yaml`` for a built-in task; for a task in a user's module, the path its
``register`` call gives, relative to that module's directory or absolute) holds presets; each preset maps learner
parameters (:class:`jaxrobo.tabular.learner.AgentParams`) and loop settings
(:class:`jaxrobo.training.trainer.TrainConfig`), plus an optional ``env:`` mapping of env overrides. ``default`` is the
textbook setup that learns; ``seed`` is the seed's own values with its learners reproduced exactly.

Overrides are ``{key: value}``; :func:`route` says where each key lives, for ``--set`` here and for the swept
keys of :mod:`jaxrobo.training.sweep`: a bare key goes to whichever of learner, loop or env declares it (learner and
loop first), ``env.KEY`` forces the env and ``agent.KEY`` the learner/loop.

Every default has one home: the dataclasses (:class:`jaxrobo.tabular.learner.AgentParams`, :class:`TrainConfig`, each
task's ``Options`` and ``Params``). The env YAML and the agent presets hold only what differs from them.
"""
from __future__ import annotations

import dataclasses
import json
import os
from typing import Any, Mapping

import numpy as np

from jaxrobo.tabular.learner import AgentParams
from jaxrobo.tabular import discretise
from jaxrobo.core.config import (ConfigError, as_dict, check_fields, flat_keys, load_yaml, shown, split_and_validate,
                                 unknown_key)
from jaxrobo.task.env import Env
from jaxrobo.task.registry import _lookup, find, learner, learners, make, qualified_id
from jaxrobo.core.struct import INT32_MAX, Rule, rules
from jaxrobo.training.trainer import TrainConfig

AGENT_CONFIG_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "agents",
                                "configs")


# ---- where a key lives ----------------------------------------------------------------------------------------
#: The four homes of a key, in the order a bare key looks for it: learner parameter (traced), loop setting
#: (static), env option (static), env parameter (traced).
HOMES = ("agent", "train", "option", "env")
_PREFIXES = {"agent": ("agent", "train"), "env": ("option", "env")}


@dataclasses.dataclass(frozen=True)
class KeyRoute:
    """Where one override or swept key lives: ``name`` is the field (the key without its ``env.``/``agent.``
    prefix), ``where`` one of :data:`HOMES`, ``rule`` the field's validation rule."""

    key: str
    name: str
    where: str
    rule: Rule

    @property
    def side(self) -> str:
        """``"agent"`` (learner and loop: :class:`AgentParams`, :class:`TrainConfig`) or ``"env"``."""
        return "agent" if self.where in _PREFIXES["agent"] else "env"

    @property
    def static(self) -> bool:
        """True for loop settings and env options, which fix shapes and code (a sweep compiles per value);
        False for learner and env parameters, which are traced (a sweep vmaps over them)."""
        return self.where in ("train", "option")


def _tables(env_cls: type) -> dict[str, dict[str, Rule]]:
    return {"agent": rules(AgentParams), "train": rules(TrainConfig), "option": rules(env_cls.Options),
            "env": rules(env_cls.Params)}


def route(env_id: str, key: Any, where: str = "--set") -> KeyRoute:
    """Where ``key`` lives for the env ``env_id``; :class:`ConfigError` naming the key and the allowed keys if nowhere.
    The one router of ``--set`` (:func:`resolve`) and of swept keys (:func:`jaxrobo.training.sweep.classify`)."""
    tables = _tables(_lookup(env_id).env_class())
    homes: tuple[str, ...] = HOMES
    name = key
    if isinstance(key, str) and key.startswith(("env.", "agent.")):
        side, name = key.split(".", 1)
        homes = _PREFIXES[side]
    if isinstance(name, str):
        for home in homes:
            if name in tables[home]:
                return KeyRoute(key, name, home, tables[home][name])
    known = {k for home in homes for k in tables[home]}
    err = unknown_key(name if isinstance(name, str) else repr(name), known, where=where)
    other = next((h for h in HOMES if h not in homes and isinstance(name, str) and name in tables[h]), None)
    if other is not None:  # e.g. agent.backend: say where the key does live
        side = "agent" if other in _PREFIXES["agent"] else "env"
        err = ConfigError(f"{err} ({name} is {'a learner/loop' if side == 'agent' else 'an env'} key: {side}.{name})")
    raise err


@dataclasses.dataclass(frozen=True)
class RunSpec:
    env_id: str
    preset: str
    env: Env
    agent_params: AgentParams
    config: TrainConfig
    env_overrides: dict[str, Any]
    #: The preset's ``on_gpu`` settings this run took (:func:`device_overlay`; those the user set are left out).
    device_defaults: dict[str, Any] = dataclasses.field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """The resolved configuration, as written to ``config.yaml`` of a run. An id a user's module registered
        is written ``module:Id``, so that ``--resume`` (another process) imports the module again."""
        return {
            "env_id": qualified_id(self.env_id),
            "preset": self.preset,
            "env_options": as_dict(self.env.options),
            "env_params": as_dict(self.env.default_params),
            "agent_params": as_dict(self.agent_params),
            "train": as_dict(self.config),
        }


def agent_presets(env_id: str) -> dict[str, dict[str, Any]]:
    """The presets in the id's agent YAML (``{}`` if it has none); ConfigError if the file is not a mapping of
    preset name to a mapping of settings."""
    spec = _lookup(env_id).spec
    if not spec.agent_config:
        return {}
    path = spec.agent_config
    if not os.path.isabs(path):
        path = os.path.join(AGENT_CONFIG_DIR, path)
    presets = load_yaml(path)
    for name, values in presets.items():
        if not isinstance(name, str):
            raise ConfigError(f"{path}: preset names must be strings, got {name!r}")
        if values is not None and not isinstance(values, dict):
            raise ConfigError(f"{path}: preset {name!r} must be a mapping of key: value, got "
                              f"{type(values).__name__} {values!r}")
        env = (values or {}).get("env")
        if env is not None and not isinstance(env, dict):
            raise ConfigError(f"{path}: preset {name!r}: env must be a mapping of key: value, got "
                              f"{type(env).__name__} {env!r}")
    return presets


#: The key of a preset's settings for an accelerator (:func:`device_overlay`).
ON_GPU = "on_gpu"


def accelerated() -> bool:
    """Whether JAX's default device is an accelerator (a GPU or TPU), where a batch of thousands of envs steps in
    about the time of one."""
    import jax

    return jax.default_backend() != "cpu"


def device_overlay(preset: dict[str, Any], where: str) -> dict[str, Any]:
    """The preset's ``on_gpu`` mapping, removed from ``preset``, when the run's device is an accelerator
    (:func:`accelerated`), else ``{}``: defaults sized to the device. A GPU steps 2,048 envs in about the time of
    16, so a shared table learns from 100x the experience per sequential step, and best-of-N per-env tables find
    a learner sooner; a 2-core CPU pays for every env. Explicit settings (``--set``, flags) still win."""
    overlay = preset.pop(ON_GPU, None)
    if overlay is None:
        return {}
    if not isinstance(overlay, dict) or "env" in overlay:
        raise ConfigError(f"{where}: {ON_GPU} must be a mapping of learner/loop settings, got {overlay!r}")
    return dict(overlay) if accelerated() else {}


#: The discretiser fields each mode leaves unused (``bins`` mode: number_splits too when bins is given).
_UNUSED_BY_MODE = {"bins": ("resolution", "edges"), "round": ("number_splits", "bins", "edges"),
                   "edges": ("number_splits", "bins", "resolution")}
#: TrainConfig field names of the discretiser's arguments, for messages.
DISCRETISER_NAMES = {"low": "state_low", "high": "state_high", "mode": "discretiser", "splits": "bins",
                     "resolution": "resolution", "edges": "edges"}


def check_combinations(config: TrainConfig, given: Mapping[str, Any], where: str = "") -> None:
    """Refuse settings that are each valid but do not go together, or that would be silently ignored.

    ``given``: the loop settings the user set explicitly (``--set``/flags); one of them that the chosen
    discretiser mode does not use is refused unless it equals the default (a saved run's config lists every
    field, so it must resolve again).
    """
    loc = f"{where}: " if where else ""
    defaults = TrainConfig()
    if config.seed_compat and learner(config.agent).n_tables > 1:
        raise ConfigError(f"{loc}agent={config.agent!r} with seed_compat=true: the seed's learners had one table "
                          f"and {config.agent} has no seed form; set seed_compat=false or agent to one of "
                          + ", ".join(n for n, lr in learners().items() if lr.n_tables == 1))
    unused = list(_UNUSED_BY_MODE[config.discretiser])
    if config.discretiser == "bins" and config.bins is not None:
        unused.append("number_splits")
    for key in unused:
        if key in given and getattr(config, key) != getattr(defaults, key):
            because = (f"bins={list(config.bins)} is given (set bins=null to use number_splits)"
                       if key == "number_splits" and config.discretiser == "bins"
                       else f"discretiser={config.discretiser!r} does not use it")
            raise ConfigError(f"{loc}{key}={given[key]!r} would be ignored: {because}")
    if config.snapshots and not config.shared_table:
        raise ConfigError(f"{loc}snapshots={config.snapshots} needs shared_table=true (the final choice flies one "
                          "table's candidates; per-env tables would keep snapshots x n_envs tables); set snapshots=0 "
                          "or shared_table=true")
    if config.total_steps and config.total_episodes:
        raise ConfigError(f"{loc}total_steps={config.total_steps} and total_episodes={config.total_episodes}: give "
                          "one run-wide budget (or neither: nepisodes per env)")
    if config.total_steps and -(-config.total_steps // config.n_envs) > INT32_MAX:
        raise ConfigError(f"{loc}total_steps={config.total_steps:,}: {-(-config.total_steps // config.n_envs):,} "
                          f"steps per env over n_envs={config.n_envs}; must be <= {INT32_MAX:,} per env (step "
                          "counters are int32): use more n_envs or fewer total_steps")
    if config.total_episodes and config.total_episodes + config.n_envs > INT32_MAX:
        raise ConfigError(f"{loc}total_episodes={config.total_episodes:,}: must be <= "
                          f"{INT32_MAX - config.n_envs:,} (episode counters are int32)")
    if config.total_episodes and -(-config.total_episodes // config.n_envs) * config.nsteps > INT32_MAX:
        raise ConfigError(f"{loc}total_episodes={config.total_episodes:,} over n_envs={config.n_envs} with "
                          f"nsteps={config.nsteps}: "
                          f"up to {-(-config.total_episodes // config.n_envs) * config.nsteps:,} "
                          f"steps per env; must be <= {INT32_MAX:,} (step counters are int32)")
    steps = config.nepisodes * config.nsteps
    if not (config.total_steps or config.total_episodes) and steps > INT32_MAX:
        raise ConfigError(f"{loc}nepisodes x nsteps = {config.nepisodes} x {config.nsteps} = {steps:,} steps per env: "
                          f"must be <= {INT32_MAX:,} (step counters are int32); use fewer nepisodes or nsteps")
    if config.eval_episodes * max(config.nsteps, 1) > INT32_MAX:
        raise ConfigError(f"{loc}eval_episodes={config.eval_episodes}: too many greedy evaluation episodes; "
                          f"must be <= {INT32_MAX // max(config.nsteps, 1):,} with nsteps={config.nsteps}")


def check_discretiser(env: Env, config: TrainConfig, where: str = "") -> int:
    """Validate the config's discretiser settings against the task's observation; returns the table's n_states."""
    loc = f"{where}: " if where else ""
    dims = int(env.observation_space().shape[0])
    low, high = config.state_low, config.state_high
    if low is None or high is None:
        task_low, task_high = (np.asarray(b, np.float64) for b in env.state_bounds())
        low = task_low if low is None else low
        high = task_high if high is None else high
    splits = config.bins if config.bins is not None else config.number_splits
    names = dict(DISCRETISER_NAMES, splits="bins" if config.bins is not None else "number_splits")
    try:
        _, _, bins, _ = discretise.check(low, high, config.discretiser, splits, config.resolution, config.edges,
                                         dims=dims, names=names)
    except ValueError as err:
        raise ConfigError(f"{loc}{err}") from None
    return int(np.prod(bins, dtype=object))


def check_tables(q: np.ndarray, env: Env, config: TrainConfig, path: str) -> None:
    """A run's saved tables (``q`` of ``qtables.npz`` at ``path``) against its config: ``[n_envs, n_tables,
    n_states, n_actions]``, one row of tables where the envs shared one, the learner's tables (two for Double
    Q-learning); ConfigError naming the file otherwise (the files are then not of one run)."""
    want = (1 if config.shared_table else config.n_envs, learner(config.agent).n_tables,
            check_discretiser(env, config), int(env.num_actions))
    if tuple(q.shape) != want:
        raise ConfigError(f"{path}: q has shape {tuple(q.shape)}, but the run's config.yaml gives {want} ("
                          f"{'one shared table' if config.shared_table else f'{config.n_envs} envs'}, "
                          f"{config.agent}'s {want[1]} table(s), {want[2]} states x {want[3]} actions); the files are "
                          "not of one run")


def check_train_arguments(env: Env, config: Any, agent_params: Any = None, env_params: Any = None, *,
                          population: bool = False, **counts: Any) -> None:
    """What a Python caller hands :func:`jaxrobo.training.train.train`, checked as :func:`resolve` checks what the
    command line reads, before anything is built or compiles: the config's every field, its combinations and its
    discretiser against the task; the learner and env parameters (a population's: its sweep checked each row, and
    its arrays may lie on other hosts); ``counts`` (``start_chunk=...``: integers >= 0; ``checkpoint_seconds``: a
    number >= 0 or None). A TypeError for an argument of the wrong class, a
    ConfigError (a ValueError) naming the argument, the field and what it accepts otherwise."""
    if not isinstance(config, TrainConfig):
        raise TypeError(f"train(config=...): expected a jaxrobo.training.trainer.TrainConfig (jaxrobo.training.run."
                        f"resolve(...).config), got {type(config).__name__}")
    check_fields(config, "train(config)")
    check_combinations(config, {}, "train(config)")
    from jaxrobo.core import spaces

    if isinstance(env.action_space(), spaces.Box):  # before the discretiser: its message would mislead
        raise ConfigError(f"train: agent={config.agent!r} is a tabular learner (a table of Discrete actions) and "
                          f"{env.name} has continuous (Box) actions; use jaxrobo.deep (Brax's PPO or SAC)")
    check_discretiser(env, config, "train(config)")
    for name, value, cls in (("agent_params", agent_params, AgentParams),
                             ("env_params", env_params, type(env.default_params))):
        if value is None:
            continue
        if not isinstance(value, cls):
            raise TypeError(f"train({name}=...): expected {cls.__module__}.{cls.__qualname__}, got "
                            f"{type(value).__name__}; build it with .replace(...) on the default")
        if not population:
            check_fields(value, f"train({name})")
    for name, value in counts.items():
        seconds = name == "checkpoint_seconds"
        kinds = (int, float) if seconds else int
        ok = (seconds and value is None) or (isinstance(value, kinds) and not isinstance(value, bool) and value >= 0)
        if not ok:  # NaN seconds too (never >= 0): a NaN would never be due, a negative count run a chunk twice
            raise ConfigError(f"train({name}={shown(value)}): expected "
                              + ("a number of seconds >= 0, or None" if seconds else "an integer >= 0"))


def resolve(env_id: str, preset: str = "default", overrides: Mapping[str, Any] | None = None,
            agent: str | None = None, check_memory: bool = True, device_defaults: bool = True,
            source: str = "--set") -> RunSpec:
    """Build env, learner parameters and loop config for a run; raises :class:`ConfigError` on any bad value.

    Everything is checked here, before anything compiles: each value against its declared rule, combinations
    (:func:`check_combinations`), the discretiser against the task's observation, and (``check_memory``) the
    batch's estimated memory against what the device has (:func:`jaxrobo.training.budget.check_memory`).
    ``device_defaults``: apply the preset's ``on_gpu`` settings on an accelerator (:func:`device_overlay`).
    ``source``: where ``overrides`` come from, as an unknown key's message names it (a run's config.yaml on
    ``--resume``, not ``--set``).
    """
    env_id = _lookup(env_id).spec.id  # a deprecated alias resolves (and warns) once; the run records the real id
    presets = agent_presets(env_id)
    if not isinstance(preset, str) or (presets and preset not in presets):
        raise ConfigError(f"{env_id}: preset={preset!r}: allowed values are {', '.join(presets) or 'default'}")
    if overrides is not None and not isinstance(overrides, Mapping):
        raise ConfigError(f"overrides: expected a mapping of key: value, got {type(overrides).__name__}")
    chosen = dict(presets.get(preset, {}) or {})
    overlay = device_overlay(chosen, where=f"{env_id} preset {preset}")
    if device_defaults:
        chosen.update(overlay)
    else:
        overlay = {}
    env_values = dict(chosen.pop("env", {}) or {})
    agent_values = chosen
    given: dict[str, Any] = {}
    for key, value in (overrides or {}).items():
        r = route(env_id, key, where=source)
        if r.side == "agent":
            agent_values[r.name] = given[r.name] = value
        else:
            env_values[r.name] = value
    if agent is not None:
        agent_values["agent"] = agent
    where = f"{env_id} preset {preset}"
    agent_kw, train_kw = split_and_validate(agent_values, AgentParams, TrainConfig, where=where)
    config = TrainConfig(**train_kw)
    check_combinations(config, given, where)
    if config.total_steps:
        # Whole chunks step each env's budget with as few idle slots as the chunk count allows (fewer than one per
        # chunk): the chunk count that chunk_steps gives, each chunk as short as that count needs. The values do
        # not depend on the chunk length; resolving the result again gives it back (--resume).
        per_env = -(-config.total_steps // config.n_envs)
        n_chunks = -(-per_env // config.chunk_steps)
        config = dataclasses.replace(config, chunk_steps=-(-per_env // n_chunks))
    env = make(env_id, **env_values)
    from jaxrobo.core import spaces

    if isinstance(env.action_space(), spaces.Box):  # before the discretiser: its message would mislead
        raise ConfigError(f"{where}: agent={config.agent!r} is a tabular learner (a table of Discrete actions) and "
                          f"{env_id} has continuous (Box) actions; use --agent ppo or --agent sac (Brax's trainers)")
    n_states = check_discretiser(env, config, where)
    if check_memory:
        from jaxrobo.training.budget import check_eval_memory, check_memory as fits

        fits(env, config, n_states, where=where)
        n_eval = 1 if config.shared_table else min(config.eval_envs, config.n_envs)
        horizon = env.spec.max_episode_steps if env.spec else 1000
        check_eval_memory(env, n_eval, config.eval_episodes, horizon, where=where)
    return RunSpec(env_id, preset, env, AgentParams(**agent_kw), config, env_values,
                   {k: v for k, v in overlay.items() if k not in given})


def spec_from_config(run_config: Any, where: str = "config.yaml", trusted_env: str | None = None,
                     check_memory: bool = True):
    """The :class:`RunSpec` a run's ``config.yaml`` describes (for ``--resume``): every saved value is
    applied as an override of the saved preset, and the result must give back the same config. Its
    ``env_id`` must be a registered id: a ``module:Id`` is imported only when it equals ``trusted_env`` (the
    id the user passed with ``--env``); a run directory never makes jaxrobo run code. ``jaxrobo export`` passes
    ``check_memory=False``: it trains nothing."""
    if not isinstance(run_config, dict):
        raise ConfigError(f"{where}: config.yaml is not a jaxrobo run configuration (a mapping)")
    try:
        env_id, preset = run_config["env_id"], run_config.get("preset", "default")
        overrides = {f"env.{k}": v for part in ("env_options", "env_params") for k, v in run_config[part].items()}
        overrides.update({f"agent.{k}": v for part in ("agent_params", "train") for k, v in run_config[part].items()})
    except (KeyError, TypeError, AttributeError) as err:
        raise ConfigError(f"{where}: config.yaml is not a jaxrobo run configuration (missing {err})") from err
    find(env_id, where=f"{where}: config.yaml env_id", may_import=trusted_env is not None and env_id == trusted_env)
    source = "" if where == "config.yaml" else f"{where}: config.yaml"  # "": the caller names the file
    spec = resolve(env_id, preset, overrides, check_memory=check_memory, source=source)
    again = json.loads(json.dumps(spec.to_dict()))
    if again != json.loads(json.dumps(run_config)):
        a, b = flat_keys(run_config), flat_keys(again)
        keys = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
        raise ConfigError(f"config.yaml: does not resolve to itself ({', '.join(keys[:5])}); edited by hand?")
    return spec
