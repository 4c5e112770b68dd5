"""ArmReach: move a planar two-joint arm's fingertip to a random goal (openai_ros' reach tasks), by stepping the
set-points of its two position servos.

Environment card
----------------
Robot        :mod:`envs.arm.robot` (``assets/arm.xml``): upper arm 0.5 m and forearm 0.4 m in the horizontal plane,
             shoulder and elbow hinges, each under an MJCF position servo (``kp`` 50 N m/rad); the elbow's
             set-point is clamped to ``[0, 2.8]`` rad (it bends one way).
Actions      ``Discrete(4)``; each moves one joint's set-point by ``joint_step`` (rad): 0 shoulder ``-``,
             1 shoulder ``+``, 2 elbow ``-``, 3 elbow ``+`` (the elbow's clipped to ``[0, 2.8]``). The servos
             track the set-points during the ``running_step`` s of the step.
Observation  ``[elbow (rad), goal_x, goal_y (m)]``: the elbow angle and the goal relative to the fingertip,
             expressed in the upper arm's frame (x along the upper arm). The arm's motion seen in this frame
             depends on the elbow angle only, not on the shoulder's, so three numbers say which action brings
             the fingertip closer. ``goal_x``, ``goal_y`` lie in ``[-1.8, 1.8]`` (goal and fingertip are both
             within 0.9 m of the shoulder); :meth:`ArmReach.state_bounds` gives the discretiser's default ranges,
             ``agents/configs/arm_reach.yaml`` cuts finer bins near 0.
Reward       ``progress_reward`` per m the fingertip-goal distance shrank this step, ``- step_cost`` every step,
             ``+ reach_bonus`` on the step that reaches the goal.
Termination  reached: fingertip-goal distance ``< goal_tolerance`` (``TaskVars.arrived``). There is no failure
             (``TaskVars.crashed`` is always False; it is there so :func:`jaxrobo.task.rollout.success_rate` reads
             the outcome). Truncation at ``max_episode_steps``.
Control      one step holds the set-points for ``running_step`` s (0.1), i.e. ``running_step / timestep``
             physics steps (10).
Reset        shoulder uniform in ``[-pi, pi]``, elbow uniform in ``[elbow_min, elbow_max]``, at rest, set-points
             at the start angles. The goal is the fingertip of a second random pose drawn the same way, so it
             is always reachable; of 8 such candidates the first at least ``min_goal_dist`` from the start
             fingertip is taken (the last if none is).
Learning     target (stated before training): the greedy policy of one tabular Q-learning run reaches the goal
             in >= 80 % of 200 fresh random episodes (``success_rate`` >= 0.8), as the **median** of 8
             independent runs of the ``default`` agent preset (``benchmarks/arm_learning.py``, docs/arm.md).
             Every seed: the preset's alpha 0.05 keeps every run of 64 seeds nobody tuned on above the target.
             The far bins (a goal component beyond +-0.3 m) hold close action values; with a large alpha the
             frozen table keeps two-state loops ("elbow +" on one side of an elbow-sector edge, "elbow -" on
             the other) until the time limit (docs/arm.md, "Learning: every seed reaches the target"). The
             joints' residual motion at a step's end (<= 0.016 rad) is not the cause.
Parameters   see :class:`Options` (static: model and code path) and :class:`Params` (numbers; vmappable).
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from envs.arm.robot import BACKENDS, ELBOW_MAX, FORE, UPPER, ArmRobot, fingertip
from jaxrobo.api import (BaseParams, LearningTarget, TaskEnv, param, pytree_dataclass, randomise, range_param, rng,
                         spaces)

OBS_NAMES = ("elbow", "goal_x", "goal_y")
#: Action ``i`` adds ``ACTION_DELTAS[i] * joint_step`` to the ``[shoulder, elbow]`` set-points.
ACTION_DELTAS = ((-1.0, 0.0), (1.0, 0.0), (0.0, -1.0), (0.0, 1.0))
#: The goal and the fingertip are both within the arm's reach of the shoulder, so each component of their
#: difference is within twice that.
GOAL_BOUND = 2.0 * (UPPER + FORE)
#: Goal candidates drawn per reset (the first far enough from the start fingertip is taken).
GOAL_CANDIDATES = 8


# ---- the task's step, written once over the array module ``xp`` ---------------------------------------------
# ``jax.numpy`` in the env's hooks (traced under jit/vmap), ``numpy`` float64 in the native port
# (``envs/arm/native.py``): one source for the action map, the observation and the success test.
def set_points(command: Any, delta: Any, joint_step: Any, xp: Any = jnp) -> Any:
    """The servo set-points ``[shoulder, elbow]`` after an action: ``delta`` (its row of :data:`ACTION_DELTAS`)
    times ``joint_step`` added, the elbow's clamped to ``[0, ELBOW_MAX]`` (the MJCF's ``ctrlrange``)."""
    command = command + delta * joint_step
    return xp.stack([command[0], xp.clip(command[1], 0.0, ELBOW_MAX)])


def observation(q: Any, goal: Any, xp: Any = jnp) -> Any:
    """``[elbow, goal_x, goal_y]`` (float32): the elbow angle, and the goal relative to the fingertip of pose ``q``
    rotated into the upper arm's frame."""
    d = goal - fingertip(q, xp)
    c, s = xp.cos(q[0]), xp.sin(q[0])
    return xp.stack([q[1], c * d[0] + s * d[1], -s * d[0] + c * d[1]]).astype(xp.float32)


