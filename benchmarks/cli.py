"""The ``synthbos`` command: one entry point, one subcommand per job.

Each subcommand parses its arguments here and calls a library function; user errors
(``synthbos.SynthbosError``) print one line and exit with status 2, bugs keep their traceback.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
from synthbos.correlation import CorrelationSettings
from synthbos.raytrace import SETUPS, load_config, read_pair, render_pair, setup_tables, write_pair
from synthbos.raytrace.config import merge_tables, read_toml
from synthbos.tracking import TrackingSettings
from tqdm.auto import tqdm

import synthbos
from synthbos import SynthbosError, check_output_file, check_output_folder
from synthbos.device import describe_device, resolve_device
from synthbos.values import error_line

from .advice import failure_advice, failure_reason
from .calibrate import calibrate_from_grid, dots_from_mapping
from .campaign import PIPELINE_DRIVERS, check_campaign_stack, check_spec, run_campaign
from .items import nominal_positions
from .plugins import PluginWarning
from .process import load_image, process_pair, process_settings, read_dots_csv, result_setup, write_result
from .registry import BUILT_IN, DENSE, GRID, default_methods, get_method, method_names, methods_table
from .regress import BASELINE, run_regress
from .spec import FULL, QUICK
from .stacks import DEFAULT_STACK, describe_stacks
from .tables import format_floor, format_summary

__all__ = ["build_parser", "in_worker_thread", "main", "work_abandoned"]


def _device(requested) -> str:
    """The Warp device of a command, reported once: the one asked for, else cuda:0 when present, else cpu."""
    device = resolve_device(requested)
    print(describe_device(device))
    return device


def _render(args):
    out = check_output_file(args.output, inputs=[args.config], what="-o")
    config = load_config(args.config, setup=args.setup)  # a bad set-up, key or value: before the device line
    device = _device(args.device)
    pair = in_worker_thread(render_pair, config, device=device, progress=not args.quiet)
    write_pair(out, pair)
    v = pair.valid
    d = pair.displacement_px[v]
    mag = (d**2).sum(axis=1) ** 0.5
    print(f"wrote {out}: {pair.n_dots} dots ({int(v.sum())} valid), {pair.attrs['rays_per_dot']} rays/dot, "
          f"M = {pair.attrs['magnification']:.4f}, "
          f"{pair.attrs['render_seconds']:.2f} s")
    if len(d):
        th = (pair.theory_px[v] ** 2).sum(axis=1) ** 0.5
        print(f"  |displacement| px: mean {mag.mean():.4f}, max {mag.max():.4f}; |theory (Eq. 4)| max {th.max():.4f}")
    return 0


#: Work shorter than this (s) shows no clock line (:func:`in_worker_thread`).
CLOCK_DELAY_S = 2.0
#: The work :func:`in_worker_thread` left running when a Ctrl-C ended its wait: one Event per thread, set when
#: the thread ends.
_ABANDONED: list[threading.Event] = []


def in_worker_thread(fn, *args, clock=None, **kwargs):
    """``fn(*args, **kwargs)`` in a daemon thread, waited for here, so that a Ctrl-C ends the wait at once.

    ``clock`` (a few words, optional): show them with the time elapsed on a tqdm line while the work runs,
    for work that reports no progress of its own.

    Python runs a signal's handler in the main thread between two bytecodes, so a Ctrl-C during one long
    Warp launch on the CPU (a render's launch takes 10-30 s there) would wait for the launch to end. Here
    the main thread only waits, in short steps, and the KeyboardInterrupt ends the wait; the abandoned
    thread's result is dropped, and the command leaves without waiting for it (:func:`work_abandoned`,
    read by ``synthbos.__main__``). An exception of ``fn`` is raised here.
    """
    box = {}
    done = threading.Event()

    def work():
        try:
            box["value"] = fn(*args, **kwargs)
        except BaseException as err:  # handed to the waiting thread
            box["error"] = err
        finally:
            done.set()

    threading.Thread(target=work, name="synthbos-work", daemon=True).start()
    bar = tqdm(desc=clock, bar_format="{desc}: {elapsed}", disable=clock is None, file=sys.stderr, delay=1e9)
    t0 = shown = time.monotonic()
    try:
        while not done.wait(0.05):  # an Event, not Thread.join: a join that a Ctrl-C ends marks the thread ended
            now = time.monotonic()
            if now - t0 > CLOCK_DELAY_S and now - shown > 0.5:
                bar.refresh()
                shown = now
    except BaseException:
        _ABANDONED.append(done)
        raise
    finally:
        if shown > t0:  # shown: end its line, or clear it before an error's line
            bar.delay, bar.leave = 0, "error" not in box and done.is_set()
        bar.close()
    if "error" in box:
        raise box["error"]
    return box["value"]


def work_abandoned() -> bool:
    """Whether work that a Ctrl-C abandoned (:func:`in_worker_thread`) still runs in a thread of this process."""
    return any(not done.is_set() for done in _ABANDONED)


def _process(args):
    inputs = [args.pair, args.reference, args.gradient, args.dots, args.settings, args.mask, args.setup_file]
    out = check_output_file(args.output, inputs=inputs, what="-o")
    method = get_method(args.method)  # an unknown or skipped method is the only line
    if args.dots and not method.uses_prior:
        users = ", ".join(n for n, m in BUILT_IN.items() if m.uses_prior)
        raise SynthbosError(f"--dots: --method {args.method} takes no dots prior and would ignore it; "
                            f"the methods that take one: {users}")
    device = _device(args.device)  # the method's processing device
    invert = None if args.invert is None else _INVERT[args.invert]
    settings, options = process_settings(
        args.method,
        config=args.settings,
        flags={"windows": args.windows, "overlap": args.overlap, "diameter": args.diameter,
               "max_displacement": args.max_displacement},
        image={"mask": args.mask, "mask_excludes": args.mask_excludes, "invert": invert},
    )
    check_output_file(out, inputs=[options.mask], what="-o")  # the configuration's mask is an input too
    if args.mask_excludes is not None and options.mask is None:
        raise SynthbosError("--mask-excludes: there is no mask to read (give --mask, or mask in the [image] table "
                            "of --settings)")
    prior = None
    attrs = {}
    notes = []
    if args.pair:
        if args.reference or args.gradient:
            raise SynthbosError("give either a pair file or --reference and --gradient, not both")
        pair = read_pair(args.pair)
        ref, grad = pair.reference, pair.gradient
        if method.uses_prior:
            prior = read_dots_csv(args.dots) if args.dots else nominal_positions(pair)
        attrs["input"] = str(args.pair)
        attrs["magnification"] = float(pair.attrs["magnification"])
    else:
        if not (args.reference and args.gradient):
            raise SynthbosError("give a pair file, or both --reference and --gradient images")
        ref, grad = load_image(args.reference, notes=notes), load_image(args.gradient, notes=notes)
        if method.uses_prior and args.dots:
            prior = read_dots_csv(args.dots)
        attrs["input"] = f"{args.reference} {args.gradient}"
    attrs["image_shape"] = np.array(ref.shape, dtype=np.int64)
    setup = result_setup(ref.shape, pair=pair if args.pair else None, pair_path=args.pair,
                         setup_file=args.setup_file, config=args.settings)
    if setup is not None:
        attrs["setup"] = setup
    t0 = time.perf_counter()
    res, image_used = in_worker_thread(process_pair, args.method, ref, grad, settings=settings, options=options,
                                       prior_xy=prior, notes=notes, device=device,
                                       clock=None if args.quiet else f"process: {args.method}")
    attrs["seconds"] = time.perf_counter() - t0
    attrs["device"] = device
    attrs["image"] = json.dumps(image_used)
    if args.settings:
        attrs["config"] = Path(args.settings).read_text()
    for note in [] if args.quiet else notes:
        print(f"note: {note}")
    write_result(out, res, extra_attrs=attrs)
    c = res.counts or {}
    ok = res.valid if res.valid is not None else np.all(np.isfinite(res.uv), axis=1)
    med = np.median(np.hypot(*res.uv[ok].T)) if ok.any() else float("nan")
    noun = {GRID: "vectors", DENSE: "pixels"}.get(method.kind, "dots")
    print(f"wrote {out}: {args.method}, {c.get('total', len(ok))} {noun}: {c.get('measured', int(ok.sum()))} measured, "
          f"{c.get('replaced', 0)} replaced, {c.get('failed', 0)} failed, {c.get('masked', 0)} masked; "
          f"median |displacement| of the measured {med:.4f} px; {attrs['seconds']:.2f} s")
    if not ok.any():  # the warning says why
        print(f"synthbos: warning: nothing was measured in {attrs['input']}; see the flags in {out}; "
              f"{failure_reason(res, kind=method.kind)}", file=sys.stderr)
        return 1
    advice = failure_advice(res, kind=method.kind, where=str(out))
    if advice and not args.quiet:
        print(advice)
    return 0


def _calibrate(args):
    inputs = [args.reference, args.mapping, args.target]
    out = check_output_file(args.output, inputs=inputs, what="-o")
    if args.mapping_out is not None:
        check_output_file(args.mapping_out, inputs=[*inputs, out], what="--mapping-out")
        args.interrupted = "the dots file was not written (the mapping file is written first: it may be there)"
    if args.grid is not None:
        if args.mapping or args.target:
            raise SynthbosError("give either --reference with --grid, or --mapping with --target, not both")
        if not args.reference:
            raise SynthbosError("--grid needs the grid image: --reference GRID.tif")
        notes = []
        image = load_image(args.reference, notes=notes)
        for note in [] if args.quiet else notes:
            print(f"note: {note}")
        s = in_worker_thread(calibrate_from_grid, image, args.grid, out, mapping_out=args.mapping_out,
                             source=args.reference, order=3 if args.order is None else args.order,
                             polarity=_grid_polarity(args.invert),
                             clock=None if args.quiet else "calibrate: finding the grid and fitting the mapping")
        print(f"wrote {out}: {s.n_dots} dots predicted ({s.n_used} of {s.n_detected} detected "
              f"{'dark' if s.dark else 'bright'} blobs on the grid fitted); mapping residual rms "
              f"{s.residual_rms:.4f} px, max {s.residual_max:.4f} px"
              + (f"; mapping {args.mapping_out}" if args.mapping_out else ""))
        return 0
    if not (args.mapping and args.target):
        raise SynthbosError("give --reference GRID.tif --grid SPACING_MM, or --mapping MAP.json --target TARGET.csv")
    if args.mapping_out or args.reference or args.invert or args.order is not None:
        raise SynthbosError("--reference, --invert, --order and --mapping-out go with --grid, not with --mapping")
    s = dots_from_mapping(args.mapping, args.target, out)
    print(f"wrote {out}: {s.n_dots} dots ({s.n_inside} inside the calibrated image) through {args.mapping} "
          f"(fit residual {s.residual_rms:.4f} px)")
    return 0


def _grid_polarity(invert):
    """The grid's dot polarity from ``--invert`` (its choice, read through ``_INVERT`` as process reads it)."""
    return {True: "dark", False: "bright"}.get(_INVERT[invert], "auto")


