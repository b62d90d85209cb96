"""Least-squares fit of the pixel-integrated Gaussian dot model, each dot jointly with its neighbours.

The model of a dot is the one the images are made of: a Gaussian of peak ``I0`` and standard deviation
``sigma`` centred at ``(x, y)``, integrated over each pixel's area, on a local constant background
``b``. Integration over a square pixel separates into a product of two 1-D pixel profiles (differences
of error functions), so a dot's model, its derivatives and its Jacobian cost a few error functions per
row and column of its window.

Dots of a dense pattern overlap in their tails. Every dot is therefore fitted to the image minus the
current model of all the *other* dots (the residual image with its own model added back), and the
model image is redrawn between Gauss-Newton steps (block-Jacobi iteration on the joint least-squares
problem of all dots). At zero noise the fit converges to the exact positions; under white noise it is
the maximum-likelihood estimate and reaches the Cramer-Rao bound (:mod:`tracking.crlb`).

:func:`fit_dots` runs the iteration with Warp kernels (one thread per dot); :func:`fit_dots_numpy` is
the array-program reference that defines the result.
"""

from __future__ import annotations

import numpy as np
import warp as wp
from numpy.lib.stride_tricks import sliding_window_view
from scipy.special import erf

from .kernels import fit_dot_step_kernel, render_dots_kernel

__all__ = [
    "PARAMS",
    "fit_dots",
    "fit_dots_numpy",
    "fit_window_half",
    "integrated_profile",
    "render_dots",
]

PARAMS = ("x", "y", "peak", "sigma", "background")
"""Columns of a parameter array: centre (x = column), peak ``I0``, standard deviation, background."""

_SQRT_HALF_PI = np.sqrt(np.pi / 2.0)


def fit_window_half(sigma):
    """Half-widths ``(fit, render)`` of the windows used for dots of standard deviation ``sigma`` (px).

    The fit window (``2 fit + 1`` pixels square, at least 5) holds the pixels that carry nearly all of
    the position information (out to ~2.7 sigma); the rendering stamp reaches 4 sigma, where a dot's
    intensity is below 4e-4 of its peak.
    """
    fit = max(2, int(np.ceil(2.5 * sigma - 0.05)))
    return fit, max(fit, int(np.ceil(4.0 * sigma)))


def integrated_profile(centre, sigma, first, n):
    """1-D pixel profile of a unit-peak Gaussian and its derivatives, for a stack of dots.

    Parameters
    ----------
    centre, sigma : (N,) arrays
        Centre and standard deviation, pixels.
    first : (N,) int array
        First pixel of each dot's window; pixel ``k`` spans ``[k - 0.5, k + 0.5]``.
    n : int
        Window length.

    Returns
    -------
    p, dp_dc, dp_ds : (N, n) arrays
        ``p_k = int_{k-1/2}^{k+1/2} exp(-(t - c)^2 / (2 s^2)) dt`` and its derivatives with respect to
        ``c`` and ``s``.

    Notes
    -----
    With the standardised edges ``z = (k -+ 1/2 - c) / s``: ``p = sqrt(pi / 2) s [erf(z / sqrt 2)]``,
    ``dp/dc = [-exp(-z^2 / 2)]`` and ``dp/ds = [-z exp(-z^2 / 2)] + p / s``, each ``[f]`` meaning
    ``f(z_upper) - f(z_lower)``. A dot's model is ``I0 p_x p_y + b``.
    """
    centre = np.asarray(centre, dtype=np.float64)
    sigma = np.asarray(sigma, dtype=np.float64)
    edges = np.asarray(first)[:, None] + np.arange(n + 1)[None, :] - 0.5
    z = (edges - centre[:, None]) / sigma[:, None]
    g = np.exp(-0.5 * z * z)
    p = np.diff(_SQRT_HALF_PI * sigma[:, None] * erf(z / np.sqrt(2.0)), axis=1)
    dp_dc = g[:, :-1] - g[:, 1:]
    zg = z * g
    dp_ds = zg[:, :-1] - zg[:, 1:] + p / sigma[:, None]
    return p, dp_dc, dp_ds


def _origin(params, half):
    return np.rint(params[:, 0]).astype(np.int64) - half, np.rint(params[:, 1]).astype(np.int64) - half


