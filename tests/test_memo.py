"""jaxrobo.core.memo: values found by the live objects they were put for, dropped when one of them dies."""
from __future__ import annotations

import gc
import threading

import numpy as np

from jaxrobo.core.memo import IdentityMemo


def test_found_by_identity_not_equality_and_dropped_on_death():
    memo = IdentityMemo()
    a, b, twin = np.zeros(3), np.ones(3), np.zeros(3)
    memo.put((a,), "A")
    memo.put((a, b), "AB")
    assert memo.get(a) == "A" and memo.get(a, b) == "AB"
    assert memo.get(twin) is None and memo.get(b, a) is None and memo.get(b, default=7) == 7
    del b
    gc.collect()
    assert len(memo) == 1 and memo.get(a) == "A"  # the pair went with b; a's own entry stays
    del a
    gc.collect()
    assert len(memo) == 0


def test_a_dead_objects_id_reused_finds_nothing():
    memo = IdentityMemo()
    objs = [np.zeros(2) for _ in range(64)]
    for x in objs:
        memo.put((x,), id(x))
    del objs, x
    gc.collect()
    fresh = [np.zeros(2) for _ in range(256)]  # CPython hands most of the freed ids out again
    assert all(memo.get(y) is None for y in fresh)


def test_latest_only_keeps_one_entry():
    memo = IdentityMemo(latest_only=True)
    a, b = np.zeros(1), np.zeros(1)
    memo.put((a,), 1)
    memo.put((b,), 2)
    assert memo.get(a) is None and memo.get(b) == 2 and len(memo) == 1


def test_get_or_make_makes_once_across_threads():
    memo = IdentityMemo(latest_only=True)
    x = np.arange(4)
    made, started = [], threading.Barrier(8)

    def make():
        made.append(1)
        return object()

    got = [None] * 8

    def worker(i):
        started.wait()
        got[i] = memo.get_or_make((x,), make)

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(made) == 1 and all(g is got[0] for g in got)
    assert memo.get_or_make((np.arange(4),), make) is not got[0] and len(made) == 2
