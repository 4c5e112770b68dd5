"""Frames of a jaxrobo state from MuJoCo's offscreen renderer, and videos of a policy's episode.

The seed watched Gazebo and asked for "videos showing how the drone has learnt"; jaxrobo has no GUI in the
loop, so a frame is drawn on demand: the robot's generalized positions (and velocities, and mocap poses where
the backend has them) are copied into a host ``MjData``, ``mj_forward`` places every body, and
:class:`mujoco.Renderer` draws the scene. This works for every backend (MJX, Brax, the quadcopter's ``rigid``)
because it needs only ``sim.mj_model``, ``sim.qpos(state)`` and ``sim.qvel(state)``.

Headless machines need an offscreen OpenGL: EGL (``libegl1``, GPU driver or Mesa) or OSMesa (software,
``apt-get install libosmesa6``). MuJoCo reads ``MUJOCO_GL`` once, when it is imported, and a backend whose
library is absent makes ``import mujoco`` itself fail inside PyOpenGL. So ``import jaxrobo`` first calls
:func:`select_gl_backend`, which sets ``MUJOCO_GL`` only to a backend whose libraries load (EGL, else OSMesa,
else ``disable``), and replaces a ``MUJOCO_GL=egl``/``osmesa`` whose library is missing with ``disable``.
Nothing but rendering needs OpenGL: without a backend, training, the CLI and ``gym.make`` work, and a
:class:`Renderer` raises :class:`RenderUnavailable` saying why (:func:`gl_unavailable_reason`).

Task hooks (optional, looked up on the env; never required):

``render_extras(state, params) -> Iterable[Mapping]``
    Geometry that is task data rather than part of the MJCF (a goal marker, obstacles held as arrays). Each
    mapping has ``type`` (``"sphere"``, ``"box"``, ``"cylinder"``, ``"capsule"``, ``"ellipsoid"``,
    ``"arrow"`` or a :class:`mujoco.mjtGeom` value), ``size`` (3 numbers, MuJoCo's half-sizes), ``pos``
    (3 numbers, world frame) and optionally ``rgba`` (4 numbers) and ``mat`` (9 numbers, row-major rotation).
    ``state`` is the :class:`jaxrobo.task.env.EnvState` with host (numpy) arrays; ``params`` the env parameters.
    They are added to the scene's user geoms with ``mujoco.mjv_initGeom``.
``render_camera``
    An attribute naming the default camera (a camera name in the MJCF, or ``"track"``).

Without a camera choice the first camera of the model is used, else a free camera that tracks body 1.
"""
from __future__ import annotations

import atexit
import ctypes
import os
import platform
import sys
import weakref
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

GEOM_TYPES = ("plane", "hfield", "sphere", "capsule", "ellipsoid", "cylinder", "box", "mesh", "sdf")


class RenderUnavailable(RuntimeError):
    """No OpenGL backend could be created (no display, and neither EGL nor OSMesa works)."""


def _headless() -> bool:
    return platform.system() == "Linux" and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


# The libraries PyOpenGL loads for each headless backend: every group needs one loadable member.
_BACKEND_LIBS = {"egl": (("EGL",), ("OpenGL", "GL", "GLESv2", "GLESv1_CM")), "osmesa": (("OSMesa",),)}
_OFF = ("disable", "disabled", "off", "false", "0")
_LOAD_ERRORS: dict[str, str | None] = {}
# Why select_gl_backend turned rendering off, for the error a Renderer raises and the tests' skip reason.
_SELECTION_NOTE: list[str] = []


def _load_error(name: str) -> str | None:
    """None when ``lib<name>.so`` loads the way PyOpenGL looks for it (``.so``, then ``.so.9`` .. ``.so.0``)."""
    if name not in _LOAD_ERRORS:
        first = None
        for filename in [f"lib{name}.so"] + [f"lib{name}.so.{i}" for i in range(9, -1, -1)]:
            try:
                ctypes.CDLL(filename)
            except OSError as err:
                first = first or str(err)
            else:
                first = None
                break
        _LOAD_ERRORS[name] = first
    return _LOAD_ERRORS[name]


