"""The AEDAT 4 file description that evnoise writes (internal; used by :mod:`evnoise.io`)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ._version import __version__
from .params import NoiseParams

#: the event stream's node (as DV's recorder names it)
TRACK_PATH = "/mainloop/Recorder/outInfo/0/"
#: name of the node holding evnoise's attributes, a child of the stream's node (the readers search the tree)
EVNOISE_NODE = "evnoise"


def aedat_description(aedat, width: int, height: int, attrs: dict):
    """AEDAT 4 description: the event track (as DV writes it) and evnoise's attributes.

    The description has one root node (``outInfo``), as DV requires; evnoise's attributes are a
    child ``evnoise`` of the stream's node, next to its ``info`` node.
    """
    A = aedat.DescriptionAttribute
    N = aedat.DescriptionNode
    info = N("info", "/mainloop/Recorder/outInfo/0/info/",
             {"sizeX": A("int", int(width)), "sizeY": A("int", int(height)), "source": A("string", "evnoise")}, [])
    children = [info]
    if attrs:
        fields = {"evnoise_version": A("string", __version__)}
        for key, value in attrs.items():
            if value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, (str, int, np.integer)):
                if isinstance(value, NoiseParams):
                    text = value.to_json()
                else:
                    text = json.dumps(value.tolist() if hasattr(value, "tolist") else
                                      (os.fspath(value) if isinstance(value, Path) else value), sort_keys=True)
                fields[f"{key}_json"] = A("string", text)
            elif isinstance(value, str):
                fields[key] = A("string", value)
            else:
                fields[key] = A("long", int(value))
        # under the stream's node: DV and dv-processing refuse a description with more than one root node
        children.append(N(EVNOISE_NODE, f"{TRACK_PATH}{EVNOISE_NODE}/", fields, []))
    track = N("0", TRACK_PATH,
              {"compression": A("string", "LZ4"), "originalOutputName": A("string", "events"),
               "typeIdentifier": A("string", "EVTS")}, children)
    return [N("outInfo", "/mainloop/Recorder/outInfo/", {}, [track])]
