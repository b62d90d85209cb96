"""The camera model on the host: lens geometry, focus, magnification, aperture and spot size.

All distances in metres. The target is the plane z = 0, the optical axis is +z; the camera is focused
on the target. The magnification ``M`` reported everywhere is the paraxial lateral magnification taken
positive (the pixel frame is upright, see ``raytrace.kernels.sensor_to_pixel``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synthbos import SynthbosError

__all__ = ["CameraModel", "camera_from_config"]


@dataclass(frozen=True)
class CameraModel:
    lens: str  # "thin" | "thick"
    focal_length: float
    f_number: float
    target_distance: float  # target to the thin lens plane, or to the thick lens's mid-thickness
    z_stop: float  # plane of the aperture stop
    aperture_radius: float
    z_sensor: float
    magnification: float  # paraxial, positive
    pixels: tuple[int, int]  # (W, H)
    pitch: float
    wavelength: float
    # thick lens only (zeros for the thin lens)
    c1: float = 0.0
    r1: float = 0.0
    c2: float = 0.0
    r2: float = 0.0
    glass_index: float = 1.0
    thickness: float = 0.0
    semi_diameter: float = 0.0

    @property
    def diffraction_spot_diameter(self) -> float:
        """Diffraction-limited spot diameter 2.44 lambda f# (1 + M) on the sensor, in metres."""
        return 2.44 * self.wavelength * self.f_number * (1.0 + self.magnification)

    @property
    def principal_point(self) -> tuple[float, float]:
        """Pixel coordinates (x, y) of the optical axis: the image centre."""
        return (self.pixels[0] - 1) / 2.0, (self.pixels[1] - 1) / 2.0

    def target_to_pixel(self, xy_m):
        """Paraxial (geometric) image of target points, in upright pixel coordinates."""
        cx, cy = self.principal_point
        xy = np.asarray(xy_m, dtype=np.float64)
        return np.stack([cx + self.magnification * xy[:, 0] / self.pitch,
                         cy + self.magnification * xy[:, 1] / self.pitch], axis=1)

    def pixel_to_target(self, xy_px):
        """Inverse of ``target_to_pixel``: where on the target a pixel position is imaged from."""
        cx, cy = self.principal_point
        xy = np.asarray(xy_px, dtype=np.float64)
        return np.stack([(xy[:, 0] - cx) * self.pitch / self.magnification,
                         (xy[:, 1] - cy) * self.pitch / self.magnification], axis=1)


def _thick_lens_radius(f, n, d):
    """Radius R of a symmetric biconvex lens (R1 = R, R2 = -R) of focal length f, index n, thickness d.

    Lensmaker's equation 1/f = (n-1) [2/R - (n-1) d / (n R^2)] gives
    R^2 - 2 (n-1) f R + (n-1)^2 d f / n = 0; the larger root is the lens of the usual shape.
    """
    disc = 1.0 - d / (n * f)
    if disc <= 0:
        raise SynthbosError(f"camera.lens_thickness_mm={d * 1e3:g} is too thick for a lens of f={f * 1e3:g} mm")
    return (n - 1.0) * f * (1.0 + np.sqrt(disc))


def _thick_lens_focus(f, n, d, R, object_distance_to_front_vertex):
    """Paraxial image distance behind the back vertex and lateral magnification (ray-transfer matrices).

    Rays are (height y, reduced angle n u). Refraction at a surface of radius R from n1 to n2 is
    [[1, 0], [-(n2 - n1)/R, 1]]; a gap of length L in index n is [[1, L/n], [0, 1]].
    """
    def gap(length, index):
        return np.array([[1.0, length / index], [0.0, 1.0]])

    def surface(radius, n1, n2):
        return np.array([[1.0, 0.0], [-(n2 - n1) / radius, 1.0]])

    system = surface(-R, n, 1.0) @ gap(d, n) @ surface(R, 1.0, n) @ gap(object_distance_to_front_vertex, 1.0)
    (_, b), (_, d_) = system
    # After a further gap s in air: B_total = b + s D = 0 (all rays from the object point meet).
    s = -b / d_
    total = gap(s, 1.0) @ system
    return s, total[0, 0]


def camera_from_config(cfg: dict) -> CameraModel:
    """Build the camera model from the validated configuration (tables ``camera`` and ``target``)."""
    cam, tgt = cfg["camera"], cfg["target"]
    f = cam["focal_length_mm"] * 1e-3
    N = cam["f_number"]
    so = tgt["distance_mm"] * 1e-3
    W, H = (int(p) for p in cam["pixels"])
    pitch = cam["pixel_pitch_um"] * 1e-6
    wavelength = cam["wavelength_nm"] * 1e-9
    aperture = f / (2.0 * N)
    if so <= f:
        raise SynthbosError(
            f"target.distance_mm={tgt['distance_mm']:g} must exceed camera.focal_length_mm={cam['focal_length_mm']:g}"
            " for the camera to focus on the target"
        )
    if cam["lens"] == "thin":
        si = 1.0 / (1.0 / f - 1.0 / so)
        return CameraModel(
            lens="thin", focal_length=f, f_number=N, target_distance=so, z_stop=so, aperture_radius=aperture,
            z_sensor=so + si, magnification=si / so, pixels=(W, H), pitch=pitch, wavelength=wavelength,
        )
    n = cam["glass_index"]
    d = cam["lens_thickness_mm"] * 1e-3
    R = _thick_lens_radius(f, n, d)
    z_front, z_back = so - d / 2.0, so + d / 2.0
    s_back, m = _thick_lens_focus(f, n, d, R, z_front)
    # Clear semi-diameter: where the two caps meet, less a small rim.
    r_edge = np.sqrt(max(R * R - (R - d / 2.0) ** 2, 0.0))
    semi = 0.95 * r_edge
    if aperture >= semi:
        raise SynthbosError(
            f"camera.f_number={N:g} opens the aperture ({aperture * 1e3:.2f} mm radius) beyond the thick lens's"
            f" clear semi-diameter ({semi * 1e3:.2f} mm); use a larger f-number or a thicker lens"
        )
    return CameraModel(
        lens="thick", focal_length=f, f_number=N, target_distance=so, z_stop=z_front, aperture_radius=aperture,
        z_sensor=z_back + s_back, magnification=abs(m), pixels=(W, H), pitch=pitch, wavelength=wavelength,
        c1=z_front + R, r1=R, c2=z_back - R, r2=R, glass_index=n, thickness=d, semi_diameter=semi,
    )
