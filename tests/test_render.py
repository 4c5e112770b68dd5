"""Offscreen rendering: frames of states, the task geometry hook, the Gymnasium render modes, episode videos,
and the choice of OpenGL backend.

Drawing needs an offscreen OpenGL (EGL or OSMesa; ``import jaxrobo`` picks one whose library loads, and
.ci/run installs libosmesa6). Where none can be had the drawing tests skip, naming the reason; the tests of
the backend choice run everywhere.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys

import jax
import numpy as np
import pytest

import jaxrobo
from jaxrobo.pictures import render
from jaxrobo.interop.gym_adapter import JaxroboEnv, JaxroboVectorEnv
from jaxrobo.task.wrappers import Wrapper

_REASON = render.gl_unavailable_reason()
needs_gl = pytest.mark.skipif(_REASON is not None, reason=str(_REASON))
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def cartpole_env():
    env = JaxroboEnv("CartPoleStayUpLeftRight-v0", render_mode="rgb_array", width=160, height=120)
    yield env
    env.close()


@needs_gl
def test_rgb_array_frame(cartpole_env):
    cartpole_env.reset(seed=0)
    frame = cartpole_env.render()
    assert frame.shape == (120, 160, 3) and frame.dtype == np.uint8
    assert frame.std() > 1.0  # something was drawn
    for _ in range(15):
        cartpole_env.step(1)
    moved = cartpole_env.render()
    assert not np.array_equal(frame, moved)  # the frame follows the state


@needs_gl
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


@needs_gl
def test_cameras_and_bad_camera():
    env = jaxrobo.make("CartPoleStayUpLeftRight-v0")
    state = jax.jit(env.reset)(jax.random.key(0))
    tracked = render.render_frame(env, state, 64, 48, camera="track")
    assert tracked.shape == (48, 64, 3)
    with pytest.raises(ValueError, match="cameras"):
        render.Renderer(env, 64, 48, camera="nope")


@needs_gl
def test_vector_env_renders_one_frame_per_env():
    venv = JaxroboVectorEnv("CartPoleStayUpLeftRight-v0", num_envs=3, render_mode="rgb_array", width=64, height=48)
    venv.reset(seed=0)
    for _ in range(15):  # the carts driven apart: env 0 left, env 1 right, env 2 back and forth
        venv.step(np.array([0, 1, _ % 2]))
    frames = venv.render()
    assert len(frames) == 3 and all(f.shape == (48, 64, 3) and f.dtype == np.uint8 for f in frames)
    host = jax.device_get(venv.states)
    for i, frame in enumerate(frames):  # each frame is its own env's state, drawn
        own = render.render_frame(venv.jax_env, jax.tree.map(lambda x: x[i], host), 64, 48, params=venv.params)
        assert np.array_equal(frame, own), i
    assert not np.array_equal(frames[0], frames[1])
    venv.close()


@needs_gl
@pytest.mark.parametrize("env_id", jaxrobo.registered())
def test_every_registered_env_renders(env_id):
    from jaxrobo.speed.compiled import compiled_for

    env = jaxrobo.make(env_id)  # a registered id whose task module is missing fails here
    state, _ = compiled_for(env).reset(jax.random.key(0), env.default_params)  # the adapter's compiled reset
    frame = render.render_frame(env, state, 96, 72)
    assert frame.shape == (72, 96, 3) and frame.dtype == np.uint8 and frame.std() > 1.0


@needs_gl
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


# -- choice of OpenGL backend -----------------------------------------------------------------------------------
EGL_ONLY = {"EGL": None, "GL": None, "OpenGL": None, "GLESv2": None, "GLESv1_CM": None, "OSMesa": "no libOSMesa"}
OSMESA_ONLY = {"EGL": "no libEGL", "GL": "no libGL", "OpenGL": "no libOpenGL", "GLESv2": "no libGLESv2",
               "GLESv1_CM": "no libGLESv1_CM", "OSMesa": None}
NONE = {name: f"no lib{name}" for name in EGL_ONLY}


@pytest.mark.parametrize("libs, env, chosen, after", [
    (EGL_ONLY, {}, "egl", "egl"),
    (OSMESA_ONLY, {}, "osmesa", "osmesa"),
    ({**EGL_ONLY, "OSMesa": None}, {"PYOPENGL_PLATFORM": "osmesa"}, "osmesa", "osmesa"),
    (NONE, {}, None, "disable"),
    (EGL_ONLY, {"MUJOCO_GL": "osmesa"}, None, "disable"),  # the README's failure: osmesa forced, not installed
    (EGL_ONLY, {"MUJOCO_GL": "egl"}, "egl", "egl"),
    (NONE, {"MUJOCO_GL": "glfw"}, "glfw", "glfw"),  # not ours to second-guess
    (NONE, {"DISPLAY": ":0"}, None, None),  # a display: MuJoCo's own default (GLFW)
    (EGL_ONLY, {"PYOPENGL_PLATFORM": "glx"}, None, None),  # EGL could not start under PyOpenGL's GLX platform
], ids=["egl", "osmesa", "pyopengl-platform", "none", "forced-missing", "forced-present", "glfw", "display",
        "pyopengl-glx"])
def test_backend_choice_names_only_loadable_libraries(monkeypatch, libs, env, chosen, after):
    """``MUJOCO_GL`` ends up naming a backend whose libraries load, or ``disable`` with the reason kept."""
    with monkeypatch.context() as m:
        m.delitem(sys.modules, "mujoco")  # select_gl_backend acts only before mujoco is imported
        m.setattr(render, "_LOAD_ERRORS", dict(libs))
        m.setattr(render, "_SELECTION_NOTE", [])
        for name in ("MUJOCO_GL", "PYOPENGL_PLATFORM", "DISPLAY", "WAYLAND_DISPLAY"):
            m.delenv(name, raising=False)
        for name, value in env.items():
            m.setenv(name, value)
        assert render.select_gl_backend() == chosen
        assert os.environ.get("MUJOCO_GL") == after
        disabled = render._disabled_reason()
        if after == "disable":
            missing = "libOSMesa" if env.get("MUJOCO_GL") else "libEGL"
            assert missing in disabled and "\n" not in disabled
            assert "libosmesa6" in disabled  # says what to install
        else:
            assert disabled is None
        note = list(render._SELECTION_NOTE)
    if after == "disable":
        with monkeypatch.context() as m:
            m.setenv("MUJOCO_GL", "disable")
            m.setattr(render, "_SELECTION_NOTE", note)
            with pytest.raises(render.RenderUnavailable, match="cannot be loaded|no loadable offscreen OpenGL"):
                render._make_renderer(None, 8, 8, None)


def test_choice_is_left_alone_once_mujoco_is_imported(monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "osmesa")
    monkeypatch.setattr(render, "_LOAD_ERRORS", dict(NONE))
    assert render.select_gl_backend() == "osmesa" and os.environ["MUJOCO_GL"] == "osmesa"


def test_a_forced_backend_that_is_absent_does_not_break_import_make_or_step(tmp_path):
    """``MUJOCO_GL`` naming a backend this machine lacks (scripts/test.sh once forced osmesa): ``import mujoco``
    used to fail inside PyOpenGL. Now everything but drawing works, and drawing says what is missing."""
    absent = [b for b in ("osmesa", "egl") if render.backend_missing(b) is not None]
    if not absent:
        pytest.skip("this machine loads both EGL and OSMesa: no absent backend to force")
    backend = absent[0]
    code = f"""