def backend_missing(backend: str) -> str | None:
    """None when the libraries of ``backend`` (``"egl"`` or ``"osmesa"``) can be loaded, else what is missing."""
    missing = []
    for group in _BACKEND_LIBS[backend]:
        errors = [_load_error(name) for name in group]
        if all(errors):
            missing.append(errors[0])
    return "; ".join(missing) or None


def select_gl_backend() -> str | None:
    """Make ``MUJOCO_GL`` name only a backend that can load, before ``mujoco`` is imported; returns the backend.

    On a display-less Linux with ``MUJOCO_GL`` unset: EGL if ``libEGL`` (and a GL library) load, else OSMesa if
    ``libOSMesa`` loads, else ``disable`` (a set ``PYOPENGL_PLATFORM`` restricts the choice to that platform).
    ``MUJOCO_GL=egl`` or ``osmesa`` whose library is missing becomes ``disable``: ``import mujoco`` would
    otherwise fail inside PyOpenGL for every use, rendering or not. Any other choice (``glfw``, ``glx``, a
    display) is left to MuJoCo. Does nothing once ``mujoco`` is imported (its choice is made then).
    """
    chosen = os.environ.get("MUJOCO_GL", "").lower().strip()
    if "mujoco" in sys.modules:
        return chosen or None
    if chosen in _BACKEND_LIBS:
        missing = backend_missing(chosen)
        if missing is None:
            return chosen
        _SELECTION_NOTE[:] = [f"MUJOCO_GL={chosen!r} is set but its library cannot be loaded ({missing})"]
        os.environ["MUJOCO_GL"] = "disable"
        return None
    if chosen or not _headless():
        return None if chosen in _OFF else (chosen or None)
    platform_var = os.environ.get("PYOPENGL_PLATFORM", "").lower().strip()
    if platform_var and platform_var not in _BACKEND_LIBS:
        return None  # PyOpenGL is told to use another platform (glx, ...): neither EGL nor OSMesa could start
    candidates = [platform_var] if platform_var else list(_BACKEND_LIBS)
    notes = []
    for backend in candidates:
        missing = backend_missing(backend)
        if missing is None:
            os.environ["MUJOCO_GL"] = backend
            return backend
        notes.append(f"{backend}: {missing}")
    _SELECTION_NOTE[:] = ["no display and no loadable offscreen OpenGL (" + "; ".join(notes) + ")"]
    os.environ["MUJOCO_GL"] = "disable"
    return None


def _install_hint() -> str:
    return "install libegl1 (or libosmesa6), or set MUJOCO_GL to a backend this machine has"


def _disabled_reason() -> str | None:
    """Why rendering is off in this process (``MUJOCO_GL`` disabled), or None when a backend was chosen."""
    if os.environ.get("MUJOCO_GL", "").lower().strip() not in _OFF:
        return None
    note = _SELECTION_NOTE[0] if _SELECTION_NOTE else "MUJOCO_GL disables OpenGL"
    return f"{note}; {_install_hint()}"


def _gl_context_class() -> type | None:
    """The GLContext class to use, or None to keep MuJoCo's own choice.

    :func:`select_gl_backend` sets ``MUJOCO_GL`` on a display-less Linux, so this matters only when ``mujoco``
    was imported before ``jaxrobo`` with ``MUJOCO_GL`` unset: MuJoCo then defaulted to GLFW, which needs a
    display, and we try EGL, then OSMesa, whose libraries load.
    """
    if os.environ.get("MUJOCO_GL") or not _headless():
        return None
    errors = []
    for name in ("egl", "osmesa"):
        try:
            missing = backend_missing(name)
            if missing is not None:
                raise ImportError(missing)
            if name == "egl":
                from mujoco.egl import GLContext
            else:
                from mujoco.osmesa import GLContext
            ctx = GLContext(16, 16)  # probe: fails here when no context can be created
            ctx.free()
            return GLContext
        except Exception as err:  # noqa: BLE001 - any failure means "try the next backend"
            errors.append(f"{name}: {err}")
    raise RenderUnavailable("no display and no offscreen OpenGL: " + "; ".join(errors) + f" ({_install_hint()})")


