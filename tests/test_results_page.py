"""docs/results.md is what benchmarks/results_page.py makes of the committed benchmark JSON, and
benchmarks/results/ holds only results: JSON and figures, no scripts, patches or notes."""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(ROOT, "benchmarks", "results")


def _results_page():
    spec = importlib.util.spec_from_file_location("results_page", os.path.join(ROOT, "benchmarks", "results_page.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_committed_results_are_json_and_figures_only():
    tracked = subprocess.run(["git", "ls-files", "benchmarks/results"], cwd=ROOT, capture_output=True, text=True)
    files = tracked.stdout.split() if tracked.returncode == 0 else [
        os.path.relpath(os.path.join(d, f), ROOT) for d, _, fs in os.walk(RESULTS) for f in fs]
    assert files, "no committed results"
    other = [f for f in files if not f.endswith((".json", ".png"))]
    assert not other, f"not a benchmark result (JSON or figure): {other}"
    for f in files:
        if f.endswith(".json"):
            with open(os.path.join(ROOT, f), encoding="utf-8") as fh:
                json.load(fh)


def test_the_results_page_is_generated_from_the_json():
    page = _results_page().page()
    with open(os.path.join(ROOT, "docs", "results.md"), encoding="utf-8") as f:
        assert f.read() == page, "docs/results.md is stale: run python benchmarks/results_page.py"
    # every device folder is a section, and its main job's table is on the page
    for device in os.listdir(RESULTS):
        if device != "local" and os.path.isdir(os.path.join(RESULTS, device)):
            assert f"\n## {device}\n" in page, device
    assert "`benchmarks/results/h100/throughput.json`" in page


def test_a_throughput_row_becomes_a_table_row_with_its_ratio(tmp_path):
    """The page's throughput table: rates in k/M/G and the like-for-like ratio throughput.py computes."""
    rp = _results_page()
    rows = [{"suite": "jaxrobo", "env": "CartPoleStayUp-v0", "backend": "analytic", "mode": "qlearn", "n_envs": 64,
             "status": "ok", "steps_per_s": 2.0e6, "physics_steps_per_s": 8.0e6, "compile_s": 1.5,
             "n_substeps": 4, "physics_dt": 0.01, "control_dt": 0.04, "sim_seconds_per_s": 8.0e4},
            {"suite": "gymnax", "env": "CartPole-v1", "backend": "-", "mode": "env", "n_envs": 64, "status": "ok",
             "steps_per_s": 1.0e6, "physics_steps_per_s": 1.0e6, "n_substeps": 1, "physics_dt": 0.02,
             "control_dt": 0.02, "sim_seconds_per_s": 2.0e4}]
    table = "\n".join(rp.throughput_rows({"rows": rows}))
    assert "| jaxrobo | CartPoleStayUp-v0 | analytic | qlearn | 64 | 2.00M | 8.00M | 1.5 | 2.00 |" in table


def test_the_headline_table_gives_the_worst_and_the_median_seed():
    """The README's seeds column: the worst figure and the median (with an even count, the mean of the middle two)."""
    rp = _results_page()
    row = {"env_id": "ArmReach-v0", "agent": "preset", "cache": "warm", "wall_seconds": 3.8, "env_steps": 1024,
           "learning_value": 0.93, "learning_target": "share >= 0.8 (greedy)"}
    runs = [{"figure": f} for f in (0.97, 0.86, 0.95, 0.99)]
    table = "\n".join(rp.time_to_trained_table({"rows": [row], "seeds": {"runs": {"ArmReach-v0": runs}}}))
    assert "| 0.86 / 0.96 (4 seeds) |" in table, table
