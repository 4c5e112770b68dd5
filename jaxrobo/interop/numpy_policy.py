"""A policy exported by ``jaxrobo export``, run with numpy alone: ``Policy.load(dir)`` then ``policy(obs) -> action``.

``jaxrobo export`` writes this module into every exported policy directory (beside ``policy.npz`` and ``policy.json``)
with the JAX-free task modules it imports written in before it (:func:`jaxrobo.export.runner_source`: the Goto task's
geometry and observation, the cart-pole's rules, and :data:`jaxrobo.core.scalar.FLOATS`, the Python-float math they run
on here): the file imports nothing but numpy and the standard library, and runs where JAX is not installed (a robot's
computer, a native MuJoCo loop). It reproduces the JAX policy of the run:

* **tabular** (``kind: tabular``): the observation is cast to float32 and cut into bins exactly as
  ``jaxrobo.tabular.discretise.Discretiser`` does (uniform bins: ``floor((obs - low) / width)`` in float32, clipped
  to the end bins; explicit edges: the number of edges ``<= obs`` per dimension), the per-dimension bins are
  combined row-major into a state index, and the action is ``action[state]``: the greedy action of the exported
  table, the first of the maximal action values (the evaluation in JAX breaks ties at random; ``n_max[state] > 1``
  marks the states where that happens, and ``jaxrobo.task.rollout.greedy_policy(..., ties="first")`` is the JAX
  policy that picks the same action everywhere);
* **mlp** (``kind: mlp``, PPO/SAC through Brax): observation normalisation ``(obs - mean) / std`` when the run
  normalised, the dense layers with the activation between them, the mode of Brax's tanh-Normal (``tanh`` of the
  first half of the last layer's output) and the affine map of ``[-1, 1]`` onto the task's action bounds. Computed
  in float32, as JAX does; the two agree to float32 round-off (a different summation order in the matrix products).

``policy.json`` describes the file (``format``, ``kind``, the env id, the observation and action layout);
``policy.npz`` holds the numbers (plain arrays, loaded without pickle). A file of another format, or arrays that do
not match the description, are refused with a ``ValueError`` naming the file.

For a task with a native port (``envs/*/native.py``), ``policy.json``'s ``robot`` section holds what turns the
robot's readings into the policy's observation and its action into the robot's command, the task's constants as
the run configured it (:class:`QuadcopterIO`, :class:`CartPoleIO`; ``policy.io``): the control period, the action
table, the drone's ``dz_lead``, radius, clear margin and sonar range, the cart-pole's rounding, action steps and
``pos_step``.
The native ports compute with these same classes, so a policy driving a robot (the ROS policy node) needs nothing
but this file and the export: no JAX, no task package, no MuJoCo.
"""
from __future__ import annotations

import json
import math
import os

import numpy as np

from envs.cartpole.rules import command_after, observation
from envs.quadcopter.geometry import euler
from envs.quadcopter.goto_step import kinds_of, loop_fold, observe
from jaxrobo.core.scalar import FLOATS

#: The version of the exported files this runner reads.
FORMAT = 1
POLICY_NPZ, POLICY_JSON = "policy.npz", "policy.json"
KINDS = ("tabular", "mlp")
ACTIVATIONS = ("relu", "swish")


def _activation(name: str):
    if name == "relu":
        return lambda x: np.maximum(x, np.float32(0))
    if name == "swish":  # x * sigmoid(x), as jax.nn.swish computes it
        def swish(x):
            with np.errstate(over="ignore"):  # exp(-x) -> inf for very negative x: sigmoid 0, as in JAX
                return x * (np.float32(1) / (np.float32(1) + np.exp(-x)))
        return swish
    raise ValueError(f"activation={name!r}: allowed values are {', '.join(ACTIVATIONS)}")


