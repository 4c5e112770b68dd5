"""The trainers' settings and how a deep run is resolved: :class:`DeepConfig` (the fields both trainers take, each
declared once), :class:`PPOConfig` and :class:`SACConfig`, the presets of ``agents/configs/``, and
:func:`resolve` / :func:`spec_from_config` into a :class:`DeepRunSpec`, every value validated before anything
compiles."""
from __future__ import annotations

import dataclasses
import os
from typing import Any, Mapping

from jaxrobo.core.config import ConfigError, as_dict, check_fields, load_yaml, split_and_validate, unknown_key
from jaxrobo.core.struct import param, rules

#: The deep-RL learners, each Brax's trainer of that name.
AGENTS = ("ppo", "sac")
AGENT_CONFIG_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                                "agents", "configs")
#: Accepted old names of config keys (Brax's argument name first): each means its new name; both at once are refused.
ALIASES = {"num_timesteps": "total_steps"}
#: The largest network layer jaxrobo accepts from a config (a typo of 1e6 units would exhaust memory, not learn).
MAX_LAYER = 8192


# ---- the hyperparameters: one home each --------------------------------------------------------------------------
def _per_agent(kind: type, **rule: Any) -> Any:
    """A shared field whose default differs between the trainers: its type, range and doc are declared here, each
    agent's config gives its default (:func:`_agent_default`)."""
    return dataclasses.field(metadata=param(kind(), kind=kind, **rule).metadata)


@dataclasses.dataclass(frozen=True, kw_only=True)
class DeepConfig:
    """The settings both of Brax's trainers take (Brax's argument names), plus the run's own evaluation
    (``num_evals`` points of ``eval_episodes`` fresh episodes) and seed. Each field, its range and its default
    are declared once, here; where the trainers' defaults differ, each agent's config gives its own."""

    agent: str = _per_agent(str, choices=AGENTS, doc="the trainer")
    total_steps: int = _per_agent(int, low=1, doc="env steps of the whole run, all envs together (Brax's "
                                                 "num_timesteps; Brax rounds up to whole epochs)")
    num_envs: int = _per_agent(int, low=1, doc="environments stepped in parallel")
    episode_length: int | None = param(None, kind=int, low=1,
                                       doc="step cap of a training episode (default: the id's max_episode_steps)")
    action_repeat: int = param(1, low=1, doc="env steps per policy action")
    learning_rate: float = _per_agent(float, low=0.0, low_open=True, high=1.0, doc="Adam step size")
    discounting: float = param(0.97, low=0.0, high=1.0, doc="discount factor gamma")
    batch_size: int = param(256, low=1, doc="segments (PPO) or transitions (SAC) per minibatch")
    normalize_observations: bool = param(True, doc="running mean/std normalisation of observations")
    reward_scaling: float = param(1.0, low=0.0, low_open=True, doc="factor on rewards in the losses")
    num_evals: int = param(10, low=1, high=1000, doc="evaluation points over the run (the first before training)")
    eval_episodes: int = param(128, low=1, high=100_000, doc="fresh episodes of each evaluation")
    seed: int = param(0, low=0, host_only=True, doc="random seed; the same seed gives the same run")
    iteration_steps: int = _per_agent(int, low=1, doc="most env steps of one host iteration of the trainer (at "
                                                     "least one training step): where a stop keeps the trainer's "
                                                     "state between evaluation points; the policy is the same "
                                                     "whatever it is")
    stop_at_target: bool = param(True, doc="stop at the first evaluation point whose fresh episodes meet the task's "
                                           "learning target (total_steps is then a cap); no effect for a task that "
                                           "declares no target")


def _agent_default(name: str, default: Any) -> Any:
    """:class:`DeepConfig`'s field ``name`` (its type, range and doc) with this agent's default."""
    return dataclasses.field(default=default, metadata=DeepConfig.__dataclass_fields__[name].metadata)


