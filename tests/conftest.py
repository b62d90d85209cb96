"""Shared pytest fixtures: the Warp devices every Warp-based test runs on."""

import pytest
import warp as wp

from synthbos.device import init_warp


def _warp_devices():
    init_warp()
    devices = ["cpu"]
    if wp.is_cuda_available():
        devices.append("cuda:0")
    return devices


@pytest.fixture
def slow_only(request):
    """The project's rule for the longest ``slow`` tests (a minute or more on two cores, or a cluster): they
    run only when selected (``-m slow``); other ``slow`` tests run in the default suite too."""
    markexpr = request.config.getoption("markexpr") or ""
    if "slow" not in markexpr or "not slow" in markexpr:
        pytest.skip("long on two cores; select with -m slow")


def pytest_generate_tests(metafunc):
    # Any test that takes a ``device`` argument runs once per Warp device: test_x[cpu], test_x[cuda:0].
    if "device" in metafunc.fixturenames:
        params = []
        for dev in _warp_devices():
            marks = [pytest.mark.gpu] if dev.startswith("cuda") else []
            params.append(pytest.param(dev, id=dev, marks=marks))
        metafunc.parametrize("device", params)


def pytest_collection_modifyitems(config, items):
    try:
        init_warp()
        has_cuda = wp.is_cuda_available()
    except Exception:
        has_cuda = False
    skip_gpu = pytest.mark.skip(reason="no CUDA device visible to Warp")
    for item in items:
        if "gpu" in item.keywords and not has_cuda:
            item.add_marker(skip_gpu)