def _floats(text, n, what):
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != n:
        raise SynthbosError(f"{what} must be {n} comma-separated numbers, got {text!r}")
    return vals


def _integrate(args):
    from .integrate import integrate_file

    out = check_output_file(args.output, inputs=[args.result, args.pair, args.config, args.setup_file], what="-o")
    region = _floats(args.reference_region, 4, "--reference-region") if args.reference_region else None
    mask = _floats(args.mask_region, 4, "--mask-region") if args.mask_region else None
    res = in_worker_thread(integrate_file, args.result, out, pair_path=args.pair, config=args.config,
                           setup_file=args.setup_file, solver=args.solver, spacing_px=args.spacing,
                           reference_density=args.reference_density, reference_region_mm=region,
                           dirichlet=args.dirichlet, mask_region_mm=mask,
                           clock=None if args.quiet else f"integrate: {args.solver} solve")
    d = res["density"]
    rho = d.density[np.isfinite(d.density)]
    print(f"wrote {out}: {args.solver}, {rho.size} nodes ({d.grid.gx.shape[1]} x {d.grid.gx.shape[0]}), "
          f"density {rho.min():.5g} .. {rho.max():.5g} kg/m^3; constant from {d.reference}; "
          f"set-up: {res['setup_source']}")
    if res["negative"]:
        print(f"synthbos: warning: the density is negative (unphysical) at {res['negative']} of {rho.size} nodes, "
              f"down to {rho.min():.4g} kg/m^3: check the reference density and the set-up", file=sys.stderr)
    s = res["summary"]
    if s:
        print(f"{'truth':<7} {'rms kg/m3':>10} {'p90 kg/m3':>10} {'rms/range':>10} {'p90/range':>10} {'offset':>10}")
        for t in ("cone", "chief"):
            print(f"{t:<7} {s[f'{t}_rms_kg_m3']:>10.3g} {s[f'{t}_p90_kg_m3']:>10.3g} {s[f'{t}_rms_rel']:>10.3g} "
                  f"{s[f'{t}_p90_rel']:>10.3g} {s[f'{t}_offset_kg_m3']:>10.3g}")
    return 0