@dataclasses.dataclass(frozen=True, kw_only=True)
class PPOConfig(DeepConfig):
    """``brax.training.agents.ppo.train``'s hyperparameters that a jaxrobo run sets (Brax's defaults where
    Brax has a sensible one): :class:`DeepConfig`'s and PPO's own."""

    agent: str = param("ppo", choices=("ppo",), doc="the trainer")
    total_steps: int = _agent_default("total_steps", 1_000_000)
    num_envs: int = _agent_default("num_envs", 1024)
    learning_rate: float = _agent_default("learning_rate", 3e-4)
    iteration_steps: int = _agent_default("iteration_steps", 1 << 16)
    entropy_cost: float = param(1e-2, low=0.0, high=1.0, doc="weight of the entropy bonus")
    unroll_length: int = param(10, low=1, doc="steps per rollout segment")
    num_minibatches: int = param(8, low=1, doc="minibatches per update")
    num_updates_per_batch: int = param(4, low=1, doc="epochs over each batch")
    clipping_epsilon: float = param(0.3, low=0.0, low_open=True, high=1.0, doc="PPO ratio clipping")
    gae_lambda: float = param(0.95, low=0.0, high=1.0, doc="GAE lambda")
    max_grad_norm: float | None = param(None, kind=float, low=0.0, low_open=True, doc="gradient clipping (null: none)")
    policy_hidden_layer_sizes: tuple = param((32, 32, 32, 32), kind=tuple, doc="policy MLP layer widths")
    value_hidden_layer_sizes: tuple = param((256, 256, 256, 256, 256), kind=tuple, doc="value MLP layer widths")


@dataclasses.dataclass(frozen=True, kw_only=True)
class SACConfig(DeepConfig):
    """``brax.training.agents.sac.train``'s hyperparameters that a jaxrobo run sets: :class:`DeepConfig`'s and
    SAC's own."""

    agent: str = param("sac", choices=("sac",), doc="the trainer")
    total_steps: int = _agent_default("total_steps", 200_000)
    num_envs: int = _agent_default("num_envs", 64)
    learning_rate: float = _agent_default("learning_rate", 6e-4)
    # An env step costs SAC grad_updates_per_step gradient steps on a batch (PPO: a share of one): its grain is
    # finer, so that a host iteration of the default run takes about a second on a 2-core CPU, not an epoch
    iteration_steps: int = _agent_default("iteration_steps", 1024)
    grad_updates_per_step: int = param(8, low=1, doc="gradient steps per env step of all envs")
    tau: float = param(0.005, low=0.0, low_open=True, high=1.0, doc="target network update rate")
    min_replay_size: int = param(1024, low=0, doc="transitions collected before learning starts")
    max_replay_size: int | None = param(None, kind=int, low=1, doc="replay capacity (null: total_steps)")
    hidden_layer_sizes: tuple = param((256, 256), kind=tuple, doc="policy and Q MLP layer widths")


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
        a = _unalias(base.get(name) or {}, f"{base_path}: preset {name}")
        b = _unalias(task.get(name) or {}, f"{task_path}: preset {name}")
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
    config: DeepConfig  # a PPOConfig or SACConfig
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
        from jaxrobo.task.registry import qualified_id

        return {"env_id": qualified_id(self.env_id), "preset": self.preset,
                "env_options": as_dict(self.env.options), "env_params": as_dict(self.env.default_params),
                "agent_params": {}, "train": as_dict(self.config)}


def _unalias(values: Mapping[str, Any], where: str) -> dict[str, Any]:
    """``values`` with each :data:`ALIASES` key (bare, or with an ``agent.`` prefix) under its new name; a key
    given under both names is refused."""
    out: dict[str, Any] = {}
    for key, value in values.items():
        prefix, name = ("agent.", key[6:]) if isinstance(key, str) and key.startswith("agent.") else ("", key)
        new = ALIASES.get(name) if isinstance(name, str) else None
        if new is not None:
            for other in (new, f"agent.{new}"):
                if other in values:
                    raise ConfigError(f"{where}: {key}={value!r} and {other}={values[other]!r} name the same "
                                      f"setting ({name} is the old name of {new}); give it once")
            key = prefix + new
        out[key] = value
    return out


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
        if config.min_replay_size >= config.total_steps:
            raise ConfigError(f"{loc}min_replay_size={config.min_replay_size} must be < total_steps="
                              f"{config.total_steps} (no training would happen)")
        cap = config.max_replay_size
        if cap is not None and cap < max(config.min_replay_size, config.batch_size * config.grad_updates_per_step):
            raise ConfigError(f"{loc}max_replay_size={cap} must be >= min_replay_size ({config.min_replay_size}) "
                              f"and >= batch_size x grad_updates_per_step "
                              f"({config.batch_size * config.grad_updates_per_step})")