import os
import gymnasium as gym
import jaxrobo
from jaxrobo.pictures import render
assert os.environ["MUJOCO_GL"] == "disable", os.environ["MUJOCO_GL"]
env = gym.make("jaxrobo/CartPoleStayUp-v0")
obs, _ = env.reset(seed=0)
obs, reward, terminated, truncated, _ = env.step(1)
assert obs.shape == (4,) and reward == 1.0
reason = render.gl_unavailable_reason()
assert reason and "MUJOCO_GL={backend!r} is set but its library cannot be loaded" in reason, reason
try:
    render.Renderer(jaxrobo.make("CartPoleStayUp-v0"))
except render.RenderUnavailable as err:
    assert "install libegl1" in str(err), err
else:
    raise AssertionError("a renderer without OpenGL")
print("ok")
"""
    env = {**os.environ, "MUJOCO_GL": backend, "PYOPENGL_PLATFORM": backend, "JAX_PLATFORMS": "cpu",
           "PYTHONPATH": ROOT, "JAX_COMPILATION_CACHE_DIR": jax.config.jax_compilation_cache_dir or "",
           "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0.5"}
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0 and proc.stdout.strip().endswith("ok"), proc.stdout + proc.stderr


# -- videos of Box-action envs and of saved PPO/SAC policies ------------------------------------------------------
def _saved_deep_run(root, agent: str, env_id: str = "CartPoleContinuous-v0", steps: int = 6) -> str:
    """A ppo/sac run directory (config.yaml + a saved policy of non-trivial parameters) without training."""
    from jaxrobo import deep
    from jaxrobo.interop.brax_env import BraxEnv
    from jaxrobo.deep.policy import _template
    from jaxrobo.io.results import write_config

    spec = deep.resolve(env_id, agent, "tiny", {"env.max_episode_steps": steps})
    benv = BraxEnv(spec.env)
    net = deep.network_config(spec, benv.observation_size, benv.action_size)
    leaves, treedef = jax.tree.flatten(_template(net))
    rng = np.random.default_rng(0)
    params = jax.tree.unflatten(treedef, [np.asarray(rng.uniform(0.5, 1.5, np.shape(x)), np.asarray(x).dtype)
                                          for x in leaves])
    out = os.path.join(str(root), f"{agent}_{env_id}")
    os.makedirs(out)
    write_config(out, spec.to_dict())
    deep.save_policy(out, params, net)
    return out


@needs_gl
def test_rollout_frames_of_a_box_action_env_random_and_with_a_policy():
    env = jaxrobo.make("CartPoleContinuous-v0")
    frames, info = render.rollout_frames(env, None, seed=2, max_steps=4, width=48, height=36)
    assert len(frames) == info["length"] + 1 and frames[0].shape == (36, 48, 3)
    pushed = []
    frames, info = render.rollout_frames(env, lambda obs: pushed.append(obs) or np.ones(1, np.float32),
                                         seed=2, max_steps=4, width=48, height=36)
    assert len(pushed) == info["length"] and not np.array_equal(frames[0], frames[-1])
    with pytest.raises(ValueError, match=r"shape \(2,\).*shape \(1,\)"):
        render.rollout_frames(env, lambda obs: np.zeros(2), max_steps=2, width=48, height=36)


@needs_gl
@pytest.mark.parametrize("agent", ["ppo", "sac"])
def test_show_video_renders_a_saved_deep_policy(tmp_path, capsys, agent):
    pytest.importorskip("imageio", reason="imageio (the test extra) writes the GIF")
    import imageio.v2 as imageio

    from jaxrobo import deep
    from jaxrobo.cli import main

    run = _saved_deep_run(tmp_path, agent)
    gif = str(tmp_path / "episode.gif")
    assert main(["show", run, "--video", gif, "--seed", "3"]) == 0
    frames = imageio.mimread(gif)
    assert f"wrote {gif} ({len(frames)} frames" in capsys.readouterr().out
    assert 2 <= len(frames) <= 7  # the run's 6-step episodes, first state included

    # The episode is the saved policy's: the same actions as the policy acting on the same observations.
    from jaxrobo.interop.brax_env import BraxEnv
    from jaxrobo.io.results import load_config

    spec = deep.spec_from_config(load_config(run))
    loaded = deep.load_policy(run)

    host = render.jax_policy(deep.env_policy(BraxEnv(spec.env), loaded.make_policy, loaded.params), 3)
    seen = []
    _, info = render.rollout_frames(spec.env, lambda obs: seen.append(host(obs)) or seen[-1], seed=3,
                                    width=32, height=24)
    assert info["length"] == len(frames) - 1 and all(a.shape == (1,) and abs(a[0]) <= 1 for a in seen)


def test_show_video_says_why_without_gl_and_checks_the_path(tmp_path, monkeypatch, capsys):
    from jaxrobo.cli import main

    run = _saved_deep_run(tmp_path, "ppo", steps=2)
    assert main(["show", run, "--video", str(tmp_path / "x.png")]) == 2
    assert "--video" in capsys.readouterr().err

    class NoGL:
        def __init__(self, *args, **kwargs):
            raise render.RenderUnavailable("no display and no offscreen OpenGL: test")

    monkeypatch.setattr(render, "Renderer", NoGL)
    assert main(["show", run, "--video", str(tmp_path / "x.gif")]) == 1
    assert "cannot render: no display and no offscreen OpenGL: test" in capsys.readouterr().err
    assert not os.path.exists(tmp_path / "x.gif")


# ---- render_mode="human": a window ------------------------------------------------------------------------------
HUMAN = r"""
import sys
import gymnasium as gym, numpy as np
import jaxrobo
from PIL import ImageGrab

