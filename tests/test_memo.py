"""synthbos.memo: results remembered by the contents of their inputs."""

import numpy as np

from synthbos.memo import RecentResults


def test_recent_results_recognise_contents_and_forget_the_oldest():
    memo, calls = RecentResults(2), []

    def get(a, extra=()):
        return memo.get([a], lambda: calls.append(1) or float(a.sum()), extra=extra)

    a = np.arange(6.0).reshape(2, 3)
    assert get(a) == 15.0 and get(a.copy()) == 15.0 and len(calls) == 1  # equal contents: one computation
    assert get(np.asfortranarray(a)) == 15.0 and len(calls) == 1  # the layout does not matter
    assert get(a.reshape(3, 2)) == 15.0 and len(calls) == 2  # another shape is another input
    assert get(a.astype(np.float32)) == 15.0 and len(calls) == 3  # another dtype too
    assert get(a) == 15.0 and len(calls) == 4  # forgotten: only the last two are kept
    assert get(a, extra=3) == 15.0 and len(calls) == 5
    b = a.copy()
    b[0, 0] = -0.0  # equal values, other bytes
    get(b)
    assert len(calls) == 6
    nan = np.array([np.nan, 1.0])
    get(nan)
    get(nan.copy())
    assert len(calls) == 7  # NaN inputs are recognised too (bytes, not values, are compared)
    memo.clear()
    get(nan)
    assert len(calls) == 8


def test_forget_all_reaches_every_memory():
    from synthbos.memo import forget_all

    memos, calls = [RecentResults(3), RecentResults(3)], []
    a = np.ones(4)
    for memo in memos:
        memo.get([a], lambda: calls.append(1))
    forget_all()
    for memo in memos:
        memo.get([a], lambda: calls.append(1))
    assert len(calls) == 4
