"""Offscreen rendering: frames of states, the task geometry hook, the Gymnasium render modes, episode videos.

Needs an offscreen OpenGL (``MUJOCO_GL=egl`` or ``osmesa``; scripts/test.sh sets osmesa and .ci/run installs
libosmesa6). Where none can be had the tests skip, naming the reason.
"""
from __future__ import annotations

import os

import jax
import numpy as np
import pytest

import jaxrobo
from jaxrobo import render
from jaxrobo.gym_adapter import JaxroboEnv, JaxroboVectorEnv
from jaxrobo.wrappers import Wrapper

_REASON = render.gl_unavailable_reason()
pytestmark = pytest.mark.skipif(_REASON is not None, reason=str(_REASON))


@pytest.fixture(scope="module")
def cartpole_env():
    env = JaxroboEnv("CartPoleStayUpLeftRight-v0", render_mode="rgb_array", width=160, height=120)
    yield env
    env.close()


def test_rgb_array_frame(cartpole_env):
    cartpole_env.reset(seed=0)
    frame = cartpole_env.render()
    assert frame.shape == (120, 160, 3) and frame.dtype == np.uint8
    assert frame.std() > 1.0  # something was drawn
    for _ in range(15):
        cartpole_env.step(1)
    moved = cartpole_env.render()
    assert not np.array_equal(frame, moved)  # the frame follows the state


def test_render_extras_hook_draws_task_geometry(cartpole_env):
    """A task may add geometry that is data, not MJCF (goals, obstacles), through ``render_extras``."""

    class WithGoal(Wrapper):
        def render_extras(self, state, params):
            assert isinstance(np.asarray(state.obs), np.ndarray)
            return [{"type": "sphere", "size": [0.4, 0, 0], "pos": [0.0, -1.0, 0.6], "rgba": [1, 0, 0, 1]}]

    cartpole_env.reset(seed=0)
    state = cartpole_env.state
    inner = cartpole_env.jax_env
    plain = render.render_frame(inner, state, 160, 120)
    marked = render.render_frame(WithGoal(inner), state, 160, 120)
    red = (marked[..., 0].astype(int) - marked[..., 1].astype(int) > 100).sum()
    red_before = (plain[..., 0].astype(int) - plain[..., 1].astype(int) > 100).sum()
    assert red > red_before + 100


def test_cameras_and_bad_camera():
    env = jaxrobo.make("CartPoleStayUpLeftRight-v0")
    state = jax.jit(env.reset)(jax.random.key(0))
    tracked = render.render_frame(env, state, 64, 48, camera="track")
    assert tracked.shape == (48, 64, 3)
    with pytest.raises(ValueError, match="cameras"):
        render.Renderer(env, 64, 48, camera="nope")


def test_vector_env_renders_one_frame_per_env():
    venv = JaxroboVectorEnv("CartPoleStayUpLeftRight-v0", num_envs=3, render_mode="rgb_array", width=64, height=48)
    venv.reset(seed=0)
    frames = venv.render()
    assert len(frames) == 3 and all(f.shape == (48, 64, 3) and f.dtype == np.uint8 for f in frames)
    venv.close()


@pytest.mark.parametrize("env_id", jaxrobo.registered())
def test_every_registered_env_renders(env_id):
    from jaxrobo.gym_adapter import compiled_for

    module = jaxrobo.registry._lookup(env_id).entry_point.partition(":")[0]
    try:
        env = jaxrobo.make(env_id)
    except ModuleNotFoundError as err:
        if err.name == module:
            pytest.skip(f"{env_id}: task module {module} is not there yet")
        raise
    state, _ = compiled_for(env).reset(jax.random.key(0), env.default_params)  # the adapter's compiled reset
    frame = render.render_frame(env, state, 96, 72)
    assert frame.shape == (72, 96, 3) and frame.dtype == np.uint8 and frame.std() > 1.0


def test_record_episode_writes_a_gif(tmp_path):
    pytest.importorskip("imageio", reason="imageio (the test extra) writes the GIF")
    import imageio.v2 as imageio

    env = jaxrobo.make("CartPoleStayUpLeftRight-v0")
    out = render.record_episode(env, str(tmp_path / "episode.gif"), policy=lambda obs: int(obs[2] > 0),
                                seed=1, max_steps=8, width=64, height=48)
    assert os.path.exists(out["path"]) and out["frames"] == out["length"] + 1 <= 9
    frames = imageio.mimread(out["path"])
    assert len(frames) == out["frames"] and frames[0].shape[:2] == (48, 64)
    with pytest.raises(ValueError, match="gif or .mp4"):
        render.write_video(str(tmp_path / "x.avi2"), [np.zeros((4, 4, 3), np.uint8)])