_GL_REASON: list[str | None] = []


#: Renderers not closed yet: closed at exit, while the GL library is still loaded (a GLFW context freed by MuJoCo's
#: ``__del__`` during the interpreter's teardown prints a traceback, as on a desktop with a window open).
_OPEN: "weakref.WeakSet[Any]" = weakref.WeakSet()


@atexit.register
def _close_open_renderers() -> None:
    for renderer in list(_OPEN):
        try:
            renderer.close()
        except Exception:  # noqa: BLE001 - the process is ending; nothing to report it to
            pass


def gl_unavailable_reason() -> str | None:
    """None when offscreen rendering works in this process, else why not, on one line (checked once)."""
    if not _GL_REASON and _disabled_reason() is not None:
        _GL_REASON.append(f"no OpenGL for offscreen rendering: {_disabled_reason()}")
    if not _GL_REASON:
        try:
            import mujoco

            model = mujoco.MjModel.from_xml_string("<mujoco><worldbody><geom size='1'/></worldbody></mujoco>")
            renderer = _make_renderer(model, 8, 8, _gl_context_class())
            renderer.close()
            _GL_REASON.append(None)
        except Exception as err:  # noqa: BLE001 - report, do not raise
            reason = f"no OpenGL for offscreen rendering (MUJOCO_GL={os.environ.get('MUJOCO_GL', '')!r}): {err}"
            _GL_REASON.append(" ".join(reason.split()))
    return _GL_REASON[0]


def _sim_of(env: Any) -> Any:
    from jaxrobo.task.env import simulator_of

    sim = simulator_of(env)
    if sim is None or not hasattr(sim, "mj_model"):
        raise ValueError(f"{env!r} has no robot.sim.mj_model; only MuJoCo-model environments can be rendered")
    return sim


def _geom_type(value: Any) -> int:
    import mujoco

    if isinstance(value, str):
        if value == "arrow":
            return int(mujoco.mjtGeom.mjGEOM_ARROW)
        if value not in GEOM_TYPES:
            raise ValueError(f"render_extras: type={value!r}: allowed values are {', '.join(GEOM_TYPES)}, arrow")
        return int(getattr(mujoco.mjtGeom, f"mjGEOM_{value.upper()}"))
    return int(value)


#: The largest frame side accepted: GL drivers' framebuffers commonly stop at 16,384 pixels, and a larger one failed
#: inside MuJoCo with "Offscreen framebuffer is not complete", read as a missing GL library.
MAX_FRAME_SIDE = 16384


def check_frame_size(width: Any, height: Any, where: str = "") -> tuple[int, int]:
    """``(width, height)`` as ints, or a ValueError naming the one that is not an integer in 1..MAX_FRAME_SIDE (a
    negative one failed in MuJoCo's renderer, 0 gave an empty frame, 2.5 was cut to 2 without a word)."""
    import operator

    out = []
    for name, value in (("width", width), ("height", height)):
        try:
            n = None if isinstance(value, bool) else operator.index(value)
        except TypeError:
            n = None
        if n is None or not 1 <= n <= MAX_FRAME_SIDE:
            raise ValueError(f"{where + ': ' if where else ''}{name}={value!r}: expected an integer >= 1 and <= "
                             f"{MAX_FRAME_SIDE} (pixels)")
        out.append(n)
    return out[0], out[1]


