"""Frozen copies of shipped parameter sets for tests that pin outputs bit for bit.

Digest pins (tests/test_speed_paths.py) check that the *code* did not change its output; they
must not break when a preset is refitted. ``LEGACY_EVK3`` is the ``evk3-hd`` preset as shipped
before issue 15 refitted it with its OFF floor (commit 4b9bd37), with every term added since at 0.
"""

import evnoise as ev

LEGACY_EVK3 = ev.NoiseParams(
    eps_pos=0.1393399605270297,
    eps_neg=0.1625114609453092,
    bias_pr=105.0117499004979,
    trial_rate_hz=39.97516802502242,
    photons_per_lux=64.0,
    dark_lux=0.10684777563918967,
    refractory_s=0.0,
    eps_sigma=0.0,
)
