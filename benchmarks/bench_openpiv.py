"""synthbos correlation against OpenPIV windef on public image pairs: PIV pairs with truth, real BOS pairs.

PIV pairs with truth: ``--piv DIR`` holds triples ``NAME_img1.tif``, ``NAME_img2.tif`` and
``NAME_flow.flo`` (Middlebury flow files: the displacement of every pixel of the first image), as in
the synthetic PIV dataset of Cai et al. (Exp. Fluids 60 (2019) 73), classes DNS turbulence, JHTDB
channel and isotropic turbulence, SQG, uniform, backstep, cylinder. Per pair it prints, for synthbos
correlation (``correlation.correlate_pair``, default settings) and OpenPIV windef (the ``openpiv``
method, ``benchmarks.openpiv_method``: the same passes, 32 then 16 px windows without overlap, two
iterations each): the RMS error against the truth (sampled bilinearly at each method's own vector
positions) over all vectors and over the accepted ones (synthbos: flag 0; OpenPIV: not replaced by
its validation), the accepted fraction, and the time ratio synthbos / OpenPIV (best of ``--repeat``
calls after a warm-up call, one CPU thread each).

Real BOS pairs: ``--bos REF,GRAD ...`` (any image files ``process`` reads). With no truth, the two
methods are compared with each other: the median and RMS of the difference of the vectors (OpenPIV's
field interpolated to synthbos's nodes, over the nodes both accepted), and the time ratio. Run::

    python3 -m synthbos.benchmarks.bench_openpiv --piv /path/to/piv --bos C000.tif,C001.tif

OpenPIV (``pip install openpiv``) is only imported through ``benchmarks.openpiv_method``.
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import re  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.interpolate import RegularGridInterpolator  # noqa: E402
from scipy.ndimage import map_coordinates  # noqa: E402
from synthbos.benchmarks.openpiv_method import OpenPIVSettings, run_openpiv  # noqa: E402
from synthbos.benchmarks.process import load_image  # noqa: E402
from synthbos.benchmarks.timing import best_time  # noqa: E402
from synthbos.correlation import CorrelationSettings, correlate_pair  # noqa: E402
from synthbos.correlation.pattern import is_periodic  # noqa: E402

from synthbos import SynthbosError  # noqa: E402

#: Classes of the PIV dataset whose fields are turbulent (the issue's criterion applies to them).
TURBULENT = ("DNS_turbulence", "JHTDB", "SQG")
FLO_MAGIC = 202021.25


def read_flo(path):
    """A Middlebury ``.flo`` file as an (H, W, 2) float64 array of (u, v) per pixel."""
    raw = np.fromfile(path, dtype="<f4")
    if raw.size < 3 or raw[0] != FLO_MAGIC:
        raise SynthbosError(f"{path} is not a Middlebury .flo file (no PIEH tag)")
    w, h = raw[1:3].view("<i4")
    if raw.size != 3 + 2 * w * h:
        raise SynthbosError(f"{path} holds {raw.size - 3} values for a {w}x{h} flow")
    return raw[3:].reshape(h, w, 2).astype(np.float64)


def truth_at(flow, x, y):
    """The flow sampled bilinearly at (x, y) (pixel centres at integers; edge values continued)."""
    pts = [np.ravel(y), np.ravel(x)]
    return [map_coordinates(flow[..., k], pts, order=1, mode="nearest").reshape(np.shape(x)) for k in (0, 1)]


def piv_pairs(folder):
    """(name, img1, img2, flo) of every complete triple in ``folder``, sorted by name."""
    found = []
    for img1 in sorted(Path(folder).glob("*_img1.tif")):
        name = img1.name[: -len("_img1.tif")]
        img2, flo = img1.with_name(f"{name}_img2.tif"), img1.with_name(f"{name}_flow.flo")
        if img2.exists() and flo.exists():
            found.append((name, img1, img2, flo))
    if not found:
        raise SynthbosError(f"no NAME_img1.tif, NAME_img2.tif, NAME_flow.flo triples in {folder}")
    return found


def run_both(a, b, repeat):
    """Both methods on one pair: (x, y, u, v, accepted, seconds) of synthbos and of OpenPIV."""
    out = []
    for run in (_synthbos, _openpiv):
        seconds, result = best_time(lambda run=run: run(a, b), repeat, warmup=True)
        out.append((*result, seconds))
    return out


def _synthbos(a, b):
    r = correlate_pair(a, b, settings=CorrelationSettings(backend="numpy"))
    return r.x, r.y, r.u, r.v, r.flags == 0


def _openpiv(a, b):
    r = run_openpiv(a, b, settings=OpenPIVSettings())
    t = r.table
    return t["x"], t["y"], t["u"], t["v"], np.asarray(r.valid).reshape(t["u"].shape)


def rms(values):
    values = np.asarray(values, dtype=np.float64)
    return float(np.sqrt(np.mean(values**2))) if values.size else float("nan")


def piv_row(name, img1, img2, flo, repeat):
    """One table row of a PIV pair with truth."""
    a, b, flow = load_image(img1), load_image(img2), read_flo(flo)
    row = {"pair": name, "turbulent": name.startswith(TURBULENT)}
    results = run_both(a, b, repeat)
    for key, (x, y, u, v, ok, seconds) in zip(("synthbos", "openpiv"), results, strict=True):
        tu, tv = truth_at(flow, x, y)
        err = np.hypot(u - tu, v - tv)
        finite = np.isfinite(err)
        row[key] = {"all": rms(err[finite]), "accepted": rms(err[ok & finite]), "fraction": float(ok.mean()),
                    "seconds": seconds}
    return row


def bos_row(ref, grad, repeat):
    """One table row of a real BOS pair: differences between the two methods."""
    a, b = load_image(ref), load_image(grad)
    (sx, sy, su, sv, sok, st), (ox, oy, ou, ov, ook, ot) = run_both(a, b, repeat)
    grid = (oy[:, 0], ox[0, :])
    pts = np.stack([sy.ravel(), sx.ravel()], axis=1)

    def at_nodes(f, fill):
        interp = RegularGridInterpolator(grid, f, bounds_error=False, fill_value=fill)
        return interp(pts).reshape(sx.shape)

    iu, iv = at_nodes(np.where(ook, ou, np.nan), np.nan), at_nodes(np.where(ook, ov, np.nan), np.nan)
    both = sok & np.isfinite(iu) & np.isfinite(iv)
    diff = np.hypot(su - iu, sv - iv)[both]
    pattern = "periodic" if is_periodic(a, CorrelationSettings().window_sizes[0]) else "random"
    return {"pair": f"{Path(ref).name}, {Path(grad).name}", "shape": a.shape, "pattern": pattern,
            "synthbos_fraction": float(sok.mean()), "openpiv_fraction": float(ook.mean()),
            "compared": int(both.sum()), "median": float(np.median(diff)) if diff.size else float("nan"),
            "rms": rms(diff), "ratio": st / ot}


def print_piv(rows):
    print("| pair | synthbos RMS all (px) | OpenPIV RMS all (px) | synthbos RMS accepted (px) | "
          "OpenPIV RMS accepted (px) | accepted synthbos / OpenPIV | time synthbos / OpenPIV |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        s, o = r["synthbos"], r["openpiv"]
        mark = "" if r["turbulent"] else " (laminar)"
        print(f"| {r['pair']}{mark} | {s['all']:.3f} | {o['all']:.3f} | {s['accepted']:.3f} | {o['accepted']:.3f} | "
              f"{s['fraction']:.2f} / {o['fraction']:.2f} | {s['seconds'] / o['seconds']:.2f} |")
    turb = [r for r in rows if r["turbulent"]]
    worse = [r["pair"] for r in turb if r["synthbos"]["all"] > r["openpiv"]["all"]]
    print(f"\nturbulent pairs: {len(turb)}; synthbos RMS over all vectors <= OpenPIV's on "
          f"{len(turb) - len(worse)}" + (f"; worse on {', '.join(worse)}" if worse else ""))


def print_bos(rows):
    print("| pair | size (px) | pattern | accepted synthbos / OpenPIV | compared vectors | median difference (px) | "
          "RMS difference (px) | time synthbos / OpenPIV |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        size = f"{r['shape'][1]} x {r['shape'][0]}"
        print(f"| {r['pair']} | {size} | {r['pattern']} | {r['synthbos_fraction']:.2f} / {r['openpiv_fraction']:.2f} | "
              f"{r['compared']} | {r['median']:.3f} | {r['rms']:.3f} | {r['ratio']:.2f} |")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--piv", help="folder of NAME_img1.tif, NAME_img2.tif, NAME_flow.flo triples")
    p.add_argument("--bos", nargs="*", default=[], metavar="REF,GRAD", help="real BOS pairs (no truth)")
    p.add_argument("--match", default=".", help="only PIV pairs whose name matches this regular expression")
    p.add_argument("--repeat", type=int, default=3, help="timed calls per method and pair (best kept)")
    args = p.parse_args(argv)
    if not args.piv and not args.bos:
        p.error("give --piv FOLDER and/or --bos REF,GRAD ...")
    if args.piv:
        rows = [piv_row(*t, args.repeat) for t in piv_pairs(args.piv) if re.search(args.match, t[0])]
        print_piv(rows)
    if args.bos:
        pairs = [s.split(",") for s in args.bos]
        if any(len(pr) != 2 for pr in pairs):
            p.error("--bos takes REF,GRAD pairs")
        print()
        print_bos([bos_row(ref, grad, args.repeat) for ref, grad in pairs])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
