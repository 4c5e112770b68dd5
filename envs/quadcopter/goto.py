"""QuadcopterGoto: the seed's homework done - random goals, obstacles in the way, a sonar, a discretisable state.

Environment card
----------------
Actions      ``Discrete(5)``, the seed's Twist at ``speed_value`` held for ``running_step`` s (as in
             :mod:`envs.quadcopter.live_show`): 0 forward, 1 turn left, 2 turn right, 3 up, 4 down.
Observation  ``[goal_dist (m, 3-D), goal_bearing (rad, goal direction relative to the heading, + = left),
             goal_dz (m, goal altitude - altitude), sonar_forward, sonar_left, sonar_right (m, level rays at 0
             and ±35° from the heading, to obstacles or the ground, clipped to sonar_range), sonar_down (m,
             altitude above ground)]``. :meth:`QuadcopterGoto.state_bounds` gives the ranges a uniform ``bins``
             discretiser cuts (``agents/configs/quadcopter_goto.yaml`` picks the bins per dimension).
Reward       ``progress_reward`` per m the goal distance shrank this step, ``- step_cost``, ``- altitude_cost``
             per m of altitude (the seed's "fly as low as possible"), ``+ arrival_bonus`` on arrival,
             ``- crash_penalty`` on a crash, leaving the workspace or breaking an altitude/inclination limit.
Termination  arrival (goal distance < ``goal_tolerance``); crash: the drone, a sphere of ``drone_radius``,
             touches the ground or an obstacle (exact geometry); |x| or |y| > ``workspace``; altitude >
             ``max_altitude``; |roll| or |pitch| >= ``max_incl``. Truncation at ``max_episode_steps``.
Reset        hovering at ``(0, 0, init_z)`` with a uniformly random heading; the goal at a uniformly random
             direction and horizontal distance in ``[goal_min_dist, goal_max_dist]``, altitude in
             ``[goal_z_min, goal_z_max]``; ``n_obstacles`` obstacles (``obstacle_kind``: vertical cylinders of
             radius ``obstacle_size``, boxes of half-width ``obstacle_size``, or a random mix), all
             ``obstacle_height`` tall (taller than ``max_altitude``: the drone must go round them), placed
             ``between`` start and goal (at a random fraction ``[obstacle_t_min, obstacle_t_max]`` of the way,
             shifted sideways by up to ``obstacle_lateral``) or ``random``ly in the workspace (kept
             ``obstacle_clearance`` clear of the start and the goal).
Success      ``TaskVars.arrived``; :func:`jaxrobo.task.rollout.success_rate` measures it for greedy or random policies.
Parameters   see :class:`Options` (static) and :class:`Params` (numbers; vmappable).
"""
from __future__ import annotations

from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from envs.quadcopter import goto_step
from envs.quadcopter.geometry import BOX, CYLINDER
from envs.quadcopter.goto_step import V1_PARAMS, V2_PARAMS, kinds_of
from envs.quadcopter.host import HostGoto
from envs.quadcopter.robot import Obstacles, QuadcopterOptions, QuadcopterTask, fold_obstacles, twist_command
from envs.quadcopter.goto_kernel import kernel_step, make_task_step, supports
from jaxrobo.api import (BaseParams, EnvState, LearningTarget, param, pytree_dataclass, randomise, range_param, rng,
                         spaces)

OBS_NAMES = ("goal_dist", "goal_bearing", "goal_dz", "sonar_forward", "sonar_left", "sonar_right", "sonar_down")


@pytree_dataclass
class Options(QuadcopterOptions):
    n_obstacles: int = param(1, low=0, high=32, static=True, doc="obstacles per episode")
    obstacle_kind: str = param("cylinder", choices=("cylinder", "box", "mixed"), static=True)
    obstacle_placement: str = param("between", choices=("between", "random"), static=True)


