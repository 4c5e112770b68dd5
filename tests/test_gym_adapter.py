"""The Gymnasium adapter: registration, check_env for every id, vector env semantics, seeding, invalid actions.

Every registered jaxrobo id is covered (ids whose task module does not exist yet are skipped with the reason).
Compiled functions are shared per env configuration (``jaxrobo.speed.compiled.compiled_for``), so each id compiles its
reset/step once for the whole module whatever the parameters.
"""
from __future__ import annotations

import importlib
import os
import subprocess
import sys
import warnings

import gymnasium as gym
import jax
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env, data_equivalence
from gymnasium.vector import AutoresetMode, SyncVectorEnv

import jaxrobo
from jaxrobo.interop import gym_adapter, gym_ids
from jaxrobo.interop.gym_adapter import InvalidActionError, JaxroboEnv, JaxroboVectorEnv
from jaxrobo.task.registry import _lookup

IDS = jaxrobo.registered()
N_VEC = 3  # one batch size throughout, so each env configuration compiles its vector step once
#: Ids kept beside a newer version of the same task (their old values stay reproducible): Gymnasium calls them
#: "out of date" and names the newer one, which is the one warning they may raise.
SUPERSEDED = {"QuadcopterGoto-v1": "QuadcopterGoto-v2"}


def _clean_make(make, env_id):
    """``make()`` with every warning an error, except Gymnasium's "out of date" for a superseded id."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        if env_id in SUPERSEDED:
            warnings.filterwarnings("ignore", message=".*is out of date.*" + SUPERSEDED[env_id].rpartition("-")[2])
        return make()
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _require(env_id: str) -> None:
    """Every registered id's task module imports: a missing one is a broken registration, and fails here."""
    entry = _lookup(env_id).entry_point
    if isinstance(entry, str):
        importlib.import_module(entry.partition(":")[0])


def _render_ok() -> bool:
    from jaxrobo.pictures.render import gl_unavailable_reason

    return gl_unavailable_reason() is None


@pytest.fixture(scope="module", params=IDS)
def env_id(request) -> str:
    _require(request.param)
    return request.param


@pytest.fixture(scope="module")
def single(env_id) -> JaxroboEnv:
    return JaxroboEnv(env_id)


def _actions(n: int | gym.spaces.Box, count: int, seed: int = 0) -> list:
    """``count`` random actions: integers below ``n``, or float32 arrays inside a continuous task's Box."""
    if isinstance(n, gym.spaces.Box):
        u = np.random.default_rng(seed).uniform(size=(count,) + n.shape)
        return list((n.low + u * (n.high - n.low)).astype(np.float32))
    return [int(a) for a in np.random.default_rng(seed).integers(n, size=count)]


# ---- registration --------------------------------------------------------------------------------------------
def test_every_id_is_registered_with_its_step_limit():
    for env_id in IDS:
        spec = gym.spec(f"jaxrobo/{env_id}")
        expected = jaxrobo.task.registry.env_config(env_id).get("max_episode_steps",
                                                                jaxrobo.spec(env_id).max_episode_steps)
        assert spec.max_episode_steps == expected
        assert spec.entry_point == "jaxrobo.interop.gym_adapter:JaxroboEnv"
        assert spec.vector_entry_point == "jaxrobo.interop.gym_adapter:JaxroboVectorEnv"
        assert spec.kwargs == {"env_id": env_id}
    assert gym_ids.register_gymnasium_envs() == []  # idempotent