def _process_device(args, device: str) -> str:
    """``--process-device`` (checked and reported) when given, else the command's ``--device``."""
    if args.process_device is None:
        return device
    process_device = resolve_device(args.process_device)
    print(f"processing {describe_device(process_device)}")
    return process_device


def _paper(args):
    setup_tables(args.setup)  # an unknown set-up: one line, before the device line
    device = _device(args.device)
    process_device = _process_device(args, device)
    worker_device = _worker_device(args, process_device)
    full = args.full or (not args.quick and device.startswith("cuda"))
    spec = paper_spec(full=full, methods=args.methods, setup=args.setup)
    out = check_output_folder(args.out or f"runs/paper-{spec.name}")
    check_spec(spec, device, process_device)  # before the banner: an error is the only line
    check_campaign_stack(args.stack, spec, device=device, scheduler=args.scheduler)
    print(f"synthbos paper: {spec.name} campaign ({len(spec.snapshots)} snapshots x {spec.pairs_per_snapshot} pairs, "
          f"noise {', '.join(f'{n:g}' for n in spec.noise_percent)} %, {spec.config['rays']['per_dot']} rays/dot) "
          f"-> {out}")
    t0 = time.perf_counter()
    timings, stacks, drivers = {}, [], []
    rows = run_campaign(spec, out, device=device, process_device=process_device, workers=args.workers,
                        progress=not args.quiet, scheduler=args.scheduler, wait=args.wait,
                        worker_device=worker_device, timings=timings, stack=args.stack, stacks=stacks,
                        drivers=args.drivers, drivers_log=drivers)
    print(format_summary(rows))
    if (out / "floor.json").exists():
        print(format_floor(json.loads((out / "floor.json").read_text())))
    _stacks_note(stacks, args.stack)
    if len(drivers) > 1:
        print(f"{len(drivers)} processes drove {device}, taking {' + '.join(map(str, drivers))} pairs")
    phases = ", ".join(f"{k} {v:.1f} s" for k, v in timings.items())
    print(f"results: {out / 'results.csv'}, {out / 'results.json'}; figures: {out / 'fig4.png'}, "
          f"{out / 'fig5.png'}, {out / 'fig_density.png'}, {out / 'fig_budget.png'} (and .pdf, .svg) "
          f"({time.perf_counter() - t0:.0f} s: {phases})")
    _budget_note(out / "fig_budget.png")
    return 0


def _stacks_note(stacks, stack) -> None:
    """The line on the stacks a campaign tracked (``stacks.describe_stacks``), when it tracked any."""
    if stacks:
        print(describe_stacks(stacks, stack))