class Policy:
    """An exported policy: ``policy(obs)`` is the action of one observation (an int for a tabular policy, a float32
    array for an MLP); ``policy.batch(obs [n, d])`` acts on many at once."""

    def __init__(self, meta: dict, arrays: dict):
        self.meta = meta
        #: The task's readings -> observation and action -> command (``None``: the export has no ``robot`` section)
        self.io = task_io(meta["robot"]) if meta.get("robot") is not None else None
        self.kind = meta["kind"]
        self.obs_size = int(meta["observation_size"])
        self._a = arrays
        if self.kind == "tabular":
            edges = meta["discretiser"] == "edges"
            self._edges = [arrays[f"edges_{i}"] for i in range(self.obs_size)] if edges else None
            self._bins = arrays["bins"].astype(np.int64)
            self._strides = np.cumprod(np.concatenate([self._bins[1:], [1]])[::-1])[::-1].astype(np.int64)
        else:
            self._act = _activation(meta["activation"])
            self._layers = [(arrays[f"kernel_{i}"], arrays[f"bias_{i}"]) for i in range(len(meta["layer_sizes"]))]

    # ---- loading ----------------------------------------------------------------------------------------
    @classmethod
    def load(cls, path: str) -> "Policy":
        """The policy exported into the directory ``path``; ``ValueError`` naming the file if it is not one."""
        json_path, npz_path = os.path.join(path, POLICY_JSON), os.path.join(path, POLICY_NPZ)
        try:
            with open(json_path) as f:
                meta = json.load(f)
        except (OSError, ValueError, RecursionError) as err:  # RecursionError: JSON nested past the limit
            raise ValueError(f"{json_path}: not an exported policy description ({err})") from None
        if not isinstance(meta, dict) or meta.get("format") != FORMAT or meta.get("kind") not in KINDS:
            got = (meta.get("format"), meta.get("kind")) if isinstance(meta, dict) else type(meta).__name__
            raise ValueError(f"{json_path}: format {FORMAT} with kind in {KINDS} expected, got {got}")
        try:
            with np.load(npz_path, allow_pickle=False) as npz:
                arrays = {k: npz[k] for k in npz.files}
        except Exception as err:  # noqa: BLE001 - any unreadable file is one error, naming it
            raise ValueError(f"{npz_path}: cannot be read as plain arrays ({type(err).__name__}: {err})") from None
        _check(meta, arrays, npz_path)
        if meta.get("robot") is not None:
            try:
                io = task_io(meta["robot"])
            except (KeyError, TypeError, ValueError) as err:
                raise ValueError(f"{json_path}: robot: {err}") from None
            tabular = meta["kind"] == "tabular"
            if tabular == io.continuous or (tabular and io.n_actions != int(meta["n_actions"])):
                raise ValueError(f"{json_path}: robot: a {io.family} with "
                                 f"{'continuous actions' if io.continuous else f'{io.n_actions} actions'} does not "
                                 f"take the actions of a {meta['kind']} policy")
        return cls(meta, arrays)

    # ---- acting -----------------------------------------------------------------------------------------
    def __call__(self, obs):
        """The action for one observation (``observation_size`` numbers)."""
        obs = np.asarray(obs, np.float32)
        if obs.shape != (self.obs_size,):
            raise ValueError(f"observation of shape {obs.shape}; expected ({self.obs_size},)")
        out = self.batch(obs[None])[0]
        return int(out) if self.kind == "tabular" else out

    def batch(self, obs):
        """Actions for observations ``[n, observation_size]``: int32 ``[n]`` or float32 ``[n, action_size]``."""
        obs = np.asarray(obs, np.float32)
        if obs.ndim != 2 or obs.shape[1] != self.obs_size:
            raise ValueError(f"observations of shape {obs.shape}; expected [n, {self.obs_size}]")
        if np.isnan(obs).any():
            raise ValueError("observation holds NaN: a policy cannot act on it (a sensor fault?)")
        if self.kind == "tabular":
            return self._a["action"][self.state(obs)]
        return self._mlp(obs)

    def state(self, obs):
        """The table's state index of each observation ``[n, d]`` (tabular policies)."""
        obs = np.asarray(obs, np.float32)
        if self._edges is not None:
            idx = np.stack([np.sum(obs[:, i:i + 1] >= e[None, :], axis=1) for i, e in enumerate(self._edges)], 1)
        else:
            with np.errstate(over="ignore", invalid="ignore"):
                cell = np.floor((obs - self._a["low"]) / self._a["width"])
            # clipped as a float first: an observation far out of range saturates into the end bin (as XLA's
            # float -> int conversion does) instead of wrapping around in the cast
            idx = np.clip(cell, 0, self._bins - 1).astype(np.int64)
        return (idx * self._strides).sum(axis=1)

    def _mlp(self, obs):
        x = obs
        if self.meta["normalize_observations"]:
            x = (x - self._a["obs_mean"]) / self._a["obs_std"]
        last = len(self._layers) - 1
        for i, (w, b) in enumerate(self._layers):
            x = x @ w + b
            if i < last:
                x = self._act(x)
        n = int(self.meta["action_size"])
        a = np.tanh(x[:, :n])  # the mode of Brax's tanh-Normal: tanh of the mean
        if self.meta["action_scaling"] == "affine":
            low, high = self._a["action_low"], self._a["action_high"]
            a = low + (a + np.float32(1)) * np.float32(0.5) * (high - low)
        return a.astype(np.float32)