def test_registration_is_cheap_and_namespace_needs_import():
    """In a fresh process: Gymnasium does not import a module named after the namespace (so ``gymnasium.make(
    "jaxrobo/...")`` needs ``import jaxrobo`` first, or the ``"jaxrobo:jaxrobo/<id>"`` form); ``import jaxrobo``
    registers every id without loading any model or task module (each id's step limit, its task's ``Params``
    default, is read when Gymnasium asks for it: ``test_every_id_is_registered_with_its_step_limit``)."""
    code = (
        "import sys, gymnasium as gym, mujoco\n"
        "loaded = []\n"
        "real = mujoco.MjSpec.from_file\n"
        "mujoco.MjSpec.from_file = lambda *a, **k: (loaded.append(a), real(*a, **k))[1]\n"
        "try:\n    gym.make('jaxrobo/CartPoleStayUpLeftRight-v0'); print('AUTO')\n"
        "except gym.error.Error as e:\n    print('NEEDS_IMPORT', type(e).__name__)\n"
        "import jaxrobo\n"
        "ids = [k for k in gym.registry if k.startswith('jaxrobo/')]\n"
        "print('IDS', len(ids), 'TASKS', loaded, sorted(m for m in sys.modules if m.startswith('envs.')))\n"
    )
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "NEEDS_IMPORT NamespaceNotFound" in out.stdout, out.stdout  # Gymnasium 1.x: no namespace auto-import
    assert f"IDS {len(IDS)} TASKS [] []" in out.stdout, out.stdout


def test_module_prefix_form_imports_jaxrobo():
    """In a fresh process with nothing of jaxrobo imported, Gymnasium's ``"jaxrobo:jaxrobo/<id>"`` form imports
    jaxrobo (which registers the ids) and makes the env."""
    code = ("import sys, gymnasium as gym\n"
            "assert 'jaxrobo' not in sys.modules\n"
            "env = gym.make('jaxrobo:jaxrobo/CartPoleStayUpLeftRight-v0')\n"
            "from jaxrobo.interop.gym_adapter import JaxroboEnv\n"
            "print('IMPORTED', 'jaxrobo' in sys.modules, type(env.unwrapped) is JaxroboEnv,\n"
            "      env.reset(seed=0)[0].shape)\n")
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "IMPORTED True True (4,)" in out.stdout, out.stdout


def test_make_passes_overrides_and_rejects_bad_ones():
    env = gym.make("jaxrobo/CartPoleStayUp-v0", control_type="position", pos_step=0.02)
    inner = env.unwrapped.jax_env
    assert inner.options.control_type == "position" and inner.default_params.pos_step == pytest.approx(0.02)
    assert env.spec.max_episode_steps == 1000
    with pytest.raises(ValueError, match="pos_stepp"):
        gym.make("jaxrobo/CartPoleStayUp-v0", pos_stepp=0.02)
    with pytest.raises(ValueError, match="control_type"):
        gym.make("jaxrobo/CartPoleStayUp-v0", control_type="magic")


# ---- the single env ------------------------------------------------------------------------------------------
def test_spaces_are_exact(env_id, single):
    jenv = jaxrobo.make(env_id)
    act = jenv.action_space()
    if isinstance(act, jaxrobo.core.spaces.Box):  # a continuous task: its own bounds, float32
        assert single.action_space == gym.spaces.Box(act.low, act.high, dtype=np.float32)
    else:
        assert single.action_space == gym.spaces.Discrete(act.n)
    box = jenv.observation_space()
    big = np.finfo(np.float32).max
    np.testing.assert_array_equal(single.observation_space.low, np.where(np.isfinite(box.low), box.low, -big))
    np.testing.assert_array_equal(single.observation_space.high, np.where(np.isfinite(box.high), box.high, big))
    assert single.observation_space.dtype == np.float32


@pytest.mark.slow
def test_check_env_passes_without_warnings(env_id, single):
    env = gym.make(f"jaxrobo/{env_id}")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # The made env's spec lets check_env re-make it for each render mode and check close() twice.
        check_env(env.unwrapped, skip_render_check=not _render_ok())
        # The wrappers gymnasium.make adds (PassiveEnvChecker, OrderEnforcing, TimeLimit) see valid data too.
        obs, info = env.reset(seed=1)
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert isinstance(obs, np.ndarray) and obs.dtype == np.float32 and obs in env.observation_space
    assert type(reward) is float and type(terminated) is bool and type(truncated) is bool
    env.close()


