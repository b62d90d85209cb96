"""Warp kernels of the first-moment step: a distorted dot's position moved to the mean of its light.

A dot seen through a flow is no longer a symmetric spot: rays through different parts of the aperture
cross different density, so its image is the spot spread (and skewed) by the distribution of their
landing positions. The renderer's truth, and the quantity BOS measures, is the mean landing position;
the symmetric model's centre is not. The mean of a dot's light is its image's first moment, and the
model fit already gives everything needed to take it in a dense pattern: the model image of every dot
tells which share of each pixel's light belongs to which dot, and the dot's own model carries the
symmetric part exactly. Only the residual (image less background less every model) is left to weigh.

The host code lives in :mod:`tracking.dotfit` (for one pair and for a stack of pairs, both through
:func:`moment_shift_stack`); the NumPy reference, ``tracking.reference.moment_shifts_numpy``,
defines the result.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

#: Shifts below this (px) are left alone: far below any measurement's noise, they would only flag the
#: dots of noise-free images whose models leave rounding-level residuals.
MIN_SHIFT_PX = 1.0e-3
MIN_SHIFT = wp.constant(wp.float64(MIN_SHIFT_PX))
#: A dot's share of a pixel is its model over the model of every dot there, the latter taken as at least
#: this fraction of the dot's peak: in the far tails, where both are rounding-level, the share falls off
#: instead of depending on the fixed-point model image's last bits.
SHARE_FLOOR_REL = 1.0e-6
SHARE_FLOOR = wp.constant(wp.float64(SHARE_FLOOR_REL))
#: The light a dot's model leaves over on its stamp (its share, signed) may be at most this fraction of
#: the model's own light. A distorted dot's is within 0.12 (99.9 % of the dots of the default snapshot 2
#: at 256 px, zero noise): the flow moves light, the fit keeps the flux. Beyond it the stamp holds a
#: dot the fit does not know (one entering at the image edge, one identification missed), whose light
#: would drag the moment: the dot keeps its model centre.
MAX_RESIDUAL_FLUX_REL = 0.25
MAX_RESIDUAL_FLUX = wp.constant(wp.float64(MAX_RESIDUAL_FLUX_REL))
#: A dot's first moment can leave its symmetric centre only as far as the flow spread its light: the
#: shift may be at most this times ``sqrt(sigma^2 - sigma_partner^2)``, the spread its fitted width adds
#: to its partner's in the other image. Distorted dots of the default snapshot 2 (256 px, zero noise)
#: stay below 0.28 of it; a neighbour's light the fit does not know has no such bound.
MAX_SHIFT_PER_SPREAD_REL = 1.0
MAX_SHIFT_PER_SPREAD = wp.constant(wp.float64(MAX_SHIFT_PER_SPREAD_REL))
#: No first-moment shift beyond this (px) is taken, whatever the rest says.
MAX_SHIFT_PX = 1.0
USABLE_CODE = wp.constant(wp.float64(1.0))
DISTORTED_CODE = wp.constant(wp.float64(2.0))


@wp.func
def stamp_unsaturated(
    image: wp.array2d(dtype=wp.float64), params: wp.array2d(dtype=wp.float64), i: int, half: int, sat: wp.float64
) -> bool:
    """True where no pixel of dot i's ``2 half + 1`` stamp that lies inside the image is at or above ``sat``."""
    if sat >= wp.float64(1.0e300):
        return True
    n = 2 * half + 1
    ox = int(wp.rint(params[i, 0])) - half
    oy = int(wp.rint(params[i, 1])) - half
    for rr in range(wp.max(-oy, 0), wp.min(n, image.shape[0] - oy)):
        for cc in range(wp.max(-ox, 0), wp.min(n, image.shape[1] - ox)):
            if image[oy + rr, ox + cc] >= sat:
                return False
    return True


