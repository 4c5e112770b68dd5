"""Deep RL on jaxrobo envs through Brax's own trainers: ``jaxrobo train --agent ppo|sac``.

The trainers are ``brax.training.agents.ppo.train`` and ``brax.training.agents.sac.train``, called unchanged on
the env's Brax face (:class:`jaxrobo.brax_env.BraxEnv`) with jaxrobo's training wrapper
(:func:`jaxrobo.brax_env.wrap_for_training`: fresh randomness at every auto-reset, truncation kept apart from
termination). jaxrobo adds what a run needs around them:

* one home for every default: :class:`PPOConfig` and :class:`SACConfig` (the trainer's hyperparameters, each with
  its allowed range); the presets in ``agents/configs/<agent>.yaml`` and the per-task presets in
  ``agents/configs/<agent>/<env id>.yaml`` hold only what differs from them (the task file: what differs from
  the agent file). :func:`resolve` validates everything, and refuses a Discrete-action id, before anything
  compiles;
* evaluation of the deterministic policy on ``eval_episodes`` fresh episodes of the jaxrobo env itself at each of
  the trainer's ``num_evals`` points (:func:`evaluate`), through :func:`jaxrobo.rollout.rollout`, so a task's
  success flags (the Goto's ``arrived``) are counted exactly as for the tabular learners;
* the run directory (:func:`write_run`: ``config.yaml``, ``evaluations.csv``, ``episode_stats.csv`` with an
  ``env_steps`` column, ``summary.json``, TensorBoard scalars, ``rewards.png``, the policy) written through
  :mod:`jaxrobo.rundir`;
* the policy saved without pickle (:func:`save_policy`: the parameter pytree flattened to ``policy.npz`` by key
  path, the network's configuration in ``policy.json``) and loaded back (:func:`load_policy`) for
  ``jaxrobo show`` and rendering.

Public surface: :data:`AGENTS`, :class:`PPOConfig`, :class:`SACConfig`, :class:`DeepRunSpec`, :func:`is_deep`,
:func:`config_class`, :func:`presets`, :func:`resolve`, :func:`check_combinations`, :func:`train`,
:class:`TrainingStopped`, :class:`DeepResult`, :func:`evaluate`, :func:`save_policy`, :func:`load_policy`, :class:`LoadedPolicy`,
:func:`write_run`, :func:`spec_from_config`.
"""
from __future__ import annotations

import dataclasses
import json
import os
import time
from typing import Any, Callable, Mapping

import numpy as np

from jaxrobo.config import ConfigError, as_dict, load_yaml, split_and_validate, unknown_key
from jaxrobo.struct import param, rules

#: The deep-RL learners, each Brax's trainer of that name.
AGENTS = ("ppo", "sac")
AGENT_CONFIG_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "agents", "configs")
#: Files of a deep run's saved policy.
POLICY_NPZ, POLICY_JSON = "policy.npz", "policy.json"
#: The largest network layer jaxrobo accepts from a config (a typo of 1e6 units would exhaust memory, not learn).
MAX_LAYER = 8192


# ---- the hyperparameters: one home each --------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """``brax.training.agents.ppo.train``'s hyperparameters that a jaxrobo run sets (Brax's defaults where
    Brax has a sensible one), plus the run's own evaluation (``eval_episodes``)."""

    agent: str = param("ppo", choices=("ppo",), doc="the trainer")
    num_timesteps: int = param(1_000_000, low=1, doc="env steps to train for (Brax rounds up to whole epochs)")
    num_envs: int = param(1024, low=1, doc="environments stepped in parallel")
    episode_length: int | None = param(None, kind=int, low=1,
                                       doc="step cap of a training episode (default: the id's max_episode_steps)")
    action_repeat: int = param(1, low=1, doc="env steps per policy action")
    learning_rate: float = param(3e-4, low=0.0, low_open=True, high=1.0, doc="Adam step size")
    entropy_cost: float = param(1e-2, low=0.0, high=1.0, doc="weight of the entropy bonus")
    discounting: float = param(0.97, low=0.0, high=1.0, doc="discount factor gamma")
    unroll_length: int = param(10, low=1, doc="steps per rollout segment")
    batch_size: int = param(256, low=1, doc="segments per minibatch")
    num_minibatches: int = param(8, low=1, doc="minibatches per update")
    num_updates_per_batch: int = param(4, low=1, doc="epochs over each batch")
    normalize_observations: bool = param(True, doc="running mean/std normalisation of observations")
    reward_scaling: float = param(1.0, low=0.0, low_open=True, doc="factor on rewards in the losses")
    clipping_epsilon: float = param(0.3, low=0.0, low_open=True, high=1.0, doc="PPO ratio clipping")
    gae_lambda: float = param(0.95, low=0.0, high=1.0, doc="GAE lambda")
    max_grad_norm: float | None = param(None, kind=float, low=0.0, low_open=True, doc="gradient clipping (null: none)")
    policy_hidden_layer_sizes: tuple = param((32, 32, 32, 32), kind=tuple, doc="policy MLP layer widths")
    value_hidden_layer_sizes: tuple = param((256, 256, 256, 256, 256), kind=tuple, doc="value MLP layer widths")
    num_evals: int = param(10, low=1, high=1000, doc="evaluation points over the run (the first before training)")
    eval_episodes: int = param(128, low=1, high=100_000, doc="fresh episodes of each evaluation")
    seed: int = param(0, low=0, doc="random seed; the same seed gives the same run")