def _check(meta: dict, a: dict, where: str) -> None:
    """The arrays must be those the description needs, of the right shapes and dtypes (hostile files)."""
    def need(name, shape=None, kind="f"):
        if name not in a:
            raise ValueError(f"{where}: no array {name!r}")
        v = a[name]
        if v.dtype.kind != kind or (shape is not None and v.shape != tuple(shape)):
            raise ValueError(f"{where}: {name} is {v.dtype} of shape {v.shape}; expected kind {kind!r} "
                             f"of shape {tuple(shape) if shape is not None else 'any'}")
        if kind == "f" and not np.all(np.isfinite(v)):
            raise ValueError(f"{where}: {name} holds non-finite values")
        return v
    try:
        d = int(meta["observation_size"])
        if meta["kind"] == "tabular":
            if meta["discretiser"] not in ("uniform", "edges"):
                raise ValueError(f"discretiser={meta['discretiser']!r}: expected 'uniform' or 'edges'")
            bins = need("bins", (d,), "i")
            if np.any(bins < 1):
                raise ValueError(f"{where}: bins must be >= 1")
            n_states = int(np.prod(bins.astype(np.int64)))
            action = need("action", (n_states,), "i")
            if np.any(action < 0) or np.any(action >= int(meta["n_actions"])):
                raise ValueError(f"{where}: action holds indices outside 0..{int(meta['n_actions']) - 1}")
            if meta["discretiser"] == "edges":
                for i in range(d):
                    e = need(f"edges_{i}", (int(bins[i]) - 1,))
                    if np.any(np.diff(e) <= 0):
                        raise ValueError(f"{where}: edges_{i} must be strictly increasing")
            else:
                need("low", (d,))
                if np.any(need("width", (d,)) <= 0):
                    raise ValueError(f"{where}: width must be > 0")
        else:
            sizes = [int(s) for s in meta["layer_sizes"]]
            _activation(meta["activation"])
            if meta["action_scaling"] not in ("affine", "none"):
                raise ValueError(f"action_scaling={meta['action_scaling']!r}")
            n_in = d
            for i, s in enumerate(sizes):
                need(f"kernel_{i}", (n_in, s))
                need(f"bias_{i}", (s,))
                n_in = s
            if sizes[-1] != 2 * int(meta["action_size"]):
                raise ValueError(f"last layer has {sizes[-1]} outputs; a tanh-Normal needs 2 x action_size")
            if meta["normalize_observations"]:
                need("obs_mean", (d,))
                if np.any(need("obs_std", (d,)) <= 0):
                    raise ValueError(f"{where}: obs_std must be > 0")
            if meta["action_scaling"] == "affine":
                need("action_low", (int(meta["action_size"]),))
                need("action_high", (int(meta["action_size"]),))
    except (KeyError, TypeError) as err:
        raise ValueError(f"{where}: the description lacks {err}") from None


