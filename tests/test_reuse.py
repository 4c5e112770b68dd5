"""Traced programs kept across processes (jaxrobo.speed.reuse): the same run whether a trace was read back or made,
a key that follows what the trace reads, and kept files that cannot be trusted traced afresh."""
from __future__ import annotations

import enum
import os
import subprocess
import sys

import numpy as np
import pytest

from jaxrobo.speed import reuse
from jaxrobo.speed.plan import ExecutionPlan
from jaxrobo.training.run import resolve
from jaxrobo.training.train import train
from jaxrobo.training.trainer import Trainer

SMALL = {"env.backend": "analytic", "n_envs": 8, "nepisodes": 4, "nsteps": 40, "chunk_steps": 40, "eval_episodes": 4,
         "eval_envs": 2, "stop_at_target": False}
PROGRAMS = ("init", "chunk", "eval_start", "eval_advance")


class Mode(enum.Enum):
    FAST = 1


@pytest.fixture
def kept(tmp_path, monkeypatch):
    """Reuse on, its files in a folder of this test's own."""
    monkeypatch.setenv("JAXROBO_REUSE_TRACES", "on")
    monkeypatch.setattr(reuse, "_directory", lambda: str(tmp_path / "traced"))
    monkeypatch.setattr(reuse, "LAST", {})
    return tmp_path / "traced"


def run(reuse_traces: bool, beside: bool = False, **overrides):
    spec = resolve("CartPoleStayUp-v0", overrides={**SMALL, **overrides})
    plan = Trainer(spec.env, spec.config).plan.replace(reuse_traces=reuse_traces, compile_beside=beside)
    r = train(spec.env, spec.config, spec.agent_params, plan=plan)
    return [np.asarray(a) for a in (r.q, r.returns, r.lengths, r.eval_returns, r.eval_lengths)]


def same(a, b):
    return all(x.shape == y.shape and x.dtype == y.dtype and x.tobytes() == y.tobytes() for x, y in zip(a, b))


@pytest.mark.parametrize("beside", [False, True])
def test_a_run_is_the_same_traced_kept_or_read_back(kept, beside):
    """Also with the first carry and the evaluation compiled in threads beside the chunk (``compile_beside``, a
    GPU's default), from the carry's shapes: every program traced and kept, then read back, and the plain run's
    bytes both times."""
    plain = run(False)
    assert all(reuse.LAST.get(p, "off") == "off" for p in PROGRAMS)
    first = run(True, beside)
    assert {p: reuse.LAST[p] for p in PROGRAMS} == dict.fromkeys(PROGRAMS, "traced")
    assert {f.split("-")[0] for f in os.listdir(kept)} == set(PROGRAMS)
    second = run(True, beside)
    assert {p: reuse.LAST[p] for p in PROGRAMS} == dict.fromkeys(PROGRAMS, "read")
    assert same(plain, first) and same(first, second)


def test_another_configuration_is_traced_again(kept):
    run(True)
    before = set(os.listdir(kept))
    run(True, nsteps=30)  # a static setting (the episode's step limit): other programs, other keys
    assert reuse.LAST["chunk"] == "traced"
    assert any(f.startswith("chunk-") for f in set(os.listdir(kept)) - before)


def test_another_seed_reads_the_traces_back_and_runs_as_its_plain_run(kept):
    """The seed is host-only (it makes the first key, an argument of every program): a run of seed 3 reads the
    traces a seed-0 run kept, and ends with the bytes of seed 3 traced afresh."""
    run(True)
    before = set(os.listdir(kept))
    again = run(True, seed=3)
    assert {p: reuse.LAST[p] for p in PROGRAMS} == dict.fromkeys(PROGRAMS, "read")
    assert set(os.listdir(kept)) == before
    assert same(run(False, seed=3), again) and not same(run(False), again)


def test_no_program_reads_the_seed():
    """What makes the seed host-only: the training chunk traced under two seeds is the same program."""
    import jax

    traced = []
    for seed in (0, 5):
        spec = resolve("CartPoleStayUp-v0", overrides={**SMALL, "seed": seed})
        t = Trainer(spec.env, spec.config)
        runner = jax.eval_shape(t.init, jax.random.key(0), spec.agent_params, spec.env.default_params)
        traced.append(str(jax.make_jaxpr(t.run_chunk)(runner, spec.agent_params, spec.env.default_params)))
    assert traced[0] == traced[1]


