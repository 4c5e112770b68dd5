"""Brax's JAXopt and Orbax imports deferred to first use (jaxrobo.interop.deferred_imports): a PPO run never loads
them, the ``generalized`` pipeline loads JAXopt as it traces a step with constraints to solve and steps as with it
imported up front, a stand-in loads once under threads, version-guarded."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading

import pytest

from jaxrobo.core import deferred
from jaxrobo.interop import brax_compat, deferred_imports

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
GUARDED = pytest.mark.skipif(
    deferred_imports.unavailable() not in (None, deferred_imports.IMPORTED_ALREADY),
    reason="the installed brax is not the one it was written for (jaxrobo.interop.deferred_imports.unavailable)")

PPO_RUN = """
import json, sys, tempfile
from jaxrobo.cli import main
out = tempfile.mkdtemp()
code = main(["train", "--env", "CartPoleContinuous-v0", "--agent", "ppo", "--preset", "tiny", "--set",
             "episode_length=20", "--set", "eval_episodes=3", "--set", "num_timesteps=512", "--out", out + "/r",
             "--no-progress"])
print(json.dumps({"code": code, "state": {n: type(sys.modules.get(n)).__name__
                                          for n in ("jaxopt", "orbax.checkpoint")},
                  "scipy.optimize": "scipy.optimize" in sys.modules}))
"""

#: A sphere on a plane through Brax's generalized pipeline: its contact makes the step solve constraints (JAXopt).
GENERALIZED = """
import json, sys
{first}
import jax, jax.numpy as jp, numpy as np
from brax.generalized import pipeline
from brax.io import mjcf
model = mjcf.loads('<mujoco><option timestep="0.01" integrator="Euler"/><worldbody><geom type="plane" '
                   'size="1 1 .1"/><body pos="0 0 0.105"><freejoint/><geom type="sphere" size="0.1" mass="1"/>'
                   '</body></worldbody></mujoco>')
state = pipeline.init(model, model.init_q, jp.zeros(model.qd_size()))
step = jax.jit(lambda s: pipeline.step(model, s, jp.zeros(model.act_size())))
for _ in range(5):
    state = step(state)
print(json.dumps({{"q": np.asarray(state.q).tolist(), "jaxopt": type(sys.modules.get("jaxopt")).__name__}}))
"""


def _run(code: str) -> dict:
    env = {**os.environ, "PYTHONPATH": ROOT, "JAX_PLATFORMS": "cpu"}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600,
                          cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.slow
@GUARDED
def test_a_ppo_run_never_loads_jaxopt_or_orbax():
    got = _run(PPO_RUN)
    assert got["code"] == 0
    assert got["state"] == {"jaxopt": "Deferred", "orbax.checkpoint": "Deferred"}, got
    assert not got["scipy.optimize"]


@pytest.mark.slow
@GUARDED
def test_the_generalized_pipeline_loads_jaxopt_as_it_traces_and_steps_as_with_it_up_front():
    deferred = _run(GENERALIZED.format(first="import jaxrobo.interop.brax_env"))
    stock = _run(GENERALIZED.format(first="import jaxopt"))
    assert deferred["jaxopt"] == "module" and stock["jaxopt"] == "module"  # loaded, and replaced in sys.modules
    assert deferred["q"] == stock["q"]
    assert deferred["q"][2] != 0.105  # it moved: gravity, and the contact's constraint force


def test_a_stand_in_loads_its_module_once_and_forwards_everything(monkeypatch):
    name = "json.tool"  # a real, small module, not imported by the suite
    monkeypatch.delitem(sys.modules, name, raising=False)
    stand_in = deferred.Deferred(name)
    monkeypatch.setitem(sys.modules, name, stand_in)
    imports = []
    real_import = deferred.importlib.import_module

    def counting(n, *a):
        imports.append(n)
        return real_import(n, *a)

    monkeypatch.setattr(deferred.importlib, "import_module", counting)
    got, start = [], threading.Barrier(8)

    def use():
        start.wait()
        got.append(stand_in.main)

    threads = [threading.Thread(target=use) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert imports == [name] and stand_in.loaded
    assert len({id(f) for f in got}) == 1 and sys.modules[name] is not stand_in
    assert got[0] is sys.modules[name].main


def test_a_module_that_fails_to_import_says_why_and_stays_deferred(monkeypatch):
    stand_in = deferred.Deferred("jaxrobo_no_such_module")
    monkeypatch.setitem(sys.modules, "jaxrobo_no_such_module", stand_in)
    with pytest.raises(ModuleNotFoundError, match="jaxrobo_no_such_module"):
        stand_in.anything
    assert sys.modules["jaxrobo_no_such_module"] is stand_in and not stand_in.loaded


def test_outside_the_versions_it_was_written_for_brax_imports_as_it_does(monkeypatch):
    """The guard is brax_compat's: one range for every Brax trick."""
    monkeypatch.setattr(brax_compat, "installed_version", lambda: "0.99.1")
    assert "outside the versions jaxrobo.interop.brax_compat was written for" in deferred_imports.unavailable()
    assert deferred_imports.defer_brax_extras() == []


BRAX_CHECKPOINT = """
import json, sys, tempfile
import jaxrobo.interop.brax_env  # the stand-ins, as in any jaxrobo process
import jax.numpy as jnp, numpy as np
from brax.training import checkpoint
from brax.training.acme import running_statistics, specs
from ml_collections import config_dict
before = type(sys.modules["orbax.checkpoint"]).__name__
import orbax
ocp_class = orbax.checkpoint.PyTreeCheckpointer  # through the package's attribute: loads the real module
norm = running_statistics.init_state(specs.Array((3,), jnp.float32))
params = (norm, {"w": jnp.arange(6.0).reshape(2, 3)}, {"b": jnp.ones(4)})
path = tempfile.mkdtemp()
checkpoint.save(path, 7, params, config_dict.ConfigDict({"network_factory_kwargs": {}}))
back = checkpoint.load(path + "/000000000007")
import orbax.checkpoint  # a user's own spelling, after the real module loaded through the stand-in
print(json.dumps({"before": before, "after": type(sys.modules["orbax.checkpoint"]).__name__,
                  "package": orbax.checkpoint.PyTreeCheckpointer is ocp_class,
                  "same": bool(np.array_equal(back[1]["w"], params[1]["w"])
                               and np.array_equal(back[2]["b"], params[2]["b"])
                               and np.array_equal(back[0].std, norm.std))}))
"""


@GUARDED
def test_brax_own_checkpoints_save_and_load_through_the_stand_in():
    """A user's Brax checkpoint (``save_checkpoint_path``'s ``checkpoint.save``/``load``, Orbax) in a process where
    jaxrobo deferred Orbax: it loads on first use and the parameters come back."""
    got = _run(BRAX_CHECKPOINT)
    assert got == {"before": "Deferred", "after": "module", "package": True, "same": True}, got
