"""Every Warp module a GPU campaign launches builds for CUDA, checked on machines without a GPU too.

Warp compiles CUDA code with NVRTC, which its wheel carries, so a CPU-only machine (CI) can build every
module for an NVIDIA architecture without running it. A construct that builds for the CPU but not for
CUDA otherwise shows only on a GPU machine: on 2026-11-27 a tile FFT built ahead at Warp's default block
size failed there and stopped every GPU campaign (docs/benchmarks.md).
"""

import pytest
import warp as wp

from synthbos.device import _warp_modules, init_warp

#: The architecture built for: Hopper (H100, H200), the GPUs synthbos is measured on.
ARCH = 90


def _campaign_modules():
    """The Python modules of a default GPU campaign's kernels: the renderer's, every built-in method's
    on CUDA and the stacked tracker's; and the opt-in shared-kernel step's, built on its first launch."""
    from synthbos.benchmarks.registry import BUILT_IN, STACK_KERNELS
    from synthbos.raytrace.kernels import MediumStraight, MediumVec, render_module
    from synthbos.raytrace.truth_kernels import truth_module

    names = set(STACK_KERNELS) | {"synthbos.tracking.kernel_step_kernels"}  # the opt-in step: built when used
    for method in BUILT_IN.values():
        names |= set(method.kernels)
    # render_modules(device="cuda:0") without a GPU to ask: the default medium at the default 64-register cap
    names |= {render_module(MediumVec, 64), render_module(MediumStraight, 64), truth_module(MediumVec)}
    return sorted(names)


@pytest.mark.slow
def test_every_campaign_module_builds_for_cuda(tmp_path):
    """About 80 s on two cores from an empty folder: each Warp module at its default block size (the one
    ``synthbos.device.load_kernels`` builds ahead of a GPU campaign)."""
    init_warp()
    from warp._src.context import runtime

    if ARCH not in runtime.nvrtc_supported_archs:
        pytest.skip(f"this Warp's NVRTC does not build sm_{ARCH}")
    failed = {}
    for name in _campaign_modules():
        for module in _warp_modules(name):
            try:
                wp.compile_aot_module(module, arch=ARCH, module_dir=tmp_path)
            except Exception as e:  # every failure named, not only the first
                failed[module.name] = f"{type(e).__name__}: {str(e)[:300]}"
    assert not failed, failed
    assert len(list(tmp_path.iterdir())) >= 25  # one build per module: the list is the campaign's
