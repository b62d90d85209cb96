"""The Python API's own functions: noise on a pair, the nominal prior, scoring, integration, DataFrames.

They join the algorithm packages' entry points (``render_pair``, ``track_pair``, ``correlate_pair``) into
the everyday path of a user: render a pair, add noise, process it, score it against the truth, integrate
to density, look at the numbers. ``import synthbos`` offers all of them as ``synthbos.<name>`` (see
``synthbos.__init__``); they live here, on the top floor, because they read the harness's pieces (the
method registry, the scoring, the integration's set-up), which the algorithm packages never import.

A result may be given in any of its forms: a :func:`synthbos.tracking.track_pair` table, a
:class:`synthbos.correlation.CorrelationResult`, or a registry ``MethodResult`` (what ``synthbos process``
writes and ``benchmarks.process.read_result`` reads). A table is read as the registered method
``tracking`` (the centroid difference ``u, v``) unless ``method`` names another tracking method, e.g.
``"tracking-cc"`` (the correlation correction ``u_cc, v_cc``).
"""

from __future__ import annotations

import numpy as np

from synthbos import SynthbosError

from . import integrate as _integrate
from . import items, scoring
from .registry import DOTS, MethodResult, correlation_result, get_method, tracking_result

__all__ = ["add_noise", "density_truth", "displacement_errors", "integrate", "nominal_prior", "score",
           "to_dataframe"]


def add_noise(pair, *, noise_percent, seed=0, peak=None):
    """The pair's two images with seeded Gaussian sensor noise, as a campaign adds it.

    Parameters
    ----------
    pair : Pair
        A rendered pair (:func:`synthbos.render_pair`, :func:`synthbos.read_pair`); it is not changed.
    noise_percent : float
        Standard deviation of the noise in percent of ``peak``.
    seed : int or (int, int), optional
        One seed, from which the two images' independent seeds are drawn, or the seeds of the reference
        and the gradient image as a campaign records them. The same seed gives the same noise.
    peak : float, optional
        The intensity the percentage refers to; default the pair's ``peak_intensity`` (a lone dot's peak).

    Returns
    -------
    reference, gradient : (H, W) float32 arrays

    See Also
    --------
    synthbos.raytrace.add_noise : the same noise on one image, with quantisation to a bit depth.

    Examples
    --------
    >>> import numpy as np
    >>> import synthbos
    >>> pair = synthbos.render_pair({"camera": {"pixels": [64, 64]}, "rays": {"per_dot": 50}})
    >>> ref, grad = synthbos.add_noise(pair, noise_percent=2.0, seed=7)
    >>> ref.shape, ref.dtype
    ((64, 64), dtype('float32'))
    >>> noise = ref - pair.reference
    >>> bool(abs(noise.std() / pair.attrs["peak_intensity"] - 0.02) < 0.002)
    True
    >>> bool(np.array_equal(ref, synthbos.add_noise(pair, noise_percent=2.0, seed=7)[0]))
    True
    """
    seeds = _two_seeds(seed)
    return items.noisy_pair(pair, noise_percent=noise_percent, seeds=seeds, peak=peak)


def _two_seeds(seed) -> tuple[int, int]:
    """The seeds of the two images: a pair as given, or two drawn from one seed (numpy's SeedSequence)."""
    if np.ndim(seed) == 0:
        if not isinstance(seed, int | np.integer) or seed < 0:
            raise SynthbosError(f"seed must be an integer >= 0 or a pair of them, got {seed!r}")
        a, b = np.random.SeedSequence(int(seed)).generate_state(2)
        return int(a), int(b)
    seeds = tuple(seed)
    if len(seeds) != 2 or not all(isinstance(s, int | np.integer) and s >= 0 for s in seeds):
        raise SynthbosError(f"seed must be an integer >= 0 or a pair of them, got {seed!r}")
    return int(seeds[0]), int(seeds[1])


def nominal_prior(pair) -> np.ndarray:
    """The prior a tracking user has: where the camera model images the pattern's known dot positions.

    The positions of the target's dots (``pair.target_xy_m``) projected by the pair's camera model
    (pinhole, with the set-up's magnification and principal point), in reference-image pixels. Row ``i``
    is pair dot ``i``, so a table tracked with this prior has one row per pair dot, in its order. This
    is the prior ``synthbos process --pair`` and every campaign give the tracker.

    Parameters
    ----------
    pair : Pair

    Returns
    -------
    (N, 2) float64 array
        x = column, y = row, pixel centres at integers.

    Examples
    --------
    >>> import numpy as np
    >>> import synthbos
    >>> pair = synthbos.render_pair({"camera": {"pixels": [64, 64]}, "rays": {"per_dot": 50}})
    >>> prior = synthbos.nominal_prior(pair)
    >>> prior.shape == (pair.n_dots, 2)
    True
    >>> float(np.abs(prior - pair.reference_px).max()) < 0.01  # the rendered dots sit where the model says
    True
    """
    if "config" not in getattr(pair, "attrs", {}):
        raise SynthbosError("the pair records no render configuration (attribute 'config'): no camera model "
                            "to project its dots with")
    return items.nominal_positions(pair)


