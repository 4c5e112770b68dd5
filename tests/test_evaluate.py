"""``jaxrobo eval``: a trained run flown on shifted physics, its table and figure; bad shifts refused (exit 2)."""
from __future__ import annotations

import csv
import os

import pytest

from jaxrobo.cli import main

TINY = ["--n-envs", "2", "--nepisodes", "3", "--no-progress", "--set", "backend=analytic", "--set", "nsteps=30",
        "--set", "chunk_steps=30", "--set", "eval_episodes=2", "--set", "eval_envs=2"]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("runs") / "cartpole")
    assert main(["train", "--env", "CartPoleStayUp-v0", "--out", out, *TINY]) == 0
    return out


def test_eval_writes_one_row_per_shift_value_and_a_figure(run_dir, tmp_path, capsys):
    out = str(tmp_path / "rob")
    assert main(["eval", run_dir, "--shift", "pole_length=0.5,1,2", "--shift", "cart_mass=1,3", "--episodes", "3",
                 "--tables", "2", "--out", out]) == 0
    rows = list(csv.DictReader(open(os.path.join(out, "robustness.csv"))))
    assert [(r["shift"], float(r["value"])) for r in rows] == [("pole_length", 0.5), ("pole_length", 1.0),
                                                               ("pole_length", 2.0), ("cart_mass", 1.0),
                                                               ("cart_mass", 3.0)]
    assert {r["metric"] for r in rows} == {"mean_length"} and {r["tables"] for r in rows} == {"2"}
    for r in rows:
        assert 1 <= float(r["worst"]) <= float(r["mean"]) <= float(r["best"]) <= 1000
    # pole_length 1 and cart_mass 1 are both the nominal physics, flown on the same episodes: the same figure
    assert rows[1]["mean"] == rows[3]["mean"]
    assert os.path.getsize(os.path.join(out, "robustness.png")) > 1000
    assert "pole_length" in capsys.readouterr().out


@pytest.mark.parametrize("shift, message", [
    ("gravity=1", "not a randomisable quantity"),
    ("pole_length=5", "pole_length"),
    ("pole_length=", "expected NAME=V1,V2"),
    ("cart_mass=x", "expected a number"),
])
def test_a_bad_shift_exits_2_naming_it(run_dir, tmp_path, capsys, shift, message):
    assert main(["eval", run_dir, "--shift", shift, "--out", str(tmp_path / "x")]) == 2
    assert message in capsys.readouterr().err


def test_more_tables_than_the_run_has_exits_2_where_it_was_cut_silently(run_dir, tmp_path, capsys):
    out = str(tmp_path / "x")
    assert main(["eval", run_dir, "--shift", "cart_mass=1", "--tables", "99", "--out", out]) == 2
    assert "--tables 99: the run has 2 tables; expected 1..2" in capsys.readouterr().err
    assert not os.path.exists(out)


def test_a_tampered_discretiser_is_refused_naming_the_file_before_anything_compiles(run_dir, tmp_path, capsys,
                                                                                     caplog):
    """qtables.npz's bins swapped (the same number of states, so q's shape still fits): the table would act on
    other states than it learnt; refused naming the file and field, exit 2, no program compiled."""
    import logging
    import shutil

    import jax
    import numpy as np

    run = str(tmp_path / "run")
    shutil.copytree(run_dir, run)
    path = os.path.join(run, "qtables.npz")
    with np.load(path) as z:
        arrays = dict(z)
    arrays["bins"] = arrays["bins"][::-1].copy()
    assert not np.array_equal(arrays["bins"], arrays["bins"][::-1])
    np.savez(path, **arrays)
    capsys.readouterr()
    with caplog.at_level(logging.WARNING), jax.log_compiles():
        assert main(["eval", run, "--shift", "cart_mass=1", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert f"{path}: the discretiser's bins[0]=" in err and "the files are not of one run" in err, err
    assert not [r.getMessage() for r in caplog.records if r.getMessage().startswith("Compiling")]
    assert not os.path.exists(tmp_path / "x")


def test_a_run_that_is_not_there_or_a_task_without_randomisation_exits_2(tmp_path, capsys):
    assert main(["eval", str(tmp_path / "nothing"), "--shift", "mass=1"]) == 2
    assert "does not exist" in capsys.readouterr().err