class Renderer:
    """Draws an env's state to ``height x width x 3`` uint8 frames; reuse one per env (it holds a GL context)."""

    def __init__(self, env: Any, width: int = 320, height: int = 240, camera: str | int | None = None):
        import mujoco

        self.width, self.height = check_frame_size(width, height)
        self.env = env
        self.sim = _sim_of(env)
        self.model = self.sim.mj_model
        self.data = mujoco.MjData(self.model)
        off_w, off_h = self.model.vis.global_.offwidth, self.model.vis.global_.offheight
        if self.width > off_w or self.height > off_h:
            # The framebuffer limits are model data; raise them on this private copy only.
            self.model = _copy_model(self.model)
            self.model.vis.global_.offwidth = max(off_w, self.width)
            self.model.vis.global_.offheight = max(off_h, self.height)
            self.data = mujoco.MjData(self.model)
        camera = getattr(env, "render_camera", None) if camera is None else camera
        self.camera = self._camera(camera)
        context_cls = _gl_context_class()
        self._renderer = _make_renderer(self.model, self.height, self.width, context_cls)
        _OPEN.add(self)

    def _camera(self, camera: str | int | None) -> Any:
        import mujoco

        if camera is None:
            camera = 0 if self.model.ncam > 0 else "track"
        if camera == "track":
            cam = mujoco.MjvCamera()
            mujoco.mjv_defaultFreeCamera(self.model, cam)
            if self.model.nbody > 1:
                cam.type = mujoco.mjtCamera.mjCAMERA_TRACKING
                cam.trackbodyid = 1
                cam.distance = max(2.0, 3.0 * float(self.model.stat.extent))
                cam.elevation = -20.0
                cam.azimuth = 90.0 + 45.0
            return cam
        if isinstance(camera, str):
            cid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
            if cid < 0:
                names = [mujoco.mj_id2name(self.model, mujoco.mjtObj.mjOBJ_CAMERA, i) for i in range(self.model.ncam)]
                raise ValueError(f"camera={camera!r}: the model's cameras are {names} (or 'track')")
            return cid
        if not 0 <= int(camera) < self.model.ncam:
            raise ValueError(f"camera={camera!r}: the model has {self.model.ncam} cameras")
        return int(camera)

    def set_state(self, state: Any) -> None:
        """Copy the robot's pose from a (single, unbatched) env state into the host MjData and run forward."""
        import jax
        import mujoco

        ps = state.pipeline_state
        parts = {"qpos": self.sim.qpos(ps), "qvel": self.sim.qvel(ps)}
        for name in ("mocap_pos", "mocap_quat"):
            if self.model.nmocap and hasattr(ps, name):
                parts[name] = getattr(ps, name)
        host = jax.device_get(parts)
        qpos = np.asarray(host["qpos"], np.float64)
        if qpos.shape != (self.model.nq,):
            raise ValueError(f"state qpos has shape {qpos.shape}, the model needs ({self.model.nq},); "
                             "render one environment of a batch at a time")
        self.data.qpos[:] = qpos
        self.data.qvel[:] = np.asarray(host["qvel"], np.float64)
        for name in ("mocap_pos", "mocap_quat"):
            if name in host:
                getattr(self.data, name)[:] = np.asarray(host[name], np.float64)
        mujoco.mj_forward(self.model, self.data)

    def render(self, state: Any, params: Any = None) -> np.ndarray:
        """The frame of ``state`` (``height x width x 3`` uint8), with the task's ``render_extras`` if any."""
        self.set_state(state)
        self._renderer.update_scene(self.data, camera=self.camera)
        extras = getattr(self.env, "render_extras", None)
        if extras is not None:
            import jax

            host_state = jax.device_get(state)
            params = getattr(self.env, "default_params", None) if params is None else params
            add_geoms(self._renderer.scene, extras(host_state, params))
        return np.asarray(self._renderer.render(), np.uint8)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def _copy_model(model: Any) -> Any:
    import copy

    return copy.copy(model)


def _make_renderer(model: Any, height: int, width: int, context_cls: type | None) -> Any:
    import mujoco

    disabled = _disabled_reason()
    if disabled is not None:  # mujoco.Renderer has no GL context to make then: say why instead of crashing
        raise RenderUnavailable(disabled)
    if context_cls is None:
        try:
            return mujoco.Renderer(model, height, width)
        except Exception as err:  # noqa: BLE001
            raise RenderUnavailable(f"mujoco.Renderer failed ({type(err).__name__}: {err}); {_install_hint()}, "
                                    "before mujoco is imported") from err
    from mujoco.rendering.classic import gl_context

    saved = getattr(gl_context, "GLContext", None)
    gl_context.GLContext = context_cls  # the renderer reads it at construction; restored right after
    try:
        return mujoco.Renderer(model, height, width)
    finally:
        gl_context.GLContext = saved