@pytest.mark.slow
def test_same_seed_same_trajectory_as_functional_api(env_id, single):
    jenv = jaxrobo.make(env_id)
    reset, step = jax.jit(jenv.reset), jax.jit(jenv.step)
    actions = _actions(getattr(single.action_space, "n", single.action_space), 12, seed=3)
    obs, _ = single.reset(seed=7)
    state = reset(jax.random.key(7))
    np.testing.assert_array_equal(obs, np.asarray(state.obs))
    for a in actions:
        obs, reward, terminated, truncated, info = single.step(a)
        state = step(state, a)
        np.testing.assert_array_equal(obs, np.asarray(state.obs))
        assert reward == float(state.reward)
        assert (terminated, truncated) == (bool(state.terminated), bool(state.truncated))
        assert info["steps"] == int(state.steps)
        if terminated or truncated:
            break
    # An unseeded reset continues from the key the episode carried.
    obs, _ = single.reset()
    state = reset(jax.random.split(state.key)[1])
    np.testing.assert_array_equal(obs, np.asarray(state.obs))


def test_reset_seeds_are_reproducible():
    env = JaxroboEnv("CartPoleStayUp-v0")
    a, _ = env.reset(seed=11)
    b, _ = env.reset(seed=11)
    c, _ = env.reset(seed=12)
    d, _ = env.reset(seed=2**40 + 11)  # large seeds are fine and distinct
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c) and not np.array_equal(a, d)
    env.reset(seed=5)
    x = [env.reset()[0] for _ in range(2)]
    env.reset(seed=5)
    y = [env.reset()[0] for _ in range(2)]
    np.testing.assert_array_equal(x, y)


def test_reset_options_set_task_parameters():
    env = JaxroboEnv("CartPoleStayUp-v0")
    obs, _ = env.reset(seed=0, options={"init_pole_angle": 0.5, "init_noise": 0.0})
    assert obs[2] == pytest.approx(0.5, abs=1e-6)
    obs, _ = env.reset(seed=0)  # options persist until changed
    assert obs[2] == pytest.approx(0.5, abs=1e-6)
    with pytest.raises(ValueError, match="init_pole_angel"):
        env.reset(options={"init_pole_angel": 0.5})
    with pytest.raises(ValueError, match="static"):
        env.reset(options={"control_type": "position"})


def test_time_limit_is_the_tasks_own_truncation():
    env = JaxroboEnv("CartPoleStayUp-v0", overrides={"max_episode_steps": 3}, init_noise=0.0)
    env.reset(seed=0)
    flags = [env.step(0)[2:4] for _ in range(3)]
    assert flags == [(False, False), (False, False), (False, True)]
    made = gym.make("jaxrobo/CartPoleStayUp-v0", max_episode_steps=2)  # Gymnasium's TimeLimit shortens it
    made.reset(seed=0)
    assert [made.step(0)[3] for _ in range(2)] == [False, True]


@pytest.mark.parametrize("bad", [-1, 4, 1.0, np.float32(np.nan), float("nan"), "1", None, True, np.bool_(False),
                                 [0], np.array([0, 1]), np.array([[1]]), 2**40])
def test_invalid_actions_raise_before_jax(bad):
    env = JaxroboEnv("CartPoleStayUp-v0")
    env.reset(seed=0)
    before = env.state
    with pytest.raises(InvalidActionError) as err:
        env.step(bad)
    assert isinstance(err.value, ValueError) and isinstance(err.value, AssertionError)
    assert "action" in str(err.value) and "Trac" not in str(err.value)
    assert env.state is before  # nothing ran
    for good in (3, np.int64(2), np.array(1), np.uint8(0)):
        env.step(good)


def test_step_before_reset_is_an_error():
    env = JaxroboEnv("CartPoleStayUpLeftRight-v0")
    with pytest.raises(gym.error.ResetNeeded):
        env.step(0)


