"""The renderer's kernels live in one Warp module per medium (``kernels.render_module``,
``truth_kernels.truth_module``): a render launches exactly the modules ``render_modules`` names, so a
first run compiles only those."""

import numpy as np
import pytest
import warp as wp
from _small import small_config
from synthbos.raytrace import kernels, truth_kernels
from synthbos.raytrace.config import load_config
from synthbos.raytrace.medium import FIELDS, is_planar, medium_from_config, medium_struct, to_warp
from synthbos.raytrace.render import render_modules, render_pair

from synthbos import SynthbosError


@pytest.mark.parametrize("planar", [True, False], ids=["slice", "3-D"])
def test_every_field_uploads_the_struct_medium_struct_names(planar):
    blob = {"source": "gaussian", "sigma_mm": 4.0, "amplitude_kg_m3": 0.05, "grid": [24, 24, 8]}
    medium = medium_from_config(load_config(small_config() if planar else small_config(volume=blob)))
    assert is_planar(medium.field) == planar
    for field in FIELDS:
        struct = medium_struct(field, planar)
        assert struct in kernels.MEDIA
        assert isinstance(to_warp(medium, device="cpu", field=field), struct.instance_type), field
        assert kernels.render_kernel(to_warp(medium, device="cpu", field=field)) is kernels.render_kernel(struct)
    # only the default field takes a struct of its own for a 3-D field (its cell reads, apart from the slice's)
    assert medium_struct("float32_vec", planar).key == ("MediumVec" if planar else "MediumVec3D")
    with pytest.raises(SynthbosError, match=r"rays\.field"):
        medium_struct("float64")


def test_each_medium_and_register_cap_has_a_module_of_its_own():
    names = {kernels.render_kernel(m, cap).module.name for m in kernels.MEDIA for cap in kernels.REGISTER_CAPS}
    assert len(names) == len(kernels.MEDIA) * len(kernels.REGISTER_CAPS)
    assert kernels.render_kernel(kernels.MediumHalf, 80).module.name == kernels.render_module(kernels.MediumHalf, 80)
    for m in truth_kernels.TRUTH_MEDIA:
        for k in (truth_kernels.integrate_grad_n, truth_kernels.integrate_cone):
            assert truth_kernels.truth_kernel(k, m).module.name == truth_kernels.truth_module(m)
    assert kernels.render_kernel(kernels.MediumVec).module is not kernels.render_rays.module


def test_render_modules_follow_the_field_the_truth_and_the_device():
    base, truth = "synthbos.raytrace.kernels.", "synthbos.raytrace.truth_kernels."
    assert render_modules(small_config(rays={"field": "float16", "max_registers": 80}), device="cpu") == [
        base + "render_MediumHalf", base + "render_MediumStraight", truth + "truth_MediumVec"]
    assert render_modules(small_config(rays={"field": "float32"}), device="cpu") == [
        base + "render_Medium", base + "render_MediumStraight", truth + "truth_Medium"]
    if wp.is_cuda_available():
        assert render_modules(small_config(rays={"max_registers": 80}), device="cuda:0") == [
            base + "render_MediumStraight_r80", base + "render_MediumVec_r80", truth + "truth_MediumVec"]


@pytest.mark.parametrize("field", ["float32_vec", "float32"])
def test_a_render_launches_exactly_the_modules_render_modules_names(device, field, monkeypatch):
    cfg = small_config(rays={"field": field, "per_dot": 20}, camera={"pixels": [48, 48]})
    launched = set()
    launch = wp.launch

    def recording(kernel, *args, **kwargs):
        launched.add(kernel.module.name)
        return launch(kernel, *args, **kwargs)

    monkeypatch.setattr(wp, "launch", recording)
    pair = render_pair(cfg, device=device)
    assert launched == set(render_modules(cfg, device=device))
    assert np.isfinite(pair.displacement_px[pair.valid]).all() and pair.valid.any()


def test_render_modules_name_the_3d_struct_for_a_3d_field():
    """A truly 3-D field takes ``MediumVec3D`` (its cell reads), a slice ``MediumVec``; the slice is known
    planar from its table (``sources.extruded``), a 3-D source from its built medium."""
    blob = {"source": "gaussian", "sigma_mm": 4.0, "amplitude_kg_m3": 0.05, "grid": [24, 24, 8]}
    base = "synthbos.raytrace.kernels."
    assert base + "render_MediumVec3D" in render_modules(small_config(volume=blob), device="cpu")
    assert base + "render_MediumVec" in render_modules(small_config(volume={"source": "slice"}), device="cpu")
