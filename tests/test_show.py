"""``jaxrobo show`` for every task and learner, and the plots a person reads (distinct labels, goals in place).

CPU-sized: runs of 2-4 envs and a few short episodes. The frames need an offscreen OpenGL; where none loads the
figure is still drawn and the command says why in one line (tested by hiding it), and the frame checks skip.
"""
from __future__ import annotations

import os
import shutil

import numpy as np
import pytest

from jaxrobo.cli import main
from jaxrobo.pictures import render

HERE = os.path.dirname(os.path.abspath(__file__))
CUSTOM = os.path.join(os.path.dirname(HERE), "examples", "custom_task")
GL = render.gl_unavailable_reason()

TINY = ["--n-envs", "2", "--nepisodes", "3", "--set", "nsteps=30", "--set", "chunk_steps=30",
        "--set", "eval_episodes=0", "--no-progress"]


def _image(path: str) -> np.ndarray:
    import matplotlib.image

    return matplotlib.image.imread(path)


@pytest.fixture(scope="module")
def cartpole_run(tmp_path_factory) -> str:
    """A tiny tabular cart-pole run with non-default bins."""
    run = str(tmp_path_factory.mktemp("show") / "cp")
    assert main(["train", "--env", "CartPoleStayUp-v0", *TINY, "--set", "bins=[1,3,5,7]", "--out", run]) == 0
    return run


def test_show_draws_a_tabular_cartpole_run_with_its_own_discretiser(cartpole_run, capsys):
    """A run with non-default bins: the table only fits the discretiser rebuilt from the run's config.yaml."""
    run = cartpole_run
    capsys.readouterr()
    assert main(["show", run, "--episodes", "3"]) == 0  # default --out: into the run directory
    out = capsys.readouterr()
    png = os.path.join(run, "show.png")
    assert f"wrote {png}" in out.out and "3 episodes: mean return" in out.out
    img = _image(png)
    assert img.shape[0] > 500 and img.shape[1] > 1000
    if GL is None:
        assert "no frames drawn" not in out.err
    else:
        assert f"no frames drawn: {GL}" in out.err


@pytest.mark.parametrize("change, fragment", [
    (lambda a: {"low": a["low"] + np.float32(0.25)}, "qtables.npz: the discretiser's low[0]=-2.15, but the run's "
     "config.yaml builds low[0]=-2.4 (uniform discretiser); the files are not of one run"),
    (lambda a: {"bins": np.array([1, 3, 7, 5])}, "qtables.npz: the discretiser's bins[2]=7, but the run's config.yaml "
     "builds bins[2]=5"),
    (lambda a: {"bins": np.array([1, 3, 5, 8])}, "qtables.npz: q of shape (2, 1, 105, 4) has 105 states, but its "
     "bins=[1, 3, 5, 8] give 120"),
    (lambda a: {"edges_0": np.zeros(0)}, "qtables.npz: array 'edges_0' is no part of the uniform discretiser"),
], ids=["low", "bins-swapped", "bins-product", "extra-edges"])
def test_show_refuses_a_tampered_discretiser_before_anything_compiles(cartpole_run, tmp_path, capsys, caplog,
                                                                      change, fragment):
    """The table acts through the discretiser config.yaml builds: qtables.npz saved with another is refused naming
    the file and field, exit 2, no program compiled and nothing drawn."""
    import logging

    import jax

    run = str(tmp_path / "cp")
    shutil.copytree(cartpole_run, run)
    path = os.path.join(run, "qtables.npz")
    with np.load(path) as z:
        arrays = dict(z)
    np.savez(path, **{**arrays, **change(arrays)})
    png = str(tmp_path / "show.png")
    capsys.readouterr()
    with caplog.at_level(logging.WARNING), jax.log_compiles():
        assert main(["show", run, "--episodes", "2", "--out", png]) == 2
    err = capsys.readouterr().err
    assert fragment in err and path in err, err
    assert not [r.getMessage() for r in caplog.records if r.getMessage().startswith("Compiling")]
    assert not os.path.exists(png)


def test_show_frames_are_the_episode_the_plots_draw(tmp_path):
    """The frames come from the same rollout as the traces: the rendered state of step t is the traced one."""
    from jaxrobo import show
    from jaxrobo.task.rollout import random_policy
    from jaxrobo.training.run import resolve

    if GL is not None:
        pytest.skip(GL)
    spec = resolve("CartPoleStayUp-v0", check_memory=False)
    res = show.episodes(spec, random_policy(spec.env.num_actions), 2, 0)
    assert res["obs"].shape[:2] == res["alive"].shape and res["action"].shape[1] == res["alive"].shape[1] - 1
    np.testing.assert_array_equal(res["alive"].sum(axis=1), res["length"] + 1)
    frames, note = show.render_frames(spec, res, count=3, width=64, height=48)
    assert note is None and len(frames) == 3 and frames[0][0] == 0 and frames[-1][0] == int(res["length"][0])
    assert frames[0][1].shape == (48, 64, 3) and not np.array_equal(frames[0][1], frames[-1][1])


