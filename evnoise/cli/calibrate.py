"""``evnoise calibrate MEASUREMENTS --out preset.toml``: fit the noise model to measurements.

MEASUREMENTS is a rate table (CSV: ``lux, rate_on_hz, rate_off_hz[, n_pixels, duration_s][, r_on,
r_off]``, or counts) or a flat-field listing (TOML ``[[level]]`` entries or CSV ``file, lux``) of
events.h5 recordings; ``--monitor`` converts grey levels to lux. The formats are described in
:mod:`evnoise.calibration.measurements`. The preset written is loadable by ``--preset`` of
``evnoise simulate`` and ``make-dataset``; the report goes to standard output.
"""

from __future__ import annotations

import logging

from ..errors import ParameterError
from ..params import parameter_names
from . import _options as opt

log = logging.getLogger(__name__)

EXAMPLE = "rates-example.csv"

#: every NoiseParams field, in field order (the one list, from the fields' metadata)
PARAMETERS = parameter_names()


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "calibrate",
        parents=[opt.output(required=True, metavar="TOML", help="preset file to write"),
                 opt.run_options(seed_help="seed of the starting points (default 0)", seed_default=0)],
        help="fit the noise model to measured rates or flat-field recordings; write a preset",
        description="Fit evnoise's noise model to measurements by maximum likelihood (exact closed form, "
        "threshold mismatch, multi-start) and write the parameters as a preset TOML with uncertainties, "
        "goodness of fit and what the data do not determine.",
        epilog="examples: evnoise calibrate --example --out cam.toml --plot cam.png ; "
        "evnoise calibrate rates.csv --out cam.toml --plot cam.png ; "
        "evnoise calibrate flats.toml --out cam.toml --fix refractory_s=0 ; "
        "evnoise calibrate grey_rates.csv --monitor monitor.csv --out cam.toml ; "
        "evnoise calibrate rec.aedat --t-start 48.87 --t-end 53.37 --out cam.toml --plot fit.png",
    )
    p.add_argument("measurements", metavar="MEASUREMENTS", nargs="*",
                   help="rate table (CSV) or flat-field listing (TOML, or CSV with a 'file' column); with "
                   "--t-start/--t-end or --window: recording(s) of a still scene (any camera file)")
    opt.add_example(p, help=f"use the bundled example rate table ({EXAMPLE}, simulated from the evk3-hd preset) "
                    "as MEASUREMENTS")
    opt.add_plot(p, help="also write a figure of the data and the fitted curves")
    p.add_argument("--monitor", metavar="CSV", help="grey -> lux table of a monitor (columns grey, lux)")
    p.add_argument("--monitor-model", choices=("interp", "gamma"), default="interp",
                   help="grey -> lux: interpolation in grey^2.2, or a straight-line fit in grey^2.2 "
                   "(default: %(default)s)")
    p.add_argument("--method", choices=("poisson", "gaussian"), default="poisson",
                   help="closed form: exact Poisson, or the paper's Gaussian eq. 3 (default: %(default)s)")
    p.add_argument("--distribution", choices=("binomial", "poisson"), default="binomial",
                   help="per-pixel count given its thresholds, for flat fields (default: %(default)s)")
    p.add_argument("--fit", nargs="+", metavar="NAME", choices=PARAMETERS,
                   help="parameters to fit (default: eps_pos eps_neg bias_pr trial_rate_hz photons_per_lux "
                   "dark_lux leak_on_hz leak_off_hz, and eps_sigma when the data carry dispersion); add refractory_s, "
                   "the growth leak_on_hz_per_lux leak_off_hz_per_lux, or (flat fields) leak_sigma and the hot_pixel_* "
                   "terms to fit them; pr_tau_s_at_1lux is never fitted (static data do not identify it)")
    p.add_argument("--fix", nargs="+", default=[], metavar="NAME=VALUE",
                   help="hold parameters at given values, e.g. --fix eps_sigma=0.05 refractory_s=1e-4")
    p.add_argument("--initial", metavar="PRESET",
                   help="starting point and values of parameters that are not fitted (a preset name or TOML)")
    p.add_argument("--starts", type=opt.count("--starts"), default=6, metavar="N",
                   help="strata of starting points (2 each are screened; more is slower and safer) "
                   "(default: %(default)s)")
    p.add_argument("--accept-rejected", action="store_true",
                   help="write the preset even when the fit is rejected (its [fit] table then says fit_status = "
                        "\"rejected\"); without it a rejected fit writes no preset and exits 1 (both modes)")
    p.add_argument("--unidentified", choices=("report", "fix"), default="report",
                   help="parameters the data do not constrain: report them, or fix them and refit the rest "
                   "(default: %(default)s)")
    from . import _calibrate_quiet

    _calibrate_quiet.add_arguments(p)
    p.set_defaults(func=run)


