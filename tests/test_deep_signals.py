"""``jaxrobo train --agent ppo|sac`` stopped by SIGTERM/SIGINT before its first evaluation point: Brax's trainer
cannot be paused, so it is stopped where it hands control back; the run directory says ``interrupted``, nothing
half-trained is published and an old run that ``--overwrite`` was to replace is kept. Brax's trainers are replaced
by fakes (nothing compiles). A run stopped after a point keeps its work: tests/test_deep_resume.py."""
from __future__ import annotations

import json
import os
import signal

import pytest
from brax.training import acting
from brax.training.agents.ppo import train as ppo
from brax.training.agents.sac import train as sac

from jaxrobo import deep
from jaxrobo.cli import main

CPC = "CartPoleContinuous-v0"
ARGS = ["--env", CPC, "--agent", "ppo", "--preset", "tiny", "--set", "episode_length=20", "--no-progress"]


def _status(path):
    with open(os.path.join(path, "status.json")) as f:
        return json.load(f)


def _hidden(root):
    return sorted(n for n in os.listdir(root) if n.startswith("."))


@pytest.mark.parametrize("agent, module, callback", [("ppo", ppo, "policy_params_fn"), ("ppo", ppo, "progress_fn"),
                                                     ("sac", sac, "progress_fn")])
def test_train_stops_where_the_trainer_hands_back_control(monkeypatch, agent, module, callback):
    calls = []

    def fake_train(**kwargs):
        calls.append(callback)
        fn = kwargs[callback]
        fn(0, *((lambda *a, **k: None, None) if callback == "policy_params_fn" else ({},)))
        raise AssertionError("not reached: should_stop said stop")

    monkeypatch.setattr(module, "train", fake_train)
    original = acting.Evaluator
    spec = deep.resolve(CPC, agent, "tiny")
    with pytest.raises(deep.TrainingStopped, match="stopped at 0 of"):
        deep.train(spec, should_stop=lambda: True)
    assert calls == [callback] and acting.Evaluator is original


def _fake_ppo(monkeypatch, behaviour):
    def fake_train(**kwargs):
        behaviour(kwargs)
        raise AssertionError("not reached: the run was to stop")

    monkeypatch.setattr(ppo, "train", fake_train)


def test_sigterm_during_training_marks_the_run_interrupted(tmp_path, monkeypatch, capsys):
    def sigterm_then_progress(kwargs):
        os.kill(os.getpid(), signal.SIGTERM)  # StopOnSignal takes it: the trainer goes on to its next callback
        kwargs["progress_fn"](0, {})

    _fake_ppo(monkeypatch, sigterm_then_progress)
    before = signal.getsignal(signal.SIGTERM)
    out = str(tmp_path / "run")
    assert main(["train", *ARGS, "--out", out]) == 128 + signal.SIGTERM
    status = _status(out)
    assert status["status"] == "interrupted" and status["signal"] == "SIGTERM"
    assert "--overwrite" in status["resume"]
    assert sorted(os.listdir(out)) == ["config.yaml", "status.json"]  # nothing trained, nothing half-written
    assert _hidden(tmp_path) == [] and signal.getsignal(signal.SIGTERM) is before
    err = capsys.readouterr().err
    assert "SIGTERM: stopping at the end of the trainer's current step" in err and "nothing trained to keep" in err


@pytest.mark.parametrize("how", ["KeyboardInterrupt", "second SIGTERM"])
def test_interrupt_that_cannot_wait_for_the_trainer(tmp_path, monkeypatch, how):
    def stop(kwargs):
        if how == "KeyboardInterrupt":
            raise KeyboardInterrupt
        os.kill(os.getpid(), signal.SIGTERM)
        os.kill(os.getpid(), signal.SIGTERM)  # the second exits at once, inside the trainer

    _fake_ppo(monkeypatch, stop)
    out = str(tmp_path / "run")
    code = main(["train", *ARGS, "--out", out])
    assert code == (130 if how == "KeyboardInterrupt" else 128 + signal.SIGTERM)
    assert _status(out)["status"] == "interrupted" and not os.path.exists(os.path.join(out, "policy.npz"))
    assert _hidden(tmp_path) == []


def test_a_stopped_overwrite_keeps_the_old_run(tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    out.mkdir()
    (out / "status.json").write_text(json.dumps({"status": "complete"}))
    (out / "summary.json").write_text("{}")

    def sigterm_then_params(kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        kwargs["policy_params_fn"](0, lambda *a, **k: None, None)

    _fake_ppo(monkeypatch, sigterm_then_params)
    assert main(["train", *ARGS, "--out", str(out), "--overwrite"]) == 128 + signal.SIGTERM
    assert _status(str(out)) == {"status": "complete"} and sorted(os.listdir(out)) == ["status.json", "summary.json"]
    assert _hidden(tmp_path) == []  # the new run's staging directory is gone
    assert "still holds the run it had (not replaced)" in capsys.readouterr().err