@pytree_dataclass
class Params(BaseParams):
    max_episode_steps: int = param(100, low=1, unit="steps")
    speed_value: float = param(1.0, low=0.0, low_open=True, high=5.0, unit="m/s or rad/s", doc="Twist magnitude")
    init_z: float = param(1.0, low=0.0, high=10.0, unit="m", doc="start altitude")
    goal_min_dist: float = param(3.0, low=0.0, high=100.0, unit="m", doc="horizontal start-goal distance, min")
    goal_max_dist: float = param(6.0, low=0.0, high=100.0, unit="m", doc="horizontal start-goal distance, max")
    goal_z_min: float = param(0.5, low=0.0, high=10.0, unit="m")
    goal_z_max: float = param(1.5, low=0.0, high=10.0, unit="m")
    goal_tolerance: float = param(0.5, low=0.0, low_open=True, high=10.0, unit="m", doc="arrival radius")
    workspace: float = param(8.0, low=0.0, low_open=True, high=1000.0, unit="m", doc="|x|, |y| limit")
    max_altitude: float = param(2.0, low=0.0, low_open=True, high=100.0, unit="m")
    max_incl: float = param(0.7, low=0.0, low_open=True, high=1.6, unit="rad", doc="roll/pitch limit")
    drone_radius: float = param(0.25, low=0.0, high=2.0, unit="m", doc="crash sphere")
    obstacle_size: float = param(0.4, low=0.0, high=10.0, unit="m", doc="cylinder radius / box half-width")
    obstacle_height: float = param(3.0, low=0.0, high=100.0, unit="m",
                                   doc="taller than max_altitude: the drone must go round, not over")
    obstacle_t_min: float = param(0.35, low=0.0, high=1.0, doc="'between': fraction of the way, min")
    obstacle_t_max: float = param(0.65, low=0.0, high=1.0, doc="'between': fraction of the way, max")
    obstacle_lateral: float = param(0.5, low=0.0, high=100.0, unit="m", doc="'between': sideways shift, max")
    obstacle_clearance: float = param(1.0, low=0.0, high=100.0, unit="m", doc="'random': free radius at start/goal")
    sonar_range: float = param(4.0, low=0.0, low_open=True, high=100.0, unit="m")
    progress_reward: float = param(10.0, low=0.0, high=1e4, unit="1/m", doc="per m closer to the goal")
    step_cost: float = param(2.0, low=0.0, high=1e4,
                             doc="per step: makes dithering loops worse than trying (greedy policies loop otherwise)")
    altitude_cost: float = param(0.5, low=0.0, high=1e4, unit="1/m",
                                 doc="per step and metre of altitude: the seed's 'fly as low as possible'")
    arrival_bonus: float = param(100.0, low=0.0, high=1e5)
    crash_penalty: float = param(50.0, low=0.0, high=1e5)
    dist_bound: float = param(3.0, low=0.0, low_open=True, high=100.0, unit="m", doc="discretiser range, distance")
    dz_bound: float = param(0.75, low=0.0, low_open=True, high=10.0, unit="m", doc="discretiser range, ±goal_dz")
    sonar_bound: float = param(3.0, low=0.0, low_open=True, high=100.0, unit="m", doc="discretiser range, sonars")
    down_bound: float = param(1.2, low=0.0, low_open=True, high=100.0, unit="m", doc="discretiser range, altitude")
    # Domain randomisation (read only with the option randomise=true; docs/randomisation.md).
    rand_mass: tuple = range_param((1.0, 1.0), low=0.25, high=4.0, doc="factor on the airframe's mass and inertia")
    rand_motor_gain: tuple = range_param((1.0, 1.0), low=0.25, high=4.0,
                                         doc="factor on every rotor's thrust and reaction torque")
    rand_wind: tuple = range_param((0.0, 0.0), low=0.0, high=5.0, unit="N",
                                   doc="constant horizontal force on the drone, random direction")
    rand_obs_noise: tuple = randomise.obs_noise_range()


@pytree_dataclass
class TaskVars:
    """Per-episode variables: start, goal, obstacles, last goal distance and how the episode ended."""

    start: jax.Array
    goal: jax.Array
    obstacles: Obstacles
    prev_dist: jax.Array
    arrived: jax.Array
    crashed: jax.Array


