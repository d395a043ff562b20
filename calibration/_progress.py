"""A progress line over the phases of a long fit: ``calibrate: 3/4 profile of photons_per_lux [02:41]``.

A phase (a profile likelihood, the uncertainties, a refit) may run for minutes without any count to
advance a bar, so the line names the phase running and its elapsed time is redrawn every second by a
daemon thread: a long phase is visibly at work, never a silent terminal. Disabled (``enabled=False``)
it does nothing, so callers need no conditionals.
"""

from __future__ import annotations

import contextlib
import threading

__all__ = ["Phases"]

#: seconds between redraws of the elapsed time
REFRESH_S = 1.0


class Phases:
    """``with Phases("calibrate", total=3, enabled=True) as ph: with ph.phase("search"): ...``.

    ``total`` is the number of phases planned; :meth:`add` plans more (a refit found necessary).
    """

    def __init__(self, desc: str, total: int, *, enabled: bool = True):
        self.desc = desc
        self.redraws = 0  # redraws of the elapsed time so far (the tests see the line is alive)
        self.bar = None
        self._stop = threading.Event()
        self._thread = None
        if not enabled:
            return
        from tqdm.auto import tqdm

        self.bar = tqdm(total=int(total), desc=desc, unit="phase", leave=False,
                        bar_format="{desc}: {n_fmt}/{total_fmt} phases [{elapsed}]")
        self._thread = threading.Thread(target=self._tick, name="evnoise-phases", daemon=True)
        self._thread.start()

    def _tick(self) -> None:
        while not self._stop.wait(REFRESH_S):
            bar = self.bar
            if bar is None:
                return
            try:
                bar.refresh()
                self.redraws += 1
            except Exception:  # pragma: no cover - a closed stream: stop redrawing, never fail the fit
                return

    def add(self, n: int = 1) -> None:
        """Plan ``n`` more phases."""
        if self.bar is not None:
            self.bar.total += int(n)
            self.bar.refresh()

    @contextlib.contextmanager
    def phase(self, name: str):
        """Show ``name`` as the running phase; count it done when the block ends."""
        if self.bar is None:
            yield
            return
        self.bar.set_description_str(f"{self.desc}: {name}", refresh=True)
        yield
        self.bar.update(1)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2 * REFRESH_S)
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
