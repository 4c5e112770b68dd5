"""Training values are unchanged by refactors: short runs hash to the fingerprints recorded before a change.

``scripts/fingerprints.py`` lists the cases (every shipped preset, every learner on both cart-pole backends) and
records them; this checks the ones that compile in seconds on a CPU, one per kind of loop (closed-form and MJX
cart-pole, each learner, the shared-table quadcopter task). ``python scripts/fingerprints.py --check
tests/data/fingerprints.json`` checks all of them.
"""
from __future__ import annotations

import importlib.util
import json
import os

import pytest

_HERE = os.path.dirname(__file__)
_spec = importlib.util.spec_from_file_location("fingerprints", os.path.join(_HERE, "..", "scripts", "fingerprints.py"))
fingerprints = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fingerprints)

with open(os.path.join(_HERE, "data", "fingerprints.json")) as f:
    RECORDED = json.load(f)

FAST = [c for c in fingerprints.cases()
        if "env.backend=analytic" in fingerprints.name(c)
        or fingerprints.name(c) in ("QuadcopterGoto-v1/default/preset-agent", "CartPoleStayUp-v0/seed/preset-agent")]


def test_every_case_is_recorded():
    assert sorted(RECORDED) == sorted(fingerprints.name(c) for c in fingerprints.cases())


@pytest.mark.parametrize("case", FAST, ids=fingerprints.name)
def test_training_values_match_the_recorded_fingerprint(case):
    assert fingerprints.fingerprint(case) == RECORDED[fingerprints.name(case)]