def add_geoms(scene: Any, geoms: Iterable[Mapping[str, Any]] | None) -> int:
    """Append task geometry to a ``mujoco.MjvScene``'s user geoms; returns how many were added."""
    import mujoco

    added = 0
    for g in geoms or ():
        if scene.ngeom >= scene.maxgeom:
            break
        size = np.zeros(3)
        given = np.asarray(g["size"], np.float64).ravel()
        size[: given.size] = given[:3]
        pos = np.asarray(g["pos"], np.float64).reshape(3)
        mat = np.asarray(g.get("mat", np.eye(3)), np.float64).reshape(9)
        rgba = np.asarray(g.get("rgba", (0.2, 0.8, 0.2, 0.6)), np.float32).reshape(4)
        mujoco.mjv_initGeom(scene.geoms[scene.ngeom], _geom_type(g["type"]), size, pos, mat, rgba)
        scene.ngeom += 1
        added += 1
    return added


def render_frame(env: Any, state: Any, width: int = 320, height: int = 240, camera: str | int | None = None,
                 params: Any = None) -> np.ndarray:
    """One frame of one state (creates and closes a renderer: use :class:`Renderer` for many frames)."""
    with Renderer(env, width, height, camera) as r:
        return r.render(state, params)


#: A host policy: observation -> action (an int for a Discrete action space, an array of the Box's shape for a
#: continuous one).
Policy = Callable[[np.ndarray], Any]


def _host_action(space: Any, policy: Policy | None, obs: np.ndarray, rng: np.random.Generator) -> Any:
    """The action to step with: the policy's (random if None), as the action space's type and shape."""
    from jaxrobo.core import spaces

    if isinstance(space, spaces.Discrete):
        return np.int32(int(rng.integers(space.n)) if policy is None else int(policy(obs)))
    if policy is None:  # uniform in the Box; an unbounded side draws from [-1, 1] as Box.sample does
        low = np.where(np.isfinite(space.low), space.low, -1.0)
        high = np.where(np.isfinite(space.high), space.high, 1.0)
        return rng.uniform(low, high).astype(space.dtype)
    action = np.asarray(policy(obs), space.dtype)
    if action.shape != space.shape:
        raise ValueError(f"the policy returned an action of shape {action.shape}; the env's Box action space has "
                         f"shape {space.shape}")
    return action


def rollout_frames(env: Any, policy: Policy | None = None, seed: int = 0, max_steps: int | None = None,
                   width: int = 320, height: int = 240, camera: str | int | None = None,
                   params: Any = None) -> tuple[list[np.ndarray], dict[str, Any]]:
    """Run one episode of ``policy`` (observation → action; random if None) and draw every state. Discrete and
    Box action spaces (a saved PPO/SAC policy: :func:`jax_policy` of :func:`jaxrobo.deep.env_policy`).

    Returns ``(frames, {"return", "length", "terminated", "truncated"})``.
    """
    import jax

    from jaxrobo.speed.compiled import compiled_for

    params = env.default_params if params is None else params
    fns = compiled_for(env)  # the Gymnasium adapter's jitted reset/step: compiled once per env configuration
    state, _ = fns.reset(jax.random.key(seed), params)
    limit = int(max_steps if max_steps is not None else params.max_episode_steps)
    rng = np.random.default_rng(seed)
    space = env.action_space(params)
    frames, total, length = [], 0.0, 0
    with Renderer(env, width, height, camera) as r:
        frames.append(r.render(state, params))
        while length < limit:
            action = _host_action(space, policy, np.asarray(state.obs), rng)
            state, _ = fns.step(state, action, params)
            total += float(state.reward)
            length += 1
            frames.append(r.render(state, params))
            if bool(state.terminated) or bool(state.truncated):
                break
    return frames, {"return": total, "length": length, "terminated": bool(state.terminated),
                    "truncated": bool(state.truncated)}