# ---- the vector env ------------------------------------------------------------------------------------------
def _check_vector_env(venv: gym.vector.VectorEnv, n: int, steps: int = 4) -> None:
    """The vector-env contract (Gymnasium 1.x has no vector check_env): spaces, dtypes, seeding, metadata."""
    assert venv.num_envs == n
    assert venv.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    assert venv.observation_space == gym.vector.utils.batch_space(venv.single_observation_space, n)
    assert venv.action_space == gym.vector.utils.batch_space(venv.single_action_space, n)
    obs1, info = venv.reset(seed=42)
    obs2, _ = venv.reset(seed=42)
    assert data_equivalence(obs1, obs2, exact=True) and isinstance(info, dict)
    assert obs1 in venv.observation_space and obs1.dtype == np.float32
    venv.action_space.seed(0)
    for _ in range(steps):
        obs, rew, term, trunc, info = venv.step(venv.action_space.sample())
        assert obs in venv.observation_space and obs.shape == (n,) + venv.single_observation_space.shape
        assert rew.shape == term.shape == trunc.shape == (n,)
        assert rew.dtype == np.float64 and term.dtype == np.bool_ and trunc.dtype == np.bool_
        for key, value in info.items():
            assert len(value) == n, key


@pytest.mark.slow
def test_make_vec_uses_the_vector_entry_point(env_id, single):
    venv = _clean_make(lambda: gym.make_vec(f"jaxrobo/{env_id}", num_envs=N_VEC), env_id)
    assert isinstance(venv.unwrapped, JaxroboVectorEnv)
    assert venv.unwrapped.params.max_episode_steps == gym.spec(f"jaxrobo/{env_id}").max_episode_steps
    _check_vector_env(venv, N_VEC)
    venv.close()


@pytest.fixture(scope="module")
def short_episodes():
    """CartPoleStayUpLeftRight-v0 with episodes that end fast both ways: the pole limit terminates, the step cap
    truncates."""
    return {"max_episode_steps": 6, "max_pole_angle": 0.03, "min_pole_angle": -0.03}


def test_vector_env_matches_sync_vector_env(short_episodes):
    """Same seeds, same actions: JaxroboVectorEnv == SyncVectorEnv(JaxroboEnv) step for step, across autoresets."""
    n = N_VEC
    ours = JaxroboVectorEnv("CartPoleStayUpLeftRight-v0", num_envs=n, overrides=short_episodes)
    ref = SyncVectorEnv([lambda: JaxroboEnv("CartPoleStayUpLeftRight-v0", overrides=short_episodes) for _ in range(n)],
                        autoreset_mode=AutoresetMode.NEXT_STEP)
    o1, _ = ours.reset(seed=9)
    o2, _ = ref.reset(seed=9)
    np.testing.assert_array_equal(o1, o2)
    rng = np.random.default_rng(1)
    saw_term = saw_trunc = saw_reset = False
    for _ in range(20):
        a = rng.integers(2, size=n)
        r1, r2 = ours.step(a), ref.step(a)
        for x, y in zip(r1[:4], r2[:4]):
            np.testing.assert_array_equal(x, y)
        assert data_equivalence(r1[4], r2[4], exact=True), (r1[4], r2[4])
        saw_term |= r1[2].any()
        saw_trunc |= r1[3].any()
        saw_reset |= (~r1[4]["_steps"]).any()
    assert saw_term and saw_trunc and saw_reset
    ours.close()
    ref.close()


def test_next_step_autoreset_semantics(short_episodes):
    venv = JaxroboVectorEnv("CartPoleStayUpLeftRight-v0", num_envs=N_VEC, overrides=short_episodes)
    venv.reset(seed=0)
    done = np.zeros(N_VEC, bool)
    for _ in range(12):
        obs, rew, term, trunc, info = venv.step(np.array([0, 1, 1]))
        # Envs that ended last step are reset now: first obs, reward 0, not done, steps masked out.
        assert np.all(rew[done] == 0.0) and not term[done].any() and not trunc[done].any()
        assert not info["_steps"][done].any() and np.all(info["_steps"][~done])
        assert np.all(info["steps"][~done] >= 1)
        done = term | trunc


def test_vector_invalid_actions():
    venv = JaxroboVectorEnv("CartPoleStayUpLeftRight-v0", num_envs=3)
    venv.reset(seed=0)
    for bad in (np.array([0, 1]), np.array([0, 1, 2]), np.array([0.0, 1.0, 0.0]), np.array([0, -1, 1]),
                np.array([[0, 1, 1]]), 1, np.array([0, np.nan, 1]), ["a", "b", "c"]):
        with pytest.raises(InvalidActionError, match="action"):
            venv.step(bad)
    venv.step([0, 1, 1])  # lists of ints are fine