def _stamps(params, half):
    """Each dot's model (without background) on its window, and the window's first column and row."""
    n = 2 * half + 1
    ox, oy = _origin(params, half)
    px, _, _ = integrated_profile(params[:, 0], params[:, 3], ox, n)
    py, _, _ = integrated_profile(params[:, 1], params[:, 3], oy, n)
    return params[:, 2, None, None] * py[:, :, None] * px[:, None, :], ox, oy


def render_dots(shape, params, *, half):
    """Image of the dots' models (backgrounds left out), each drawn on a ``2 half + 1`` square stamp.

    Parameters
    ----------
    shape : (H, W)
    params : (N, 5) array
        Columns :data:`PARAMS`; rows with a non-finite entry are not drawn.
    half : int, keyword-only
        Stamp half-width, centred on the pixel nearest each dot.

    Returns
    -------
    (H, W) float64 array
    """
    params = np.asarray(params, dtype=np.float64).reshape(-1, 5)
    params = params[np.isfinite(params).all(axis=1)]
    h, w = shape
    if len(params) == 0:
        return np.zeros(shape)
    stamp, ox, oy = _stamps(params, half)
    n = 2 * half + 1
    cols = np.broadcast_to((ox[:, None] + np.arange(n))[:, None, :], stamp.shape)
    rows = np.broadcast_to((oy[:, None] + np.arange(n))[:, :, None], stamp.shape)
    inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    flat = (rows * w + cols)[inside]
    return np.bincount(flat, weights=stamp[inside], minlength=h * w).reshape(shape)


def _step_numpy(image, model, params, start, *, half, fit_shape, max_move, sigma_range):
    """One Gauss-Newton step of every dot against the image minus the other dots (NumPy)."""
    n_dots = len(params)
    n = 2 * half + 1
    h, w = image.shape
    ox, oy = _origin(params, half)
    pad = n + 1
    win = sliding_window_view(np.pad(image - model, pad), (n, n))[oy + pad, ox + pad]
    cols = ox[:, None] + np.arange(n)
    rows = oy[:, None] + np.arange(n)
    inside = ((rows >= 0) & (rows < h))[:, :, None] & ((cols >= 0) & (cols < w))[:, None, :]
    x, y, a, s, b = params.T
    px, dpx, spx = integrated_profile(x, s, ox, n)
    py, dpy, spy = integrated_profile(y, s, oy, n)
    shape_xy = py[:, :, None] * px[:, None, :]
    # The data are win + own (the image less the other dots); the residual, data - own - b, is win - b.
    resid = np.where(inside, win - b[:, None, None], 0.0)
    jac = np.stack(
        [
            a[:, None, None] * py[:, :, None] * dpx[:, None, :],
            a[:, None, None] * dpy[:, :, None] * px[:, None, :],
            shape_xy,
            a[:, None, None] * (spy[:, :, None] * px[:, None, :] + py[:, :, None] * spx[:, None, :]),
            np.ones_like(shape_xy),
        ],
        axis=-1,
    ) * inside[..., None]
    jac = jac.reshape(n_dots, n * n, 5)
    normal = np.einsum("npk,npl->nkl", jac, jac)
    rhs = np.einsum("npk,np->nk", jac, resid.reshape(n_dots, n * n))
    if not fit_shape:
        for k in (2, 3):
            normal[:, k, :] = 0.0
            normal[:, :, k] = 0.0
            normal[:, k, k] = 1.0
            rhs[:, k] = 0.0
    normal += 1e-12 * np.eye(5)
    step = np.linalg.solve(normal, rhs[:, :, None])[:, :, 0]
    # The position moves at most half a pixel per step.
    scale = np.minimum(1.0, 0.5 / np.maximum(np.abs(step[:, :2]).max(axis=1), 1e-300))
    new = params + step * scale[:, None]
    ok = np.isfinite(new).all(axis=1)
    ok &= (np.abs(new[:, 0] - start[:, 0]) <= max_move) & (np.abs(new[:, 1] - start[:, 1]) <= max_move)
    ok &= (new[:, 2] > 0) & (new[:, 3] >= sigma_range[0]) & (new[:, 3] <= sigma_range[1])
    return np.where(ok[:, None], new, params), ok