def _as_result(result, method=None) -> MethodResult:
    """A table, a CorrelationResult or a MethodResult as the registry's ``MethodResult``."""
    if isinstance(result, MethodResult):
        if method is not None and method != result.method:
            raise SynthbosError(f"the result is {result.method!r}'s, not {method!r}'s")
        return result
    names = getattr(getattr(result, "dtype", None), "names", None)
    if names is not None:
        method = "tracking" if method is None else method
        columns = getattr(get_method(method).run, "columns", None)
        if columns is None:
            raise SynthbosError(f"method {method!r} does not read a tracking table")
        missing = [c for c in ("x", "y", "status", *columns) if c not in names]
        if missing:
            raise SynthbosError(f"not a tracking table: no field(s) {', '.join(missing)}")
        return tracking_result(result, name=method, columns=columns)
    if all(hasattr(result, a) for a in ("x", "y", "u", "v", "flags", "peak_ratio")):
        if method not in (None, "correlation"):
            raise SynthbosError(f"a correlation result cannot be read as method {method!r}")
        return correlation_result(result)
    raise SynthbosError(f"expected a tracking table, a CorrelationResult or a MethodResult, got "
                        f"{type(result).__name__}")


def _scores(pair, result, method):
    res = _as_result(result, method)
    m = get_method(res.method)
    if m.kind == DOTS and m.uses_prior:
        if len(res.xy) != pair.n_dots:
            raise SynthbosError(f"the table has {len(res.xy)} rows but the pair {pair.n_dots} dots: track with "
                                "prior_xy=synthbos.nominal_prior(pair) so that row i is pair dot i")
        ids = res.table.get("dot_id")
        if ids is not None and not np.array_equal(np.asarray(ids), np.arange(pair.n_dots)):
            raise SynthbosError("the table's dot_id is not the pair's dot order: it was tracked with another prior")
    return res, items.score_result(pair, res.method, res)


def score(pair, result, *, method=None) -> dict:
    """Score a result against the pair's truth, as a campaign does: displacement error percentiles, yield.

    Parameters
    ----------
    pair : Pair
        The pair the result was measured on (its noise-free truth).
    result : tracking table, CorrelationResult or MethodResult
        A table must be tracked with the pair's prior (:func:`nominal_prior`): row ``i`` is pair dot ``i``.
    method : str, optional
        The registered method the result is read as (see the module docstring); default ``"tracking"``
        for a table, ``"correlation"`` for a correlation result.

    Returns
    -------
    dict
        ``method``; ``n`` (scored points with a measurement) and ``expected`` (points with a truth);
        ``yield`` (``n / expected``); ``p50``, ``p68``, ``p90``, ``p95``, ``p99`` and ``rms`` of the
        displacement error magnitude, px (tracking: at each dot against its own ray-traced displacement;
        correlation: at each window centre against the dots' displacements interpolated there);
        ``density_rms_rel``: RMS error of the density integrated from the result against the cone truth,
        relative to the truth's range (NaN when the pair has no density truth). Same numbers as the
        campaign's ``results.csv`` (split ``all``).

    Examples
    --------
    >>> import synthbos
    >>> pair = synthbos.render_pair({"camera": {"pixels": [64, 64]}, "rays": {"per_dot": 50}})
    >>> ref, grad = synthbos.add_noise(pair, noise_percent=1.0, seed=0)
    >>> table = synthbos.track_pair(ref, grad, prior_xy=synthbos.nominal_prior(pair))
    >>> s = synthbos.score(pair, table)
    >>> s["method"], s["expected"] == int(pair.valid.sum())
    ('tracking', True)
    >>> bool(s["p90"] < 0.1), bool(s["yield"] > 0.9)
    (True, True)
    """
    res, s = _scores(pair, result, method)
    err = np.asarray(s["error"], dtype=np.float64)
    fin = err[np.isfinite(err)]
    out = {"method": res.method, "n": int(s["measured"]), "expected": int(s["expected"]),
           "yield": float(s["measured"] / s["expected"]) if s["expected"] else float("nan")}
    out.update({f"p{k}": v for k, v in scoring.error_percentiles(err).items()})
    out["rms"] = float(np.sqrt(np.mean(fin**2))) if len(fin) else float("nan")
    rel = np.asarray(s["density_error_cone"]) / s["density_range_cone"] if s["density_range_cone"] > 0 else []
    out["density_rms_rel"] = float(np.sqrt(np.mean(np.square(rel)))) if len(rel) else float("nan")
    return out