def test_show_random_arm_says_arrivals_and_draws_without_gl(tmp_path, monkeypatch, capsys):
    """--env on a goal task that does not fly; with OpenGL hidden the figure is still drawn, the reason printed."""
    from jaxrobo import show

    monkeypatch.setattr(render, "gl_unavailable_reason", lambda: "no OpenGL for offscreen rendering: test")
    png = str(tmp_path / "arm.png")
    assert main(["show", "--env", "ArmReach-v0", "--episodes", "2", "--out", png]) == 0
    out = capsys.readouterr()
    assert "arrived" in out.out and f"wrote {png}" in out.out
    assert "jaxrobo show: no frames drawn: no OpenGL for offscreen rendering: test" in out.err
    assert _image(png).shape[1] > 1000
    assert show.default_out(None, "my_task:MyPendulum-v0") == os.path.join("runs", "show", "my_task_MyPendulum-v0.png")


@pytest.mark.slow
def test_show_and_video_of_a_users_module_task(tmp_path, monkeypatch, capsys):
    """examples/custom_task: trained from its folder by `module:Id`, shown and (with OpenGL) rendered to a GIF."""
    work = tmp_path / "custom"
    shutil.copytree(CUSTOM, work, ignore=shutil.ignore_patterns("__pycache__", "runs"))
    monkeypatch.chdir(work)
    monkeypatch.syspath_prepend(str(work))
    run = str(tmp_path / "pend")
    assert main(["train", "--env", "my_task:MyPendulum-v0", *TINY, "--out", run]) == 0
    png = str(tmp_path / "pend.png")
    assert main(["show", run, "--episodes", "2", "--out", png]) == 0
    assert "MyPendulum" not in capsys.readouterr().err
    assert os.path.getsize(png) > 20_000
    if GL is not None:
        return
    pytest.importorskip("imageio", reason="imageio (the test extra) writes the GIF")
    gif = str(tmp_path / "pend.gif")
    assert main(["show", run, "--video", gif]) == 0
    assert os.path.getsize(gif) > 0


def test_plot_labels_are_the_run_names_and_distinct():
    from jaxrobo.pictures.plots import run_labels

    assert run_labels(["runs/q", "runs/s"]) == ["q", "s"]
    assert run_labels(["a/x/q", "b/x/q", "c/r"]) == ["a/x/q", "b/x/q", "r"]


def test_goto_side_view_draws_each_goal_at_its_distance_from_the_start(tmp_path, monkeypatch):
    """A flight that stops short of its goal ends short of its star (not on it)."""
    from matplotlib.axes import Axes

    from jaxrobo import show

    pos = np.zeros((1, 4, 3), np.float32)
    pos[0, :, 0] = [0.0, 1.0, 2.0, 2.0]  # flies 2 m along x, then stops
    pos[0, :, 2] = 1.0
    res = {"pos": pos, "alive": np.ones((1, 4), bool), "goal": np.array([[5.0, 0.0, 1.5]], np.float32),
           "return": np.zeros(1)}
    drawn = []
    original = Axes.plot

    def spy(self, *args, **kw):
        drawn.append((self.get_title(), args))
        return original(self, *args, **kw)

    monkeypatch.setattr(Axes, "plot", spy)
    show.draw(res, "t", str(tmp_path / "f.png"))
    stars = [a for _, a in drawn if len(a) == 3 and a[2] == "*" and np.ndim(a[0]) == 0]
    assert [float(a[0]) for a in stars] == [5.0, 5.0]  # top view: x of the goal; side view: 5 m from the start
    ends = [a for _, a in drawn if len(a) == 3 and a[2] == "x"]
    assert float(ends[-1][0]) == 2.0


def test_show_and_export_act_with_the_run_s_selected_table_by_default(tmp_path, capsys):
    """A run of several tables: ``show`` (like ``export``) flies the table its evaluation selected
    (``summary.json``), not table 0, unless ``--table`` says otherwise; a summary that names no table of the run
    (hostile, out of range, missing) falls back to 0."""
    import json

    from jaxrobo.io.results import selected_table

    run = str(tmp_path / "cp")
    assert main(["train", "--env", "CartPoleStayUp-v0", *TINY, "--out", run]) == 0
    path = os.path.join(run, "summary.json")
    with open(path) as f:
        summary = json.load(f)
    for chosen, expect in ((1, 1), (0, 0), (2, 0), (True, 0), ("1", 0), (-1, 0)):
        with open(path, "w") as f:
            json.dump({**summary, "selected_table": chosen}, f)
        assert selected_table(run, 2) == expect
    with open(path, "w") as f:
        json.dump({**summary, "selected_table": 1}, f)
    capsys.readouterr()
    assert main(["show", run, "--episodes", "2"]) == 0
    assert "policy: greedy qlearn, table 1, cp" in capsys.readouterr().out
    assert main(["show", run, "--episodes", "2", "--table", "0"]) == 0
    assert "policy: greedy qlearn, table 0, cp" in capsys.readouterr().out
    for hostile in ("[1, 2]", "{not json", ""):
        with open(path, "w") as f:
            f.write(hostile)
        assert selected_table(run, 2) == 0
    os.remove(path)
    assert selected_table(run, 2) == 0
