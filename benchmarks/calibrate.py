"""``synthbos calibrate``: the tracking prior (a dots file) from a calibration image or a mapping.

Two jobs, both ending in a dots file (CSV, header ``x,y``, one reference-image position in pixels per
line, as ``synthbos process --dots`` reads it):

* from an image of a regular square dot grid (:func:`calibrate_from_grid`): the lattice is found, the
  Soloff mapping target (mm) -> image (px) fitted, and every grid node inside the image predicted,
  including dots the image shows poorly; the mapping can be saved as JSON;
* from a saved mapping and a target file (CSV, header ``x_mm,y_mm``) of a pattern whose dot positions are
  known in mm, in the grid's frame (:func:`dots_from_mapping`): row i of the dots file is target row i.

Mapping file (JSON, UTF-8): the fields of :func:`synthbos.tracking.calibration.mapping_to_dict` -
``format`` ("synthbos-soloff-mapping"), ``version`` (1), ``order``, ``terms`` ([i, j] exponents),
``coef_x``, ``coef_y``, ``centre``, ``scale``, ``rms_px`` - plus ``target_unit`` ("mm"), ``spacing_mm``,
``image_shape`` ([rows, columns]), ``residual_rms_px``, ``residual_max_px``, ``n_dots_used``, ``dots``
("bright on dark" or "dark on bright"), ``source``
(the grid image) and ``frame``, which states the target frame: origin at the grid dot nearest the image
centre, x along the grid direction nearest the image's +x (columns), y along the one nearest +y (rows,
downwards). A target file must use that frame.
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from synthbos.tracking.calibration import MAX_ORDER, calibrate_grid, mapping_from_dict, mapping_to_dict

from synthbos import SynthbosError, atomic_output
from synthbos.values import number

__all__ = [
    "CalibrationSummary",
    "calibrate_from_grid",
    "dots_from_mapping",
    "read_mapping",
    "read_target_csv",
    "write_dots_csv",
    "write_mapping",
]

FRAME = (
    "origin at the grid dot nearest the image centre; x along the grid direction nearest the image's +x "
    "(columns), y along the one nearest +y (rows, downwards); mm"
)


@dataclass(frozen=True)
class CalibrationSummary:
    """What a calibrate run did, for the one-line report."""

    n_dots: int
    n_inside: int
    n_detected: int | None = None
    n_used: int | None = None
    residual_rms: float | None = None
    residual_max: float | None = None
    dark: bool | None = None


def _read_text(path, what):
    path = Path(path)
    if not path.is_file():
        raise SynthbosError(f"{what} {path} does not exist")
    try:
        return path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError:
        raise SynthbosError(f"{what} {path} is not UTF-8 text") from None
    except OSError as err:
        raise SynthbosError(f"cannot read {what} {path}: {err.strerror}") from None


def read_target_csv(path) -> np.ndarray:
    """Dot positions on the target, mm, from a UTF-8 CSV whose header line is ``x_mm,y_mm``."""
    rows = [r for r in csv.reader(io.StringIO(_read_text(path, "target file"))) if r]
    if not rows or [c.strip().lower() for c in rows[0]] != ["x_mm", "y_mm"]:
        raise SynthbosError(f"target file {path} must start with the header line 'x_mm,y_mm'")
    try:
        xy = np.array([[float(a), float(b)] for a, b in rows[1:]], dtype=np.float64)
    except ValueError as err:
        raise SynthbosError(f"target file {path}: a line is not two numbers ({err})") from None
    if xy.size == 0 or not np.isfinite(xy).all():
        raise SynthbosError(f"target file {path} has no dots or non-finite positions")
    return xy.reshape(-1, 2)


def write_dots_csv(path, xy) -> Path:
    """Write a dots file (header ``x,y``, px, 4 decimals) atomically."""
    path = Path(path)
    lines = ["x,y"] + [f"{x:.4f},{y:.4f}" for x, y in np.asarray(xy, dtype=np.float64)]
    with atomic_output(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def read_mapping(path):
    """A :class:`~synthbos.tracking.calibration.SoloffMapping` and the whole JSON dict from a mapping file."""
    try:
        data = json.loads(_read_text(path, "mapping file"))
    except json.JSONDecodeError as err:
        raise SynthbosError(f"mapping file {path} is not valid JSON ({err.msg}, line {err.lineno})") from None
    try:
        return mapping_from_dict(data), data
    except SynthbosError as err:
        raise SynthbosError(f"mapping file {path}: {err}") from None


def write_mapping(path, mapping, **extra) -> Path:
    """Write a mapping file atomically (layout in the module docstring)."""
    path = Path(path)
    text = json.dumps(mapping_to_dict(mapping, **extra), indent=1)
    with atomic_output(path) as tmp:
        tmp.write_text(text + "\n", encoding="utf-8")
    return path


def calibrate_from_grid(image, spacing_mm, dots_out, *, mapping_out=None, source="", order=3, polarity="auto"):
    """Find the grid in ``image``, fit the mapping, write the dots file (and the mapping file).

    ``polarity`` ("auto", "bright" or "dark") is the dots' (:func:`~synthbos.tracking.calibration.calibrate_grid`);
    the CLI's ``--invert`` asks for "dark". When no grid is found, nothing is written and the error says
    what was found, and how to force the other polarity.

    Returns
    -------
    CalibrationSummary
    """
    number("--grid (the grid spacing, mm)", spacing_mm, above=0.0, maximum=1e4)
    number("--order (the mapping's polynomial degree)", order, integer=True, minimum=1, maximum=MAX_ORDER)
    for out in (dots_out, mapping_out):
        if out is not None and not Path(out).parent.is_dir():
            raise SynthbosError(f"output folder {Path(out).parent} does not exist")
    try:
        cal = calibrate_grid(image, float(spacing_mm), order=order, polarity=polarity)
    except SynthbosError as err:
        if not str(err).startswith("no regular dot grid"):
            raise
        hint = {"auto": "--invert forces dark dots", "dark": "--invert was given: leave it out for bright dots",
                "bright": "the dots were taken as bright"}[polarity]
        raise SynthbosError(f"{err}; {hint}") from None
    if mapping_out is not None:
        write_mapping(
            mapping_out,
            cal.mapping,
            target_unit="mm",
            spacing_mm=float(spacing_mm),
            image_shape=list(np.shape(image)),
            residual_rms_px=cal.residual_rms,
            residual_max_px=cal.residual_max,
            n_dots_used=int(cal.detected.sum()),
            dots="dark on bright" if cal.dark else "bright on dark",
            source=str(source),
            frame=FRAME,
        )
    write_dots_csv(dots_out, cal.image_xy)
    return CalibrationSummary(
        n_dots=len(cal.image_xy),
        n_inside=len(cal.image_xy),
        n_detected=cal.n_detected,
        n_used=int(cal.detected.sum()),
        residual_rms=cal.residual_rms,
        residual_max=cal.residual_max,
        dark=cal.dark,
    )


def dots_from_mapping(mapping_path, target_path, dots_out):
    """Map a target file's mm positions to the image with a saved mapping and write the dots file."""
    mapping, data = read_mapping(mapping_path)
    target = read_target_csv(target_path)
    with np.errstate(all="ignore"):  # an overflow is reported as the non-finite positions it gives
        xy = mapping(target)
    if not np.isfinite(xy).all():
        raise SynthbosError("the mapping gives non-finite image positions for this target")
    n_inside = len(xy)
    shape = data.get("image_shape")
    if isinstance(shape, list) and len(shape) == 2:
        h, w = (number(f"mapping file {mapping_path}: image_shape[{i}]", v, above=0.0) for i, v in enumerate(shape))
        n_inside = int(((xy[:, 0] > -0.5) & (xy[:, 0] < w - 0.5) & (xy[:, 1] > -0.5) & (xy[:, 1] < h - 0.5)).sum())
        if n_inside == 0:
            lo, hi = target.min(axis=0), target.max(axis=0)
            raise SynthbosError(f"none of the {len(xy)} target dots maps into the calibrated {w:g} x {h:g} px "
                                f"image (target x {lo[0]:.4g} .. {hi[0]:.4g}, y {lo[1]:.4g} .. {hi[1]:.4g}): "
                                "is the target in mm, in the grid's frame?")
    write_dots_csv(dots_out, xy)
    return CalibrationSummary(n_dots=len(xy), n_inside=n_inside, residual_rms=mapping.rms)
