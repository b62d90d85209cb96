"""The tracking vocabulary as Warp constants: the status bits and rule constants of
:mod:`tracking.settings` (their one home), read by the stacked tracker's kernel modules.

Float64 constants, since a literal in a kernel may be float32.
"""

import warp as wp

from synthbos.device import quiet_warp

from .settings import (
    DIAMETER_PER_WIDTH,
    EDGE_CUT_PX,
    ELLIPSE_DAMPING,
    ELLIPSE_MARQUARDT,
    ELLIPSE_MAX_STEP,
    ELLIPSE_WIDTH_RANGE,
    KERNEL_FLUX_BOUND,
    KERNEL_FLUX_STEP,
    KERNEL_GRID_STEP,
    KERNEL_MAX_NEIGHBOURS,
    KERNEL_PRIOR_MIN_VAR_PX2,
    KERNEL_REACH_PX,
    KERNEL_RIDGE,
    KERNEL_TAPS,
    KERNEL_WINDOW_HALF,
    KERNEL_WINDOW_SIGMA_PX,
    PIXEL_EDGE_PX,
    RESIDUAL_STAMP_WIDTHS,
    RESIDUAL_WIDTH_CLIP,
    THREE_POINT_WIDTH_RANGE,
    DotStatus,
)

quiet_warp()  # no banner or module-load lines from library code (synthbos.device)
wp.set_module_options({"enable_backward": False})  # forward-only kernels: no adjoint code to compile


# the status bits, from their one home
FOUND_REFERENCE = wp.constant(int(DotStatus.FOUND_REFERENCE))
FOUND_GRADIENT = wp.constant(int(DotStatus.FOUND_GRADIENT))
MATCHED = wp.constant(int(DotStatus.MATCHED))
CC_VALID = wp.constant(int(DotStatus.CC_VALID))
CC_FLAGGED = wp.constant(int(DotStatus.CC_FLAGGED))
OUTSIDE_IMAGE = wp.constant(int(DotStatus.OUTSIDE_IMAGE))
NEAR_BORDER = wp.constant(int(DotStatus.NEAR_BORDER))
SATURATED = wp.constant(int(DotStatus.SATURATED))
OVERLAPPED = wp.constant(int(DotStatus.OVERLAPPED))
AMBIGUOUS = wp.constant(int(DotStatus.AMBIGUOUS))
FIT_FALLBACK = wp.constant(int(DotStatus.FIT_FALLBACK))
DISTORTED = wp.constant(int(DotStatus.DISTORTED))
PREDICTOR_MISMATCH = wp.constant(int(DotStatus.PREDICTOR_MISMATCH))
PREDICTOR_WEAK = wp.constant(int(DotStatus.PREDICTOR_WEAK))
EDGE_CUT = wp.constant(int(DotStatus.EDGE_CUT))
OUTLIER = wp.constant(int(DotStatus.OUTLIER))
MASKED = wp.constant(int(DotStatus.MASKED))
MISREGISTERED = wp.constant(int(DotStatus.MISREGISTERED))

# the rule constants, from their one home (float64 constants: a literal in a kernel may be float32)
PIXEL_EDGE = wp.constant(wp.float64(PIXEL_EDGE_PX))
WIDTH_LO = wp.constant(wp.float64(THREE_POINT_WIDTH_RANGE[0]))
WIDTH_HI = wp.constant(wp.float64(THREE_POINT_WIDTH_RANGE[1]))
CLIP_LO = wp.constant(wp.float64(RESIDUAL_WIDTH_CLIP[0]))
CLIP_HI = wp.constant(wp.float64(RESIDUAL_WIDTH_CLIP[1]))
STAMP_WIDTHS = wp.constant(wp.float64(RESIDUAL_STAMP_WIDTHS))
EDGE_CUT_MAX = wp.constant(wp.float64(EDGE_CUT_PX))
DIAMETER_WIDTHS = wp.constant(wp.float64(DIAMETER_PER_WIDTH))
ELL_DAMPING = wp.constant(wp.float64(ELLIPSE_DAMPING))
ELL_MARQUARDT = wp.constant(wp.float64(ELLIPSE_MARQUARDT))
ELL_MAX_STEP = wp.constant(wp.float64(ELLIPSE_MAX_STEP))
ELL_WIDTH_LO = wp.constant(wp.float64(ELLIPSE_WIDTH_RANGE[0]))
ELL_WIDTH_HI = wp.constant(wp.float64(ELLIPSE_WIDTH_RANGE[1]))
KER_STEP = wp.constant(wp.float64(KERNEL_GRID_STEP))
KER_TAPS = wp.constant(KERNEL_TAPS)
KER_UNKNOWNS = wp.constant(KERNEL_TAPS * KERNEL_TAPS)
KER_WINDOW_HALF = wp.constant(KERNEL_WINDOW_HALF)
KER_WINDOW = wp.constant(2 * KERNEL_WINDOW_HALF + 1)
KER_WINDOW_SIGMA = wp.constant(wp.float64(KERNEL_WINDOW_SIGMA_PX))
KER_REACH = wp.constant(wp.float64(KERNEL_REACH_PX))
KER_MAX_NEIGHBOURS = wp.constant(KERNEL_MAX_NEIGHBOURS)
KER_RIDGE = wp.constant(wp.float64(KERNEL_RIDGE))
KER_PRIOR_MIN_VAR = wp.constant(wp.float64(KERNEL_PRIOR_MIN_VAR_PX2))
KER_FLUX_STEP = wp.constant(wp.float64(KERNEL_FLUX_STEP))
KER_FLUX_BOUND = wp.constant(wp.float64(KERNEL_FLUX_BOUND))