def paper_spec(*, full=False, methods=None, setup="default"):
    """The campaign of ``synthbos paper``: ``FULL`` or ``QUICK``, with ``methods`` (``"a,b"``) and a named set-up.

    A set-up other than the default is merged into the campaign's configuration and named in the campaign
    (``quick-narrow``), so its folder, figures and tables say which set-up they show; the seeds stay the
    same, so two set-ups see the same dot patterns and rays.
    """
    spec = FULL if full else QUICK
    if methods:
        spec = replace(spec, methods=_method_list(methods))
    if setup != "default":
        spec = replace(spec.with_config(setup_tables(setup)), name=f"{spec.name}-{setup}")
    return spec


def _budget_note(png: Path) -> None:
    """A note where an error-budget figure was left out: its pairs hold no ray covariance."""
    if not png.exists():
        print(f"note: {png.name} not drawn: the pair files hold no ray covariance (rendered before it was recorded)")


def _regress(args):
    if args.out is None:
        args.interrupted = "nothing was kept (the campaign ran in a temporary folder; -o FOLDER keeps it to resume)"
    _device("cpu")  # the regression campaign runs on the CPU, so it gives the same numbers everywhere
    methods = _method_list(args.methods) if args.methods else None
    stacks = []
    rows, problems = run_regress(update=args.update, out=args.out, workers=args.workers, progress=not args.quiet,
                                 scheduler=args.scheduler, wait=args.wait, methods=methods,
                                 baseline=args.baseline or BASELINE, stack=args.stack, stacks=stacks)
    _stacks_note(stacks, args.stack)
    if args.update:
        print(f"regression baseline written to {args.baseline or BASELINE} ({len(rows)} rows)")
        return 0
    if problems:
        print(f"synthbos regress: {len(problems)} result(s) worse than the baseline:", file=sys.stderr)
        for p in problems:
            print(f"  {p}", file=sys.stderr)
        return 1
    print(f"synthbos regress: all {len(rows)} rows within tolerance of {Path(args.baseline or BASELINE).name}")
    return 0


def _sweep(args):
    from .sweep import parse_parameter, run_sweep  # here, as the plots': matplotlib only where a command draws

    base = merge_tables(setup_tables(args.setup), read_toml(args.config) if args.config else {})
    params = [parse_parameter(p) for p in args.param]
    if args.out is None:
        raise SynthbosError("sweep: name the sweep folder with -o FOLDER")
    check_output_folder(args.out)
    device = _device(args.device)
    process_device = _process_device(args, device)
    worker_device = _worker_device(args, process_device)
    stacks = []
    rows = run_sweep(base, params, args.out, size=args.size, device=device,
                     methods=_method_list(args.methods) if args.methods else None,
                     process_device=process_device, worker_device=worker_device,
                     workers=args.workers, stack=args.stack, stacks=stacks, drivers=args.drivers,
                     progress=not args.quiet, scheduler=args.scheduler, wait=args.wait)
    _stacks_note(stacks, args.stack)
    print(f"sweep: {len(rows)} rows -> {Path(args.out) / 'sweep.csv'}, {Path(args.out) / 'sweep.png'}, "
          f"{Path(args.out) / 'sweep_budget.png'} (and .pdf, .svg)")
    _budget_note(Path(args.out) / "sweep_budget.png")
    return 0


def _show_density(args):
    # The plotting modules load here, not with the command line: matplotlib took 0.6 s of every command's
    # start (an H200's host), and a campaign's process never draws (its workers do).
    from .show_density import plot_density_file, plot_snapshots, snapshot_table

    if args.density is not None:  # a density file of 'synthbos integrate'
        if args.snapshots is not None:
            raise SynthbosError("give a density file or --snapshots, not both")
        out = check_output_file(args.output, inputs=[args.density], what="-o")
        summary = plot_density_file(args.density, out)
        print(f"wrote {out}\n{summary}")
        return 0
    out = check_output_file(args.output, inputs=[args.snapshots], what="-o")
    stats = plot_snapshots(out, snapshots_file=args.snapshots, progress=not args.quiet)
    print(snapshot_table(stats))
    print(f"wrote {out}")
    return 0


def _show_result(args):
    from .show_result import plot_result  # here, as in _show_density

    out = check_output_file(args.output, inputs=[args.result, args.pair], what="-o")
    summary = plot_result(args.result, out, pair=args.pair)
    print(f"wrote {out}\n{summary}")
    return 0


def _methods(args):
    print("\n".join(method_names()) if args.quiet else methods_table())
    return 0


def _method_list(text: str) -> tuple[str, ...]:
    """``--methods a,b,c``: registered method names, checked."""
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    if not names:
        raise SynthbosError("--methods: name at least one method")
    for n in names:
        get_method(n)
    return names


def _add_setup_option(p, note) -> None:
    names = "; ".join(f"{name}: {what}" for name, (_, what) in SETUPS.items())
    p.add_argument("--setup", default="default", metavar="NAME",
                   help=f"named set-up to start from ({note}; see docs/fig5.md): {names}")


def _add_scheduler_option(p) -> None:
    p.add_argument("--scheduler", default=None, metavar="local|tcp://HOST:PORT|FILE.json",
                   help="run on a Dask cluster: 'local' starts one worker per GPU (or --workers CPU workers), "
                        "an address or a scheduler file joins a running one (needs dask[distributed])")