@dataclasses.dataclass(frozen=True)
class SACConfig:
    """``brax.training.agents.sac.train``'s hyperparameters that a jaxrobo run sets, plus ``eval_episodes``."""

    agent: str = param("sac", choices=("sac",), doc="the trainer")
    num_timesteps: int = param(200_000, low=1, doc="env steps to train for")
    num_envs: int = param(64, low=1, doc="environments stepped in parallel")
    episode_length: int | None = param(None, kind=int, low=1,
                                       doc="step cap of a training episode (default: the id's max_episode_steps)")
    action_repeat: int = param(1, low=1, doc="env steps per policy action")
    learning_rate: float = param(6e-4, low=0.0, low_open=True, high=1.0, doc="Adam step size")
    discounting: float = param(0.97, low=0.0, high=1.0, doc="discount factor gamma")
    batch_size: int = param(256, low=1, doc="transitions per gradient step")
    grad_updates_per_step: int = param(8, low=1, doc="gradient steps per env step of all envs")
    reward_scaling: float = param(1.0, low=0.0, low_open=True, doc="factor on rewards in the losses")
    tau: float = param(0.005, low=0.0, low_open=True, high=1.0, doc="target network update rate")
    min_replay_size: int = param(1024, low=0, doc="transitions collected before learning starts")
    max_replay_size: int | None = param(None, kind=int, low=1, doc="replay capacity (null: num_timesteps)")
    normalize_observations: bool = param(True, doc="running mean/std normalisation of observations")
    hidden_layer_sizes: tuple = param((256, 256), kind=tuple, doc="policy and Q MLP layer widths")
    num_evals: int = param(10, low=1, high=1000, doc="evaluation points over the run (the first before training)")
    eval_episodes: int = param(128, low=1, high=100_000, doc="fresh episodes of each evaluation")
    seed: int = param(0, low=0, doc="random seed; the same seed gives the same run")


_CONFIGS = {"ppo": PPOConfig, "sac": SACConfig}
#: The layer-width fields of each config (lists of positive integers).
_LAYERS = {"ppo": ("policy_hidden_layer_sizes", "value_hidden_layer_sizes"), "sac": ("hidden_layer_sizes",)}


def is_deep(agent: Any) -> bool:
    """True for the names of Brax's trainers (``ppo``, ``sac``)."""
    return isinstance(agent, str) and agent in AGENTS


def config_class(agent: str) -> type:
    if agent not in _CONFIGS:
        raise ConfigError(f"agent={agent!r}: allowed deep-RL agents are {', '.join(AGENTS)}")
    return _CONFIGS[agent]


# ---- presets --------------------------------------------------------------------------------------------------
def _preset_file(path: str) -> dict[str, dict[str, Any]]:
    out = load_yaml(path) if os.path.isfile(path) else {}
    for name, values in out.items():
        if not isinstance(name, str) or (values is not None and not isinstance(values, dict)):
            raise ConfigError(f"{path}: expected preset name: mapping of key: value, got {name!r}: {values!r}")
        env = (values or {}).get("env")
        if env is not None and not isinstance(env, dict):
            raise ConfigError(f"{path}: preset {name!r}: env must be a mapping of key: value, got {env!r}")
    return out


def preset_paths(agent: str, env_id: str) -> tuple[str, str]:
    """``agents/configs/<agent>.yaml`` and the task's ``agents/configs/<agent>/<env id>.yaml`` (may be absent)."""
    return (os.path.join(AGENT_CONFIG_DIR, f"{agent}.yaml"),
            os.path.join(AGENT_CONFIG_DIR, agent, f"{env_id.replace(':', '_')}.yaml"))


