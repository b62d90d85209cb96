"""The host's own limit in ``bench_scaling``: plain campaigns run side by side, each in its own process."""

from __future__ import annotations

from pathlib import Path

import pytest
from synthbos.benchmarks.bench_scaling import campaign_spec, run_side_by_side
from synthbos.benchmarks.campaign import run_campaign

from synthbos import SynthbosError

TINY = {"pixels": 96, "rays": 10, "noise": [0.0, 3.0]}


@pytest.mark.slow
def test_side_by_side_campaigns_give_the_plain_campaigns_results(slow_only, tmp_path):
    side = run_side_by_side([0, 1], device="cpu", pairs=5, workers=1, folder=tmp_path / "side", **TINY)
    assert side["units"] == 2 and side["identical_results"]
    assert len(side["campaigns"]) == 2
    assert side["pairs_per_s"] == pytest.approx(sum(c["pairs_per_s"] for c in side["campaigns"]))
    for c in side["campaigns"]:
        assert c["campaign_s"] > 0 and c["pairs_per_s"] == pytest.approx(5 / c["campaign_s"])
    # the same files as the campaign run here
    run_campaign(campaign_spec(5, **TINY), tmp_path / "here", device="cpu", workers=1, progress=False, figures=False)
    here = (tmp_path / "here" / "results.json").read_bytes()
    assert here == (Path(side["campaigns"][0]["folder"]) / "results.json").read_bytes()


def test_a_side_by_side_campaign_that_fails_is_reported(tmp_path, capfd):
    with pytest.raises(SynthbosError, match="failed in its warm-up"):
        run_side_by_side([0], device="cuda:7", pairs=5, workers=1, folder=tmp_path, **TINY)
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "cuda:7" in err[0]
