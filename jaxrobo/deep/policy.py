"""Brax's networks of a deep run and its policy on disk: :func:`network_config` (what rebuilds the networks),
:func:`save_policy` / :func:`load_policy` (the parameter pytree as plain arrays in ``policy.npz`` by key path, no
pickle; the network config in ``policy.json``) and :func:`env_policy` (the deterministic policy acting on the
jaxrobo env)."""
from __future__ import annotations

import dataclasses
import os
from typing import Any, Callable, Mapping

import numpy as np

from jaxrobo.core.config import ConfigError, parse_json
from jaxrobo.deep.config import AGENTS, DeepRunSpec

#: Files of a deep run's saved policy.
POLICY_NPZ, POLICY_JSON = "policy.npz", "policy.json"


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
    arrays, no pickle) and ``policy.json`` (:func:`network_config`, with the evaluation point it was saved at
    where the caller adds it), each written atomically."""
    import jax

    from jaxrobo.io import rundir

    leaves = jax.tree_util.tree_flatten_with_path(jax.device_get(params))[0]
    arrays = {_path_name(path): np.asarray(leaf) for path, leaf in leaves}
    # Each file atomically: a run stopped or killed while saving keeps the previous policy whole.
    rundir.atomic_savez(os.path.join(out_dir, POLICY_NPZ), **arrays)
    rundir.atomic_write_json(os.path.join(out_dir, POLICY_JSON), dict(net))


@dataclasses.dataclass
class LoadedPolicy:
    """A saved policy: ``act(obs, key) -> action`` in [-1, 1] (Brax's deterministic action, the mode), the
    parameters and the network config."""

    net: dict[str, Any]
    params: Any
    make_policy: Callable

    def act(self, obs: Any, key: Any = None) -> Any:
        """The action for ``obs`` (one observation or a batch ``[..., observation_size]``; a list or numpy array
        too); a ValueError naming the sizes for an observation of another size (Brax's networks broadcast it, or
        fail inside its normaliser)."""
        import jax

        if not hasattr(obs, "shape"):  # a list is no array to Brax's normaliser (a pytree error there)
            obs = np.asarray(obs, np.float32)
        # An array is passed as it is: a numpy one is normalised in numpy, a JAX one by XLA (last bits differ).
        size = int(self.net["observation_size"])
        if len(obs.shape) == 0 or obs.shape[-1] != size:
            raise ValueError(f"LoadedPolicy.act(obs): obs has shape {tuple(obs.shape)}; this policy takes "
                             f"observations of size {size} (shape ({size},), or a batch (..., {size}))")
        key = jax.random.key(0) if key is None else key
        return self.make_policy(self.params, deterministic=True)(obs, key)[0]

    def __reduce__(self) -> tuple:
        # Brax's inference function is a local closure that pickle cannot name: rebuilt from the network config.
        import jax

        return (_loaded, (dict(self.net), jax.device_get(self.params)))


def _loaded(net: dict[str, Any], params: Any) -> LoadedPolicy:
    """A :class:`LoadedPolicy` unpickled: its networks rebuilt from ``net``."""
    return LoadedPolicy(net, params, _networks(net)[1])


#: The policies a deep run keeps: ``latest`` (the run directory's own ``policy.npz``: the last evaluation point's,
#: the trained policy of a finished run) and ``best`` (``best/policy.npz``: the point with the best evaluation).
POLICIES = {"latest": "", "best": "best"}


def policy_dir(run_dir: str, which: str = "latest") -> str:
    """Where a run keeps its ``which`` policy (:data:`POLICIES`)."""
    if which not in POLICIES:
        raise ConfigError(f"policy={which!r}: allowed values are {', '.join(POLICIES)}")
    return os.path.join(run_dir, POLICIES[which]) if POLICIES[which] else run_dir


def _check_network_config(net: Mapping[str, Any]) -> None:
    """ValueError naming the field of a ``policy.json`` whose sizes or flags Brax's network makers would take
    and fail on deep inside (a traceback) or silently misread (``"normalize_observations": "yes"``)."""
    from jaxrobo.deep.config import _LAYERS, MAX_LAYER

    def is_int(x: Any, high: int) -> bool:
        return isinstance(x, int) and not isinstance(x, bool) and 1 <= x <= high

    for name in ("observation_size", "action_size"):
        if not is_int(net[name], 1 << 20):
            raise ValueError(f"{name}={net[name]!r}: expected an integer >= 1 and <= {1 << 20}")
    if not isinstance(net["normalize_observations"], bool):
        raise ValueError(f"normalize_observations={net['normalize_observations']!r}: expected true or false")
    for name in _LAYERS[net["agent"]]:
        sizes = net.get(name)
        if not isinstance(sizes, list) or not sizes or not all(is_int(x, MAX_LAYER) for x in sizes):
            raise ValueError(f"{name}={sizes!r}: expected a non-empty list of integers >= 1 and <= {MAX_LAYER} "
                             f"(the {net['agent']} networks' layer widths)")


def load_policy(run_dir: str, which: str = "latest") -> LoadedPolicy:
    """The ``which`` policy (:data:`POLICIES`) a deep run saved (a finished run, or one stopped after its first
    evaluation point); :class:`ConfigError` naming the file when it is missing, pickled, or does not match its
    ``policy.json`` (a missing, extra or misshapen array)."""
    import jax

    where = policy_dir(run_dir, which)
    npz_path, json_path = os.path.join(where, POLICY_NPZ), os.path.join(where, POLICY_JSON)
    for path in (npz_path, json_path):
        if not os.path.isfile(path):
            raise ConfigError(f"{run_dir}: no {os.path.relpath(path, run_dir)}; is it a deep-RL run directory that "
                              "reached an evaluation point?")
    try:
        with open(json_path) as f:
            net = parse_json(f.read())
        if not isinstance(net, dict):
            raise ValueError("not a JSON object")
        nets_config_keys = ("agent", "observation_size", "action_size", "normalize_observations")
        missing = [k for k in nets_config_keys if k not in net]
        if missing or net["agent"] not in AGENTS:
            raise ValueError(f"missing {', '.join(missing)}" if missing else f"agent={net['agent']!r}")
        _check_network_config(net)
    except (OSError, ValueError) as err:
        raise ConfigError(f"{json_path}: not a policy description ({err})") from None
    from jaxrobo.io.npz import read_npz

    # Headers checked first (NpzError); NaN or inf weights (a diverged run's) would fly or export as a policy.
    arrays = read_npz(npz_path, "the policy's parameters", finite=True)
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
        if name.endswith("/std") and np.any(value <= 0):  # the normaliser divides by it: inf or flipped obs
            raise ConfigError(f"{npz_path}: {name} holds values <= 0 (the observation normaliser's standard "
                              "deviations must be > 0)")
        leaves.append(value.astype(np.asarray(leaf).dtype))
    extra = sorted(set(arrays) - names)
    if extra:
        raise ConfigError(f"{npz_path}: arrays {', '.join(extra[:5])} are not parameters of the networks of "
                          f"{POLICY_JSON}")
    params = jax.tree_util.tree_unflatten(treedef, leaves)
    _, make_policy = _networks(net)
    return LoadedPolicy(net, params, make_policy)


def env_policy(benv: Any, make_policy: Callable, params: Any) -> Callable:
    """A :data:`jaxrobo.task.rollout.Policy` ``(key, obs) -> action`` of the jaxrobo env, acting as the trained
    deterministic policy does through ``benv`` (its Brax action, mapped to the env's action space as the Brax
    face maps it)."""
    policy = make_policy(params, deterministic=True)
    return lambda key, obs: benv.scale_action(policy(obs, key)[0])