@pytest.mark.parametrize("damage", ["garbage", "empty", "fifo", "link", "directory"])
def test_a_kept_file_that_cannot_be_trusted_is_traced_afresh(kept, tmp_path, damage):
    good = run(True)
    for name in os.listdir(kept):
        path = kept / name
        path.unlink()
        if damage == "garbage":
            path.write_bytes(os.urandom(4096))
        elif damage == "empty":
            path.write_bytes(b"")
        elif damage == "fifo":
            os.mkfifo(path)  # reading it would wait for a writer
        elif damage == "link":
            (tmp_path / "elsewhere").write_bytes(b"not an export")
            path.symlink_to(tmp_path / "elsewhere")
        else:
            path.mkdir()
    again = run(True)
    assert all(reuse.LAST[p].startswith(("traced", "off")) for p in PROGRAMS)
    assert same(good, again)
    if damage == "link":  # the link's target is never written through
        assert (tmp_path / "elsewhere").read_bytes() == b"not an export"


def test_the_key_follows_what_the_trace_reads():
    spec = resolve("CartPoleStayUp-v0", overrides=SMALL)
    t = Trainer(spec.env, spec.config)
    args = (np.zeros(3, np.float32),)
    base = reuse._key("chunk", t, t.plan, args, (0,))
    assert base == reuse._key("chunk", t, t.plan, args, (0,))  # deterministic
    other = resolve("CartPoleStayUp-v0", overrides={**SMALL, "n_envs": 16})
    assert base != reuse._key("chunk", Trainer(other.env, other.config), t.plan, args, (0,))
    assert base != reuse._key("chunk", t, t.plan.replace(unrolled_groups=2), args, (0,))
    assert base != reuse._key("chunk", t, t.plan, (np.zeros(4, np.float32),), (0,))
    assert base != reuse._key("chunk", t, t.plan, (np.zeros(3, np.int32),), (0,))
    assert base != reuse._key("init", t, t.plan, args, (0,))
    assert base != reuse._key("chunk", t, t.plan, args, ())
    # arrays count by their values, not their repr (which numpy abbreviates)
    a, b = np.zeros(5000, np.float32), np.zeros(5000, np.float32)
    b[2500] = 1
    assert reuse.describe(a) != reuse.describe(b)


def test_the_environment_switch_turns_reuse_off(kept, monkeypatch):
    assert reuse.available()
    monkeypatch.setenv("JAXROBO_REUSE_TRACES", "off")
    assert not reuse.available()
    spec = resolve("CartPoleStayUp-v0", overrides=SMALL)
    assert not Trainer(spec.env, spec.config).plan.reuse_traces
    monkeypatch.setenv("JAXROBO_REUSE_TRACES", "on")
    assert Trainer(spec.env, spec.config).plan.reuse_traces


def test_a_patch_at_run_time_changes_the_key_and_undoing_it_restores_it(monkeypatch):
    import importlib

    from envs.cartpole.dynamics import CartPoleSim

    before = reuse._live_code()
    for name in ("envs.quadcopter.native", "jaxrobo.pictures.plots", "jaxrobo.interop.numpy_policy"):
        importlib.import_module(name)  # more modules loaded, none patched: the same key
    assert reuse._live_code() == before
    monkeypatch.setattr(CartPoleSim, "physics_step", lambda self, s, ctrl: s)
    patched = reuse._live_code()
    assert patched != before
    monkeypatch.undo()
    assert reuse._live_code() == before


def test_what_the_key_cannot_describe_is_not_reused(kept):
    class Opaque:
        __slots__ = ()

    with pytest.raises(reuse.NotKeyable):
        reuse.describe([1, Opaque()])
    plan = ExecutionPlan(reuse_traces=True)
    f = reuse.compile_reusing(plan, "probe", lambda x: x * 2, (np.float32(3),), Opaque())
    assert float(f(np.float32(3))) == 6.0 and reuse.LAST["probe"].startswith("off: ")