def reached(obs: Any, goal_tolerance: Any, xp: Any = jnp) -> Any:
    """Whether the fingertip is within ``goal_tolerance`` of the goal (the observation's goal offset)."""
    return xp.linalg.norm(obs[1:]) < goal_tolerance


@pytree_dataclass
class Options:
    backend: str = param("mjx", choices=BACKENDS, static=True,
                         doc="physics engine (MJX, a Brax pipeline or the closed form)")
    running_step: float = param(0.1, low=0.0, low_open=True, high=1.0, static=True, unit="s", doc="control period")
    timestep: float = param(0.01, low=0.0, low_open=True, high=0.02, static=True, unit="s",
                            doc="physics step (the servos are stiff: explicit Euler needs <= 0.02 s)")
    randomise: bool = param(False, static=True,
                            doc="domain randomisation: draw the physics (the rand_* ranges) at every reset")


@pytree_dataclass
class Params(BaseParams):
    max_episode_steps: int = param(100, low=1, unit="steps")
    joint_step: float = param(0.1, low=0.0, low_open=True, high=0.5, unit="rad", doc="set-point change per action")
    goal_tolerance: float = param(0.06, low=0.0, low_open=True, high=0.5, unit="m", doc="reached within this")
    elbow_min: float = param(0.3, low=0.0, high=ELBOW_MAX, unit="rad", doc="elbow at reset and in goals, min")
    elbow_max: float = param(2.5, low=0.0, high=ELBOW_MAX, unit="rad", doc="elbow at reset and in goals, max")
    min_goal_dist: float = param(0.2, low=0.0, high=1.8, unit="m", doc="start fingertip-goal distance, min")
    progress_reward: float = param(10.0, low=0.0, high=1e4, unit="1/m", doc="per m closer to the goal")
    step_cost: float = param(0.1, low=0.0, high=1e4, doc="per step")
    reach_bonus: float = param(10.0, low=0.0, high=1e5, doc="on reaching the goal")
    elbow_bound: float = param(ELBOW_MAX, low=0.0, low_open=True, high=3.2, unit="rad",
                               doc="discretiser range of the elbow: [0, elbow_bound]")
    goal_bound: float = param(0.5, low=0.0, low_open=True, high=GOAL_BOUND, unit="m",
                              doc="discretiser range of goal_x, goal_y: +-goal_bound")
    # Domain randomisation (read only with the option randomise=true; docs/randomisation.md).
    rand_link_mass: tuple = range_param((1.0, 1.0), low=0.25, high=4.0, doc="factor on both links' masses")
    rand_damping: tuple = range_param((1.0, 1.0), low=0.0, high=4.0, doc="factor on the joints' damping")
    rand_obs_noise: tuple = randomise.obs_noise_range()


@pytree_dataclass
class TaskVars:
    """Per-episode variables: the servo set-points, the goal, the last distance and how the episode ended."""

    command: jax.Array  # [shoulder, elbow] set-points (rad)
    goal: jax.Array  # (x, y) (m)
    prev_dist: jax.Array  # fingertip-goal distance after the previous step (m)
    arrived: jax.Array
    crashed: jax.Array