@wp.func
def moment_shift(
    image: wp.array2d(dtype=wp.float64),
    models: wp.array(dtype=wp.int64),
    inv_scale: wp.float64,
    f: int,
    params: wp.array2d(dtype=wp.float64),
    i: int,
    half: int,
    background: wp.float64,
    spread2: wp.float64,
    sat: wp.float64,
    noise: wp.float64,
    chi2: wp.float64,
    max_shift: wp.float64,
    prof: wp.array3d(dtype=wp.float64),
) -> wp.vec3d:
    """Shift ``(dx, dy)`` from dot i's model centre to the first moment of its share of the light, and
    its code: ``DISTORTED_CODE`` where the dot is distorted, ``USABLE_CODE`` where the shift is usable
    but not significant on its own, 0 where neither (see ``tracking.reference.moment_shifts_numpy``).

    ``models``: the fixed-point model images ``[frames, height, width]`` (flat) of every dot at
    ``params``; ``prof`` holds dot i's profiles on its ``2 half + 1`` stamp at ``params``;
    ``background``: the level under the dot; ``spread2``: the square of the largest shift its width
    allows (``reference_spread2``).
    """
    zero = wp.float64(0.0)
    if not stamp_unsaturated(image, params, i, half, sat):
        return wp.vec3d(zero, zero, zero)
    n = 2 * half + 1
    ox = int(wp.rint(params[i, 0])) - half
    oy = int(wp.rint(params[i, 1])) - half
    height = image.shape[0]
    width = image.shape[1]
    x0 = params[i, 0]
    y0 = params[i, 1]
    floor = SHARE_FLOOR * wp.abs(params[i, 2])
    flux = zero
    own_flux = zero
    sx = zero
    sy = zero
    vx = zero
    vy = zero
    for r in range(n):
        own_row = params[i, 2] * prof[i, 3, r]
        row_inside = oy + r >= 0 and oy + r < height
        at = (f * height + oy + r) * width + ox
        dy = wp.float64(oy + r) - y0
        for c in range(n):
            own = own_row * prof[i, 0, c]
            own_flux += own
            if not (row_inside and ox + c >= 0 and ox + c < width):
                flux += own  # outside the image: the dot's own model, which has no first moment
                continue
            total = wp.float64(models[at + c]) * inv_scale
            share = wp.clamp(own / wp.max(total, floor), zero, wp.float64(1.0))
            wr = share * (image[oy + r, ox + c] - background - total)
            dx = wp.float64(ox + c) - x0
            flux += own + wr
            sx += dx * wr
            sy += dy * wr
            vx += dx * dx * share * share
            vy += dy * dy * share * share
    if not (flux > zero) or wp.abs(flux - own_flux) > MAX_RESIDUAL_FLUX * own_flux:
        return wp.vec3d(zero, zero, zero)
    mx = sx / flux
    my = sy / flux
    shift2 = mx * mx + my * my
    if shift2 > max_shift * max_shift:
        return wp.vec3d(zero, zero, zero)
    var = noise * noise * (vx + vy) / (flux * flux)
    if shift2 > chi2 * wp.float64(0.5) * var and shift2 >= MIN_SHIFT * MIN_SHIFT and shift2 <= spread2:
        return wp.vec3d(mx, my, DISTORTED_CODE)
    return wp.vec3d(mx, my, USABLE_CODE)


@wp.func
def moves(code: wp.array(dtype=wp.vec3d), partner: wp.array(dtype=wp.int32), i: int) -> bool:
    """Whether dot i moves to its first moment: its shift is usable and it or its partner is distorted
    (a matched pair is measured alike in both images)."""
    if code[i][2] < USABLE_CODE:
        return False
    j = partner[i]
    return code[i][2] == DISTORTED_CODE or (j >= 0 and code[j][2] == DISTORTED_CODE)


@wp.func
def reference_background(
    params: wp.array2d(dtype=wp.float64), partner: wp.array(dtype=wp.int32), i: int, gradient: bool
) -> wp.float64:
    """The level under dot i: its partner's fitted background where dot i lies in a gradient image and
    has a partner (the reference image sees the same target and light, undistorted), else its own."""
    j = partner[i]
    if gradient and j >= 0:
        return params[j, 4]
    return params[i, 4]