def presets(agent: str, env_id: str) -> dict[str, dict[str, Any]]:
    """The presets of ``agent`` on ``env_id``: each the agent file's preset with the task file's on top (the
    ``env:`` mappings merged the same way)."""
    base_path, task_path = preset_paths(agent, env_id)
    base, task = _preset_file(base_path), _preset_file(task_path)
    out: dict[str, dict[str, Any]] = {}
    for name in list(base) + [n for n in task if n not in base]:
        a, b = dict(base.get(name) or {}), dict(task.get(name) or {})
        env = {**(a.pop("env", None) or {}), **(b.pop("env", None) or {})}
        out[name] = {**a, **b, **({"env": env} if env else {})}
    return out


# ---- resolving a run --------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class DeepRunSpec:
    """A resolved deep-RL run: the env (its overrides applied), the trainer's config, and where they came from."""

    env_id: str
    preset: str
    env: Any
    config: Any  # PPOConfig | SACConfig
    env_overrides: dict[str, Any]

    @property
    def agent(self) -> str:
        return self.config.agent

    @property
    def episode_length(self) -> int:
        if self.config.episode_length is not None:
            return int(self.config.episode_length)
        return int(self.env.default_params.max_episode_steps)

    def to_dict(self) -> dict[str, Any]:
        """The resolved configuration, as written to ``config.yaml``: the same sections as a tabular run's
        (``env_options``, ``env_params``), the trainer's settings under ``train`` (``train.agent`` names it)."""
        from jaxrobo.registry import qualified_id

        return {"env_id": qualified_id(self.env_id), "preset": self.preset,
                "env_options": as_dict(self.env.options), "env_params": as_dict(self.env.default_params),
                "agent_params": {}, "train": as_dict(self.config)}


def check_combinations(config: Any, where: str = "") -> None:
    """Refuse values that are each in range but do not go together (Brax would assert deep inside a compile)."""
    loc = f"{where}: " if where else ""
    for name in _LAYERS[config.agent]:
        sizes = getattr(config, name)
        if not sizes or not all(isinstance(s, int) and not isinstance(s, bool) and 1 <= s <= MAX_LAYER
                                for s in sizes):
            raise ConfigError(f"{loc}{name}={list(sizes)!r}: expected a non-empty list of integers >= 1 and "
                              f"<= {MAX_LAYER} (layer widths)")
    if config.agent == "ppo":
        if (config.batch_size * config.num_minibatches) % config.num_envs:
            raise ConfigError(f"{loc}batch_size x num_minibatches = {config.batch_size} x {config.num_minibatches} "
                              f"= {config.batch_size * config.num_minibatches} must be a multiple of "
                              f"num_envs={config.num_envs} (each minibatch splits the envs' rollouts evenly)")
    else:
        if config.min_replay_size >= config.num_timesteps:
            raise ConfigError(f"{loc}min_replay_size={config.min_replay_size} must be < num_timesteps="
                              f"{config.num_timesteps} (no training would happen)")
        cap = config.max_replay_size
        if cap is not None and cap < max(config.min_replay_size, config.batch_size * config.grad_updates_per_step):
            raise ConfigError(f"{loc}max_replay_size={cap} must be >= min_replay_size ({config.min_replay_size}) "
                              f"and >= batch_size x grad_updates_per_step "
                              f"({config.batch_size * config.grad_updates_per_step})")


def check_action_space(env: Any, agent: str, env_id: str) -> None:
    """Brax's trainers act in a continuous (Box) action space: the env's Brax face refuses a Discrete id (naming
    the continuous id of the same task where there is one); said here as the ``--agent``'s refusal."""
    from jaxrobo.brax_env import BraxEnv

    try:
        BraxEnv(env)
    except ConfigError as err:
        raise ConfigError(f"--agent {agent} on {env_id}: {err} (or train {env_id} with a tabular agent)") from None


