"""``evnoise separate IN --out signal.h5 --noise-out noise.h5``: split signal from noise events.

IN is an events.h5 file or any camera recording evnoise reads; the output suffixes decide the formats."""

from __future__ import annotations


def register(subparsers):
    from . import _options as opt

    p = subparsers.add_parser(
        "separate",
        help="split an event file (events.h5 or a camera recording) into signal and noise events",
        description="Label every event of a recording (events.h5 or a camera file: "
        f"{opt.event_suffixes()}) as signal (caused by an intensity change) or "
        "noise with a spatio-temporal correlation filter, streaming the file, and write the two parts to "
        "event files (the suffix decides the format: .h5, .aedat4, .raw (EVT3), .dat, .es, .csv). "
        "density: YNoise-style event density in a (2R+1)x(2R+1) neighbourhood and the time "
        "window [t - WINDOW, t + LOOKAHEAD] (signal if >= THRESHOLD other events); activity: the background-"
        "activity filter (signal if another pixel within R fired in the last WINDOW).",
        parents=[opt.events_input(),
                 opt.output(metavar="FILE", help="event file for the signal events (.h5, .aedat4, .raw, .dat, .es, "
                            ".csv)")],
    )
    p.add_argument("--noise-out", default=None, help="event file for the noise events (same formats)")
    p.add_argument("--method", choices=("density", "activity"), default="density", help="filter (default density)")
    p.add_argument("--radius", type=int, default=None, metavar="PX",
                   help="neighbourhood half-side in pixels (default 2 for density, 1 for activity)")
    p.add_argument("--window-us", type=int, default=None, metavar="US",
                   help="time window back from each event in microseconds (default 5000)")
    p.add_argument("--lookahead-us", type=int, default=None, metavar="US",
                   help="density: time window forward in microseconds (default 5000; 0 = causal)")
    p.add_argument("--threshold", type=opt.count("--threshold", maximum=2**62), default=None, metavar="N",
                   help="density: minimum number of other events in the window (default 3)")
    p.add_argument("--polarity", choices=("any", "same"), default=None,
                   help="density: count events of any polarity or only the event's own (default same)")
    opt.add_png(p, help="also write a picture of the signal and noise event rates (PNG)")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..errors import ParameterError
    from ..separation import separate_file

    params = {}
    if args.radius is not None:
        params["radius_px"] = args.radius
    if args.window_us is not None:
        params["window_us"] = args.window_us
    density_only = {"lookahead_us": args.lookahead_us, "threshold": args.threshold, "polarity": args.polarity}
    for key, value in density_only.items():
        if value is not None:
            if args.method != "density":
                flag = "--" + key.replace("_", "-")
                raise ParameterError(f"{flag} applies to --method density only")
            params[key] = value
    if args.out is None and args.noise_out is None:
        raise ParameterError("give --out (signal events) and/or --noise-out (noise events)")
    from ._paths import refuse_writing_inputs
    from ._pictures import check_png_output

    refuse_writing_inputs([("--out", args.out), ("--noise-out", args.noise_out), ("--png", args.png)],
                          [("the input events file", args.events)])
    check_png_output(args.png, [args.out, args.noise_out], overwrite=args.overwrite)
    res = separate_file(args.events, args.out, args.noise_out, args.method, overwrite=args.overwrite,
                        progress=not args.quiet, sensor=args.sensor, csv_columns=args.csv_columns, **params)
    if not args.quiet:
        n = res["n_events"]
        share = res["n_signal"] / n if n else 0.0
        pairs = (("signal", args.out), ("noise", args.noise_out))
        outs = ", ".join(f"{what} -> {path}" for what, path in pairs if path)
        print(f"{n:,} events: {res['n_signal']:,} signal ({share:.1%}), {res['n_noise']:,} noise; {outs} "
              f"[{res['filter']}]")
    if args.png:
        from ._pictures import write_separation_png

        write_separation_png(args.events, args.out, args.noise_out, args.png, overwrite=args.overwrite,
                             filter_text=str(res["filter"]), sensor=args.sensor, csv_columns=args.csv_columns)
    return 0
