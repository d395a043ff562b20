"""``evnoise calibrate REC --t-start A --t-end B --out cam.toml``: calibrate from a quiet recording.

The recording's window ``[A, B)`` (seconds on the file's clock; several files or ``--window A:B``
entries combine) holds a still scene, so its per-pixel counts are pure noise. Fitted with
:mod:`evnoise.calibration.quiet`: the ON/OFF background rates, their regularity, their spread and
the hot pixels, each only where the data carry it. Without ``--lux`` the illuminance is unknown and
the rates are the totals at the recording's light (the preset reproduces them at 0 lux).

A *rejected* fit (a window's count histogram, its polarity alternation or its same-pixel inter-event
intervals not described at ``GOODNESS_P``, or a window failing a check that it is pure stationary noise;
``fit status`` in the report, ``fit_status`` in ``[fit]``)
writes no preset and exits 1, unless ``--accept-rejected``: then the preset is written, its ``[fit]``
table says ``fit_status = "rejected"`` with the reasons, and the exit code is 0.
"""

from __future__ import annotations

import logging
import math

from ..errors import InputError, ParameterError
from . import _options as opt

log = logging.getLogger(__name__)


#: What to do when a window fails a check of :mod:`evnoise.calibration.quiet.checks`.
_ADVICE = {
    "polarity_pairs": "the model's ON and OFF events are independent, so no preset reproduces these pairs",
    "stationarity": "the rate drifts; a shorter window, or several windows, describe it better",
    "scene_motion": "the pattern of the noise changes (something moves, or parts drift differently); choose a "
                    "window where nothing does",
}


def add_arguments(p) -> None:
    g = p.add_argument_group("quiet recording (calibrate from a camera file of a still scene)")
    opt.add_t_start(g, help="start of the still window in seconds on the file's clock (switches to this mode)")
    opt.add_t_end(g, help="end of the still window in seconds")
    g.add_argument("--window", action="append", default=[], metavar="A:B[@LUX]",
                   help="another still window of the same file(s), seconds (repeatable; optional lux)")
    g.add_argument("--lux", type=float, metavar="LUX",
                   help="illuminance of the windows, if known (the base preset's shot noise is then part of the model)")
    g.add_argument("--base", default="davis346", metavar="PRESET",
                   help="preset for the photon-noise part of the written preset (default: %(default)s)")
    opt.add_sensor(g)
    opt.add_csv_columns(g)
    g.add_argument("--spread", choices=("auto", "on", "off"), default="auto",
                   help="per-pixel spread of the rates (default: kept if a likelihood-ratio test says so)")
    g.add_argument("--hot", choices=("auto", "on", "off"), default="auto", help="hot pixels (default: auto)")
    g.add_argument("--regularity", choices=("auto", "on", "off"), default="auto",
                   help="regular (near-periodic) arrivals (default: auto)")
    g.add_argument("--timing", choices=("auto", "on", "off"), default="off",
                   help="fit the pixels' event times, not only their counts (several times the count fit's "
                        "time; default: off, the counts are fitted and the timing tested)")
    g.add_argument("--hot-regularity", choices=("auto", "on", "off"), default="off",
                   help="give the hot pixels a regularity of their own (the preset's hot_pixel_regularity; identified "
                        "by the event times: use with --timing; the fit without it runs first and starts this one, "
                        "so it cannot end lower; default: off, one regularity for every pixel)")
    g.add_argument("--drop-oscillating", action="store_true",
                   help="leave out of the fit the pixels that fire near-periodically far above the others (at least 15 "
                        "events of one polarity, 10 times the mean, interval CV < 0.3; no term of the model makes a "
                        "lone periodic pixel). Default: kept, and named in the fit's notes")
    g.add_argument("--no-checks", dest="checks", action="store_false",
                   help="skip the checks that each window is pure stationary noise (OFF/ON pairs, drift, a changing "
                        "pattern; about 15 s per million events)")


def wanted(args) -> bool:
    return args.t_start is not None or args.t_end is not None or bool(args.window)


def _windows(args):
    spans = []
    if args.t_start is not None or args.t_end is not None:
        if args.t_start is None or args.t_end is None:
            raise ParameterError("--t-start and --t-end go together")
        spans.append((args.t_start, args.t_end, args.lux))
    for text in args.window:
        span, _, lux = text.partition("@")
        a, sep, b = span.partition(":")
        try:
            spans.append((float(a), float(b), float(lux) if lux else args.lux))
        except ValueError:
            raise ParameterError(f"--window expects A:B or A:B@LUX in seconds, got {text!r}") from None
        if not sep:
            raise ParameterError(f"--window expects A:B or A:B@LUX in seconds, got {text!r}")
    for a, b, lux in spans:
        if not (math.isfinite(a) and math.isfinite(b) and b > a and max(abs(a), abs(b)) <= opt.MAX_SECONDS):
            raise ParameterError(f"a window must have its end after its start (finite seconds, at most "
                                 f"{opt.MAX_SECONDS:.3g}), got {a:g}..{b:g} s")
        if lux is not None and not (math.isfinite(lux) and lux >= 0):
            raise ParameterError(f"--lux must be finite and >= 0, got {lux!r}")
    return spans


