"""The Python API (``synthbos.<name>``): its loading, its doctests, and its numbers on a rendered pair."""

import doctest
import io
import subprocess
import sys

import numpy as np
import pytest
from numpy.lib import recfunctions
from numpy.testing import assert_allclose, assert_array_equal

import synthbos
from synthbos import SynthbosError

API_NAMES = sorted(synthbos._API)

# The homes of the API's names (the report's list; a name that moves must be moved here on purpose).
HOMES = {
    "render_pair": "synthbos.raytrace", "read_pair": "synthbos.raytrace", "write_pair": "synthbos.raytrace",
    "track_pair": "synthbos.tracking", "TrackingSettings": "synthbos.tracking", "DotStatus": "synthbos.tracking",
    "is_valid": "synthbos.tracking", "correlate_pair": "synthbos.correlation",
    "CorrelationSettings": "synthbos.correlation",
    **{n: "synthbos.benchmarks.api" for n in ("add_noise", "nominal_prior", "score", "displacement_errors",
                                             "integrate", "density_truth", "to_dataframe")},
}


@pytest.fixture(scope="module")
def pair():
    return synthbos.render_pair({"camera": {"pixels": [96, 96]}, "rays": {"per_dot": 100}})


@pytest.fixture(scope="module")
def noisy(pair):
    return synthbos.add_noise(pair, noise_percent=1.0, seed=0)


@pytest.fixture(scope="module")
def table(pair, noisy):
    return synthbos.track_pair(*noisy, prior_xy=synthbos.nominal_prior(pair))


def test_import_loads_no_subpackage():
    code = "import sys, synthbos; print(sorted(m for m in sys.modules if m.split('.')[0] in ('warp', 'numpy', " \
           "'scipy', 'h5py') or m.startswith(('synthbos.raytrace', 'synthbos.tracking', 'synthbos.benchmarks'))))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_names_are_listed_and_found_in_their_homes():
    assert set(HOMES) == set(API_NAMES)
    assert set(API_NAMES) <= set(synthbos.__all__)
    assert set(synthbos.__all__) - set(API_NAMES) <= set(vars(synthbos))  # the rest is defined at import
    assert set(API_NAMES) <= set(dir(synthbos))
    for name, home in HOMES.items():
        obj = getattr(synthbos, name)
        assert obj is getattr(sys.modules[home], name), name
    with pytest.raises(AttributeError, match="no attribute 'no_such_name'"):
        synthbos.no_such_name  # noqa: B018
    from synthbos import raytrace  # subpackages are still imported as such

    assert raytrace.render_pair is synthbos.render_pair


@pytest.mark.parametrize("name", API_NAMES)
def test_docstring_example_runs(name):
    obj = getattr(synthbos, name)
    tests = [t for t in doctest.DocTestFinder(recurse=False).find(obj, f"synthbos.{name}", globs={}) if t.examples]
    assert tests, f"synthbos.{name} has no Examples section with a doctest"
    out = io.StringIO()
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    for t in tests:
        runner.run(t, out=out.write)
    assert runner.failures == 0, out.getvalue()


def test_add_noise_is_seeded_and_sized(pair):
    ref, grad = synthbos.add_noise(pair, noise_percent=2.0, seed=3)
    peak = pair.attrs["peak_intensity"]
    assert_allclose(np.std(ref - pair.reference) / peak, 0.02, rtol=0.05)
    assert_allclose(np.std(grad - pair.gradient) / peak, 0.02, rtol=0.05)
    assert abs(np.corrcoef((ref - pair.reference).ravel(), (grad - pair.gradient).ravel())[0, 1]) < 0.05
    assert_array_equal(synthbos.add_noise(pair, noise_percent=2.0, seed=3)[1], grad)
    assert not np.array_equal(synthbos.add_noise(pair, noise_percent=2.0, seed=4)[0], ref)
    # two seeds: the campaign's (reference, gradient) seeds, the images of its score items
    from synthbos.benchmarks.items import noisy_pair

    for a, b in zip(synthbos.add_noise(pair, noise_percent=1.0, seed=(5, 9)),
                    noisy_pair(pair, noise_percent=1.0, seeds=(5, 9)), strict=True):
        assert_array_equal(a, b)
    for bad in (-1, 1.5, (1, 2, 3), "0"):
        with pytest.raises(SynthbosError, match="seed must be"):
            synthbos.add_noise(pair, noise_percent=1.0, seed=bad)


