"""NumPy reference of the shared-kernel step (:func:`tracking.kernel_step.kernel_step`), for the tests
only, called by :func:`tracking.reference.moment_shifts_numpy` with ``kernel=True``. No production module
imports it."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .dotfit import integrated_profile
from .moment_kernels import SHARE_FLOOR_REL
from .settings import (
    KERNEL_FITS,
    KERNEL_FLUX_BOUND,
    KERNEL_FLUX_STEP,
    KERNEL_FLUX_SWEEPS,
    KERNEL_GRID_STEP,
    KERNEL_ITERATIONS,
    KERNEL_MAX_NEIGHBOURS,
    KERNEL_PRIOR_MIN_VAR_PX2,
    KERNEL_REACH_PX,
    KERNEL_RIDGE,
    KERNEL_TAPS,
    KERNEL_WINDOW_HALF,
    KERNEL_WINDOW_SIGMA_PX,
)

__all__ = ["kernel_shifts", "taking_part"]


def taking_part(p, frame, applied):
    """The rows of the shared-kernel step: those within ``KERNEL_REACH_PX`` of a moving (``applied``) row of
    their frame (``kernel_rows``)."""
    moving = np.flatnonzero(applied)
    part = np.zeros(len(p), dtype=bool)
    if moving.size:
        tree = cKDTree(np.column_stack([p[moving, :2], frame[moving] * 1e6]))
        near = tree.query_ball_point(np.column_stack([p[:, :2], frame * 1e6]), KERNEL_REACH_PX)
        part = np.array([len(q) > 0 for q in near], dtype=bool)
    return part


def kernel_shifts(stack, p, frame, partner, applied, distorted, part, others, shift, background, half, max_shift, ell,
                  record, *, fit=True):  # fmt: skip
    """The shared-kernel step (:func:`tracking.kernel_step.kernel_step`) of the rows ``part`` (:func:`taking_part`;
    ``others``: the model image of the rest), their prior ``ell`` the elliptical fit of them all, then
    ``KERNEL_ITERATIONS`` moments, the ``distorted`` rows' kernels fitted in the first ``KERNEL_FITS``; the
    moving rows take their last positions where usable (``record``: as ``moment_shifts``'s ``kernels``)."""
    rows = np.flatnonzero(part)
    gradient = (frame[rows] % 2 == 1) & (partner[rows] >= 0)
    src = np.where(gradient, np.maximum(partner[rows], 0), rows)  # the reference partner: width and flux
    sigma, flux = p[src, 3], p[src, 2]
    pos = p[rows, :2] + np.where(applied[rows, None], shift[rows], 0.0)
    prior = _kernel_prior(ell, sigma)
    b = background[rows]
    level = {f: np.median(b[frame[rows] == f]) for f in np.unique(frame[rows])}
    kern, failed, alpha = prior.copy(), np.zeros(len(rows), dtype=bool), np.ones(len(rows))
    for iteration in range(KERNEL_ITERATIONS):
        if fit and iteration < KERNEL_FITS:  # else the kernels stay as they are
            kern = _kernel_fit(stack, frame[rows], level, pos, flux, sigma, prior, kern, distorted[rows])
        pos, failed, alpha = _kernel_moments(stack, others, p[rows, 2], frame[rows], pos, flux, sigma, kern, b, half,
                                             failed, alpha)  # fmt: skip
    d = pos - p[rows, :2]
    take = applied[rows] & ~failed & ((d**2).sum(axis=1) <= max_shift**2)
    shift = shift.copy()
    shift[rows[take]] = d[take]
    record.update(rows=rows, kernel=kern, position=pos)
    return shift


def _taps():
    return (np.arange(KERNEL_TAPS) - KERNEL_TAPS // 2) * KERNEL_GRID_STEP


def _kernel_prior(ell, sigma):
    """The elliptical models' covariances less the pixel's and the spot's, eigenvalues at least
    ``KERNEL_PRIOR_MIN_VAR_PX2``, as Gaussians on the kernel grid summing to 1 (rows (b, a): y tap, x tap)."""
    r1, r2, r3 = ell[:, 3], ell[:, 4], ell[:, 5]
    det = (r1 * r3) ** 2
    extra = 1.0 / 12.0 + sigma**2
    cov = np.stack([[(r2**2 + r3**2) / det - extra, -r1 * r2 / det], [-r1 * r2 / det, r1**2 / det - extra]])
    ev, vec = np.linalg.eigh(cov.transpose(2, 0, 1))
    cov = np.einsum("nij,nj,nkj->nik", vec, np.maximum(ev, KERNEL_PRIOR_MIN_VAR_PX2), vec)
    gx, gy = (g.ravel()[None] for g in np.meshgrid(_taps(), _taps()))
    inv = np.linalg.inv(cov)
    q = inv[:, 0, 0, None] * gx**2 + 2 * inv[:, 0, 1, None] * gx * gy + inv[:, 1, 1, None] * gy**2
    prior = np.exp(-0.5 * q)
    return prior / prior.sum(axis=1, keepdims=True)


def _kernel_mean(kern):
    k3 = kern.reshape(len(kern), KERNEL_TAPS, KERNEL_TAPS)
    total = kern.sum(axis=1)
    return k3.sum(axis=1) @ _taps() / total, k3.sum(axis=2) @ _taps() / total


def _kernel_fit(stack, frame, level, pos, flux, sigma, prior, last, distorted):
    """Each distorted row's kernel, the weighted ridge fit to its window (every row of its frame within
    ``KERNEL_REACH_PX`` drawn with it); the last one kept elsewhere, with too many neighbours or no solution."""
    h, w = stack.shape[1:]
    n = 2 * KERNEL_WINDOW_HALF + 1
    taps, k2 = _taps(), KERNEL_TAPS**2
    mux, muy = _kernel_mean(last)
    out = last.copy()
    tree = cKDTree(np.column_stack([pos, frame * 1e6]))
    for i, near in enumerate(tree.query_ball_point(np.column_stack([pos, frame * 1e6]), KERNEL_REACH_PX)):
        near = np.asarray(near)
        if not distorted[i] or len(near) > KERNEL_MAX_NEIGHBOURS:
            continue
        ox, oy = np.rint(pos[i]).astype(np.int64) - KERNEL_WINDOW_HALF
        cx = (pos[near, 0, None] - mux[i] + taps[None]).ravel()
        cy = (pos[near, 1, None] - muy[i] + taps[None]).ravel()
        px = integrated_profile(cx, np.repeat(sigma[near], KERNEL_TAPS), np.full(cx.size, ox), n)[0]
        py = integrated_profile(cy, np.repeat(sigma[near], KERNEL_TAPS), np.full(cy.size, oy), n)[0]
        px = px.reshape(len(near), KERNEL_TAPS, n) * flux[near, None, None]
        py = py.reshape(len(near), KERNEL_TAPS, n)
        design = np.einsum("jby,jax->bayx", py, px).reshape(k2, n * n)
        xs, ys = ox + np.arange(n), oy + np.arange(n)
        wx = np.exp(-0.5 * (xs - pos[i, 0]) ** 2 / KERNEL_WINDOW_SIGMA_PX**2) * ((xs >= 0) & (xs < w))
        wy = np.exp(-0.5 * (ys - pos[i, 1]) ** 2 / KERNEL_WINDOW_SIGMA_PX**2) * ((ys >= 0) & (ys < h))
        weight = (wy[:, None] * wx[None, :]).ravel()
        data = stack[frame[i], np.clip(ys, 0, h - 1)[:, None], np.clip(xs, 0, w - 1)[None, :]].ravel() - level[frame[i]]
        normal = (design * weight) @ design.T
        lam = KERNEL_RIDGE * np.trace(normal) / k2
        try:
            np.linalg.cholesky(normal + lam * np.eye(k2))
        except np.linalg.LinAlgError:
            continue
        out[i] = np.linalg.solve(normal + lam * np.eye(k2), (design * weight) @ data + lam * prior[i])
    return out


def _kernel_moments(stack, others, peak, frame, pos, flux, sigma, kern, b, half, failed, alpha):
    """Every row's kernel model on its stamp about its position (``others``: the model image of the rows
    that do not take part), the shares held to the reference flux
    (``KERNEL_FLUX_SWEEPS`` sweeps of the multipliers ``alpha``), and each row moved to the first moment of
    its held share of the light; failed where it holds none."""
    h, w = stack.shape[1:]
    n = 2 * half + 1
    taps = _taps()
    mux, muy = _kernel_mean(kern)
    ox, oy = np.rint(pos[:, 0]).astype(np.int64) - half, np.rint(pos[:, 1]).astype(np.int64) - half
    px = integrated_profile((pos[:, 0, None] - mux[:, None] + taps).ravel(), np.repeat(sigma, KERNEL_TAPS),
                            np.repeat(ox, KERNEL_TAPS), n)[0].reshape(len(pos), KERNEL_TAPS, n)  # fmt: skip
    py = integrated_profile((pos[:, 1, None] - muy[:, None] + taps).ravel(), np.repeat(sigma, KERNEL_TAPS),
                            np.repeat(oy, KERNEL_TAPS), n)[0].reshape(len(pos), KERNEL_TAPS, n)  # fmt: skip
    k3 = kern.reshape(len(pos), KERNEL_TAPS, KERNEL_TAPS)
    models = flux[:, None, None] * np.einsum("nba,nby,nax->nyx", k3, py, px)
    xs = np.broadcast_to((ox[:, None] + np.arange(n))[:, None, :], models.shape)
    ys = np.broadcast_to((oy[:, None] + np.arange(n))[:, :, None], models.shape)
    inside = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)
    fr = np.broadcast_to(frame[:, None, None], models.shape)
    at = (fr, np.clip(ys, 0, h - 1), np.clip(xs, 0, w - 1))
    data = stack[at] - b[:, None, None]

    def held(a):  # the light each row's share ``a m / M`` holds (inside the image)
        total = others.copy()
        np.add.at(total, (fr[inside], ys[inside], xs[inside]), (a[:, None, None] * models)[inside])
        floor = SHARE_FLOOR_REL * np.abs(peak[:, None, None])
        return np.where(inside, np.clip(a[:, None, None] * models / np.maximum(total[at], floor), 0.0, 1.0) * data, 0)

    target = models.sum(axis=(1, 2)) / kern.sum(axis=1) - np.where(inside, 0.0, models).sum(axis=(1, 2))
    for _ in range(KERNEL_FLUX_SWEEPS):
        have = held(alpha).sum(axis=(1, 2))
        ok = (target > 0) & (have > 0)
        ratio = np.clip(target / np.where(ok, have, 1.0), 1 / KERNEL_FLUX_STEP, KERNEL_FLUX_STEP)
        alpha = np.where(ok, np.clip(alpha * ratio, 1 / KERNEL_FLUX_BOUND, KERNEL_FLUX_BOUND), alpha)
    light = np.where(inside, held(alpha), models)
    light_sum = light.sum(axis=(1, 2))
    go = light_sum > 0
    safe = np.where(go, light_sum, 1.0)
    first = np.stack([((xs - pos[:, 0, None, None]) * light).sum(axis=(1, 2)),
                      ((ys - pos[:, 1, None, None]) * light).sum(axis=(1, 2))], axis=1)  # fmt: skip
    return np.where(go[:, None], pos + first / safe[:, None], pos), failed | ~go, alpha