def test_vector_env_seeds_per_env():
    venv = JaxroboVectorEnv("CartPoleStayUpLeftRight-v0", num_envs=3)
    a, _ = venv.reset(seed=[5, 6, 7])
    b, _ = venv.reset(seed=5)
    single = JaxroboEnv("CartPoleStayUpLeftRight-v0")
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a[1], single.reset(seed=6)[0])
    with pytest.raises(ValueError, match="2 seeds for 3 envs"):
        venv.reset(seed=[1, 2])


def test_gym_make_of_every_id_raises_no_warning():
    """Two versions of one name are the same task revised (Gymnasium calls the lower one "out of date" and names
    the newer): only the ids in SUPERSEDED may be such a lower version (the 2-action cart-pole, a different task,
    has a name of its own), and every id makes cleanly with warnings as errors, the superseded ones but for
    Gymnasium's pointer to their successor."""
    names: dict[str, list[str]] = {}
    for env_id in IDS:
        name, _, version = env_id.rpartition("-v")
        names.setdefault(name, []).append(version)
    for name, versions in names.items():
        older = sorted(versions, key=int)[:-1]
        assert all(f"{name}-v{v}" in SUPERSEDED for v in older), f"{name} has versions {versions}"
    gym_ids.register_gymnasium_envs()
    for env_id in IDS:
        _clean_make(lambda: gym.make(gym_ids.gym_id(env_id)), env_id).close()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env = gym.make("jaxrobo/CartPoleStayUp-v0", backend="analytic")
    assert env.unwrapped.jax_env.robot.sim.backend == "analytic"


def test_old_v1_name_is_a_jaxrobo_alias_only():
    """CartPoleStayUp-v1 (the first name of the 2-action task) still makes it in jaxrobo, with a FutureWarning;
    it is not a registered id, so Gymnasium never sees a v1 beside CartPoleStayUp-v0."""
    assert "CartPoleStayUp-v1" not in IDS and "jaxrobo/CartPoleStayUp-v1" not in gym.registry
    with pytest.warns(FutureWarning, match="CartPoleStayUpLeftRight-v0"):
        env = jaxrobo.make("CartPoleStayUp-v1")
    assert env.num_actions == 2 and env.spec.id == "CartPoleStayUpLeftRight-v0"


@pytest.mark.parametrize("size", [{"width": -1}, {"width": 0}, {"height": 2.5}, {"width": True},
                                  {"height": 10**6}, {"width": "320"}])
def test_a_bad_frame_size_is_refused_when_the_env_is_made(size, monkeypatch):
    """width/height are checked by gym.make / make_vec, before the env is built (it was a MuJoCo error at the first
    render() for -1, an empty frame for 0, 2.5 cut to 2, and for 10**6 a framebuffer failure read as a missing GL
    library); the Renderer checks them too."""
    from jaxrobo.pictures import render

    def built(*_a, **_kw):
        raise AssertionError("the env was built: the frame size was not refused first")
    monkeypatch.setattr(gym_adapter, "_make_env", built)
    name = next(iter(size))
    with pytest.raises(ValueError, match=rf"JaxroboEnv: {name}=.*: expected an integer >= 1 and <= 16384"):
        gym.make("jaxrobo/CartPoleStayUp-v0", render_mode="rgb_array", **size)
    with pytest.raises(ValueError, match=rf"JaxroboVectorEnv: {name}=.*: expected an integer >= 1"):
        gym.make_vec("jaxrobo/CartPoleStayUp-v0", num_envs=2, render_mode="rgb_array", **size)
    with pytest.raises(ValueError, match=rf"^{name}=.*: expected an integer >= 1"):
        render.Renderer(None, **{"width": 64, "height": 48, **size})
    assert render.check_frame_size(np.int64(64), 48) == (64, 48)
