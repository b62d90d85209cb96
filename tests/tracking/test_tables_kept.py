"""The tracker's tables kept from before the one orchestration (2026-11-27, commit a7dd7f5, the CPU).

``data/tables_2026-11-27.npz`` holds six tables that ``track_pair`` gave on the CPU before its per-pair
orchestration was folded into the stack (``tracking.stack.track_pairs``): the default with a prior, the
paper's procedure, a mask, a mapping, and standard tracking (no prior) with both estimators, on the
pairs of ``test_stack._batch``. Today's tables are within 1e-9 px of them, with the same status bits.
"""

from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal
from synthbos.tracking import TrackingSettings, track_pair
from test_stack import SHAPE, _batch

KEPT = np.load(Path(__file__).parent / "data" / "tables_2026-11-27.npz")
_OFFSET = np.array([0.3, -0.2])


def _case(name):
    """(reference, gradient, keyword arguments of track_pair) of a kept table."""
    refs, grads, prior = _batch()
    yy, xx = np.mgrid[: SHAPE[0], : SHAPE[1]]
    disk = (xx - 40) ** 2 + (yy - 50) ** 2 < 15**2
    paper = TrackingSettings.paper()
    cases = {
        "default_prior": (0, {"prior_xy": prior[0]}),
        "paper_prior": (1, {"prior_xy": prior[1], "settings": paper}),
        "default_mask": (0, {"prior_xy": prior[0], "mask": disk}),
        "default_mapping": (0, {"prior_xy": prior[0] - _OFFSET, "mapping": lambda p: p * 1.0 + _OFFSET}),
        "standard_default": (0, {}),
        "standard_paper": (1, {"settings": paper}),
    }
    b, kw = cases[name]
    return refs[b], grads[b], kw


@pytest.mark.parametrize("name", sorted(KEPT.files))
def test_tables_as_before_the_one_orchestration(name):
    reference, gradient, kw = _case(name)
    table = track_pair(reference, gradient, device="cpu", **kw)
    kept = KEPT[name]
    assert table.dtype == kept.dtype and table.shape == kept.shape
    for field in kept.dtype.names:
        if kept.dtype[field].kind == "f":
            assert_array_equal(np.isnan(table[field]), np.isnan(kept[field]), err_msg=field)
            assert_allclose(table[field], kept[field], rtol=0, atol=1e-9, equal_nan=True, err_msg=field)
        else:
            assert_array_equal(table[field], kept[field], err_msg=field)
    status = kept["status"]
    assert np.count_nonzero(status & 4) > 300  # MATCHED rows: a real table, not an empty one
