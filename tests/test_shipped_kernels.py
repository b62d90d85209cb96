"""The CPU kernels shipped with the package (synthbos.shipped_kernels): seeding Warp's cache, and the shipped
set being the one Warp would build from the code as it is."""

import importlib
import pkgutil
from pathlib import Path

import pytest
import warp as wp

from synthbos.device import init_warp
from synthbos.shipped_kernels import DISABLE_ENV, seed_kernel_cache, shipped_folder


def _fake_shipped(root: Path) -> Path:
    for name in ("wp_a_1111111", "wp_b_2222222"):
        Path(root, name).mkdir(parents=True)
        Path(root, name, f"{name}.meta").write_text(f'{{"name": "{name}"}}')
        Path(root, name, f"{name}.cpu0000000.o").write_bytes(b"\x7fELF" + name.encode())
    return root


def test_seed_copies_what_the_cache_lacks_and_nothing_else(tmp_path):
    src = _fake_shipped(tmp_path / "shipped")
    cache = tmp_path / "cache"
    Path(cache, "wp_a_1111111").mkdir(parents=True)
    Path(cache, "wp_a_1111111", "wp_a_1111111.meta").write_text("mine")  # the cache's own: kept
    assert seed_kernel_cache(cache, source=src) == 3
    assert Path(cache, "wp_a_1111111", "wp_a_1111111.meta").read_text() == "mine"
    for name in ("wp_a_1111111", "wp_b_2222222"):
        assert Path(cache, name, f"{name}.cpu0000000.o").read_bytes() == b"\x7fELF" + name.encode()
    assert Path(cache, "wp_b_2222222", "wp_b_2222222.meta").read_text() == '{"name": "wp_b_2222222"}'
    assert not list(cache.rglob("*.part"))
    assert seed_kernel_cache(cache, source=src) == 0  # a second time: nothing left to copy


def test_seed_does_nothing_when_switched_off_or_nothing_is_shipped(tmp_path, monkeypatch):
    src = _fake_shipped(tmp_path / "shipped")
    monkeypatch.setenv(DISABLE_ENV, "0")
    assert seed_kernel_cache(tmp_path / "cache", source=src) == 0
    assert not (tmp_path / "cache").exists()
    monkeypatch.delenv(DISABLE_ENV)
    assert seed_kernel_cache(tmp_path / "cache", source=tmp_path / "none") == 0


def _import_kernel_modules():
    """Every synthbos Python module that declares Warp kernels (their Warp modules are registered on import)."""
    for package in ("synthbos.raytrace", "synthbos.tracking", "synthbos.correlation"):
        pkg = importlib.import_module(package)
        for info in pkgutil.iter_modules(pkg.__path__):
            if "kernel" in info.name:
                importlib.import_module(f"{package}.{info.name}")


def test_shipped_modules_are_those_warp_builds_from_this_code():
    """Each shipped folder is the cache folder Warp would build for a current module (its name carries the
    hash of the module's kernels and options), holding the object Warp would look for on this CPU. Fails
    after a kernel changes until ``python -m synthbos.shipped_kernels`` has rebuilt the set."""
    folder = shipped_folder()
    if not folder.is_dir():
        pytest.skip(f"no CPU kernels shipped for Warp {wp.config.version}")
    init_warp()
    _import_kernel_modules()
    from warp._src.context import user_modules

    cpu = wp.get_device("cpu")
    shipped = sorted(p.name for p in folder.iterdir() if p.is_dir())
    assert len(shipped) >= 10
    modules = {name: user_modules.get(name[len("wp_") : -len("_1234567")]) for name in shipped}  # wp_<name>_<hash>
    stale = [name for name, m in modules.items() if m is None or m.get_module_identifier(1) != name]
    assert not stale, f"shipped CPU kernels out of date ({stale}): run python -m synthbos.shipped_kernels"
    objects = {name: m._get_compile_output_name(cpu, block_dim=1) for name, m in modules.items()}
    if not all(Path(folder, name, obj).exists() for name, obj in objects.items()):
        pytest.skip("the shipped objects were built for another CPU target than this machine's")
    assert all(Path(folder, name, f"{name}.meta").exists() for name in shipped)