def jax_policy(policy: Callable[[Any, Any], Any], seed: int = 0) -> Policy:
    """A :data:`jaxrobo.task.rollout.Policy` ``(key, obs) -> action`` (e.g. :func:`jaxrobo.deep.env_policy` of a saved
    PPO/SAC policy) as a host :data:`Policy` ``obs -> action array``: jitted once, the ``t``-th call acting with
    ``fold_in(key(seed), t)`` as :class:`jaxrobo.task.rollout.host_policy` does for a Discrete policy."""
    import jax
    import jax.numpy as jnp

    act = jax.jit(policy)
    key = jax.random.key(seed)
    t = [0]

    def host(obs: np.ndarray) -> np.ndarray:
        k = jax.random.fold_in(key, t[0])
        t[0] += 1
        return np.asarray(act(k, jnp.asarray(obs)))

    return host


def write_video(path: str, frames: Sequence[np.ndarray], fps: float = 25.0) -> str:
    """Write frames to ``.gif`` (Pillow, via imageio) or ``.mp4`` (needs ``imageio-ffmpeg``); returns ``path``."""
    try:
        import imageio.v2 as imageio
    except ImportError as err:
        raise ImportError("writing videos needs imageio: pip install imageio (and imageio-ffmpeg for .mp4)") from err
    if not frames:
        raise ValueError("write_video: no frames")
    ext = os.path.splitext(path)[1].lower()
    if ext not in (".gif", ".mp4", ".mov", ".avi", ".mkv"):
        raise ValueError(f"write_video: {path!r}: use a .gif or .mp4 file name")
    from jaxrobo.io.rundir import atomic_path

    # Written beside, then renamed: a full disk or a failed encoder leaves no truncated video at ``path``.
    with atomic_path(path, suffix=ext) as tmp:
        if ext == ".gif":
            imageio.mimsave(tmp, list(frames), duration=1000.0 / fps, loop=0)  # duration per frame, in ms
        else:
            try:
                imageio.mimsave(tmp, list(frames), fps=fps, macro_block_size=1)
            except (ImportError, ValueError, RuntimeError) as err:
                raise RuntimeError(f"{path}: writing {ext} needs imageio-ffmpeg (pip install imageio-ffmpeg); "
                                   f"a .gif needs nothing more ({err})") from err
    return path


def record_episode(env: Any, path: str, policy: Policy | None = None, seed: int = 0, max_steps: int | None = None,
                   width: int = 320, height: int = 240, camera: str | int | None = None,
                   fps: float | None = None, params: Any = None) -> dict[str, Any]:
    """Roll out one episode of ``policy`` and write it as a GIF/MP4 at real-time speed by default.

    Returns the episode's ``return``, ``length``, ``terminated``, ``truncated`` and the video ``path``.
    """
    frames, info = rollout_frames(env, policy, seed, max_steps, width, height, camera, params)
    if fps is None:
        fps = 1.0 / float(getattr(_sim_of(env), "running_step", 0.04) or 0.04)
    write_video(path, frames, fps)
    return {**info, "path": path, "frames": len(frames)}


def q_policy(q: np.ndarray, discretiser: Callable[[Any], Any], seed: int = 0) -> Policy:
    """A greedy policy ``obs -> action`` from a Q-table ``[n_tables, n_states, n_actions]`` (or
    ``[n_states, n_actions]``; Double Q-learning's tables act on their sum).

    Ties are broken as everywhere else (:func:`jaxrobo.task.rollout.greedy_action`, as the trainer's evaluation):
    uniformly at random among the maximal values, the ``t``-th call drawing from ``fold_in(key(seed), t)``.
    ``discretiser`` must be traceable (a :class:`jaxrobo.tabular.discretise.Discretiser`)."""
    from jaxrobo.task.rollout import greedy_policy, host_policy

    q = np.asarray(q)
    return host_policy(greedy_policy(q if q.ndim == 3 else q[None], discretiser), seed)
