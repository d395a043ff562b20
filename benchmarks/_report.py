"""Helpers the benchmark scripts share: the machine's CPU name, and one section of REPORT.md replaced in place."""

from __future__ import annotations

import platform
from pathlib import Path


def cpu_name() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else what :func:`platform.processor` says."""
    try:
        with open("/proc/cpuinfo") as fh:
            return next(line.split(":", 1)[1].strip() for line in fh if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.processor()


def replace_section(report: Path, title: str, text: str) -> None:
    """Write ``text`` (starting with the heading ``title``) into ``report`` in place of the section under
    ``title`` (up to the next ``## `` heading), or append it when the report has no such section."""
    report = Path(report)
    old = report.read_text(encoding="utf-8") if report.exists() else ""
    at = old.find(title)
    if at < 0:
        new = old.rstrip("\n") + "\n\n" + text
    else:
        nxt = old.find("\n## ", at + len(title))
        new = old[:at] + text + ("" if nxt < 0 else old[nxt:])
    report.write_text(new.rstrip("\n") + "\n", encoding="utf-8")
