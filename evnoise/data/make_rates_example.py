"""Make ``rates-example.csv``, the bundled example rate table of ``evnoise calibrate --example``.

Run ``python -m evnoise.data.make_rates_example [OUT]`` (default: next to this file). The table
is simulated from the shipped ``evk3-hd`` preset, nothing measured: a dark level (0 lux, which
identifies the background floors) and 15 illuminance levels from 0.05 to 50 lux (geometric), ON
and OFF event counts summed over 10,000 pixels and 1 s, drawn
from the Poisson distribution of the preset's population rate with seed 0 (the total of many
independent pixels' counts). Same NumPy, same bytes.

A calibration of it shows what such a table determines: ``trial_rate_hz``, ``dark_lux`` and the
OFF background floor, but not ``photons_per_lux`` (the preset has 3200 photons per trial at 50 lux, the many-photon
regime, where the thresholds and the bias only enter through combinations with it).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

PRESET = "evk3-hd"
LUX = np.concatenate([[0.0], np.geomspace(0.05, 50.0, 15)])
N_PIXELS = 10_000
DURATION_S = 1.0
SEED = 0
NAME = "rates-example.csv"


def render() -> str:
    """The CSV text."""
    from evnoise.calibration import population_rate
    from evnoise.params import load_preset

    params = load_preset(PRESET)
    rate = population_rate(LUX, params)  # (2, J) events/s per pixel, [ON, OFF]
    counts = np.random.default_rng(SEED).poisson(rate * N_PIXELS * DURATION_S)
    lines = [
        f"# Example rate table for evnoise calibrate: simulated from the {PRESET!r} preset (not a measurement)",
        f"# by python -m evnoise.data.make_rates_example: {LUX.size} levels {LUX[0]:g}-{LUX[-1]:g} lux, ON/OFF counts",
        f"# summed over {N_PIXELS} pixels and {DURATION_S:g} s, Poisson, seed {SEED}.",
        "lux,count_on,count_off,n_pixels,duration_s",
    ]
    for j, lux in enumerate(LUX):
        lines.append(f"{lux:.6g},{int(counts[0, j])},{int(counts[1, j])},{N_PIXELS},{DURATION_S:g}")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    out = Path(argv[0]) if argv else Path(__file__).with_name(NAME)
    out.write_text(render())
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