def _parse_fix(items) -> dict:
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep:
            raise ParameterError(f"--fix expects NAME=VALUE, got {item!r}")
        if name not in PARAMETERS:
            raise ParameterError(f"--fix: unknown parameter {name!r}; parameters: {', '.join(PARAMETERS)}")
        try:
            out[name] = float(value)
        except ValueError:
            raise ParameterError(f"--fix {name}: {value!r} is not a number") from None
    return out


def _measurements_path(args):
    from ..errors import InputError

    if args.example and args.measurements:
        raise InputError(f"give either MEASUREMENTS ({args.measurements}) or --example, not both")
    if not args.example:
        if not args.measurements:
            raise InputError("no input: give MEASUREMENTS (a rate table or flat-field listing) or --example")
        return args.measurements
    from importlib import resources

    path = resources.files("evnoise.data") / EXAMPLE
    if not path.is_file():
        raise InputError(f"the bundled example table {EXAMPLE} is missing from the installed evnoise package")
    return str(path)


def run(args) -> int:
    from . import _calibrate_quiet

    if _calibrate_quiet.wanted(args):
        if args.example:
            raise ParameterError("--example is a rate table; it does not go with --t-start/--t-end/--window")
        return _calibrate_quiet.run(args, list(args.measurements))
    if len(args.measurements) > 1:
        raise ParameterError(f"give one MEASUREMENTS file (got {len(args.measurements)}); several recordings need "
                             "--t-start/--t-end (a quiet-scene calibration)")
    args.measurements = args.measurements[0] if args.measurements else None
    from ..io import open_output_path

    source = _measurements_path(args)
    fixed = _parse_fix(args.fix)
    from ._paths import check_output_suffixes, refuse_writing_inputs

    refuse_writing_inputs([("--out", args.out), ("--plot", args.plot)],
                          [("the measurements", args.measurements), ("the --monitor table", args.monitor),
                           ("the --initial preset", args.initial)])
    check_output_suffixes(args)
    out = open_output_path(args.out, overwrite=args.overwrite, what="preset")
    plot = open_output_path(args.plot, overwrite=args.overwrite, what="plot") if args.plot else None
    initial = opt.load_preset_arg(args.initial, "--initial") if args.initial else None

    from ..calibration import calibrate, read_measurements

    meas = read_measurements(source, monitor=args.monitor, monitor_model=args.monitor_model,
                             progress=not args.quiet)
    log.info("%d levels (%s), %.4g to %.4g lux", meas.n_levels, meas.kind, meas.lux.min(), meas.lux.max())
    result = calibrate(meas, method=args.method, distribution=args.distribution, free=args.fit, fixed=fixed,
                       initial=initial, n_starts=args.starts, n_seeds=max(2048, args.starts), rng=args.seed,
                       unidentified=args.unidentified, progress=not args.quiet)
    # a rejected fit or a parameter on a bound must not go unnoticed (shown with -q too)
    for text in result.warnings:
        log.warning("calibrate: %s", text)
    # as in the quiet mode: a rejected fit writes no preset (it would look like any other) unless asked to
    written = result.fit_status != "rejected" or args.accept_rejected
    if written:
        result.write_preset(out, overwrite=args.overwrite,
                            extra_provenance={"command": "evnoise calibrate "
                                              + ("--example" if args.example else str(args.measurements))})
    if plot is not None:  # a rejected fit's figure too: it shows where the model misses
        result.plot(plot, overwrite=args.overwrite)
    if not args.quiet:
        print(result.summary())
        wrote = ([str(out)] if written else []) + ([str(plot)] if plot is not None else [])
        if wrote:
            print("wrote " + " and ".join(wrote))
    if not written:
        log.error("the fit is rejected: no preset written to %s; --accept-rejected writes it anyway", out)
        return 1
    return 0