def check_action_space(env: Any, agent: str, env_id: str) -> None:
    """Brax's trainers act in a continuous (Box) action space: the env's Brax face refuses a Discrete id (naming
    the continuous id of the same task where there is one); said here as the ``--agent``'s refusal."""
    from jaxrobo.interop.brax_env import BraxEnv

    try:
        BraxEnv(env)
    except ConfigError as err:
        raise ConfigError(f"--agent {agent} on {env_id}: {err} (or train {env_id} with a tabular agent)") from None


def check_spec(spec: Any, where: str = "deep.train(spec)") -> None:
    """A :class:`DeepRunSpec` a Python caller built or edited (``dataclasses.replace(spec, config=...)``), checked
    as :func:`resolve` checks what it reads, before Brax's trainer is built: every field of its config against its
    rule, their combinations, the env's parameters and its action space. Brax asserts with no message (a
    ``batch_size`` that does not divide), divides by zero (``num_envs=0``) or trains on a NaN learning rate
    before an assertion inside its pmap; here a TypeError or a ConfigError names the field."""
    if not isinstance(spec, DeepRunSpec):
        raise TypeError(f"{where}: expected a jaxrobo.deep.DeepRunSpec (jaxrobo.deep.resolve(...)), got "
                        f"{type(spec).__name__}")
    if not isinstance(spec.config, DeepConfig):
        raise TypeError(f"{where}: config: expected a jaxrobo.deep.PPOConfig or SACConfig, got "
                        f"{type(spec.config).__name__}")
    check_fields(spec.config, where)
    check_combinations(spec.config, where)
    check_fields(spec.env.default_params, where)
    check_action_space(spec.env, spec.config.agent, spec.env_id)


def resolve(env_id: str, agent: str, preset: str = "default", overrides: Mapping[str, Any] | None = None,
            source: str = "--set") -> DeepRunSpec:
    """Build the env and the trainer's config of a deep run; :class:`ConfigError` on any bad value, before
    anything compiles. Override keys: a field of the agent's config, or an env option/parameter (``env.KEY``
    forces the env, ``agent.KEY`` the config). ``source``: where the overrides come from, as an unknown key's
    message names it (``""`` where the caller names a run's config.yaml)."""
    from jaxrobo.task.registry import _lookup, make

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
    loc = f"{source} " if source else ""
    for key, value in _unalias(overrides or {}, "--set").items():
        if not isinstance(key, str):
            raise unknown_key(repr(key), set(agent_keys) | set(env_keys), where=source)
        side, name = key.split(".", 1) if key.startswith(("env.", "agent.")) else (None, key)
        if side != "env" and name in agent_keys:
            agent_values[name] = value
        elif side != "agent" and name in env_keys:
            env_values[name] = value
        else:
            known = agent_keys if side == "agent" else env_keys if side == "env" else {**agent_keys, **env_keys}
            raise unknown_key(name, known, where=f"{loc}({agent} on {env_id})")
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
    from jaxrobo.task.registry import find

    try:
        env_id, preset, train = run_config["env_id"], run_config.get("preset", "default"), run_config["train"]
        overrides = {f"env.{k}": v for part in ("env_options", "env_params") for k, v in run_config[part].items()}
        agent = train["agent"]
        overrides.update({f"agent.{k}": v for k, v in train.items() if k != "agent"})
    except (KeyError, TypeError, AttributeError) as err:
        raise ConfigError(f"{where}: not a jaxrobo deep-RL run configuration (missing {err})") from err
    find(env_id, where=f"{where}: env_id {env_id}")
    try:
        return resolve(env_id, agent, preset, overrides, source="")  # an unknown key: named after the file
    except ConfigError as err:
        raise ConfigError(f"{where}: {err}") from None