def test_nominal_prior_is_where_the_dots_are(pair):
    prior = synthbos.nominal_prior(pair)
    assert prior.shape == (pair.n_dots, 2)
    assert_allclose(prior, pair.reference_px, atol=1e-3)  # measured: 4e-5 px
    from dataclasses import replace

    with pytest.raises(SynthbosError, match="configuration"):
        synthbos.nominal_prior(replace(pair, attrs={}))


def test_is_valid_takes_a_table(table):
    ok = synthbos.is_valid(table)
    assert ok.dtype == bool and ok.shape == (len(table),)
    assert_array_equal(ok, (table["status"] & 4) != 0)
    assert_array_equal(ok, synthbos.is_valid(table["status"]))
    mixed = np.zeros(4, dtype=table.dtype)
    mixed["status"] = [0, synthbos.DotStatus.MATCHED, synthbos.DotStatus.FOUND_REFERENCE | synthbos.DotStatus.OUTLIER,
                       synthbos.DotStatus.MATCHED | synthbos.DotStatus.NEAR_BORDER]
    assert_array_equal(synthbos.is_valid(mixed), [False, True, False, True])
    with pytest.raises(SynthbosError, match="status field"):
        synthbos.is_valid(np.zeros(3, dtype=[("x", "f8")]))
    with pytest.raises(SynthbosError, match="integer status"):
        synthbos.is_valid(np.array([4.0, 0.0]))


def _without_dot_id(table):
    """The table without a dot_id field (tracking tables may carry one)."""
    if "dot_id" in table.dtype.names:
        return recfunctions.drop_fields(table, "dot_id", usemask=False)
    return table


def _error_p90(pair, table, columns=("u", "v")):
    ok = pair.valid & np.all(np.isfinite(pair.displacement_px), axis=1)
    uv = np.stack([table[columns[0]], table[columns[1]]], axis=1)[ok]
    e = np.hypot(*(uv - pair.displacement_px[ok]).T)
    return np.nanpercentile(e, 90), np.isfinite(e).sum(), ok.sum()


def test_track_and_score(pair, table):
    s = synthbos.score(pair, table)
    p90, n, expected = _error_p90(pair, table)
    assert (s["method"], s["n"], s["expected"]) == ("tracking", n, expected)
    assert_allclose(s["p90"], p90, rtol=1e-12)
    # 1 % noise on 96 x 96 px, 100 rays per dot: p90 0.054-0.058 px over seeds 0-3 (no noise: 0.028)
    assert 0.035 < s["p90"] < 0.08
    assert s["yield"] >= 0.97
    assert s["p50"] < s["p68"] < s["p90"] < s["p95"] < s["p99"]
    assert np.isfinite(s["density_rms_rel"]) and s["density_rms_rel"] < 0.2  # 0.09-0.12 measured
    e = synthbos.displacement_errors(pair, table)
    assert len(e) == expected
    assert_allclose(np.nanpercentile(e, 90), p90, rtol=1e-12)
    cc = synthbos.score(pair, table, method="tracking-cc")
    assert_allclose(cc["p90"], _error_p90(pair, table, ("u_cc", "v_cc"))[0], rtol=1e-12)


def test_score_refuses_what_does_not_fit(pair, table):
    with pytest.raises(SynthbosError, match="rows but the pair"):
        synthbos.score(pair, table[:10])
    with pytest.raises(SynthbosError, match="does not read a tracking table"):
        synthbos.score(pair, table, method="correlation")
    with pytest.raises(SynthbosError, match="expected a tracking table"):
        synthbos.score(pair, np.zeros((3, 2)))
    shuffled = recfunctions.append_fields(_without_dot_id(table), "dot_id", np.arange(len(table))[::-1],
                                          usemask=False)
    with pytest.raises(SynthbosError, match="dot_id"):
        synthbos.score(pair, shuffled)