def displacement_errors(pair, result, *, method=None) -> np.ndarray:
    """The displacement error magnitude at every scored point of a result (px), for CDFs and maps.

    Parameters
    ----------
    pair, result, method
        As for :func:`score`.

    Returns
    -------
    (M,) float64 array
        One entry per point with a truth (tracking: each valid pair dot, in the pair's order; correlation:
        each window centre inside the dots' hull, row after row); NaN where the method measured nothing.
        :func:`score`'s percentiles are those of its finite entries.

    Examples
    --------
    >>> import numpy as np
    >>> import synthbos
    >>> pair = synthbos.render_pair({"camera": {"pixels": [64, 64]}, "rays": {"per_dot": 50}})
    >>> table = synthbos.track_pair(pair.reference, pair.gradient, prior_xy=synthbos.nominal_prior(pair))
    >>> e = synthbos.displacement_errors(pair, table)
    >>> len(e) == int(pair.valid.sum())
    True
    >>> bool(np.nanpercentile(e, 90) < 0.05)  # no noise: the dots' own distortion is what is left
    True
    """
    return np.asarray(_scores(pair, result, method)[1]["error"], dtype=np.float64)


def _geometry(setup):
    if isinstance(setup, _integrate.Geometry):
        return setup
    if hasattr(setup, "attrs") and hasattr(setup, "reference"):
        return _integrate.geometry_from_pair(setup)
    return _integrate.geometry_from_config(setup)


def integrate(result, setup, *, method=None, solver="lsq", spacing_px=None, reference_density=None):
    """Integrate a result's displacements to the depth-averaged density, as ``synthbos integrate`` does.

    Parameters
    ----------
    result : tracking table, CorrelationResult or MethodResult
        As for :func:`score`; a table tracked without a prior works too.
    setup : Pair, dict, str or Path
        The set-up the images were taken with: a pair (its recorded set-up), or a render configuration
        (a dict of tables or a TOML file, merged over the defaults like ``render_pair``'s).
    method : str, optional
        As for :func:`score`.
    solver : {"lsq", "wlsq", "dct"}
        Least squares on the measured nodes, the same weighted by each vector's uncertainty, or Poisson by
        DCT on the full rectangle.
    spacing_px : float, optional
        Grid spacing for tracked dots (default: their mean spacing); a correlation keeps its own grid.
    reference_density : float, optional
        Mean density over the border of the measured domain, kg/m^3 (the constant of integration);
        default the set-up's ambient density.

    Returns
    -------
    DensityMap
        ``density`` (ny, nx) kg/m^3, NaN where not reconstructed; ``grid`` with the node positions
        ``x_mm``, ``y_mm`` (at the volume's mid-plane, the volume's frame) and ``x_px``, ``y_px``, and
        ``measured``; ``solver`` and ``reference`` (how the constant was fixed, in words).

    Examples
    --------
    >>> import numpy as np
    >>> import synthbos
    >>> pair = synthbos.render_pair({"camera": {"pixels": [64, 64]}, "rays": {"per_dot": 50}})
    >>> table = synthbos.track_pair(pair.reference, pair.gradient, prior_xy=synthbos.nominal_prior(pair))
    >>> dmap = synthbos.integrate(table, pair)
    >>> dmap.density.shape == (len(dmap.grid.y_mm), len(dmap.grid.x_mm))
    True
    >>> truth = synthbos.density_truth(pair, dmap)
    >>> error = dmap.density - truth  # its mean: the constant of integration, the border is not ambient
    >>> bool(np.nanstd(error) < 0.15 * (np.nanmax(truth) - np.nanmin(truth)))
    True
    """
    _integrate.check_integrate_options(spacing_px=spacing_px, reference_density=reference_density)
    res = _as_result(result, method)
    geometry = _geometry(setup)
    _integrate.check_displacements(res, geometry)
    dmap = _integrate.density_from_result(res, geometry, solver=solver, spacing_px=spacing_px,
                                          reference_value=reference_density)
    _integrate.check_density_range(dmap)
    return dmap


