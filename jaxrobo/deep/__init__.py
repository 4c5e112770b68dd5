"""Deep RL on jaxrobo envs through Brax's own trainers: ``jaxrobo train --agent ppo|sac``.

The trainers are ``brax.training.agents.ppo.train`` and ``brax.training.agents.sac.train``, called unchanged on
the env's Brax face (:class:`jaxrobo.interop.brax_env.BraxEnv`) with jaxrobo's training wrapper
(:func:`jaxrobo.interop.brax_env.wrap_for_training`: fresh randomness at every auto-reset, truncation kept apart from
termination). jaxrobo adds what a run needs around them, one concern per module:

* :mod:`jaxrobo.deep.config`: one home for every default: :class:`DeepConfig` (the fields both trainers take,
  each with its allowed range), :class:`PPOConfig` and :class:`SACConfig` (each trainer's own); the presets in
  ``agents/configs/<agent>.yaml`` and the per-task presets in ``agents/configs/<agent>/<env id>.yaml`` hold only
  what differs from them (the task file: what differs from the agent file). :func:`resolve` validates
  everything, and refuses a Discrete-action id, before anything compiles;
* :mod:`jaxrobo.deep.training`: Brax's trainer with the evaluation of the deterministic policy on
  ``eval_episodes`` fresh episodes of the jaxrobo env itself at each of the trainer's ``num_evals`` points
  (:func:`evaluate`), through :func:`jaxrobo.task.rollout.rollout`, so a task's success flags (the Goto's
  ``arrived``) are counted exactly as for the tabular learners;
* :mod:`jaxrobo.deep.output`: the run directory, kept at every evaluation point while the run trains
  (:class:`LiveRun`: checkpoint, latest and best policy, ``episode_stats.csv``, live TensorBoard scalars) and
  written whole at the end (:func:`write_run`: ``config.yaml``, ``evaluations.csv``, ``episode_stats.csv`` with an
  ``env_steps`` column, ``summary.json``, TensorBoard scalars, ``rewards.png``, the policy) through
  :mod:`jaxrobo.io.rundir`;
* :mod:`jaxrobo.deep.checkpoint`: the trainer's whole state at the last evaluation point, or at the end of a host
  iteration between points (optimiser, normaliser, parameters, env state, SAC's replay buffer) and the run's
  record, what ``jaxrobo train --resume`` continues;
* :mod:`jaxrobo.deep.policy`: the policy saved without pickle (:func:`save_policy`: the parameter pytree
  flattened to ``policy.npz`` by key path, the network's configuration in ``policy.json``) and loaded back
  (:func:`load_policy`) for ``jaxrobo show`` and rendering.

Public surface (all importable from ``jaxrobo.deep``): :data:`AGENTS`, :class:`DeepConfig`, :class:`PPOConfig`,
:class:`SACConfig`, :class:`DeepRunSpec`, :func:`is_deep`, :func:`config_class`, :func:`presets`,
:func:`resolve`, :func:`check_combinations`, :func:`check_spec`, :func:`train`, :class:`TrainingStopped`,
:class:`TrainerWatch`, :class:`DeepResult`, :func:`evaluate`, :func:`save_policy`, :func:`load_policy`,
:class:`LoadedPolicy`, :func:`write_run`, :func:`spec_from_config`.
"""
from __future__ import annotations

from jaxrobo.deep.config import (AGENT_CONFIG_DIR, AGENTS, MAX_LAYER, DeepConfig, DeepRunSpec, PPOConfig, SACConfig,
                                 check_action_space, check_combinations, check_spec, config_class, is_deep,
                                 preset_paths, presets, resolve, spec_from_config)
from jaxrobo.deep.output import EVAL_COLUMNS, STAT_COLUMNS, LiveRun, eval_means, is_deep_run, write_run
from jaxrobo.deep.policy import (POLICIES, POLICY_JSON, POLICY_NPZ, LoadedPolicy, env_policy, load_policy,
                                 network_config, policy_dir, save_policy)
from jaxrobo.deep.training import (DeepResult, EpochPlan, Point, TrainerWatch, TrainingStopped, best_index, epoch_plan,
                                   evaluate, train)

__all__ = ["AGENTS", "AGENT_CONFIG_DIR", "DeepConfig", "DeepResult", "DeepRunSpec", "EVAL_COLUMNS", "EpochPlan",
           "LiveRun", "LoadedPolicy", "MAX_LAYER", "POLICIES", "POLICY_JSON", "POLICY_NPZ", "PPOConfig", "Point",
           "SACConfig", "STAT_COLUMNS", "TrainerWatch", "TrainingStopped", "best_index", "check_action_space",
           "check_combinations", "check_spec", "config_class", "env_policy", "epoch_plan", "eval_means", "evaluate",
           "is_deep", "is_deep_run", "load_policy", "network_config", "policy_dir", "preset_paths", "presets",
           "resolve", "save_policy", "spec_from_config", "train", "write_run"]