def test_the_command_line_reads_its_traces_back_in_a_second_process(tmp_path):
    """As a user runs it: the second start of the same command reads every program back and trains the same."""
    code = ("import sys; from jaxrobo.cli import main; from jaxrobo.speed import reuse\n"
            "rc = main(sys.argv[1:]); print('REUSE', sorted(reuse.LAST.items())); sys.exit(rc)")
    env = {**os.environ, "JAXROBO_CACHE_DIR": str(tmp_path / "cache"), "JAX_PLATFORMS": "cpu",
           "JAXROBO_REUSE_TRACES": "on"}
    out = []
    for i in range(2):
        cmd = [sys.executable, "-c", code, "train", "--env", "CartPoleStayUp-v0", "--no-progress", "--out",
               str(tmp_path / f"run{i}"), "--set", "env.backend=analytic", "--n-envs", "8", "--set", "nepisodes=4",
               "--set", "nsteps=40", "--set", "stop_at_target=false"]
        p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
        assert p.returncode == 0, p.stderr[-2000:]
        out.append(p.stdout)
    assert "reuse_traces=on" in out[0]
    assert "('chunk', 'traced')" in out[0] and "('chunk', 'read')" in out[1], out[1][-500:]
    assert "('eval_advance', 'read')" in out[1]
    tables = [np.load(tmp_path / f"run{i}" / "qtables.npz") for i in range(2)]
    assert sorted(tables[0].files) == sorted(tables[1].files)
    assert all(tables[0][k].tobytes() == tables[1][k].tobytes() for k in tables[0].files)


def test_a_sweep_reads_its_group_back_and_gives_the_same_rows(kept):
    from jaxrobo.training.sweep.running import run_sweep

    def sweep():
        r = run_sweep("CartPoleStayUp-v0", [{"alpha": 0.1}, {"alpha": 0.3}], seeds=(0, 1), eval_episodes=2,
                      overrides={k: v for k, v in SMALL.items() if k not in ("eval_episodes", "eval_envs")})
        return [{k: v for k, v in row.items() if not k.endswith("seconds")} for row in r.rows]

    first = sweep()
    assert reuse.LAST["sweep_chunk"] == "traced"
    second = sweep()
    assert {p: reuse.LAST[p] for p in ("sweep_init", "sweep_chunk", "sweep_finish")} == dict.fromkeys(
        ("sweep_init", "sweep_chunk", "sweep_finish"), "read")
    assert repr(first) == repr(second)


@pytest.mark.slow  # three processes of a user's own task
def test_a_users_own_task_edited_between_runs_is_traced_again(tmp_path):
    """A task in the user's own module (examples/custom_task): its code is part of the key, so a second run reads
    the traces back, and a run after an edit of the task's step traces afresh and trains the edited task."""
    import shutil

    folder = tmp_path / "custom_task"
    shutil.copytree(os.path.join(os.path.dirname(__file__), "..", "examples", "custom_task"), folder)
    code = ("import sys; from jaxrobo.cli import main; from jaxrobo.speed import reuse\n"
            "rc = main(sys.argv[1:]); print('REUSE', sorted(reuse.LAST.items())); sys.exit(rc)")
    env = {**os.environ, "JAXROBO_CACHE_DIR": str(tmp_path / "cache"), "JAX_PLATFORMS": "cpu",
           "JAXROBO_REUSE_TRACES": "on", "PYTHONPATH": os.path.dirname(os.path.dirname(os.path.abspath(__file__)))}

    def run(i):
        cmd = [sys.executable, "-c", code, "train", "--env", "my_task:MyPendulum-v0", "--n-envs", "2", "--nepisodes",
               "3", "--no-progress", "--set", "nsteps=20", "--set", "eval_episodes=2", "--set", "eval_envs=1",
               "--set", "stop_at_target=false", "--out", str(tmp_path / f"run{i}")]
        p = subprocess.run(cmd, env=env, cwd=folder, capture_output=True, text=True, timeout=600)
        assert p.returncode == 0, p.stderr[-2000:]
        with np.load(tmp_path / f"run{i}" / "qtables.npz") as z:
            return p.stdout, z["q"].tobytes()

    out0, q0 = run(0)
    out1, q1 = run(1)
    assert "('chunk', 'traced')" in out0 and "('chunk', 'read')" in out1 and q0 == q1
    task = folder / "my_task.py"
    text = task.read_text()
    assert "return jnp.abs(obs[0]) >= params.max_angle" in text
    task.write_text(text.replace("return jnp.abs(obs[0]) >= params.max_angle",
                                 "return jnp.abs(obs[0]) >= 0.5 * params.max_angle"))
    out2, q2 = run(2)
    assert "('chunk', 'traced')" in out2 and q2 != q0