def resolve(env_id: str, agent: str, preset: str = "default", overrides: Mapping[str, Any] | None = None
            ) -> DeepRunSpec:
    """Build the env and the trainer's config of a deep run; :class:`ConfigError` on any bad value, before
    anything compiles. Override keys: a field of the agent's config, or an env option/parameter (``env.KEY``
    forces the env, ``agent.KEY`` the config)."""
    from jaxrobo.registry import _lookup, make

    cls = config_class(agent)
    env_id = _lookup(env_id).spec.id
    all_presets = presets(agent, env_id)
    if not isinstance(preset, str) or preset not in all_presets:
        raise ConfigError(f"{env_id} --agent {agent}: preset={preset!r}: allowed values are "
                          f"{', '.join(all_presets) or '(none: ' + preset_paths(agent, env_id)[0] + ' is missing)'}")
    if overrides is not None and not isinstance(overrides, Mapping):
        raise ConfigError(f"overrides: expected a mapping of key: value, got {type(overrides).__name__}")
    chosen = dict(all_presets[preset])
    env_values = dict(chosen.pop("env", {}) or {})
    agent_values = chosen
    env_cls = _lookup(env_id).env_class()
    env_keys = {**rules(env_cls.Options), **rules(env_cls.Params)}
    agent_keys = rules(cls)
    for key, value in (overrides or {}).items():
        if not isinstance(key, str):
            raise unknown_key(repr(key), set(agent_keys) | set(env_keys), where="--set")
        side, name = key.split(".", 1) if key.startswith(("env.", "agent.")) else (None, key)
        if side != "env" and name in agent_keys:
            agent_values[name] = value
        elif side != "agent" and name in env_keys:
            env_values[name] = value
        else:
            known = agent_keys if side == "agent" else env_keys if side == "env" else {**agent_keys, **env_keys}
            raise unknown_key(name, known, where=f"--set ({agent} on {env_id})")
    agent_values["agent"] = agent
    where = f"{env_id} --agent {agent} preset {preset}"
    (kw,) = split_and_validate(agent_values, cls, where=where)
    config = cls(**kw)
    check_combinations(config, where)
    env = make(env_id, **env_values)
    check_action_space(env, agent, env_id)
    return DeepRunSpec(env_id, preset, env, config, env_values)


def spec_from_config(run_config: Mapping[str, Any], where: str = "config.yaml") -> DeepRunSpec:
    """The :class:`DeepRunSpec` a deep run's ``config.yaml`` describes (for ``jaxrobo show``)."""
    from jaxrobo.registry import find

    try:
        env_id, preset, train = run_config["env_id"], run_config.get("preset", "default"), run_config["train"]
        overrides = {f"env.{k}": v for part in ("env_options", "env_params") for k, v in run_config[part].items()}
        agent = train["agent"]
        overrides.update({f"agent.{k}": v for k, v in train.items() if k != "agent"})
    except (KeyError, TypeError, AttributeError) as err:
        raise ConfigError(f"{where}: not a jaxrobo deep-RL run configuration (missing {err})") from err
    find(env_id, where=f"{where}: env_id {env_id}")
    try:
        return resolve(env_id, agent, preset, overrides)
    except ConfigError as err:
        raise ConfigError(f"{where}: {err}") from None


# ---- networks and policies -------------------------------------------------------------------------------------
def network_config(spec: DeepRunSpec, observation_size: int, action_size: int) -> dict[str, Any]:
    """What rebuilds the networks of a run (saved as ``policy.json``)."""
    c = spec.config
    out = {"format": 1, "agent": c.agent, "observation_size": int(observation_size), "action_size": int(action_size),
           "normalize_observations": bool(c.normalize_observations), "env_id": spec.env_id}
    if c.agent == "ppo":
        out.update(policy_hidden_layer_sizes=list(c.policy_hidden_layer_sizes),
                   value_hidden_layer_sizes=list(c.value_hidden_layer_sizes))
    else:
        out.update(hidden_layer_sizes=list(c.hidden_layer_sizes))
    return out


def _networks(net: Mapping[str, Any]):
    """Brax's networks and inference-function maker for a :func:`network_config`."""
    from brax.training import types
    from brax.training.acme import running_statistics

    pre = running_statistics.normalize if net["normalize_observations"] else types.identity_observation_preprocessor
    if net["agent"] == "ppo":
        from brax.training.agents.ppo import networks as ppo_networks

        nets = ppo_networks.make_ppo_networks(
            net["observation_size"], net["action_size"], preprocess_observations_fn=pre,
            policy_hidden_layer_sizes=tuple(net["policy_hidden_layer_sizes"]),
            value_hidden_layer_sizes=tuple(net["value_hidden_layer_sizes"]))
        return nets, ppo_networks.make_inference_fn(nets)
    from brax.training.agents.sac import networks as sac_networks

    nets = sac_networks.make_sac_networks(net["observation_size"], net["action_size"], preprocess_observations_fn=pre,
                                          hidden_layer_sizes=tuple(net["hidden_layer_sizes"]))
    return nets, sac_networks.make_inference_fn(nets)


def _factory(spec: DeepRunSpec) -> Callable:
    """The ``network_factory`` passed to Brax's trainer: its own maker with the config's layer widths."""
    import functools

    c = spec.config
    if c.agent == "ppo":
        from brax.training.agents.ppo import networks as ppo_networks

        return functools.partial(ppo_networks.make_ppo_networks,
                                 policy_hidden_layer_sizes=tuple(c.policy_hidden_layer_sizes),
                                 value_hidden_layer_sizes=tuple(c.value_hidden_layer_sizes))
    from brax.training.agents.sac import networks as sac_networks

    return functools.partial(sac_networks.make_sac_networks, hidden_layer_sizes=tuple(c.hidden_layer_sizes))


