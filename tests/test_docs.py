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