def _checked(params):
    p = np.array(params, dtype=np.float64).reshape(-1, 5)
    if not np.isfinite(p).all():
        raise ValueError("fit_dots needs finite starting parameters")
    return p


def fit_dots_numpy(
    image,
    params,
    *,
    half,
    render_half,
    iterations=4,
    fit_shape=True,
    max_move=1.0,
    sigma_range=(0.2, 10.0),
):
    """Fit the pixel-integrated Gaussian model to every dot of an image, jointly with its neighbours.

    Parameters
    ----------
    image : (H, W) array
    params : (N, 5) array
        Starting parameters, columns :data:`PARAMS` (finite).
    half, render_half : int, keyword-only
        Half-widths of each dot's fit window and of its rendered stamp (:func:`fit_window_half`).
    iterations : int, keyword-only
        Gauss-Newton steps; the model image of all dots is redrawn before each.
    fit_shape : bool, keyword-only
        Fit ``I0`` and ``sigma`` too; False keeps them and fits position and background only.
    max_move : float, keyword-only
        A step that takes a dot farther than this (px, per axis) from its start is refused.
    sigma_range : (float, float), keyword-only
        A step that takes ``sigma`` outside this range (or ``I0`` to zero) is refused.

    Returns
    -------
    params : (N, 5) array
        Fitted parameters.
    ok : (N,) bool array
        False where the last step was refused (the dot keeps its previous parameters).

    Notes
    -----
    Block-Jacobi Gauss-Newton on ``sum_pixels (I - sum_dots (I0 p_x p_y + b))^2``: before each step the
    model image ``R`` of all dots is drawn, and dot ``i`` takes one Gauss-Newton step on its window of
    ``I - R + I0_i p_x p_y`` (the image with the other dots removed) with its five parameters. For
    non-touching dots it is the plain Gauss-Newton fit of Brady, Raben and Vlachos (2009, section 2.3)
    with the pixel-integrated model instead of a sampled Gaussian, which removes that fit's bias on
    small dots; the joint fit removes the bias that neighbours' tails cause in a dense pattern.
    """
    image = np.asarray(image, dtype=np.float64)
    p = _checked(params)
    start = p.copy()
    ok = np.ones(len(p), dtype=bool)
    for _ in range(iterations):
        model = render_dots(image.shape, p, half=render_half)
        p, ok = _step_numpy(
            image,
            model,
            p,
            start,
            half=half,
            fit_shape=fit_shape,
            max_move=max_move,
            sigma_range=sigma_range,
        )
    return p, ok


def fit_dots(
    image,
    params,
    *,
    half,
    render_half,
    iterations=4,
    fit_shape=True,
    max_move=1.0,
    sigma_range=(0.2, 10.0),
    device=None,
):
    """Same as :func:`fit_dots_numpy`, with Warp kernels (one thread per dot).

    Parameters
    ----------
    device : str or None, keyword-only
        Warp device ("cpu", "cuda:0"); Warp's default when None.

    Other parameters and the result are those of :func:`fit_dots_numpy`.
    """
    p = _checked(params)
    n = len(p)
    if n == 0:
        return p, np.ones(0, dtype=bool)
    img = wp.array(np.ascontiguousarray(image, dtype=np.float64), dtype=wp.float64, device=device)
    model = wp.zeros(img.shape, dtype=wp.float64, device=device)
    cur = wp.array(p, dtype=wp.float64, device=device)
    nxt = wp.array(p, dtype=wp.float64, device=device)
    start = wp.array(p, dtype=wp.float64, device=device)
    ok = wp.zeros(n, dtype=wp.int32, device=device)
    nmax = 2 * max(half, render_half) + 2
    prof = wp.empty((n, 6, nmax), dtype=wp.float64, device=device)
    for _ in range(iterations):
        model.zero_()
        wp.launch(render_dots_kernel, dim=n, inputs=[cur, int(render_half), prof, model], device=device)
        wp.launch(
            fit_dot_step_kernel,
            dim=n,
            inputs=[
                img,
                model,
                cur,
                start,
                int(half),
                int(bool(fit_shape)),
                float(max_move),
                float(sigma_range[0]),
                float(sigma_range[1]),
                prof,
                nxt,
                ok,
            ],
            device=device,
        )
        cur, nxt = nxt, cur
    return cur.numpy(), ok.numpy().astype(bool)