def _template(net: Mapping[str, Any]) -> Any:
    """A parameter pytree of the shape the trainer returns: PPO ``(normalizer, policy, value)``, SAC
    ``(normalizer, policy)``."""
    import jax
    import jax.numpy as jnp
    from brax.training.acme import running_statistics, specs

    nets, _ = _networks(net)
    key = jax.random.key(0)
    norm = running_statistics.init_state(specs.Array((net["observation_size"],), jnp.dtype("float32")))
    if net["agent"] == "ppo":
        return (norm, nets.policy_network.init(key), nets.value_network.init(key))
    return (norm, nets.policy_network.init(key))


def _path_name(path: tuple) -> str:
    import jax

    parts = []
    for entry in path:
        if isinstance(entry, jax.tree_util.SequenceKey):
            parts.append(str(entry.idx))
        elif isinstance(entry, jax.tree_util.DictKey):
            parts.append(str(entry.key))
        elif isinstance(entry, jax.tree_util.GetAttrKey):
            parts.append(entry.name)
        else:
            parts.append(str(entry))
    return "/".join(parts)


def save_policy(out_dir: str, params: Any, net: Mapping[str, Any]) -> None:
    """``policy.npz`` (each leaf of ``params`` under its key path, e.g. ``1/params/hidden_0/kernel``; plain
    arrays, no pickle) and ``policy.json`` (:func:`network_config`)."""
    import jax

    leaves = jax.tree_util.tree_flatten_with_path(jax.device_get(params))[0]
    arrays = {_path_name(path): np.asarray(leaf) for path, leaf in leaves}
    np.savez(os.path.join(out_dir, POLICY_NPZ), **arrays)
    with open(os.path.join(out_dir, POLICY_JSON), "w") as f:
        json.dump(dict(net), f, indent=2)


@dataclasses.dataclass
class LoadedPolicy:
    """A saved policy: ``act(obs, key) -> action`` in [-1, 1] (Brax's deterministic action, the mode), the
    parameters and the network config."""

    net: dict[str, Any]
    params: Any
    make_policy: Callable

    def act(self, obs: Any, key: Any = None) -> Any:
        import jax

        key = jax.random.key(0) if key is None else key
        return self.make_policy(self.params, deterministic=True)(obs, key)[0]