class QuadcopterGoto(QuadcopterTask):
    Options = Options
    Params = Params
    #: Learned: most greedy flights arrive (the arrival flag; measured by :func:`success_rate`).
    learning_target = LearningTarget("arriving", "success_rate", 0.8,
                                     "share of greedy episodes arriving at the goal >= 0.8 (success_rate)")
    #: Which of :mod:`envs.quadcopter.goto_kernel`'s task kernels holds this class's hooks (a subclass that
    #: overrides one of them gets none).
    step_kernel_variant: ClassVar[str | None] = "v1"
    #: v2's observation (``goal_clear``, ``goal_dz`` with its lead) and reward (the shaping terms), as
    #: :mod:`envs.quadcopter.goto_step` writes them.
    v2: ClassVar[bool] = False
    #: One env's step on the host without JAX (``gymnasium.make(..., engine="numpy")``): the same goto_step
    #: functions on Python floats (:mod:`envs.quadcopter.host`).
    host_step = HostGoto

    def __init__(self, options: Any = None, params: Any = None):
        super().__init__(options, params)
        #: The whole step (action, control step, observation, outcome, reward, NaN guard) over a batch as one
        #: Pallas kernel, which ``ExecutionPlan(fused="pallas", task_kernel=True)`` runs; None where the task's
        #: configuration has none (:func:`envs.quadcopter.goto_kernel.supports`).
        self.step_kernel_refusal = supports(self)
        self.step_kernel = make_task_step(self) if self.step_kernel_refusal is None else None

    def _kernel_step(self, state: EnvState, action: jax.Array, params: Params) -> EnvState:
        """The step as one kernel over the batch (:func:`envs.quadcopter.goto_kernel.kernel_step`, equal to the
        hooks' step to float32 round-off)."""
        return kernel_step(self, state, action, params)

    def observation_space(self, params: Params | None = None) -> spaces.Box:
        n = len(OBS_NAMES)
        return spaces.Box(np.full(n, -np.inf, np.float32), np.full(n, np.inf, np.float32), OBS_NAMES)

    def state_bounds(self, params: Params | None = None) -> tuple[np.ndarray, np.ndarray]:
        p = self.default_params if params is None else params
        dist, dz, sonar, down = (float(b) for b in (p.dist_bound, p.dz_bound, p.sonar_bound, p.down_bound))
        return (np.array([0.0, -np.pi, -dz, 0.0, 0.0, 0.0, 0.0], np.float32),
                np.array([dist, np.pi, dz, sonar, sonar, sonar, down], np.float32))

    # ---- episode layout ---------------------------------------------------------------------------------
    def _obstacles(self, key: jax.Array, start: jax.Array, goal: jax.Array, params: Params) -> Obstacles:
        o, n = self.options, self.options.n_obstacles
        if n == 0:
            return Obstacles.empty()
        k_t, k_lat, k_kind, k_xy = rng.split(key, 4)
        if o.obstacle_placement == "between":
            t = rng.uniform(k_t, (n,), params.obstacle_t_min, params.obstacle_t_max)
            lat = rng.uniform(k_lat, (n,), -params.obstacle_lateral, params.obstacle_lateral)
            d = goal[:2] - start[:2]
            side = jnp.stack([-d[1], d[0]]) / jnp.maximum(jnp.linalg.norm(d), 1e-6)
            xy = start[:2] + t[:, None] * d + lat[:, None] * side
        else:  # random: 16 candidates each, the first clear of start and goal (else the last)
            cand = rng.uniform(k_xy, (n, 16, 2), -params.workspace, params.workspace)
            free = params.obstacle_clearance + params.obstacle_size * np.sqrt(2.0)
            ok = ((jnp.linalg.norm(cand - start[:2], axis=-1) > free)
                  & (jnp.linalg.norm(cand - goal[:2], axis=-1) > free))
            idx = jnp.where(jnp.any(ok, axis=1), jnp.argmax(ok, axis=1), 15)
            xy = jnp.take_along_axis(cand, idx[:, None, None], axis=1)[:, 0]
        if o.obstacle_kind == "cylinder":
            kind = jnp.full((n,), CYLINDER, jnp.int32)
        elif o.obstacle_kind == "box":
            kind = jnp.full((n,), BOX, jnp.int32)
        else:
            kind = jax.random.randint(k_kind, (n,), 0, 2).astype(jnp.int32)
        half_h = 0.5 * params.obstacle_height
        center = jnp.concatenate([xy, jnp.full((n, 1), half_h)], axis=1)
        size = jnp.broadcast_to(jnp.stack([params.obstacle_size, params.obstacle_size, half_h]), (n, 3))
        return Obstacles(kind, center.astype(jnp.float32), size.astype(jnp.float32), jnp.ones(n, bool))

    # ---- the seed's hooks -------------------------------------------------------------------------------
    def _set_init_pose(self, key: jax.Array, params: Params) -> tuple[jax.Array, jax.Array]:
        yaw = rng.uniform(key, (), -jnp.pi, jnp.pi)
        return self.robot.init_pose(jnp.stack([0.0, 0.0, params.init_z]), yaw)

    def _init_env_variables(self, key: jax.Array, pipeline_state: Any, params: Params) -> TaskVars:
        k_dir, k_dist, k_z, k_obs = rng.split(key, 4)
        start = self.robot.read_sensors(pipeline_state)["pos"]
        heading = rng.uniform(k_dir, (), -jnp.pi, jnp.pi)
        dist = rng.uniform(k_dist, (), params.goal_min_dist, params.goal_max_dist)
        z = rng.uniform(k_z, (), params.goal_z_min, params.goal_z_max)
        goal = jnp.stack([start[0] + dist * jnp.cos(heading), start[1] + dist * jnp.sin(heading), z])
        obstacles = self._obstacles(k_obs, start, goal, params)
        false = jnp.zeros((), bool)
        return TaskVars(start, goal.astype(jnp.float32), obstacles, jnp.linalg.norm(goal - start), false, false)

    def _set_action(self, action: jax.Array, task: TaskVars, params: Params) -> tuple[jax.Array, TaskVars]:
        return twist_command(action, params.speed_value), task

    def _p(self, params: Params) -> dict:
        return {name: getattr(params, name) for name in (V2_PARAMS if self.v2 else V1_PARAMS)}

    def _observe(self, pipeline_state: Any, task: TaskVars, params: Params) -> tuple:
        """``(sensors, obs, goal distance, nearest obstacle surface)``: :func:`envs.quadcopter.goto_step.observe`
        on the robot's readings, folding over the obstacles with :func:`envs.quadcopter.robot.fold_obstacles`."""
        s = self.robot.read_sensors(pipeline_state)
        pos, goal = [s["pos"][i] for i in range(3)], [task.goal[i] for i in range(3)]
        obs, dist, point = goto_step.observe(
            jnp, pos, s["rpy"][2], s["vel"][2], goal, self._p(params), self.v2, kinds_of(self.options.obstacle_kind),
            lambda distances, init: fold_obstacles(task.obstacles, distances, init))
        return s, obs, dist, point

    def _get_obs(self, pipeline_state: Any, task: TaskVars, params: Params) -> jax.Array:
        return jnp.stack(self._observe(pipeline_state, task, params)[1]).astype(jnp.float32)

    def _outcome(self, pipeline_state: Any, task: TaskVars, params: Params) -> tuple[jax.Array, jax.Array]:
        """``(arrived, failed)``: failed = crash, out of the workspace, or an altitude/inclination limit."""
        s, _, dist, point = self._observe(pipeline_state, task, params)
        pos, rpy = s["pos"], s["rpy"]
        return goto_step.outcome(jnp, [pos[i] for i in range(3)], rpy[0], rpy[1], dist, point, self._p(params))

    def _is_done(self, obs: jax.Array, pipeline_state: Any, task: TaskVars, params: Params) -> jax.Array:
        arrived, failed = self._outcome(pipeline_state, task, params)
        return arrived | failed

    def _compute_reward(self, obs, done, action, pipeline_state, task, params) -> tuple[jax.Array, TaskVars]:
        arrived, failed = self._outcome(pipeline_state, task, params)
        z = self.robot.read_sensors(pipeline_state)["pos"][2]
        names = ("prev_dist", "arrived", "crashed") + (("prev_bearing", "prev_dz") if self.v2 else ())
        reward, changes = goto_step.reward(jnp, self._p(params), {n: getattr(task, n) for n in names},
                                           [obs[i] for i in range(3)], obs[0], z, arrived, failed, self.v2)
        return reward.astype(jnp.float32), task.replace(**changes)


__all__ = ["QuadcopterGoto", "Options", "Params", "TaskVars", "EnvState"]
