"""Shared fixtures: CPU JAX, a persistent compilation cache for the session, and compiled cartpole functions."""
from __future__ import annotations

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402

# Property tests draw the same examples on every run, so a CI result does not depend on the day's random draw
# (a grazing ray once failed one run in many). HYPOTHESIS_PROFILE=explore searches fresh examples instead.
settings.register_profile("reproducible", derandomize=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "reproducible"))

# Identical programs compiled by several tests (e.g. the determinism check) are compiled once.
_BASE = os.path.abspath(
    os.environ.get("JAXROBO_TEST_CACHE", os.path.join(os.path.dirname(__file__), "..", ".jax_cache", "tests")))
# Under pytest-xdist (scripts/test.sh) each worker gets a cache folder of its own: JAX writes an entry in place,
# not through a temporary file and a rename, so a worker could read the half-written entry of another.
_WORKER = os.environ.get("PYTEST_XDIST_WORKER")
_CACHE = os.path.join(_BASE, _WORKER) if _WORKER else _BASE
jax.config.update("jax_compilation_cache_dir", _CACHE)
# `jaxrobo train` & co., run in-process by many tests (and by the subprocesses of some), turn on the user's cache
# (~/.cache/jaxrobo/jax) unless JAXROBO_CACHE_DIR names another: name this one, so that the whole session
# compiles into one cache (a program compiled before the first command is found after it) and a run of the suite
# neither reads nor fills the user's cache (a cold run is cold). A worker inherits the base folder from the xdist
# controller, whose conftest named it: it takes its own folder instead (a folder the caller named is kept).
if os.environ.get("JAXROBO_CACHE_DIR") in (None, _BASE):
    os.environ["JAXROBO_CACHE_DIR"] = _CACHE
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)

# Plans reuse traces (jaxrobo.speed.reuse) only where a test asks (tests/test_reuse.py, tests/test_cache.py): the
# suite's programs are many small ones each compiled once, which reuse would trace and export on top.
os.environ.setdefault("JAXROBO_REUSE_TRACES", "off")

import jaxrobo  # noqa: E402  (picks an OpenGL backend whose library loads, or none: jaxrobo.pictures.render)


def pytest_report_header(config):
    """Which OpenGL the rendering tests use, or why they skip (one line in the session header)."""
    from jaxrobo.pictures.render import gl_unavailable_reason

    reason = gl_unavailable_reason()
    return f"OpenGL: MUJOCO_GL={os.environ.get('MUJOCO_GL')}" if reason is None else f"OpenGL: none, {reason}"


@pytest.fixture(scope="session")
def cartpole():
    """CartPoleStayUp-v0 with its jitted reset and step."""
    env = jaxrobo.make("CartPoleStayUp-v0")
    return env, jax.jit(env.reset), jax.jit(env.step)


@pytest.fixture
def mjx_step_spy(monkeypatch):
    """A list that gets, for each ``mjx.step`` traced while the test runs, whether jaxrobo's lean MJX stage
    (:mod:`jaxrobo.physics.mjx_lean`) was swapped in for it: one bool per traced step, in order."""
    from jaxrobo.physics import mjx_lean
    from jaxrobo.physics.sim import mjx

    swapped = []
    step = mjx.step

    def spy(m, d):
        swapped.append(getattr(mjx_lean._mjx_smooth.com_pos, "jaxrobo_lean", False))
        return step(m, d)

    monkeypatch.setattr(mjx, "step", spy)
    return swapped