def load_policy(run_dir: str) -> LoadedPolicy:
    """The policy a deep run saved; :class:`ConfigError` naming the file when it is missing, pickled, or does
    not match its ``policy.json`` (a missing, extra or misshapen array)."""
    import zipfile

    import jax

    npz_path, json_path = os.path.join(run_dir, POLICY_NPZ), os.path.join(run_dir, POLICY_JSON)
    for path in (npz_path, json_path):
        if not os.path.isfile(path):
            raise ConfigError(f"{run_dir}: no {os.path.basename(path)}; is it a finished deep-RL run directory?")
    try:
        with open(json_path) as f:
            net = json.load(f)
        if not isinstance(net, dict):
            raise ValueError("not a JSON object")
        nets_config_keys = ("agent", "observation_size", "action_size", "normalize_observations")
        missing = [k for k in nets_config_keys if k not in net]
        if missing or net["agent"] not in AGENTS:
            raise ValueError(f"missing {', '.join(missing)}" if missing else f"agent={net['agent']!r}")
    except (OSError, ValueError) as err:
        raise ConfigError(f"{json_path}: not a policy description ({err})") from None
    try:
        with np.load(npz_path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as err:
        raise ConfigError(f"{npz_path}: cannot be read as plain arrays ({type(err).__name__}: {err})") from None
    try:
        template = _template(net)
    except (KeyError, TypeError, ValueError) as err:
        raise ConfigError(f"{json_path}: cannot rebuild the networks ({type(err).__name__}: {err})") from None
    paths, treedef = jax.tree_util.tree_flatten_with_path(template)
    leaves = []
    names = set()
    for path, leaf in paths:
        name = _path_name(path)
        names.add(name)
        if name not in arrays:
            raise ConfigError(f"{npz_path}: no array {name!r} (the networks of {POLICY_JSON} need it)")
        value = arrays[name]
        if value.shape != np.shape(leaf):
            raise ConfigError(f"{npz_path}: {name} has shape {value.shape}, the networks of {POLICY_JSON} need "
                              f"{np.shape(leaf)}")
        leaves.append(value.astype(np.asarray(leaf).dtype))
    extra = sorted(set(arrays) - names)
    if extra:
        raise ConfigError(f"{npz_path}: arrays {', '.join(extra[:5])} are not parameters of the networks of "
                          f"{POLICY_JSON}")
    params = jax.tree_util.tree_unflatten(treedef, leaves)
    _, make_policy = _networks(net)
    return LoadedPolicy(net, params, make_policy)


# ---- evaluation ----------------------------------------------------------------------------------------------------
def env_policy(benv: Any, make_policy: Callable, params: Any) -> Callable:
    """A :data:`jaxrobo.rollout.Policy` ``(key, obs) -> action`` of the jaxrobo env, acting as the trained
    deterministic policy does through ``benv`` (its Brax action, mapped to the env's action space as the Brax
    face maps it)."""
    policy = make_policy(params, deterministic=True)
    return lambda key, obs: benv.scale_action(policy(obs, key)[0])


def evaluate(env: Any, benv: Any, make_policy: Callable, n_episodes: int, horizon: int) -> Callable:
    """A jitted ``(params, key) -> dict`` of ``n_episodes`` fresh episodes of the deterministic policy on the
    jaxrobo env (:func:`jaxrobo.rollout.rollout`): ``return``, ``length``, ``terminated`` and, for a task with an
    ``arrived`` flag, ``success``."""
    import jax
    import jax.numpy as jnp

    from jaxrobo.rollout import rollout

    # The step limit of training (the wrapper's episode_length) is the evaluation's too.
    env_params = benv.params.replace(max_episode_steps=horizon)

    def run(params, key):
        out = rollout(env, env_policy(benv, make_policy, params), key, n_episodes, horizon, env_params)
        last = out["last"]
        res = {"return": out["return"], "length": out["length"], "terminated": last.terminated}
        arrived = getattr(last.task, "arrived", None)
        if arrived is not None:
            res["success"] = jnp.asarray(arrived, bool)
        return res

    return jax.jit(run)


# ---- training ----------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class DeepResult:
    """What a deep run produced (host values)."""

    spec: DeepRunSpec
    params: Any
    net: dict[str, Any]
    #: One dict per evaluation: ``env_steps``, ``seconds`` (training wall time so far, compile included, the
    #: evaluations excluded) and the episodes' ``return``/``length``/``terminated`` (and ``success``) arrays.
    evaluations: list[dict[str, Any]]
    #: Brax's training metrics at each evaluation point after the first (losses, ``training/sps``, ...).
    training_metrics: list[dict[str, float]]
    seconds: float  # wall time of the trainer call, compile and evaluations included
    eval_seconds: float  # of which the evaluations

    @property
    def env_steps(self) -> int:
        return int(self.evaluations[-1]["env_steps"]) if self.evaluations else 0

    def summary(self) -> dict[str, Any]:
        c = self.spec.config
        last = self.evaluations[-1]
        train_seconds = self.seconds - self.eval_seconds
        out: dict[str, Any] = {
            "env_id": self.spec.env_id, "agent": c.agent, "preset": self.spec.preset,
            "num_envs": c.num_envs, "num_timesteps": c.num_timesteps, "env_steps": self.env_steps,
            "episode_length": self.spec.episode_length,
            "train_seconds": round(train_seconds, 3), "eval_seconds": round(self.eval_seconds, 3),
            "env_steps_per_second": round(self.env_steps / max(train_seconds, 1e-9), 1),
            "evaluations": len(self.evaluations), "eval_episodes": c.eval_episodes,
            "final_eval_mean_return": float(np.mean(last["return"])),
            "final_eval_mean_length": float(np.mean(last["length"])),
            "best_eval_mean_return": float(max(np.mean(e["return"]) for e in self.evaluations)),
        }
        sps = [m["training/sps"] for m in self.training_metrics if "training/sps" in m]
        if sps:
            out["training_sps_last_epoch"] = round(float(sps[-1]), 1)
        if "success" in last:
            rates = [float(np.mean(e["success"])) for e in self.evaluations]
            out["final_eval_success_rate"] = rates[-1]
            out["best_eval_success_rate"] = max(rates)
        target = getattr(self.spec.env, "learning_target", None)
        if target is not None:
            out["learning_target"] = target.description
        return out


class TrainingStopped(Exception):
    """:func:`train` stopped at one of the trainer's evaluation points because ``should_stop()`` said so."""


def train(spec: DeepRunSpec, progress: Callable[[dict[str, Any]], None] | None = None,
          should_stop: Callable[[], bool] | None = None) -> DeepResult:
    """Train with Brax's trainer on the env's Brax face; evaluate at each of its ``num_evals`` points.

    ``progress(evaluation)`` is called with each evaluation's dict (host arrays). Brax's own evaluator is not
    run (``run_evals=False`` for PPO; SAC's ``num_eval_envs`` is kept minimal): the run's evaluation is
    :func:`evaluate` on fresh episodes of the jaxrobo env.

    Brax's trainer runs as one call with no way to pause it: ``should_stop()`` (e.g. a
    :class:`jaxrobo.driver.StopOnSignal`) is asked each time the trainer hands control back (its progress and
    parameter callbacks, at each evaluation point), and :class:`TrainingStopped` is raised out of the trainer
    there when it says so; nothing of the unfinished training is returned."""
    import jax

    from jaxrobo import brax_env  # its import gives Brax 0.14's trainers the JAX calls they need

    c = spec.config
    benv = brax_env.BraxEnv(spec.env)
    length = spec.episode_length
    evaluations: list[dict[str, Any]] = []
    metrics_log: list[dict[str, float]] = []
    timer = {"eval": 0.0, "start": time.perf_counter(), "net": None, "evaluate": None}
    key = jax.random.fold_in(jax.random.key(c.seed), 7)
    net = network_config(spec, int(benv.observation_size), int(benv.action_size))

    def stop_here() -> None:
        if should_stop is not None and should_stop():
            raise TrainingStopped(f"stopped at {len(evaluations)} of {c.num_evals} evaluation points")

    def on_params(step: int, make_policy: Callable, params: Any) -> None:
        stop_here()
        t0 = time.perf_counter()
        if timer["evaluate"] is None:
            timer["evaluate"] = evaluate(spec.env, benv, make_policy, c.eval_episodes, length)
        res = jax.device_get(timer["evaluate"](params, jax.random.fold_in(key, len(evaluations))))
        row = {k: np.asarray(v) for k, v in res.items()}
        row["env_steps"] = int(step)
        row["seconds"] = t0 - timer["start"] - timer["eval"]
        evaluations.append(row)
        timer["eval"] += time.perf_counter() - t0
        if progress is not None:
            progress(row)

    def on_progress(step: int, metrics: Mapping[str, Any]) -> None:
        stop_here()
        if metrics:
            metrics_log.append({"env_steps": int(step), **{k: float(np.asarray(v)) for k, v in metrics.items()
                                                            if np.size(v) == 1}})

    common = dict(environment=benv, num_timesteps=c.num_timesteps, episode_length=length,
                  action_repeat=c.action_repeat, num_envs=c.num_envs, learning_rate=c.learning_rate,
                  discounting=c.discounting, seed=c.seed, batch_size=c.batch_size, num_evals=c.num_evals,
                  normalize_observations=c.normalize_observations, reward_scaling=c.reward_scaling,
                  max_devices_per_host=1, network_factory=_factory(spec), progress_fn=on_progress,
                  wrap_env_fn=brax_env.wrap_for_training)
    if c.agent == "ppo":
        from brax.training.agents.ppo import train as ppo

        _, params, _ = ppo.train(**common, entropy_cost=c.entropy_cost, unroll_length=c.unroll_length,
                                 num_minibatches=c.num_minibatches, num_updates_per_batch=c.num_updates_per_batch,
                                 clipping_epsilon=c.clipping_epsilon, gae_lambda=c.gae_lambda,
                                 max_grad_norm=c.max_grad_norm, policy_params_fn=on_params, run_evals=False)
    else:
        params = _train_sac(common, c, lambda step, p: on_params(step, _networks(net)[1], p))
    seconds = time.perf_counter() - timer["start"]
    return DeepResult(spec, jax.device_get(params), net, evaluations, metrics_log, seconds, timer["eval"])


def _train_sac(common: dict[str, Any], c: SACConfig, on_params: Callable[[int, Any], None]) -> Any:
    """``sac.train`` with the run's evaluation at each of its evaluation points.

    Brax's SAC takes no ``policy_params_fn``: it hands the parameters at each point to the
    ``acting.Evaluator`` it builds, then calls ``progress_fn(step, metrics)``. For the length of the call
    :func:`jaxrobo.brax_compat.keep_evaluator_params` makes that evaluator one that keeps those parameters (and
    skips Brax's own evaluation rollout), and ``progress_fn`` runs the run's evaluation with them at that step;
    the trainer itself runs unchanged."""
    from brax.training.agents.sac import train as sac

    from jaxrobo.brax_compat import keep_evaluator_params

    progress = common["progress_fn"]
    with keep_evaluator_params() as hook:
        def on_progress(step: int, metrics: Mapping[str, Any]) -> None:
            progress(step, metrics)
            if hook.has_params:
                on_params(step, hook.pop())

        _, params, _ = sac.train(**{**common, "progress_fn": on_progress}, tau=c.tau,
                                 min_replay_size=c.min_replay_size, max_replay_size=c.max_replay_size,
                                 grad_updates_per_step=c.grad_updates_per_step, num_eval_envs=1)
    hook.check()
    return params


# ---- the run directory -------------------------------------------------------------------------------------------
#: ``evaluations.csv``: one row per evaluation episode.
EVAL_COLUMNS = ("evaluation", "env_steps", "episode", "return", "length", "terminated")
#: ``episode_stats.csv`` of a deep run: one row per evaluation (``episode`` is the evaluation's index, so
#: ``jaxrobo plot`` reads it as it reads a tabular run's; ``env_steps`` is the common x axis of both kinds).
STAT_COLUMNS = ("episode", "env_steps", "seconds", "return_mean", "return_std", "return_p10", "return_p50",
                "return_p90", "length_mean", "length_std", "length_p10", "length_p50", "length_p90")


def _stats_rows(result: DeepResult) -> tuple[tuple[str, ...], list[list[Any]]]:
    with_success = "success" in result.evaluations[0]
    cols = STAT_COLUMNS + (("success_rate",) if with_success else ())
    rows = []
    for i, e in enumerate(result.evaluations):
        r, n = e["return"].astype(np.float64), e["length"].astype(np.float64)
        row: list[Any] = [i, e["env_steps"], f"{e['seconds']:.3f}"]
        for x in (r, n):
            row += [f"{v:.6g}" for v in (x.mean(), x.std(), *np.percentile(x, (10, 50, 90)))]
        if with_success:
            row.append(f"{float(np.mean(e['success'])):.6g}")
        rows.append(row)
    return cols, rows


def write_run(out_dir: str, result: DeepResult) -> str:
    """Everything a deep run produced, into ``out_dir`` (a staging directory: :mod:`jaxrobo.rundir` publishes
    it whole): ``config.yaml``, ``policy.npz`` + ``policy.json``, ``evaluations.csv``, ``episode_stats.csv``,
    ``training_metrics.csv``, ``summary.json``, ``tensorboard/`` and ``rewards.png``."""
    import csv

    from jaxrobo.results import write_config, write_summary

    write_config(out_dir, result.spec.to_dict())
    save_policy(out_dir, result.params, result.net)
    with_success = "success" in result.evaluations[0]
    with open(os.path.join(out_dir, "evaluations.csv"), "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(EVAL_COLUMNS + (("success",) if with_success else ()))
        for i, e in enumerate(result.evaluations):
            for j in range(e["return"].shape[0]):
                row = [i, e["env_steps"], j, f"{e['return'][j]:.6g}", int(e["length"][j]), int(e["terminated"][j])]
                w.writerow(row + ([int(e["success"][j])] if with_success else []))
    cols, rows = _stats_rows(result)
    with open(os.path.join(out_dir, "episode_stats.csv"), "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(cols)
        w.writerows(rows)
    if result.training_metrics:
        keys = sorted({k for m in result.training_metrics for k in m} - {"env_steps"})
        with open(os.path.join(out_dir, "training_metrics.csv"), "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["env_steps", *keys])
            for m in result.training_metrics:
                w.writerow([m["env_steps"], *(f"{m[k]:.6g}" if k in m else "" for k in keys)])
    write_summary(out_dir, result.summary())
    _write_tensorboard(out_dir, result)
    from jaxrobo.plots import plot_runs

    plot_runs([out_dir], os.path.join(out_dir, "rewards.png"), labels=[f"{result.spec.env_id} · {result.spec.agent}"],
              window=1)
    return out_dir


def _write_tensorboard(out_dir: str, result: DeepResult) -> None:
    """Scalars at each evaluation (x: env steps): the evaluation's mean return, length (and success rate), and
    Brax's training metrics."""
    try:
        from tensorboardX import SummaryWriter
    except ImportError:  # pragma: no cover - a dependency, but keep runs working without it
        return
    writer = SummaryWriter(os.path.join(out_dir, "tensorboard"))
    try:
        for e in result.evaluations:
            step = int(e["env_steps"])
            writer.add_scalar("eval/return_mean", float(np.mean(e["return"])), step)
            writer.add_scalar("eval/length_mean", float(np.mean(e["length"])), step)
            if "success" in e:
                writer.add_scalar("eval/success_rate", float(np.mean(e["success"])), step)
        for m in result.training_metrics:
            for k, v in m.items():
                if k != "env_steps" and np.isfinite(v):
                    writer.add_scalar(k, v, int(m["env_steps"]))
    finally:
        writer.close()


def is_deep_run(run_dir: str) -> bool:
    """A run directory written by a deep-RL run (its ``config.yaml`` names ``ppo`` or ``sac``)."""
    from jaxrobo.results import load_config

    try:
        return is_deep((load_config(run_dir).get("train") or {}).get("agent"))
    except (FileNotFoundError, OSError, ValueError):
        return False