def test_correlate_and_score(pair, noisy):
    res = synthbos.correlate_pair(*noisy)
    s = synthbos.score(pair, res)
    assert s["method"] == "correlation" and s["n"] == res.u.size == 36
    # 16 px windows, 1 % noise: p90 0.064-0.075 px over seeds 0-3, against the dots' interpolated truth
    assert 0.03 < s["p90"] < 0.11
    assert s["density_rms_rel"] < 0.12  # 0.055-0.066 measured


def test_integrate_against_the_truth(pair, table, noisy):
    for result, bound in ((table, 0.18), (synthbos.correlate_pair(*noisy), 0.1)):
        dmap = synthbos.integrate(result, pair)
        truth = synthbos.density_truth(pair, dmap)
        assert truth.shape == dmap.density.shape == (len(dmap.grid.y_mm), len(dmap.grid.x_mm))
        span = np.nanmax(truth) - np.nanmin(truth)
        # the error's spread; its mean is the constant of integration (the border is taken as ambient)
        assert np.nanstd(dmap.density - truth) < bound * span  # measured 0.09-0.11 (tracking), 0.05-0.06
        border = dmap.reference_region & np.isfinite(dmap.density)
        assert_allclose(np.mean(dmap.density[border]), pair.attrs["ambient_density_kg_m3"], rtol=1e-9)
        moved = synthbos.integrate(result, pair, reference_density=1.3)
        ok = np.isfinite(dmap.density)
        assert_array_equal(np.isfinite(moved.density), ok)
        assert_allclose(moved.density[ok] - dmap.density[ok], 1.3 - pair.attrs["ambient_density_kg_m3"], atol=1e-9)
    chief = synthbos.density_truth(pair, dmap, truth="chief")
    assert np.nanmax(np.abs(chief - truth)) < 0.5 * span
    with pytest.raises(SynthbosError, match="truth must be"):
        synthbos.density_truth(pair, dmap, truth="exact")
    with pytest.raises(SynthbosError, match="spacing"):
        synthbos.integrate(table, pair, spacing_px=0.1)
    # the set-up as a configuration: the pair's own, the same density
    from_config = synthbos.integrate(table, {"camera": {"pixels": [96, 96]}, "rays": {"per_dot": 100}})
    assert_allclose(from_config.density, synthbos.integrate(table, pair).density, rtol=1e-9, equal_nan=True)


def test_to_dataframe(pair, table, noisy):
    plain = _without_dot_id(table)
    df = synthbos.to_dataframe(plain)
    assert list(df.columns) == ["dot_id", *plain.dtype.names, "valid"]
    assert len(df) == len(table) == pair.n_dots
    assert_array_equal(df["dot_id"], np.arange(len(table)))  # the prior's row: pair dot i
    assert_array_equal(df["valid"], synthbos.is_valid(table))
    assert_array_equal(df["u"], table["u"])
    # a table with its own dot_id (tracking files and tables that carry one) keeps it
    ids = np.arange(len(table)) * 3 + 1
    with_ids = recfunctions.append_fields(plain, "dot_id", ids, usemask=False)
    df_ids = synthbos.to_dataframe(with_ids)
    assert list(df_ids.columns) == ["dot_id", *plain.dtype.names, "valid"]
    assert_array_equal(df_ids["dot_id"], ids)
    res = synthbos.correlate_pair(*noisy)
    dfc = synthbos.to_dataframe(res)
    assert len(dfc) == res.u.size
    assert {"x", "y", "u", "v", "flags", "peak_ratio", "correlation", "valid"} <= set(dfc.columns)
    assert_array_equal(dfc["u"], res.u.ravel())
    assert_array_equal(dfc["valid"], (res.flags.ravel() == 0) & np.isfinite(res.u.ravel()))
    dmap = synthbos.integrate(table, pair)
    dfd = synthbos.to_dataframe(dmap)
    assert len(dfd) == dmap.density.size
    assert_array_equal(dfd["density_kg_m3"], dmap.density.ravel())
    assert_array_equal(dfd["x_mm"].to_numpy().reshape(dmap.density.shape)[0], dmap.grid.x_mm)
    from synthbos.benchmarks.api import _as_result

    dfm = synthbos.to_dataframe(_as_result(table, "tracking-cc"))  # a MethodResult: the table's own columns
    assert_array_equal(dfm["u"], table["u"])
    assert_array_equal(dfm["u_cc"], table["u_cc"])
