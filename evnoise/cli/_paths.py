"""One check shared by every command: never write over one of the command's own inputs.

``--overwrite`` replaces an earlier *output*; it must never replace an input (``evnoise simulate
photo.png --out photo.png --overwrite`` would otherwise turn the photo into an HDF5 file). The
comparison is by file identity (:func:`os.path.samefile`: symlinks, hard links, ``./a`` vs ``a``,
case-insensitive file systems) where both exist, else by resolved path.
"""

from __future__ import annotations

import fnmatch
import os
from pathlib import Path

from ..errors import OutputError


def _same(a: Path, b: Path) -> bool:
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
        return a.resolve() == b.resolve()
    except OSError:
        return False


def _inside(child: Path, folder: Path, *, direct: bool) -> bool:
    """Whether ``child`` lies in ``folder`` (directly, or at any depth)."""
    try:
        parent = child.parent if str(child.parent) else Path(".")
        if direct:
            return folder.is_dir() and _same(parent, folder)
        child_r, folder_r = child.resolve(), folder.resolve()
    except OSError:
        return False
    return folder_r in child_r.parents


def refuse_writing_inputs(outputs, inputs, *, frames_folder: bool = False, output_folder: bool = False,
                          folder_files=None) -> None:
    """Raise :class:`~evnoise.OutputError` if an output would write over (or into) an input.

    Parameters
    ----------
    outputs : iterable of (str, path or None)
        ``(flag, path)`` of every file or folder the command writes (``None`` entries are
        skipped), e.g. ``[("--out", args.out), ("--png", args.png)]``.
    inputs : iterable of (str, path or None)
        ``(description, path)`` of everything the command reads, e.g.
        ``[("the input image", args.input), ("the preset", args.preset)]``; entries that do
        not name an existing file or folder (``None``, a preset *name*) are skipped.
    frames_folder : bool
        An input folder is read as a whole (a folder of frames, listed non-recursively): an
        output file directly inside it is refused as well, since it would join the input (and
        could replace one of its files).
    output_folder : bool
        The outputs are folders (``make-dataset --out``): one that contains an input is refused
        too.
    folder_files : sequence of str, optional
        The outputs are folders into which files named by these glob patterns are written
        (``reconstruct --fps``: ``frame_*.png``, ...): an input inside one with such a name is
        refused (any other file there is left alone, so it is allowed).
    """
    outs = [(flag, Path(p)) for flag, p in outputs if p is not None and str(p) != ""]
    ins = [(what, Path(p)) for what, p in inputs if p is not None and str(p) != ""]
    ins = [(what, p) for what, p in ins if p.exists()]
    for flag, out in outs:
        for what, inp in ins:
            if _same(out, inp):
                raise OutputError(f"{flag} {out} is {what} ({inp}); evnoise never writes over its own input, "
                                  f"not even with --overwrite: choose another name")
            if inp.is_dir() and frames_folder and _inside(out, inp, direct=True):
                raise OutputError(f"{flag} {out} is inside {what} {inp}, which is read as a whole; write it "
                                  f"elsewhere")
            if folder_files and _inside(inp, out, direct=True) and any(
                    fnmatch.fnmatch(inp.name, pattern) for pattern in folder_files):
                raise OutputError(f"{flag} {out} would receive files named {' / '.join(folder_files)}, and "
                                  f"{what} {inp} is one of them; evnoise never writes over its own input")
            if output_folder and out.is_dir() and _inside(inp, out, direct=False):
                raise OutputError(f"{flag} {out} contains {what} ({inp}); evnoise never writes over its own "
                                  f"input: choose another folder")


__all__ = ["refuse_writing_inputs", "check_output_suffixes"]


def check_output_suffixes(args) -> None:
    """``calibrate``'s preset is TOML and its plot PNG whatever the names say: a name saying otherwise is a slip
    (checked after the outputs are known not to name an input, the graver slip)."""
    from pathlib import Path

    from ..errors import OutputError

    if args.out is not None and Path(args.out).suffix.lower() != ".toml":
        raise OutputError(f"--out must name a .toml file (the preset is TOML), got {args.out}")
    if args.plot is not None and Path(args.plot).suffix.lower() != ".png":
        raise OutputError(f"--plot must name a .png file, got {args.plot}")
