"""docs/extending.md's reference of learners, keys and learning targets is generated from the dataclasses
(scripts/gen_docs.py): it must be up to date, list every field, and a hand edit or a changed default is caught."""
from __future__ import annotations

import dataclasses
import importlib.util
import os

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _gen():
    spec = importlib.util.spec_from_file_location("gen_docs", os.path.join(ROOT, "scripts", "gen_docs.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_generated_reference_is_up_to_date(capsys):
    assert _gen().main(["--check"]) == 0, "run: python scripts/gen_docs.py"


def test_the_reference_lists_every_key_learner_and_target():
    from jaxrobo import deep
    from jaxrobo.tabular.learner import AgentParams
    from jaxrobo.task.env import TARGET_METRICS
    from jaxrobo.task.registry import learners
    from jaxrobo.training.trainer import TrainConfig

    block = _gen().render()
    for cls in (AgentParams, TrainConfig, deep.PPOConfig, deep.SACConfig):
        for f in dataclasses.fields(cls):
            if f.name != "agent" or cls is TrainConfig:
                assert f"| `{f.name}` |" in block, f"{cls.__name__}.{f.name}"
    assert "| `alpha` | `0.5` | a number > 0.0 and <= 1.0 | learning rate |" in block
    assert all(f"| `{name}` |" in block for name in learners())
    assert all(f"| `{metric}` |" in block for metric in TARGET_METRICS)


def test_a_stale_block_is_caught(tmp_path, monkeypatch, capsys):
    gen = _gen()
    with open(gen.DOC, encoding="utf-8") as f:
        text = f.read()
    stale = text.replace("| `alpha` | `0.5` |", "| `alpha` | `0.7` |")
    assert stale != text
    doc = tmp_path / "extending.md"
    doc.write_text(stale, encoding="utf-8")
    monkeypatch.setattr(gen, "DOC", str(doc))
    assert gen.main(["--check"]) == 1
    assert "stale; run python scripts/gen_docs.py" in capsys.readouterr().err
    assert doc.read_text(encoding="utf-8") == stale  # --check writes nothing
    assert gen.main([]) == 0 and doc.read_text(encoding="utf-8") == text


def test_the_readmes_quickstart_times_are_the_transcripts():
    """Each "~N s" the README's quickstart gives a command is its wall in docs/transcripts/cpu-2cores.md (the
    transcript scripts/readme_transcript.py writes from the README itself), to the rounding a "~" allows."""
    import re

    def bare(command: str) -> str:  # a command without its "# ~N s: ..." comment, which a new transcript updates
        return re.sub(r"\s+# ~\d+ s.*$", "", command)

    spec = importlib.util.spec_from_file_location("readme_transcript",
                                                  os.path.join(ROOT, "scripts", "readme_transcript.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    with open(os.path.join(ROOT, "docs", "transcripts", "cpu-2cores.md"), encoding="utf-8") as f:
        walls = {}
        for line in f:
            row = re.match(r"\| \d+ \| `(.*)` \| ([0-9.]+) \| 0 \|", line)
            if row:
                walls[bare(row.group(1).replace("\\|", "|"))] = float(row.group(2))
    with open(os.path.join(ROOT, "README.md"), encoding="utf-8") as f:
        readme = f.read()
    said = {}
    for kind, text in mod.readme_commands(os.path.join(ROOT, "README.md")):
        if kind == "bash":
            key, about = bare(text), re.search(r"# ~(\d+) s", text)
        else:  # the library block: its time is in the sentence that opens it
            key = "python block: " + text.strip().splitlines()[0] + " …"
            about = re.search(r"\(~(\d+) s\):\n+```python\n" + re.escape(text.strip().splitlines()[0]), readme)
        assert about, f"the README gives no ~time for {key!r}"
        assert key in walls, f"not in the transcript (run scripts/readme_transcript.py): {key!r}"
        said[key] = int(about.group(1))
    for key, n in said.items():
        assert abs(n - walls[key]) <= max(1.5, 0.25 * walls[key]), (key, n, walls[key])  # a "~": run to run
    total = sum(walls[k] for k in said)
    about = re.search(r"\(about (\d+) s\s+in\s+all", readme)
    assert about and abs(int(about.group(1)) - total) <= 0.1 * total, (about and about.group(1), total)