@wp.func
def reference_spread2(params: wp.array2d(dtype=wp.float64), partner: wp.array(dtype=wp.int32), i: int) -> wp.float64:
    """The square of the largest first-moment shift dot i's image allows: ``MAX_SHIFT_PER_SPREAD^2`` times
    the variance its fitted width adds to its partner's, ``sigma_i^2 - sigma_j^2`` (0 without a partner
    or when it is not the wider of the two)."""
    j = partner[i]
    if j < 0:
        return wp.float64(0.0)
    extra = params[i, 3] * params[i, 3] - params[j, 3] * params[j, 3]
    return MAX_SHIFT_PER_SPREAD * MAX_SHIFT_PER_SPREAD * wp.max(extra, wp.float64(0.0))


@wp.kernel
def moment_moves_kernel(
    shift: wp.array(dtype=wp.vec3d), partner: wp.array(dtype=wp.int32), moved: wp.array(dtype=wp.int32)
):
    """``moves`` of dot i."""
    i = wp.tid()
    moved[i] = int(moves(shift, partner, i))


# --- the step on a stack of pairs (tracking.dotfit) ------------------------------------------------


@wp.kernel
def moment_shift_stack(
    references: wp.array3d(dtype=wp.float64),
    gradients: wp.array3d(dtype=wp.float64),
    models: wp.array(dtype=wp.int64),
    scales: wp.array(dtype=wp.float64),
    params: wp.array2d(dtype=wp.float64),
    frame: wp.array(dtype=wp.int32),
    partner: wp.array(dtype=wp.int32),
    live: wp.array(dtype=wp.int32),
    saturation: wp.array(dtype=wp.float64),
    noise: wp.array(dtype=wp.float64),
    half: int,
    chi2: wp.float64,
    max_shift: wp.float64,
    prof: wp.array3d(dtype=wp.float64),
    shift: wp.array(dtype=wp.vec3d),
):
    """``moment_shift`` of row i (model frame ``2 b``: pair b's reference image, ``2 b + 1`` its gradient
    image; ``noise`` per frame); ``apply_moment_shift`` then moves the rows."""
    i = wp.tid()
    shift[i] = wp.vec3d()
    if live[i] == 0:
        return
    f = frame[i]
    inv_scale = wp.float64(1.0) / scales[f]
    b = f // 2
    bg = reference_background(params, partner, i, f % 2 == 1)
    s2 = reference_spread2(params, partner, i)
    if f % 2 == 0:
        shift[i] = moment_shift(
            references[b], models, inv_scale, f, params, i, half, bg, s2, saturation[f], noise[f], chi2, max_shift,
            prof,
        )  # fmt: skip
    else:
        shift[i] = moment_shift(
            gradients[b], models, inv_scale, f, params, i, half, bg, s2, saturation[f], noise[f], chi2, max_shift,
            prof,
        )  # fmt: skip


@wp.kernel
def apply_moment_shift(
    shift: wp.array(dtype=wp.vec3d),
    partner: wp.array(dtype=wp.int32),
    params: wp.array2d(dtype=wp.float64),
    shared_xy: wp.array2d(dtype=wp.float64),
    moved: wp.array(dtype=wp.int32),
):
    """The model fit's first-moment step (:func:`tracking.dotfit.fit_stack`), in place: where row i
    ``moves``, its position moves by its shift, and its common-shape position (where it has one) becomes
    that moved position: the shift is measured about the own fit's centre, and the moved position is the
    mean of the dot's light,
    which both corrections then read."""
    i = wp.tid()
    moved[i] = 0
    if moves(shift, partner, i):
        d = shift[i]
        params[i, 0] = params[i, 0] + d[0]
        params[i, 1] = params[i, 1] + d[1]
        if wp.isfinite(shared_xy[i, 0]):
            shared_xy[i, 0] = params[i, 0]
            shared_xy[i, 1] = params[i, 1]
        moved[i] = 1