def _add_process_device_option(p) -> None:
    p.add_argument("--process-device", default=None, metavar="DEVICE",
                   help="Warp device for the processing when it differs from --device (e.g. render on cuda:0, "
                        "process on cpu)")
    p.add_argument("--worker-device", default=None, metavar="DEVICE",
                   help="when processing on a GPU: the device of the worker processes that run the methods with "
                        "host work between their kernels (tracking not in stacks: --stack 0, or the paper's "
                        "procedure), e.g. cuda:0 (default: cpu, measured faster than a dozen processes sharing "
                        "one GPU)")


def _add_stack_option(p, *, cpu_only=False) -> None:
    where = ("the regression campaign processes on the CPU, where it tracks item by item unless told" if cpu_only
             else f"default: {DEFAULT_STACK} when processing on a GPU, 0 on the CPU")
    p.add_argument("--stack", type=_stack_count, default=None, metavar="N",
                   help="track the tracking items in stacks: the noisy images of every noise level of up to N "
                        "pairs in one batched call on the processing device (tracking.stack.track_pairs), the "
                        f"results equal to rounding; 0: item by item in the worker processes ({where})")


def _add_drivers_option(p) -> None:
    p.add_argument("--drivers", type=_driver_count, default=None, metavar="N",
                   help=f"processes that drive the GPU, each taking the next pair no one has taken, with its share "
                        f"of --workers (default: {PIPELINE_DRIVERS}; the files are the same whatever N; for GPU "
                        "workers that share GPUs, started before the campaign, use --scheduler local)")


def _count(of: str, least: int, at_least: str):
    """An argparse type: a whole number (``of``: " of pairs", ...) of at least ``least``, which
    ``at_least`` says in the message.

    Examples
    --------
    >>> _count(" of pairs", 0, "0 or more pairs")("3")
    3
    """
    def count(text):
        try:
            n = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a whole number{of}, got {text!r}") from None
        if n < least:
            raise argparse.ArgumentTypeError(f"must be {at_least}, got {n}")
        return n

    return count


_driver_count = _count(" of processes", 1, "1 or more processes")
_stack_count = _count(" of pairs", 0, "0 (item by item) or more pairs")
_workers = _count("", 1, "at least 1")


def _worker_device(args, process_device: str):
    """``--worker-device``, checked, or None; refused where the campaign would ignore it: processing on the CPU."""
    if args.worker_device is None:
        return None
    worker_device = resolve_device(args.worker_device)
    if not process_device.startswith("cuda"):
        raise SynthbosError(f"--worker-device {args.worker_device}: it applies when processing on a GPU; the "
                            f"processing runs on {process_device}")
    return worker_device


_WAIT_HELP = "if another run holds the folder, wait for it to finish (default: refuse at once)"


class _HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Each option's default after its help, where it has one and the text does not already say it; the
    examples epilog as written."""

    def _get_help_string(self, action):
        text = action.help or ""
        default = action.default
        if default is None or default is False or default == argparse.SUPPRESS or "default" in text.lower():
            return text
        if not action.option_strings and action.nargs not in (argparse.OPTIONAL, argparse.ZERO_OR_MORE):
            return text
        return f"{text} (default: %(default)s)"


class _Alias(argparse.Action):
    """Another spelling of an option, left out of the help (the option's own help names it): it sets the
    option's value as the option does."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, **{**kwargs, "help": argparse.SUPPRESS})

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, values)


#: Every command's examples, shown at the end of its help.
EXAMPLES = {
    "render": ("synthbos render -o pair.h5                      # the paper's set-up (raytrace/default.toml)",
               "synthbos render my.toml --setup narrow -o pair.h5 --device cpu"),
    "process": ("synthbos process pair.h5 --method tracking-cc -o dots.h5",
                "synthbos process --reference ref.tif --gradient grad.tif --method correlation --windows 64,32,16 "
                "-o piv.h5",
                "synthbos process --reference ref.tif --gradient grad.tif --method tracking --dots dots.csv "
                "--settings process.toml -o dots.h5"),
    "integrate": ("synthbos integrate dots.h5 --pair pair.h5 -o density.h5   # scored against the pair's truths",
                  "synthbos integrate piv.h5 --config my.toml --solver wlsq -o density.h5",
                  "synthbos integrate pair.h5 -o floor.h5                     # the pair's exact displacements"),
    "calibrate": ("synthbos calibrate --reference grid.tif --grid 2.0 --mapping-out map.json -o grid_dots.csv",
                  "synthbos calibrate --mapping map.json --target target.csv -o dots.csv"),
    "paper": ("synthbos paper --quick -o runs/quick",
              "synthbos paper --full --device cuda:0 --methods correlation,tracking-cc"),
    "regress": ("synthbos regress",
                "synthbos regress --methods my-method --baseline mine.json --update"),
    "sweep": ("synthbos sweep --param density=6,10,14 -o runs/density",
              "synthbos sweep my.toml --param f_number=8,16 --param noise=0,3 --size quick -o runs/f-noise"),
    "methods": ("synthbos methods", "synthbos methods -q                               # the names only"),
    "show-density": ("synthbos show-density -o snapshots.pdf",),
    "show-result": ("synthbos show-result dots.h5 -o dots.png", "synthbos show-result piv.h5 -o piv.svg"),
}