class ArmReach(TaskEnv):
    Options = Options
    Params = Params
    #: Learned: most greedy episodes reach their goal (the arrival flag; measured by :func:`success_rate`).
    learning_target = LearningTarget("reaching", "success_rate", 0.8,
                                     "share of greedy episodes reaching the goal >= 0.8 (success_rate)")

    def __init__(self, options: Options | None = None, params: Params | None = None):
        super().__init__(options, params)
        o = self.options
        self.robot = ArmRobot(o.backend, o.running_step, o.timestep)
        randomise.check(self)
        self._deltas = jax.device_put(np.asarray(ACTION_DELTAS, np.float32))  # on the host: no program to compile

    # ---- spaces -----------------------------------------------------------------------------------------
    def action_space(self, params: Params | None = None) -> spaces.Discrete:
        return spaces.Discrete(len(ACTION_DELTAS))

    def observation_space(self, params: Params | None = None) -> spaces.Box:
        # The elbow follows a clamped set-point but may overshoot it a little: no tight bound is declared.
        high = np.array([np.inf, GOAL_BOUND, GOAL_BOUND], np.float32)
        return spaces.Box(-high, high, OBS_NAMES)

    def state_bounds(self, params: Params | None = None) -> tuple[np.ndarray, np.ndarray]:
        p = self.default_params if params is None else params
        elbow, goal = float(p.elbow_bound), float(p.goal_bound)
        return np.array([0.0, -goal, -goal], np.float32), np.array([elbow, goal, goal], np.float32)

    # ---- rendering (optional hooks read by jaxrobo.pictures.render) --------------------------------------------------
    #: The MJCF's camera looking down on the arm's plane.
    render_camera = "top"

    def render_extras(self, state: Any, params: Params) -> list[dict]:
        """The goal (task data, not MJCF): a translucent red sphere of radius ``goal_tolerance``."""
        x, y = (float(v) for v in np.asarray(state.task.goal))
        r = float(np.asarray(params.goal_tolerance))
        return [{"type": "sphere", "size": [r, r, r], "pos": [x, y, 0.0], "rgba": [0.9, 0.1, 0.1, 0.6]}]

    # ---- helpers ----------------------------------------------------------------------------------------
    def _random_pose(self, key: jax.Array, shape: tuple[int, ...], params: Params) -> jax.Array:
        k1, k2 = rng.split(key)
        shoulder = rng.uniform(k1, shape, -jnp.pi, jnp.pi)
        elbow = rng.uniform(k2, shape, params.elbow_min, params.elbow_max)
        return jnp.stack([shoulder, elbow], axis=-1)

    # ---- the seed's hooks -------------------------------------------------------------------------------
    def _set_init_pose(self, key: jax.Array, params: Params) -> tuple[jax.Array, jax.Array]:
        return self.robot.init_pose(self._random_pose(key, (), params))

    def _init_env_variables(self, key: jax.Array, pipeline_state: Any, params: Params) -> TaskVars:
        q = self.robot.joint_angles(pipeline_state)
        tip = fingertip(q)
        goals = fingertip(self._random_pose(key, (GOAL_CANDIDATES,), params))
        far = jnp.linalg.norm(goals - tip, axis=-1) >= params.min_goal_dist
        goal = goals[jnp.where(jnp.any(far), jnp.argmax(far), GOAL_CANDIDATES - 1)]
        false = jnp.zeros((), bool)
        return TaskVars(q.astype(jnp.float32), goal.astype(jnp.float32),
                        jnp.linalg.norm(goal - tip).astype(jnp.float32), false, false)

    def _set_action(self, action: jax.Array, task: TaskVars, params: Params) -> tuple[jax.Array, TaskVars]:
        command = set_points(task.command, self._deltas[action], params.joint_step)
        return command, task.replace(command=command)

    def _get_obs(self, pipeline_state: Any, task: TaskVars, params: Params) -> jax.Array:
        return observation(self.robot.joint_angles(pipeline_state), task.goal)

    def _is_done(self, obs: jax.Array, pipeline_state: Any, task: TaskVars, params: Params) -> jax.Array:
        return reached(obs, params.goal_tolerance)

    def _compute_reward(self, obs, done, action, pipeline_state, task, params) -> tuple[jax.Array, TaskVars]:
        dist = jnp.linalg.norm(obs[1:])
        reward = params.progress_reward * (task.prev_dist - dist) - params.step_cost + \
            jnp.where(done, params.reach_bonus, 0.0)
        return reward.astype(jnp.float32), task.replace(prev_dist=dist, arrived=done)
