"""evnoise inside the tools people already use: tonic transforms and frame-driven emulators (v2e).

``evnoise.plugins.tonic.PhotonNoise``
    A tonic transform: adds photon-noise events to a structured event array for the sample's
    own time span (the physical replacement for ``tonic.transforms.UniformNoise``); runs in
    forked torch DataLoader workers.
``evnoise.plugins.v2e.PhotonNoise``
    Wraps a v2e ``EventEmulator`` (duck-typed) and adds photon noise to the events of every
    frame interval, in v2e's own ``N x 4`` ``[t_s, x, y, +-1]`` rows, and to the files and
    counts v2e writes itself; ``python -m evnoise.plugins.v2e ... -- <v2e.py arguments>``
    runs v2e's ``v2e.py`` with it.
``evnoise.plugins.frames.EmulatorNoise``
    The same for any emulator with v2e's ``generate_events(frame, t_s)`` interface whose frames
    can be turned into lux (the ESIM-style example uses it with frames already in lux).

Neither tonic nor v2e is imported here: the plugins work on their data conventions only, so
importing them is cheap and needs neither package.
"""

from __future__ import annotations

__all__ = ["frames", "tonic", "v2e"]