_QUIET_HELP = "no progress bars and no notes; the result line, warnings and errors still print"
_INVERT = {"auto": "auto", "true": True, "false": False, None: "auto"}


def _add_output(p, what, *, required=True, default=None, alias=False) -> None:
    """``-o/--output`` of a command that writes (``what``: the file or folder); ``alias``: ``--out`` too, the
    campaign commands' older spelling, whose name (``args.out``) they keep."""
    dest = "out" if alias else "output"
    p.add_argument("-o", "--output", required=required, default=default, metavar="PATH", dest=dest,
                   help=what + (" (also --out)" if alias else ""))
    if alias:
        p.add_argument("--out", dest=dest, action=_Alias)


def _add_invert_option(p, what) -> None:
    p.add_argument("--invert", nargs="?", const="true", choices=("auto", "true", "false"), default=None,
                   help=f"make the dots bright: true (also --invert alone) for dark dots on a bright background, "
                        f"false to leave {what} as given, auto to decide from the background level "
                        "(default: auto)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="synthbos", formatter_class=_HelpFormatter,
        description="Synthetic background-oriented schlieren: render BOS image pairs with their truth,\n"
                    "measure displacements (correlation, dot tracking), integrate them into density,\n"
                    "and score it all.",
        epilog="synthbos COMMAND --help shows a command's options, their defaults and examples.")
    parser.add_argument("--version", action="version", version=f"synthbos {synthbos.__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("render", help="ray-trace one BOS image pair into an HDF5 pair file")
    p.add_argument("config", nargs="?", default=None, metavar="CONFIG.toml",
                   help="render configuration (TOML): the set-up, target, camera, volume and rays "
                        "(default: the embedded raytrace/default.toml)")
    _add_output(p, "pair file to write (HDF5)")
    _add_setup_option(p, "the configuration changes it")
    p.add_argument("--device", default=None, help="Warp device: cpu or cuda:0 (default: cuda:0 if present, else cpu)")
    p.set_defaults(func=_render, interrupted="nothing was written (the pair file is written whole at the end); "
                                             "re-run to render it again")

    p = sub.add_parser("process", help="measure displacements: correlation or dot tracking")
    p.add_argument("pair", nargs="?", default=None, metavar="PAIR.h5",
                   help="pair file from 'synthbos render' (or give --reference and --gradient)")
    p.add_argument("--method", required=True, metavar="NAME",
                   help=f"a registered method: {', '.join(BUILT_IN)} or an installed plugin's (synthbos methods)")
    p.add_argument("--reference", metavar="IMAGE", help="reference (no-flow) camera image, TIFF or PNG")
    p.add_argument("--gradient", metavar="IMAGE", help="gradient (with-flow) camera image, TIFF or PNG")
    p.add_argument("--dots", metavar="DOTS.csv",
                   help="CSV (header x,y, px) of predicted reference-image dot positions: the prior of the methods "
                        "that take one (the tracking methods; refused with the others) (default: a pair file's "
                        "nominal positions; none for camera images)")
    _add_output(p, "result file to write (HDF5)")
    p.add_argument("--settings", metavar="PROCESS.toml",
                   help="process settings (TOML) with [correlation], [tracking] and [image] tables; the options "
                        "below override it (formerly --config, still accepted)")
    p.add_argument("--config", dest="settings", action=_Alias)
    p.add_argument("--setup-file", metavar="CAMERA.toml", default=None,
                   help="the camera pair's set-up ([setup]: z_d_mm, depth_mm, magnification, ...; "
                        "docs/own-images.md), recorded in the result for 'synthbos integrate'")
    p.add_argument("--mask", metavar="IMAGE", help="mask image of the camera images' size; see --mask-excludes")
    p.add_argument("--mask-excludes", choices=("dark", "bright"), default=None,
                   help="which mask pixels are left out: dark (default: white marks the region to measure) "
                        "or bright")
    _add_invert_option(p, "the images")
    cs, ts = CorrelationSettings(), TrackingSettings()
    p.add_argument("--windows", metavar="N,N,...",
                   help="correlation: window sizes per pass, e.g. 64,32,16 (default: --settings' [correlation] "
                        f"window_sizes, else {','.join(map(str, cs.window_sizes))})")
    p.add_argument("--overlap", type=float,
                   help="correlation: window overlap fraction, e.g. 0.5 (default: --settings' [correlation] "
                        f"overlaps, else {np.atleast_1d(cs.overlaps)[0]:g})")
    p.add_argument("--diameter", type=float,
                   help="tracking: dot diameter in px (default: --settings' [tracking] diameter, else "
                        + ("measured from the images)" if ts.diameter is None else f"{ts.diameter:g})"))
    p.add_argument("--max-displacement", type=float,
                   help="tracking: largest displacement in px (default: --settings' [tracking] max_displacement, "
                        f"else {ts.max_displacement:g})")
    p.add_argument("--device", default=None,
                   help="Warp device of the processing: cpu or cuda:0 (default: cuda:0 if present, else cpu)")
    p.set_defaults(func=_process, interrupted="nothing was written")

    p = sub.add_parser("integrate", help="integrate a result's displacements into the depth-averaged density")
    p.add_argument("result", metavar="RESULT.h5",
                   help="result file from 'synthbos process', or a pair file from 'synthbos render' alone: "
                        "its exact displacements, the floor set by the dot spacing and the solver")
    p.add_argument("--pair", metavar="PAIR.h5",
                   help="the pair file the result came from: its set-up, and the truths to score against")
    p.add_argument("--config", metavar="CONFIG.toml",
                   help="render configuration (TOML, as for render) giving the set-up when there is no pair file "
                        "(default: the embedded default)")
    p.add_argument("--setup-file", metavar="CAMERA.toml", default=None,
                   help="the camera pair's set-up ([setup]: z_d_mm, depth_mm, magnification, ...; docs/own-images.md)"
                        " (default: the set-up the result recorded: its pair file's, or process --setup-file)")
    p.add_argument("--solver", default="lsq", choices=("dct", "lsq", "wlsq"),
                   help="dct: Poisson by DCT (full rectangle); lsq: sparse least squares; wlsq: uncertainty-weighted")
    p.add_argument("--spacing", type=float, default=None,
                   help="grid spacing in px for tracked dots (default: the mean dot spacing)")
    p.add_argument("--reference-density", type=float, default=None,
                   help="density (kg/m^3) of the reference region (default: the configuration's ambient density)")
    p.add_argument("--reference-region", default=None, metavar="X0,X1,Y0,Y1",
                   help="mm (volume frame) where the reference density holds (default: the border); "
                        "write --reference-region=-5,5,-5,5 when it starts with a minus")
    p.add_argument("--dirichlet", action="store_true",
                   help="hold the reference region fixed (lsq, wlsq; refused with dct) instead of matching its mean")
    p.add_argument("--mask-region", default=None, metavar="X0,X1,Y0,Y1",
                   help="mm (volume frame): nodes left out (default: none)")
    _add_output(p, "density file to write (HDF5)")
    p.set_defaults(func=_integrate, interrupted="nothing was written")

    p = sub.add_parser("calibrate", help="tracking prior (dots file) from a grid image, or from a mapping and a target")
    p.add_argument("--reference", metavar="IMAGE", help="image of a regular square dot grid (TIFF or PNG), with --grid")
    p.add_argument("--grid", type=float, metavar="SPACING_MM", help="grid spacing in mm")
    p.add_argument("--mapping-out", metavar="MAP.json", help="also write the fitted mapping (JSON) here")
    p.add_argument("--order", type=int, default=None, help="Soloff polynomial degree, with --grid (default: 3)")
    _add_invert_option(p, "the grid image")
    p.add_argument("--mapping", metavar="MAP.json",
                   help="mapping file (JSON) from an earlier 'calibrate --grid --mapping-out'")
    p.add_argument("--target", metavar="TARGET.csv",
                   help="CSV (header x_mm,y_mm) of the pattern's dot positions in the grid's frame")
    _add_output(p, "dots file to write (CSV, header x,y, px)")
    p.set_defaults(func=_calibrate, interrupted="nothing was written")

    for name, helptext in (("paper", "the paper's error analysis: render, process, score, figures"),):
        p = sub.add_parser(name, help=helptext)
        g = p.add_mutually_exclusive_group()
        g.add_argument("--quick", action="store_true", help="reduced campaign for two CPU cores (default without GPU)")
        g.add_argument("--full", action="store_true", help="the paper's size (default with a GPU)")
        _add_setup_option(p, "default folder runs/paper-quick-NAME")
        _add_output(p, "campaign folder (default: runs/paper-quick or runs/paper-full)", required=False, alias=True)
        p.add_argument("--device", default=None,
                       help="Warp device for rendering and processing (default: cuda:0 if present, else cpu)")
        _add_process_device_option(p)
        p.add_argument("--workers", type=_workers, default=None,
                       help="processes (default: all CPU cores, at most 16 when processing on a GPU); processing "
                            "on a GPU, this process drives the GPU and the others score")
        p.add_argument("--wait", action="store_true", help=_WAIT_HELP)
        p.add_argument("--methods", default=None, metavar="A,B,...",
                       help=f"methods to run (default: {','.join(default_methods())}; also: "
                            f"{','.join(n for n in BUILT_IN if n not in default_methods())} and installed "
                            "plugins' methods: synthbos methods lists them)")
        _add_scheduler_option(p)
        _add_stack_option(p)
        _add_drivers_option(p)
        p.set_defaults(func=_paper, interrupted=_KEPT)

    p = sub.add_parser("regress", help="CI guard: compare a small campaign's error percentiles with the baseline")
    p.add_argument("--update", action="store_true",
                   help="rewrite the baseline on purpose (with --methods: only those methods' rows)")
    p.add_argument("--methods", default=None, metavar="A,B,...",
                   help=f"methods to check (default: {','.join(default_methods())}); a plugin's rows enter the "
                        "baseline only with --update")
    p.add_argument("--baseline", default=None, metavar="FILE.json",
                   help="baseline file (default: the one synthbos ships); e.g. your own for a plugin")
    _add_output(p, "keep the campaign in this folder (default: a temporary one, removed at the end)", required=False,
                alias=True)
    p.add_argument("--workers", type=_workers, default=None,
                   help="processes (default: all CPU cores, at most 16 when processing on a GPU)")
    p.add_argument("--wait", action="store_true", help=_WAIT_HELP)
    _add_scheduler_option(p)
    _add_stack_option(p, cpu_only=True)
    p.set_defaults(func=_regress, interrupted=_KEPT)

    p = sub.add_parser("sweep", help="experiment design: errors and yield against one or two parameters")
    p.add_argument("config", nargs="?", default=None, metavar="CONFIG.toml",
                   help="render configuration (TOML, as for render) to start from (default: the embedded default)")
    p.add_argument("--param", action="append", required=True, metavar="NAME=V1,V2,...",
                   help="table.key, or density, diameter, noise, f_number, z_d, magnification, rays, window; "
                        "give it once or twice")
    _add_setup_option(p, "the configuration changes it")
    _add_output(p, "sweep folder (required)", required=False, alias=True)
    p.add_argument("--size", default="regress", choices=("regress", "quick", "full"), help="campaign size per point")
    p.add_argument("--methods", default=None, metavar="A,B,...",
                   help=f"methods to run at every point (default: {','.join(default_methods())})")
    p.add_argument("--device", default=None,
                   help="Warp device for rendering and processing (default: cuda:0 if present, else cpu)")
    _add_process_device_option(p)
    p.add_argument("--workers", type=_workers, default=None,
                   help="processes (default: all CPU cores, at most 16 when processing on a GPU)")
    p.add_argument("--wait", action="store_true", help=_WAIT_HELP)
    _add_scheduler_option(p)
    _add_stack_option(p)
    _add_drivers_option(p)
    p.set_defaults(func=_sweep, interrupted=_KEPT)

    p = sub.add_parser("methods", help="list the registered methods: kind, source package and version")
    p.set_defaults(func=_methods)

    p = sub.add_parser("show-density", help="figure of a density file of 'synthbos integrate', or of the density "
                                            "snapshots and their gradients")
    p.add_argument("density", nargs="?", default=None,
                   help="density file of 'synthbos integrate' (default: draw the density snapshots instead)")
    p.add_argument("-o", "--output", default="density_snapshots.png",
                   help="figure to write, in the format of its suffix: .png (300 dpi), .pdf, .svg, .jpg "
                        "(only this file; default: %(default)s)")
    p.add_argument("--snapshots", default=None, help="another snapshots file (default: the embedded one)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_show_density)

    p = sub.add_parser("show-result", help="figure of any synthbos file: a result (displacement magnitude, vectors "
                                           "with a key, flagged points, errors against the truth) or a density file")
    p.add_argument("result", help="result file of 'synthbos process', or density file of 'synthbos integrate' (HDF5)")
    p.add_argument("-o", "--output", required=True,
                   help="figure to write, in the format of its suffix: .png (300 dpi), .pdf, .svg, .jpg "
                        "(only this file)")
    p.add_argument("--pair", default=None,
                   help="pair file of 'synthbos render' to draw the errors against its truth (default: the pair file "
                        "the result was processed from, when it still exists)")
    p.add_argument("-q", "--quiet", action="store_true", help="accepted for a uniform command line: nothing to silence")
    p.set_defaults(func=_show_result)
    _finish_commands(sub)
    return parser


_KEPT = "finished items are kept, re-run to resume"


def _finish_commands(sub) -> None:
    """What every command has: -q/--quiet, its examples after the help, defaults shown, and a note for Ctrl-C."""
    for name, p in sub.choices.items():
        p.formatter_class = _HelpFormatter
        p.epilog = "examples:\n" + "\n".join(f"  {line}" for line in EXAMPLES[name])
        if "-q" not in p._option_string_actions:  # a command's own -q says what it silences
            p.add_argument("-q", "--quiet", action="store_true", help=_QUIET_HELP)
        if p.get_default("interrupted") is None:
            p.set_defaults(interrupted="nothing was written")


def _one_line_warnings(show):
    """``warnings.showwarning`` that prints a skipped plugin's warning as one line, ``synthbos: warning:
    ...``, and hands every other warning to ``show``."""
    def showwarning(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, PluginWarning):
            print(f"synthbos: warning: {message}", file=sys.stderr if file is None else file)
        else:
            show(message, category, filename, lineno, file, line)

    return showwarning


def _silence_stdout() -> None:
    """Point standard output at /dev/null, so the interpreter's last flush to a closed pipe writes nothing."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # not a real file (a test's capture)
        return
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, fd)
    os.close(null)


def main(argv=None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except KeyboardInterrupt:  # Ctrl-C while the options are read (a loaded machine): one line, nothing started
        print("synthbos: interrupted", file=sys.stderr)
        return 130
    shown = warnings.showwarning
    warnings.showwarning = _one_line_warnings(shown)
    try:
        status = args.func(args)
        sys.stdout.flush()  # a closed pipe shows here, inside the try, not at the interpreter's exit
        return status
    except BrokenPipeError:  # `synthbos ... | head`: the reader is gone; end quietly, as Unix tools do
        _silence_stdout()
        return 128 + signal.SIGPIPE
    except SynthbosError as err:
        print(error_line(err), file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        if any(not bar.disable for bar in list(getattr(tqdm, "_instances", ()))):
            print(file=sys.stderr)  # a progress bar that another thread left open: the message on a line of its own
        print(f"synthbos: interrupted; {args.interrupted}", file=sys.stderr)
        return 130
    finally:
        warnings.showwarning = shown


if __name__ == "__main__":
    sys.exit(main())
