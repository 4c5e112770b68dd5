"""The native-MuJoCo ports (``envs/*/native.py``) step as the JAX tasks do: from the same reset, under the same
actions, the observations agree to float32 round-off of the JAX side (float32 there, float64 in MuJoCo's C engine)
and the episode ends at the same step. ``scripts/sim2sim.py`` runs end to end on a tiny run."""
from __future__ import annotations

import importlib
import importlib.util
import os

import jax
import numpy as np
import pytest

import jaxrobo
from jaxrobo.cli import main

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
STEPS = 12

#: id, native module and class (each task on its default backend: MJX for the cart-pole and the arm, the closed
#: forms for the continuous cart-pole and the quadcopter)
CASES = [("CartPoleStayUp-v0", "envs.cartpole.native", "NativeCartPole"),
         ("CartPoleContinuous-v0", "envs.cartpole.native", "NativeCartPole"),
         ("QuadcopterGoto-v2", "envs.quadcopter.native", "NativeGoto"),
         ("QuadcopterGoto-v1", "envs.quadcopter.native", "NativeGoto"),
         ("QuadcopterGotoTwist-v0", "envs.quadcopter.native", "NativeGoto"),
         ("ArmReach-v0", "envs.arm.native", "NativeArm")]


@pytest.mark.slow
@pytest.mark.parametrize("env_id,module,name", CASES, ids=[c[0] for c in CASES])
def test_native_port_steps_as_jax(env_id, module, name):
    env = jaxrobo.make(env_id)
    native = getattr(importlib.import_module(module), name)(env)
    rng = np.random.default_rng(0)
    for episode in range(3):
        state = jax.jit(env.reset)(jax.random.key(episode))
        space = env.action_space()
        actions = (rng.uniform(-1, 1, (STEPS, *space.shape)).astype(np.float32) if hasattr(space, "low")
                   else rng.integers(0, space.n, STEPS))
        step = jax.jit(env.step)
        obs, done_at = [np.asarray(state.obs)], None
        for t, a in enumerate(actions):
            state = step(state, a)
            obs.append(np.asarray(state.obs))
            if bool(state.terminated):
                done_at = t + 1
                break
        first = jax.jit(env.reset)(jax.random.key(episode))
        qpos = np.asarray(env.robot.sim.qpos(first.pipeline_state), np.float64)
        qvel = np.asarray(env.robot.sim.qvel(first.pipeline_state), np.float64)
        it = iter(actions)
        ep = native.episode(lambda o: next(it), qpos, qvel, jax.tree.map(np.asarray, first.task),
                            horizon=STEPS)
        n = len(obs)
        assert ep["obs"].shape[0] == n, (env_id, episode, ep["length"], done_at)
        scale = np.maximum(1.0, np.abs(np.asarray(obs)))
        assert np.max(np.abs(ep["obs"] - np.asarray(obs)) / scale) < 1e-4, (env_id, episode)


@pytest.mark.slow
def test_sim2sim_script(tmp_path, capsys):
    run = str(tmp_path / "run")
    assert main(["train", "--env", "ArmReach-v0", "--n-envs", "2", "--nepisodes", "4", "--set", "nsteps=30",
                 "--set", "eval_episodes=2", "--set", "chunk_steps=30", "--out", run, "--no-progress"]) == 0
    spec = importlib.util.spec_from_file_location("sim2sim", os.path.join(ROOT, "scripts", "sim2sim.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    capsys.readouterr()
    assert mod.main([run, "--episodes", "5"]) == 0
    out = capsys.readouterr().out
    assert "native MuJoCo" in out and "same outcome in" in out
    line = next(s for s in out.splitlines() if s.startswith("exported runner on JAX's observations"))
    agree, total = line.split(": ")[1].split(" ")[0].split("/")
    assert agree == total and int(total) > 0
    assert mod.main([str(tmp_path / "nothing"), "--episodes", "5"]) == 2
    # the run's tables read through another discretiser than they were exported with: refused before any program
    policy = str(tmp_path / "policy")
    assert main(["export", run, "--out", policy]) == 0
    path = os.path.join(run, "qtables.npz")
    with np.load(path) as z:
        arrays = dict(z)
    np.savez(path, **{**arrays, "low": arrays["low"] + np.float32(0.5)})
    capsys.readouterr()
    assert mod.main([run, "--policy", policy, "--episodes", "5"]) == 2
    err = capsys.readouterr().err
    assert f"sim2sim: {path}: the discretiser's low[0]=" in err, err


def test_native_base_imports_no_jax():
    """The native side of the check runs an export without JAX: the ports' shared base (``jaxrobo/interop/native.py``)
    imports MuJoCo and numpy only."""
    import ast

    with open(os.path.join(ROOT, "jaxrobo", "interop", "native.py")) as f:
        tree = ast.parse(f.read())
    names = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    names |= {(n.module or "").split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    assert names <= {"__future__", "typing", "mujoco", "numpy"}, names


def test_task_step_modules_import_no_jax():
    """The ``envs`` package registers its ids only when the registry asks: in a fresh process, the package and the
    per-coordinate modules the quadcopter's hooks, kernels and native port share import without loading JAX."""
    import subprocess
    import sys

    code = ("import sys\n"
            "import envs, envs.quadcopter.geometry, envs.quadcopter.dynamics, envs.quadcopter.goto_step\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('jax', 'jaxlib', 'jaxrobo')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]", out.stdout
