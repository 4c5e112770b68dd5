"""``jaxrobo check``: the shipped envs pass, and envs broken in each of the ways the checker knows fail with a
message naming the problem (built by subclassing CartPoleStayUp on its analytic backend, fast to compile)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrobo
from envs.cartpole.stay_up import CartPoleStayUp
from jaxrobo.core import spaces
from jaxrobo.check import check_env
from jaxrobo.cli import main

# The checks a broken env is run through (the MJX and Gymnasium ones are for shipped ids, below).
FAST = ("spaces", "actions", "trace", "carry", "pure", "jit_vmap", "reset_keys", "rollout", "nan_guard")


def _make(cls):
    base = jaxrobo.make("CartPoleStayUp-v0", backend="analytic")
    return cls(base.options, base.default_params)


def _failures(cls) -> dict[str, str]:
    return {r.name: r.message for r in check_env(_make(cls), quick=True, checks=FAST) if not r.ok}


def test_the_analytic_cartpole_passes_every_fast_check():
    results = check_env(_make(CartPoleStayUp), quick=True, checks=FAST)
    assert [r.name for r in results] == list(FAST)
    assert all(r.status == "ok" for r in results), [r.line() for r in results]


_COUNTER = [0]


class GlobalCounterReward(CartPoleStayUp):
    def _compute_reward(self, obs, done, action, pipeline_state, task, params):
        _COUNTER[0] += 1
        return jnp.asarray(float(_COUNTER[0] % 3), jnp.float32), task


class NumpyRandomReset(CartPoleStayUp):
    def _set_init_pose(self, key, params):
        noise = np.random.uniform(-0.05, 0.05, 4)
        return self.robot.init_pose(noise[0], noise[2], noise[1], noise[3])


class PythonBranchDone(CartPoleStayUp):
    def _is_done(self, obs, pipeline_state, task, params):
        if obs[2] > params.max_pole_angle:  # a Python branch on a traced value
            return jnp.bool_(True)
        return jnp.bool_(False)


class Float64Obs(CartPoleStayUp):
    def _get_obs(self, pipeline_state, task, params):
        return np.asarray(super()._get_obs(pipeline_state, task, params), np.float64)


class IntObs(CartPoleStayUp):
    def _get_obs(self, pipeline_state, task, params):
        return super()._get_obs(pipeline_state, task, params).astype(jnp.int32)


class TightObsBounds(CartPoleStayUp):
    def observation_space(self, params=None):
        return spaces.Box(np.full(4, -1e-3, np.float32), np.full(4, 1e-3, np.float32))


class CachedReset(CartPoleStayUp):
    _pose = None

    def _set_init_pose(self, key, params):
        if self._pose is None:
            self._pose = super()._set_init_pose(key, params)
        return self._pose


class NanObs(CartPoleStayUp):
    def _get_obs(self, pipeline_state, task, params):
        return super()._get_obs(pipeline_state, task, params).at[3].set(jnp.nan)


class TooManyActions(CartPoleStayUp):
    def action_space(self, params=None):
        return spaces.Discrete(6)  # _set_action knows 4: indices 4 and 5 clamp to action 3


class BoxActions(CartPoleStayUp):
    def action_space(self, params=None):
        return spaces.Box(np.full(1, -1.0, np.float32), np.full(1, 1.0, np.float32))


class LateTruncation(CartPoleStayUp):
    def step(self, state, action, params=None):
        out = super().step(state, action, params)
        return out.replace(truncated=out.steps >= 10_000)


@pytest.mark.parametrize("cls,check,words", [
    (GlobalCounterReward, "pure", ["_compute_reward", "same inputs"]),
    (NumpyRandomReset, "pure", ["_set_init_pose", "same inputs"]),
    (PythonBranchDone, "trace", ["Python control flow", "_is_done", "jit(step)"]),
    (Float64Obs, "spaces", ["_get_obs", "float64", "float32"]),
    (IntObs, "spaces", ["_get_obs", "int32", "float32"]),
    (TightObsBounds, "rollout", ["outside observation_space()"]),
    (CachedReset, "reset_keys", ["_set_init_pose", "distinct", "cached"]),
    (NanObs, "rollout", ["_get_obs", "non-finite observation"]),
    (TooManyActions, "actions", ["_set_action", "Discrete(6)", "same command"]),
    (BoxActions, "spaces", ["Box", "Discrete"]),
    (LateTruncation, "rollout", ["truncated", "max_episode_steps"]),
])
@pytest.mark.slow
def test_a_broken_env_fails_with_a_message_naming_the_problem(cls, check, words):
    failures = _failures(cls)
    assert check in failures, f"{cls.__name__}: expected {check} to fail; failures: {failures}"
    for word in words:
        assert word in failures[check], f"{cls.__name__}: {word!r} not in {failures[check]!r}"


class IgnoredTwistDimension:
    """A continuous task that declares a 4-D Twist but drops yaw_rate (built lazily: the class imports the task)."""

    @staticmethod
    def make():
        from envs.quadcopter.goto_twist import QuadcopterGotoTwist

        class Ignored(QuadcopterGotoTwist):
            def _set_action(self, action, task, params):
                command, task = super()._set_action(action, task, params)
                return command.at[3].set(0.0), task

        base = jaxrobo.make("QuadcopterGotoTwist-v0")
        return Ignored(base.options, base.default_params)


def test_continuous_task_checks_each_action_dimension():
    """A Box task is accepted when it declares continuous actions, and a dimension it ignores fails ``actions``."""
    results = {r.name: r for r in check_env(IgnoredTwistDimension.make(), quick=True, checks=("spaces", "actions"))}
    assert results["spaces"].status == "ok" and "Box(4,)" in results["spaces"].message
    assert results["actions"].status == "FAIL"
    assert "yaw_rate" in results["actions"].message and "_set_action" in results["actions"].message


def test_numpy_random_reset_also_fails_the_key_check():
    """Without the purity check in front, the key check still sees a reset that does not follow its key."""
    results = {r.name: r for r in check_env(_make(NumpyRandomReset), quick=True, checks=("spaces", "reset_keys"))}
    assert results["reset_keys"].status == "FAIL" and "numpy" in results["reset_keys"].message


def test_a_deterministic_reset_passes_the_key_check():
    base = jaxrobo.make("CartPoleStayUp-v0", backend="analytic", init_noise=0.0)
    (result,) = check_env(base, checks=("reset_keys",))
    assert result.status == "ok" and "deterministic" in result.message


#: Ids whose quick check runs through ``jaxrobo check ID --quick`` in another test (the same checks, the same
#: compiles): the test below leaves them to it rather than compile them twice.
CHECKED_BY_THE_CLI = {"QuadcopterLiveShow-v0": "test_cli_check_prints_one_line_per_check_and_exits_by_result",
                      "ArmReach-v0": "tests/test_arm_reach.py::test_jaxrobo_check_quick_passes"}


@pytest.mark.slow
@pytest.mark.parametrize("env_id", [i for i in jaxrobo.registered() if i not in CHECKED_BY_THE_CLI])
def test_every_shipped_id_passes_quick(env_id, capsys):
    # MJX compiles are slow on a CPU: the cart-pole ids run on the analytic backend (same task code and model);
    # the CLI test below runs one MJX id end to end.
    backend = {"backend": "analytic"} if env_id.startswith("CartPole") else {}
    results = check_env(env_id, quick=True, checks=FAST, **backend)
    assert all(r.ok for r in results), [r.line() for r in results]


def test_the_ids_left_to_the_cli_are_shipped_ids():
    assert set(CHECKED_BY_THE_CLI) <= set(jaxrobo.registered())


def test_cli_check_prints_one_line_per_check_and_exits_by_result(capsys):
    assert main(["check", "QuadcopterLiveShow-v0", "--quick"]) == 0
    out = capsys.readouterr().out
    assert "ok   spaces" in out and "skip gymnasium   --quick" in out and "all 12 checks pass" in out
    assert main(["check", "NoSuchEnv-v0"]) == 2
    assert "NoSuchEnv-v0" in capsys.readouterr().err


def test_gymnasium_and_mjx_checks_on_a_made_env():
    """The two slow checks, on the analytic cart-pole: Gymnasium's check_env runs through the adapter; the MJX
    comparison skips with its reason."""
    results = {r.name: r for r in check_env(_make(CartPoleStayUp), checks=("gymnasium", "mjx_native"))}
    assert results["gymnasium"].status == "ok", results["gymnasium"].message
    assert results["mjx_native"].status == "skip" and "analytic" in results["mjx_native"].message


# ---- the carry's types and the long rollout ----------------------------------------------------------------------
class CountsInFloat(CartPoleStayUp):
    """A task variable reset as int32 that _compute_reward turns into float32."""

    def _init_env_variables(self, key, pipeline_state, params):
        return {"base": super()._init_env_variables(key, pipeline_state, params), "n": jnp.int32(0)}

    def _set_action(self, action, task, params):
        command, base = super()._set_action(action, task["base"], params)
        return command, {**task, "base": base}

    def _compute_reward(self, obs, done, action, pipeline_state, task, params):
        return jnp.ones((), jnp.float32), {**task, "n": task["n"] + 0.5}


class CommandGrowsAShape(CartPoleStayUp):
    """_set_action returns the command variable as shape (1,) where reset made it a scalar."""

    def _set_action(self, action, task, params):
        command, task = super()._set_action(action, task, params)
        return command, task.replace(command=jnp.reshape(task.command, (1,)))


class EnergyBlowsUp(CartPoleStayUp):
    """A task variable that grows tenfold each step: finite (float32 holds 1e38) but far out of any sane range."""

    def _init_env_variables(self, key, pipeline_state, params):
        return {"base": super()._init_env_variables(key, pipeline_state, params), "energy": jnp.float32(1.0)}

    def _set_action(self, action, task, params):
        command, base = super()._set_action(action, task["base"], params)
        return command, {"base": base, "energy": task["energy"] * 10.0}


def test_a_carry_type_change_names_the_hook_and_the_field():
    results = {r.name: r for r in check_env(_make(CountsInFloat), quick=True, checks=FAST[:4] + ("rollout",))}
    carry = results["carry"]
    assert carry.status == "FAIL"
    assert carry.message.startswith("_compute_reward: state.task['n'] changes from int32[] to float32[] over a step")
    assert results["rollout"].status == "skip" and results["rollout"].message == "needs carry to pass"
    (shape,) = check_env(_make(CommandGrowsAShape), checks=("carry",))
    assert shape.status == "FAIL" and shape.message.startswith(
        "_set_action: state.task.command changes from float32[] to float32[1] over a step"), shape.message


def test_long_rollout_flags_a_finite_but_huge_state_and_passes_a_sound_one(capsys):
    (blown,) = check_env(_make(EnergyBlowsUp), checks=("long",), long=200)
    assert blown.status == "FAIL" and blown.message.startswith(
        "state.task['energy'] passed |x| > 1e+06 at step 7 of env 0 and reached "), blown.message
    assert "NaN guard lets it through" in blown.message
    (sound,) = check_env(_make(CartPoleStayUp), checks=("long",), long=300)
    assert sound.status == "ok" and sound.message.startswith("4 envs x 300 steps: every float within 1e+06")
    (skipped,) = check_env(_make(CartPoleStayUp), checks=("long",))
    assert skipped.status == "skip" and "--long N" in skipped.message
    from jaxrobo.core.config import ConfigError

    with pytest.raises(ConfigError, match=r"long=-1: expected an integer >= 0"):
        check_env(_make(CartPoleStayUp), long=-1)
    assert main(["check", "CartPoleStayUp-v0", "--long", "-5"]) == 2
    assert "long=-5" in capsys.readouterr().err
