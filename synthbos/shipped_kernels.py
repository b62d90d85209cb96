"""The CPU kernels of a first run, compiled ahead of time and shipped with the package.

Warp compiles a module of kernels on its first launch and keeps the result in its kernel cache. A first
``synthbos paper --quick`` on an empty cache compiles 16 CPU modules (the renderer's, the truth's, the
trackers' and the correlation's: some 20 core-seconds on a 2-core machine, a third of the warm run).
The package ships those objects (``synthbos/kernels/<Warp version>/``, about 0.5 MB), and
:func:`seed_kernel_cache` copies the ones missing from Warp's cache there before the first launch
(:func:`synthbos.device.init_warp` calls it).

Nothing is loaded that Warp would not have built itself. Warp names each cached module by a hash of its
kernels' source and options, and each object by the CPU target it was built for (Warp's version, its
LLVM, the target triple and, under Warp's default ``-march=native``, the host's instruction-set
features). Where any of them differs (another Warp, a changed kernel, another CPU), Warp does not find a
shipped object under the name it looks for and compiles as before; the shipped files then merely lie in
the cache unused. The objects here were built on the project's 2-core machine (AMD EPYC, Zen 4) by
``python -m synthbos.shipped_kernels`` (run it from a checkout after changing a kernel:
``tests/test_shipped_kernels.py`` fails while a shipped module is stale).

``SYNTHBOS_SHIPPED_KERNELS=0`` leaves the cache alone (every module is then compiled on first use, as
without this module): ``python -m synthbos.benchmarks.bench_cold`` times a first run both ways.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

__all__ = ["DISABLE_ENV", "SHIPPED", "seed_kernel_cache", "ship_kernels", "shipped_folder"]

#: The shipped objects, one folder per Warp version, as Warp's kernel cache holds them.
SHIPPED = Path(__file__).with_name("kernels")
#: Set to 0 (or "no", "false") to copy nothing into Warp's kernel cache.
DISABLE_ENV = "SYNTHBOS_SHIPPED_KERNELS"
#: The command whose CPU modules are shipped: the README's first run.
FIRST_RUN = ("paper", "--quick", "-q")


def shipped_folder(version: str | None = None) -> Path:
    """The folder of the objects shipped for Warp ``version`` (the running Warp's by default).

    Examples
    --------
    >>> shipped_folder("1.19.0").name
    '1.19.0'
    """
    if version is None:
        import warp as wp

        version = wp.config.version
    return SHIPPED / version


def _enabled() -> bool:
    return os.environ.get(DISABLE_ENV, "1").strip().lower() not in ("0", "no", "false", "off")


def seed_kernel_cache(cache_dir=None, *, source=None) -> int:
    """Copy the shipped module files that Warp's kernel cache lacks into it; return how many were copied.

    A file the cache holds already is left as it is. Each file is written under a temporary name and
    renamed, each module's metadata before its object, so that a process starting beside this one never
    sees a part of one. Nothing is copied when ``SYNTHBOS_SHIPPED_KERNELS`` is 0, when nothing is shipped
    for this Warp version, or when the cache cannot be written (Warp then compiles, as it would anyway).

    Parameters
    ----------
    cache_dir : path, optional
        The kernel cache; Warp's (``warp.config.kernel_cache_dir``, known once Warp is initialised) by default.
    source : path, optional
        The shipped folder; :func:`shipped_folder` by default.

    Examples
    --------
    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as src, tempfile.TemporaryDirectory() as cache:
    ...     _ = Path(src, "wp_m_1234567").mkdir()
    ...     _ = Path(src, "wp_m_1234567", "wp_m_1234567.meta").write_text("{}")
    ...     seed_kernel_cache(cache, source=src), seed_kernel_cache(cache, source=src)
    (1, 0)
    """
    if not _enabled():
        return 0
    src = Path(source) if source is not None else shipped_folder()
    if cache_dir is None:
        import warp as wp

        cache_dir = wp.config.kernel_cache_dir
    if cache_dir is None or not src.is_dir():
        return 0
    copied = 0
    try:
        for module in sorted(p for p in src.iterdir() if p.is_dir()):
            # the metadata first: Warp reads it once it finds the object
            for f in sorted(module.iterdir(), key=lambda p: (p.suffix != ".meta", p.name)):
                target = Path(cache_dir, module.name, f.name)
                if target.exists():
                    continue
                target.parent.mkdir(parents=True, exist_ok=True)
                part = target.with_name(f".{f.name}.{os.getpid()}.part")
                shutil.copyfile(f, part)
                os.replace(part, target)
                copied += 1
    except OSError:
        pass  # a cache that cannot be written: Warp compiles there as usual
    return copied


def ship_kernels(out=None, *, python=sys.executable) -> list[str]:
    """Build the CPU modules of a first run (:data:`FIRST_RUN`) in an empty kernel cache and make them the
    shipped set for the running Warp version (``out``, :func:`shipped_folder` by default, replaced whole);
    return the module folders shipped. Only each module's CPU object and metadata are kept."""
    import warp as wp

    out = Path(out) if out is not None else shipped_folder()
    with tempfile.TemporaryDirectory(prefix="synthbos-ship-") as tmp:
        env = {**os.environ, "WARP_CACHE_PATH": str(Path(tmp, "cache")), DISABLE_ENV: "0"}
        subprocess.run([python, "-m", "synthbos", *FIRST_RUN, "-o", str(Path(tmp, "out"))], env=env, check=True)
        built = Path(tmp, "cache", wp.config.version)
        if out.exists():
            shutil.rmtree(out)
        names = []
        for module in sorted(p for p in built.iterdir() if p.is_dir()):
            files = [f for f in module.iterdir() if f.suffix == ".meta" or (f.suffix == ".o" and ".cpu" in f.name)]
            if not any(f.suffix == ".o" for f in files):
                continue
            (out / module.name).mkdir(parents=True)
            for f in files:
                shutil.copyfile(f, out / module.name / f.name)
            names.append(module.name)
    return names


def main(argv=None) -> int:
    import argparse

    parser = argparse.ArgumentParser(description="Rebuild the shipped CPU kernels (synthbos/kernels/<Warp version>/).")
    parser.add_argument("--out", help="folder to write instead of the package's own")
    args = parser.parse_args(argv)
    names = ship_kernels(args.out)
    print(f"{len(names)} modules shipped in {Path(args.out) if args.out else shipped_folder()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