# ---- the robot's side of the task: readings -> observation, action -> command --------------------------------
def _number(c: dict, key: str, low: float = -math.inf, high: float = math.inf) -> float:
    v = c[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not low <= v <= high:
        raise ValueError(f"{key}={v!r}: expected a number in [{low}, {high}]")
    return float(v)


def _flag(c: dict, key: str) -> bool:
    if not isinstance(c[key], bool):
        raise ValueError(f"{key}={c[key]!r}: expected true or false")
    return c[key]


def _table(c: dict, key: str, width: int | None) -> np.ndarray:
    a = np.asarray(c[key], np.float64)
    if a.ndim != (1 if width is None else 2) or len(a) < 1 or (width is not None and a.shape[1] != width) \
            or not np.all(np.isfinite(a)):
        raise ValueError(f"{key}: expected finite numbers of shape [n{'' if width is None else f', {width}'}]")
    return a


class QuadcopterIO:
    """QuadcopterGoto-v1/-v2 and GotoTwist-v0: the observation from the drone's readings (position, orientation,
    vertical speed, the four sonars, the goal and the obstacles map) and the Twist of an action. The observation
    is the task's own (:func:`envs.quadcopter.goto_step.observe` on :mod:`envs.quadcopter.geometry`, on float64
    scalars), with the sonars read instead of cast."""

    family = "quadcopter"

    def __init__(self, c: dict):
        self.period = _number(c, "period", 1e-6, 60.0)
        self.continuous, self.v2 = _flag(c, "continuous"), _flag(c, "v2")
        self.speed_value = _number(c, "speed_value", 0.0)
        #: The task's parameters the observation reads (:func:`envs.quadcopter.goto_step.observe`).
        self.p = {"sonar_range": _number(c, "sonar_range", 0.0)}
        if self.v2:
            self.p.update(dz_lead=_number(c, "dz_lead"), drone_radius=_number(c, "drone_radius", 0.0),
                          clear_margin=_number(c, "clear_margin", 0.0))
        self.actions = None if self.continuous else _table(c, "actions", 4)
        self.n_actions = None if self.continuous else len(self.actions)
        self.observation_size = 8 if self.v2 else 7

    def observation(self, pos, quat, vz: float, sonars, goal, obstacles: dict) -> np.ndarray:
        """Position (m), orientation quaternion ``(w, x, y, z)``, vertical velocity (m/s), the four sonars (m),
        the goal (m) and the obstacles (``kind``, ``center``, ``size``, ``active``) -> the task's observation."""
        pos, goal = np.asarray(pos, np.float64).tolist(), np.asarray(goal, np.float64).tolist()
        yaw = euler(FLOATS, *np.asarray(quat, np.float64).tolist())[2]
        obstacles = {"kind": np.asarray(obstacles["kind"]), "center": np.asarray(obstacles["center"], np.float64),
                     "size": np.asarray(obstacles["size"], np.float64), "active": np.asarray(obstacles["active"])}
        obs, _, _ = observe(FLOATS, pos, yaw, float(vz), goal, self.p, self.v2, kinds_of("mixed"),
                            loop_fold(FLOATS, obstacles), sonars=[float(s) for s in sonars])
        return np.asarray(obs, np.float64).astype(np.float32)

    def command(self, action) -> tuple:
        """``(action as recorded, Twist [vx, vy, vz, yaw_rate])`` (heading frame, m/s, rad/s): a discrete action's
        row of the action table, or GotoTwist's ``speed_value * clip(a, -1, 1)``."""
        if self.continuous:
            a = np.clip(np.reshape(np.asarray(action, np.float64), -1)[:4], -1.0, 1.0)
            return a, self.speed_value * a
        a = int(action)
        return a, self.actions[a].copy()


class CartPoleIO:
    """CartPoleStayUp and CartPoleContinuous: the observation from the joint readings, and the cart command of an
    action (a discrete action adds its step to the last command, clipped under velocity control; a continuous one
    is ``max_command * clip(a, -1, 1)``)."""

    family = "cartpole"
    observation_size = 4

    def __init__(self, c: dict):
        self.period = _number(c, "period", 1e-6, 60.0)
        self.continuous, self.round_obs = _flag(c, "continuous"), _flag(c, "round_obs")
        self.start = _number(c, "start_command")  # the command an episode starts from (the task's reset)
        self.n_actions = None
        if self.continuous:
            self.max_command = _number(c, "max_command", 0.0)
        else:
            self.steps = _table(c, "steps", None)  # each action's step (the task's ACTION_STEPS)
            self.pos_step = _number(c, "pos_step", 0.0)
            self.n_actions = len(self.steps)
            self.velocity = _flag(c, "velocity")
            self.vmax = _number(c, "vmax", 0.0)

    def observation(self, joints) -> np.ndarray:
        """``[cart_x, cart_v, pole_angle, pole_angular_velocity]`` -> the task's observation
        (:func:`envs.cartpole.rules.observation`)."""
        return observation(np.asarray(joints, np.float64), self.round_obs, np)

    def command(self, action, command: float) -> tuple:
        """``(action as recorded, new cart command)`` after the last ``command``."""
        if self.continuous:
            a = np.reshape(np.asarray(action, np.float64), -1)[:1]
            return a, self.max_command * min(max(float(a[0]), -1.0), 1.0)
        a = int(action)
        return a, command_after(command, float(self.steps[a]), self.pos_step, self.vmax if self.velocity else None,
                                FLOATS)


#: The task families with a robot section, by its ``family``.
TASK_IO = {cls.family: cls for cls in (QuadcopterIO, CartPoleIO)}


def task_io(section: dict):
    """The robot side of ``policy.json``'s ``robot`` section; ``ValueError`` naming the field that is wrong."""
    if not isinstance(section, dict) or section.get("family") not in TASK_IO:
        got = section.get("family") if isinstance(section, dict) else type(section).__name__
        raise ValueError(f"family={got!r}: expected one of {', '.join(TASK_IO)}")
    try:
        return TASK_IO[section["family"]](section)
    except KeyError as err:
        raise ValueError(f"no field {err}") from None


__all__ = ["Policy", "FORMAT", "POLICY_NPZ", "POLICY_JSON", "CartPoleIO", "QuadcopterIO", "TASK_IO", "task_io"]
