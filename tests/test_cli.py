"""The `jaxrobo` command end to end: train writes a complete run directory, plot draws it, errors are clean."""
from __future__ import annotations

import csv
import json
import os

import numpy as np
import pytest
import yaml

from jaxrobo.cli import main
from jaxrobo.io.results import load_stats

TINY = ["--set", "nsteps=40", "--set", "chunk_steps=50", "--set", "eval_episodes=2", "--set", "eval_envs=2",
        "--set", "bins=[3, 6, 8, 10]", "--set", "state_low=[-2.4, -1.0, -0.3, -2.0]",
        "--set", "state_high=[2.4, 1.0, 0.3, 2.0]"]


#: What the module's one training printed on stderr (its progress: the bar and the evaluation's lines).
STDERR: list[str] = []
#: How often the module's one training built a Trainer and traced its programs (the Python bodies ran).
TRACES: dict[str, int] = {}


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    import contextlib
    import io

    from jaxrobo.training.trainer import Trainer

    def counted(name):
        real = getattr(Trainer, name)

        def call(self, *args, **kwargs):
            TRACES[name] = TRACES.get(name, 0) + 1
            return real(self, *args, **kwargs)
        return real, call

    out = str(tmp_path_factory.mktemp("runs") / "q")
    err = io.StringIO()
    patched = {name: counted(name) for name in ("__init__", "init", "run_chunk")}
    try:
        for name, (_, call) in patched.items():
            setattr(Trainer, name, call)
        with contextlib.redirect_stderr(err):
            assert main(["train", "--env", "CartPoleStayUp-v0", "--agent", "qlearn", "--n-envs", "4", "--nepisodes",
                         "6", "--out", out, *TINY]) == 0
    finally:
        for name, (real, _) in patched.items():
            setattr(Trainer, name, real)
    STDERR.append(err.getvalue())
    return out


def test_the_command_builds_one_trainer_and_traces_each_program_once(run_dir):
    """The command's trainer (built to check the budget and trace the checkpoint's template) is the one train()
    runs: one Trainer, and the carry's init and the training chunk each traced once."""
    assert TRACES == {"__init__": 1, "init": 1, "run_chunk": 1}, TRACES


def test_the_evaluation_reports_its_progress_with_an_eta(run_dir):
    """After the bar's 100 % the greedy evaluation is not silent: a line per segment of its steps, with the
    episodes still running and an ETA, for the tables and for the best table's fresh episodes."""
    log = STDERR[0]
    assert "evaluating 2 table(s) × 2 greedy episodes" in log
    lines = [ln for ln in log.splitlines() if ln.startswith("  evaluation (")]
    assert any(ln.startswith("  evaluation (tables): step ") for ln in lines), log
    assert any(ln.startswith("  evaluation (best table): step ") for ln in lines), log
    assert all("episodes running" in ln and ("ETA ≤" in ln or ln.endswith("done")) for ln in lines), lines


def test_train_writes_config_records_tables_summary_and_tensorboard(run_dir):
    files = set(os.listdir(run_dir))
    assert {"config.yaml", "episodes.csv", "episode_stats.csv", "records.npz", "summary.json", "qtables.npz",
            "eval.csv", "tensorboard"} <= files
    cfg = yaml.safe_load(open(os.path.join(run_dir, "config.yaml")))
    assert cfg["env_id"] == "CartPoleStayUp-v0" and cfg["train"]["agent"] == "qlearn"
    assert cfg["train"]["n_envs"] == 4 and cfg["env_options"]["control_type"] == "velocity"
    rows = list(csv.DictReader(open(os.path.join(run_dir, "episodes.csv"))))
    assert len(rows) == 4 * 6 and set(rows[0]) == {"env", "episode", "return", "length", "terminated", "epsilon"}
    summary = json.load(open(os.path.join(run_dir, "summary.json")))
    assert summary["n_envs"] == 4 and "best_100_mean_length" in summary
    tables = np.load(os.path.join(run_dir, "qtables.npz"), allow_pickle=False)
    assert tables["q"].shape == (4, 1, 1440, 4) and tuple(tables["bins"]) == (3, 6, 8, 10)
    assert os.listdir(os.path.join(run_dir, "tensorboard"))
    stats = load_stats(run_dir)
    assert stats["return_mean"].shape == (6,)


def test_plot_overlays_runs_into_a_png(run_dir, tmp_path):
    png = str(tmp_path / "cmp.png")
    assert main(["plot", run_dir, run_dir, "--labels", "a", "b", "--out", png]) == 0
    with open(png, "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"


def test_plot_reads_a_run_with_only_episodes_csv(run_dir, tmp_path):
    slim = tmp_path / "slim"
    slim.mkdir()
    (slim / "episodes.csv").write_text(open(os.path.join(run_dir, "episodes.csv")).read())
    stats = load_stats(str(slim))
    np.testing.assert_allclose(stats["return_mean"], load_stats(run_dir)["return_mean"], rtol=1e-5)


def test_bad_values_exit_2_with_the_key_named(capsys):
    assert main(["train", "--set", "alpha=7", "--no-progress"]) == 2
    assert "alpha=7.0: expected a number > 0.0 and <= 1.0" in capsys.readouterr().err
    assert main(["plot", "/nonexistent/run"]) == 2


def test_list_names_envs_and_agents(capsys):
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    assert "CartPoleStayUp-v0" in out and "qlearn" in out


def test_train_help_and_readme_say_what_a_new_user_needs(capsys):
    """`jaxrobo train --help`: the carry is also saved at the end of training; the README links every docs page
    it names (they exist) and the usage guide shows a PPO run and `show` on it; the envs package lists its
    continuous-action task modules."""
    import re

    import envs
    from jaxrobo.task import registry
    from jaxrobo.core import spaces

    with pytest.raises(SystemExit):
        main(["train", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    entry = help_text[help_text.index("--checkpoint-every N save"):]
    assert "also always saved at the end of training, before the evaluation" in entry[:400]

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    with open(os.path.join(root, "README.md")) as f:
        readme = f.read()
    links = re.findall(r"\]\((docs/[^)#]+)\)", readme)
    assert "docs/deep_rl.md" in links and "docs/usage.md" in links
    for link in links:
        assert os.path.isfile(os.path.join(root, link)), link
    with open(os.path.join(root, "docs", "usage.md")) as f:
        usage = f.read()
    assert "jaxrobo train --env QuadcopterGotoTwist-v0 --agent ppo --out runs/goto_ppo" in usage
    assert re.search(r"^jaxrobo show runs/ppo_smoke\b", usage, re.M)  # show on a deep run the guide trains

    for env_id in registry.registered():
        reg = registry.registration(env_id)
        if reg.module is None and isinstance(registry.make(env_id).action_space(), spaces.Box):
            module = "/".join(reg.env_class().__module__.split(".")[1:])  # family/module, e.g. cartpole/continuous
            assert f"``{module}.py``" in envs.__doc__ and f"``{env_id}``" in envs.__doc__, env_id