shown = gym.make("jaxrobo/QuadcopterGoto-v2", render_mode="human")
drawn = gym.make("jaxrobo/QuadcopterGoto-v2", render_mode="rgb_array")
shown.reset(seed=3), drawn.reset(seed=3)
for action in (0, 1, 2):
    shown.step(action), drawn.step(action)
frame = drawn.render()
screen = np.asarray(ImageGrab.grab(xdisplay=sys.argv[1]).convert("RGB"))
window = screen[:frame.shape[0], :frame.shape[1]]  # SDL_VIDEO_WINDOW_POS=0,0
print("RESULT", shown.render() is None, float(np.abs(window.astype(int) - frame.astype(int)).mean()),
      float(frame.astype(int).mean()))
shown.close()
"""


def _xvfb() -> tuple[subprocess.Popen, str]:
    """A virtual screen (Xvfb picks a free display number and writes it to the pipe)."""
    r, w = os.pipe()
    proc = subprocess.Popen(["Xvfb", "-displayfd", str(w), "-screen", "0", "640x480x24", "-nolisten", "tcp"],
                            pass_fds=(w,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(w)
    with os.fdopen(r) as f:
        number = f.readline().strip()
    assert number, "Xvfb gave no display number"
    return proc, f":{number}"


@needs_gl
@pytest.mark.skipif(shutil.which("Xvfb") is None, reason="no Xvfb (apt-get install xvfb) for a virtual screen")
def test_human_mode_shows_the_frames_in_a_window():
    """``render_mode="human"`` under Xvfb: reset and step draw the state in a window, and what the screen shows
    is the ``rgb_array`` frame of the same episode (the drone, its goal, the floor): the same picture, up to the
    round-off of two OpenGL contexts (a mean difference of 1.5 levels of 255 measured; a blank screen would
    differ by the frame's whole mean)."""
    pytest.importorskip("pygame")
    pytest.importorskip("PIL.ImageGrab")
    xvfb, display = _xvfb()
    try:
        # As on a desktop: MUJOCO_GL unset (this session's offscreen choice, EGL or OSMesa, is left out).
        env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
        env.update(DISPLAY=display, SDL_VIDEO_WINDOW_POS="0,0", JAX_PLATFORMS="cpu")
        proc = subprocess.run([sys.executable, "-c", HUMAN, display], env=env, capture_output=True, text=True,
                              timeout=300)
    finally:
        xvfb.terminate()
        xvfb.wait()
    assert proc.returncode == 0, proc.stderr[-3000:]
    returned_none, difference, brightness = proc.stdout.split("RESULT", 1)[1].split()
    assert returned_none == "True" and float(difference) < 4.0 and 3 * float(difference) < float(brightness)


def test_human_mode_without_a_screen_is_refused_at_make(monkeypatch):
    """No display (or no pygame): ``gym.make(..., render_mode="human")`` says why at once, not at render()."""
    import gymnasium as gym

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(gym.error.DependencyNotInstalled, match=r"render_mode='human': (no display|a window needs)"):
        gym.make("jaxrobo/CartPoleStayUp-v0", render_mode="human")
    assert JaxroboEnv("CartPoleStayUp-v0").metadata["render_modes"] == ["rgb_array"]  # what check_env will make
    with pytest.raises(ValueError, match="render_mode='human' is the single env's"):
        JaxroboVectorEnv("CartPoleStayUp-v0", num_envs=2, render_mode="human")
