"""From image displacements to density gradients at the volume's mid-plane (Eq. 4 inverted).

Everything here takes plain numbers and arrays; the camera and volume quantities come from whoever
calls (the pair file's attributes, or a user's set-up).

Sign convention (the renderer's, see ``raytrace.pairfile``): images upright (x = column grows with
target x, y = row with target y), displacement = gradient image minus reference image, and a dot
appears shifted *down* the density gradient::

    dX = -(M Z_D / n0) * integral of grad n dz,    n = 1 + K rho.

With ``rho_avg`` the density averaged over the depth ``L`` of the volume,
``integral of grad n dz = K L grad rho_avg``, so::

    grad rho_avg = -n0 dX / (M Z_D K L)        (dX in metres on the sensor: px times the pitch).
"""

from __future__ import annotations

import numpy as np

__all__ = ["displacement_to_density_gradient", "midplane_scale", "pixel_to_midplane"]


def displacement_to_density_gradient(u_px, v_px, *, magnification, z_d_m, depth_m, gladstone_dale_m3_per_kg,
                                     n0, pixel_pitch_m):
    """Depth-averaged density gradient from image displacements (Eq. 4 solved for grad rho).

    Parameters
    ----------
    u_px, v_px : array_like
        Displacements along x (columns) and y (rows) in pixels, gradient minus reference.
    magnification : float
        Lateral magnification of the target plane, taken positive.
    z_d_m : float
        Distance Z_D from the target to the mid-plane of the volume (m).
    depth_m : float
        Depth L of the density volume along the optical axis (m).
    gladstone_dale_m3_per_kg : float
        Gladstone-Dale constant K (n = 1 + K rho).
    n0 : float
        Refractive index of the undisturbed medium.
    pixel_pitch_m : float
        Sensor pixel pitch (m).

    Returns
    -------
    gx, gy : ndarray
        d rho_avg / dx and d rho_avg / dy in kg/m^4, x and y as in the volume's frame.

    Notes
    -----
    Eq. 4 of Rajendran, Bane and Vlachos (2019), dX = -(M Z_D / n0) K L grad rho_avg, inverted.
    """
    factor = -n0 * pixel_pitch_m / (magnification * z_d_m * gladstone_dale_m3_per_kg * depth_m)
    return factor * np.asarray(u_px, dtype=np.float64), factor * np.asarray(v_px, dtype=np.float64)


def midplane_scale(*, magnification, pixel_pitch_m, z_d_m, z_stop_m):
    """Metres at the volume's mid-plane per image pixel, along the chief rays.

    A pixel images the target point ``X = (p - c) pitch / M``; its chief ray, from that point towards
    the centre of the aperture stop at ``z_stop``, crosses the mid-plane ``z = Z_D`` at
    ``X (1 - Z_D / z_stop)``.
    """
    return pixel_pitch_m / magnification * (1.0 - z_d_m / z_stop_m)


def pixel_to_midplane(x_px, y_px, *, principal_point_px, magnification, pixel_pitch_m, z_d_m, z_stop_m,
                      volume_centre_m=(0.0, 0.0)):
    """Image pixel coordinates to coordinates in the volume's frame at its mid-plane.

    Parameters
    ----------
    x_px, y_px : array_like
        Pixel coordinates (x = column, y = row, pixel centres at integers).
    principal_point_px : (float, float)
        Pixel coordinates of the optical axis.
    magnification, pixel_pitch_m, z_d_m : float
        As in :func:`displacement_to_density_gradient`.
    z_stop_m : float
        Distance from the target to the aperture stop (the lens for a thin lens).
    volume_centre_m : (float, float)
        Lateral position of the volume's centre off the optical axis (m).

    Returns
    -------
    x_m, y_m : ndarray
        Where the chief ray of each pixel crosses the mid-plane, in the volume's frame (centred on its
        mid-point; x and y as in the density sources), metres.
    """
    s = midplane_scale(magnification=magnification, pixel_pitch_m=pixel_pitch_m, z_d_m=z_d_m, z_stop_m=z_stop_m)
    cx, cy = principal_point_px
    x = (np.asarray(x_px, dtype=np.float64) - cx) * s - volume_centre_m[0]
    y = (np.asarray(y_px, dtype=np.float64) - cy) * s - volume_centre_m[1]
    return x, y