def run(args, recordings) -> int:
    from pathlib import Path

    from evnoise.calibration import (
        GOODNESS_P,
        check_verdict,
        failed_checks,
        fit_quiet,
        preset_toml,
        quiet_window,
        write_text_atomic,
    )

    from ..io import open_output_path
    from ._paths import refuse_writing_inputs

    if not recordings:
        raise InputError("give the recording(s) to calibrate from (camera files or events.h5)")
    spans = _windows(args)
    refuse_writing_inputs([("--out", args.out), ("--plot", args.plot)],
                          [(f"the recording {r}", r) for r in recordings])
    from ._paths import check_output_suffixes

    check_output_suffixes(args)
    out = open_output_path(args.out, overwrite=args.overwrite, what="preset")
    if args.plot:
        open_output_path(args.plot, overwrite=args.overwrite, what="plot")
    base = opt.load_preset_arg(args.base, "--base")
    windows = []
    for rec in recordings:
        for a, b, lux in spans:
            w = quiet_window(rec, a, b, lux=lux, sensor=args.sensor, csv_columns=args.csv_columns,
                             checks=args.checks, progress=not args.quiet, drop_oscillating=args.drop_oscillating)
            windows.append(w)
            log.info("%s: %d events in %d pixels over %.3g s", w.describe(), int(w.counts.sum()),
                     w.n_pixels, w.duration_s)
    fit = fit_quiet(windows, base=base, spread=args.spread, hot=args.hot, regularity=args.regularity,
                    timing=args.timing, hot_regularity=args.hot_regularity, start="nested", progress=not args.quiet)
    print(fit.summary())
    params = fit.to_params(base)
    height, width = windows[0].shape
    provenance = {
        "summary": f"background fitted to {len(windows)} quiet window(s) of "
                   f"{', '.join(Path(r).name for r in recordings)}",
        "source": [w.describe() for w in windows],
        "method": "evnoise.calibration.quiet (evnoise calibrate REC --t-start --t-end)",
        "base": f"photon-noise parameters from preset {args.base} (not identified by quiet data)",
        "lux": ("the windows' illuminance is unknown: the fitted rates are the totals at the recording's light; "
                "simulate at lux 0 to reproduce them") if all(w.lux is None for w in windows) else
               "windows at " + ", ".join(f"{w.lux:g}" for w in windows) + " lux",
    }
    if fit.fit_status == "rejected":
        provenance["fit_status"] = ("REJECTED, written with --accept-rejected: " + "; ".join(fit.rejections))
    text = preset_toml(params, sensor=(width, height, "calibrated camera"), header="Calibrated from a quiet "
                       "recording by evnoise calibrate; see [provenance] and [fit].", provenance=provenance, fit=fit)
    written = fit.fit_status != "rejected" or args.accept_rejected
    if written:
        write_text_atomic(out, text, overwrite=True)
        print(f"wrote {out}")
    for w in windows:
        for c in failed_checks(w.checks):
            log.warning("%s is not pure stationary noise (%s %s): %s; %s", w.describe(), c["check"],
                        check_verdict(c), c["detail"], _ADVICE[c["check"]])
    tested = [g["p_value"] for g in fit.goodness if math.isfinite(g["p_value"])]
    if tested and min(tested) < GOODNESS_P:
        log.warning("the fitted model does not describe every window (lowest goodness-of-fit p = %.2g < %g): the "
                    "scene may not be still, or its noise not stationary", min(tested), GOODNESS_P)
    if args.plot:  # a rejected fit's figure too: it shows where the model misses
        fit.plot(args.plot, params=params)
        print(f"wrote {args.plot}")
    if fit.fit_status == "rejected":
        more = len(fit.rejections) - 1
        reasons = fit.rejections[0] + (f"; and {more} more in the report's 'rejected:' lines" if more else "")
        if not written:
            log.error("the fit is rejected (%s): no preset written to %s; --accept-rejected writes it anyway",
                      reasons, out)
            return 1
        log.warning("the fit is rejected (%s); written to %s as asked (--accept-rejected)", reasons, out)
    return 0
