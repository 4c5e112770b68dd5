"""The user-facing walk-throughs run as written: the quickstart notebook and the seed's modernised script."""
from __future__ import annotations

import json
import os
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.mark.slow
def test_quickstart_notebook_runs_learns_and_shows_its_pictures(tmp_path, monkeypatch):
    """Runs notebooks/quickstart.ipynb top to bottom in a fresh kernel (make → rollout → train → plot → show →
    render): its training demo learns, and its outputs hold the pictures themselves (PNG plots and figures, the
    frame, and the GIF where OpenGL renders), not only their paths."""
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    import re

    import jax

    from jaxrobo.pictures.render import gl_unavailable_reason

    # The kernel inherits the environment: CPU JAX, and this session's compilation cache so that programs the
    # adapter tests already compiled are not compiled again.
    monkeypatch.setenv("JAX_PLATFORMS", os.environ.get("JAX_PLATFORMS", "cpu"))
    cache = jax.config.jax_compilation_cache_dir
    if cache:
        monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", cache)
        monkeypatch.setenv("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")
    monkeypatch.setenv("PYTHONPATH", ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    nb = nbformat.read(os.path.join(ROOT, "notebooks", "quickstart.ipynb"), as_version=4)
    source = "\n".join(c.source for c in nb.cells)
    assert "-v1" not in source  # the text names the ids the code uses
    client = nbclient.NotebookClient(nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": ROOT}})
    client.execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
    text = "\n".join(o.get("text", "") for o in outputs)
    assert "jaxrobo/CartPoleStayUpLeftRight-v0" in text
    assert "random policy:" in text and "compiled in" in text
    learned = re.search(r"before: ([\d.]+) steps per episode .*keeps the pole up (\d+) of 1000 steps", text)
    assert learned, text
    assert float(learned[2]) >= 300 and float(learned[2]) >= 5 * float(learned[1])
    mimes = [m for o in outputs for m in o.get("data", {})]
    # the plot, the before and after figures of section 5 (and the frame with a GL library): inline PNGs
    assert mimes.count("image/png") >= 3, mimes
    if gl_unavailable_reason() is None:
        assert mimes.count("image/png") >= 4 and "image/gif" in mimes, mimes
    else:
        assert "no offscreen OpenGL here" in text


def test_start_training_example_writes_a_plottable_run(tmp_path, capsys):
    sys.path.insert(0, os.path.join(ROOT, "examples"))
    try:
        import start_training
    finally:
        sys.path.pop(0)
    out = tmp_path / "classic"
    assert start_training.main(["--env", "CartPoleStayUp-v0", "--episodes", "4", "--steps", "30",
                                "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.count("EP: ") == 4 and "Overall score:" in printed and "Best 100 score:" in printed
    for name in ("config.yaml", "episodes.csv", "summary.json", "qtables.npz"):
        assert (out / name).exists(), name
    header, *rows = (out / "episodes.csv").read_text().splitlines()
    assert header == "env,episode,return,length,terminated,epsilon" and len(rows) == 4
    assert json.loads((out / "summary.json").read_text())["nepisodes"] == 4
    from jaxrobo.pictures.plots import plot_runs

    assert os.path.exists(plot_runs([str(out)], str(tmp_path / "plot.png")))
    assert start_training.main(["--set", "alpha=7"]) == 2  # bad values are reported, not raised