def test_a_deep_runs_programs_are_read_back_and_evaluate_the_same(kept):
    """A PPO run's evaluation of its policy (jaxrobo.deep.training.evaluate) and Brax's training epoch are kept
    like a tabular run's programs: the second run reads them back instead of tracing them, and every evaluation
    point has the same bytes."""
    from jaxrobo import deep

    spec = deep.resolve("QuadcopterGotoTwist-v0", "ppo", "tiny",
                        {"episode_length": 20, "eval_episodes": 3, "num_timesteps": 512})
    got = []
    for expected in ("traced", "read"):
        result = deep.train(spec)
        assert reuse.LAST["deep_evaluation"] == reuse.LAST["deep_epoch_ppo"] == expected
        got.append([np.asarray(e[k]) for e in result.evaluations for k in ("return", "length", "success")])
    assert len(got[0]) >= 6 and same(got[0], got[1])


def test_static_fields_are_kept_as_literals_and_enums_by_name():
    """A structure's static fields are written as Python literals (reading them back runs no code); an enum
    member (Brax's normaliser names its mode with one) by its loaded class and name; anything else is refused."""
    aux = (("a", 1), {"mode": "x"}, [2.5, None], Mode.FAST)
    assert reuse._aux_value(reuse._aux_bytes(aux)) == aux
    with pytest.raises(reuse.NotKeyable):
        reuse._aux_bytes((object(),))
    forged = repr({reuse._ENUM: ("os", "system", "x")}).encode()  # names something that is not an enum
    with pytest.raises(ValueError, match="not a member of a loaded enum"):
        reuse._aux_value(forged)
    with pytest.raises(ValueError, match="not a member of a loaded enum"):  # a loaded enum, no such member
        reuse._aux_value(repr({reuse._ENUM: (Mode.__module__, "Mode", "SLOW")}).encode())


def test_a_deep_run_through_kept_traces_stopped_and_resumed_ends_as_the_plain_run(kept, tmp_path, monkeypatch):
    """Brax's training epoch runs through a kept trace (program ``deep_epoch_ppo``) where the process reuses
    traces: a run stopped by SIGTERM after its third epoch and resumed, both through kept traces, ends with the
    bytes of the uninterrupted run that traced nothing (Brax's own mapped epoch)."""
    import signal

    from jaxrobo import deep
    from jaxrobo.cli import main

    args = ["train", "--env", "CartPoleContinuous-v0", "--agent", "ppo", "--preset", "tiny", "--set",
            "episode_length=20", "--set", "eval_episodes=3", "--set", "num_evals=6", "--total-steps", "1024",
            "--no-progress"]
    plain, stopped = str(tmp_path / "plain"), str(tmp_path / "stopped")
    monkeypatch.setenv("JAXROBO_REUSE_TRACES", "off")
    assert main([*args, "--out", plain]) == 0
    assert reuse.LAST.get("deep_epoch_ppo") is None
    monkeypatch.setenv("JAXROBO_REUSE_TRACES", "on")
    original = deep.LiveRun.point

    def point(self, p):
        original(self, p)
        if p.epochs_done == 3:
            os.kill(os.getpid(), signal.SIGTERM)  # StopOnSignal takes it: the run stops right after this point

    with monkeypatch.context() as m:
        m.setattr(deep.LiveRun, "point", point)
        assert main([*args, "--out", stopped]) == 128 + signal.SIGTERM
    assert reuse.LAST["deep_epoch_ppo"] == "traced"
    assert main(["train", "--resume", stopped, "--no-progress"]) == 0
    assert reuse.LAST["deep_epoch_ppo"] == "traced"  # the resumed call's budget is another key
    for name in ("policy.npz", "evaluations.csv", "best/policy.npz"):
        with open(os.path.join(plain, name), "rb") as a, open(os.path.join(stopped, name), "rb") as b:
            assert a.read() == b.read(), name