def density_truth(pair, density, *, truth="cone") -> np.ndarray:
    """The pair's density truth on the grid of an integrated density map, to compare with it.

    Parameters
    ----------
    pair : Pair
    density : DensityMap
        From :func:`integrate`.
    truth : {"cone", "chief"}
        The depth-averaged density over each dot's cone of rays, or along its chief ray; the dots' values
        are interpolated onto the grid as the dots' displacements were.

    Returns
    -------
    (ny, nx) float64 array
        kg/m^3, NaN outside the valid dots' convex hull.

    Examples
    --------
    >>> import numpy as np
    >>> import synthbos
    >>> pair = synthbos.render_pair({"camera": {"pixels": [64, 64]}, "rays": {"per_dot": 50}})
    >>> table = synthbos.track_pair(pair.reference, pair.gradient, prior_xy=synthbos.nominal_prior(pair))
    >>> dmap = synthbos.integrate(table, pair)
    >>> cone = synthbos.density_truth(pair, dmap)
    >>> cone.shape == dmap.density.shape
    True
    >>> bool(np.nanmin(cone) > 0)
    True
    """
    if truth not in ("cone", "chief"):
        raise SynthbosError(f"truth must be 'cone' or 'chief', got {truth!r}")
    cone, chief = _integrate.truth_on_grid(pair, density.grid)
    return cone if truth == "cone" else chief


def to_dataframe(result):
    """A pandas DataFrame of a result, one row per dot, window centre or grid node, one column per field.

    Parameters
    ----------
    result : tracking table, CorrelationResult, MethodResult or DensityMap
        A tracking table gives every field of the table, and ``dot_id``: the table's own field when it has
        one, otherwise the row index (the prior's row: pair dot ``i`` for a table tracked with
        :func:`nominal_prior`), plus ``valid`` (:func:`synthbos.is_valid`). A correlation result gives
        ``x, y, u, v, peak_ratio, correlation, flags`` of each window, row after row, and ``valid`` (flags 0).
        A MethodResult gives ``x, y, u, v, valid`` and its table's per-point arrays; a DensityMap gives
        ``x_mm, y_mm, x_px, y_px, density_kg_m3, measured``.

    Returns
    -------
    pandas.DataFrame

    Examples
    --------
    >>> import synthbos
    >>> pair = synthbos.render_pair({"camera": {"pixels": [64, 64]}, "rays": {"per_dot": 50}})
    >>> table = synthbos.track_pair(pair.reference, pair.gradient, prior_xy=synthbos.nominal_prior(pair))
    >>> df = synthbos.to_dataframe(table)
    >>> len(df) == len(table) == pair.n_dots
    True
    >>> list(df.columns[:5])
    ['dot_id', 'x', 'y', 'u', 'v']
    >>> bool((df["valid"] == synthbos.is_valid(table)).all())
    True
    """
    try:
        import pandas as pd
    except ImportError:  # pandas is not a dependency of synthbos
        raise ImportError("to_dataframe needs pandas: pip install pandas") from None
    return pd.DataFrame(_columns(result))


def _columns(result) -> dict:
    """Column name -> 1-D array of :func:`to_dataframe`."""
    if isinstance(result, _integrate.DensityMap):
        g = result.grid
        x_mm, y_mm = np.meshgrid(g.x_mm, g.y_mm)
        x_px, y_px = np.meshgrid(g.x_px, g.y_px)
        return {"x_mm": x_mm.ravel(), "y_mm": y_mm.ravel(), "x_px": x_px.ravel(), "y_px": y_px.ravel(),
                "density_kg_m3": result.density.ravel(), "measured": g.measured.ravel()}
    names = getattr(getattr(result, "dtype", None), "names", None)
    if names is not None:
        if "status" not in names:
            raise SynthbosError(f"not a tracking table: no status field among {', '.join(names)}")
        cols = {"dot_id": np.asarray(result["dot_id"]) if "dot_id" in names else np.arange(len(result))}
        cols.update({n: np.asarray(result[n]) for n in names if n != "dot_id"})
        from synthbos.tracking import is_valid
        cols["valid"] = is_valid(result)
        return cols
    res = _as_result(result)
    n = len(res.xy)
    table = {k: np.asarray(v) for k, v in res.table.items() if v is not None and np.size(v) == n and np.ndim(v) >= 1}
    cols = {k: table.pop(k).ravel() for k in ("dot_id", "x", "y", "u", "v") if k in table}
    for k, values in (("x", res.xy[:, 0]), ("y", res.xy[:, 1]), ("u", res.uv[:, 0]), ("v", res.uv[:, 1])):
        cols.setdefault(k, values)
    cols.update({k: v.ravel() for k, v in table.items()})
    cols["valid"] = np.ones(n, bool) if res.valid is None else np.asarray(res.valid, bool)
    return cols
