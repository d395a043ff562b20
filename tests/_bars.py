"""A stand-in for evnoise's progress bars: tqdm redraws at most every 0.1 s, so a test cannot read a bar's final
state from the screen; it counts through this instead."""


class CountingBar:
    """What a test asks of a bar: its total, what was counted, whether it was closed."""

    def __init__(self, total):
        self.total, self.counted, self.closed = total, 0, False

    def update(self, n):
        self.counted += n

    def close(self):
        self.closed = True


def stand_in_bars(monkeypatch, module, desc: str, *, others_shown: bool = True) -> dict:
    """Replace ``module.progress_bar`` so that the bar named ``desc`` is a :class:`CountingBar` (None when not
    enabled), stored in the returned dict under ``desc``; other bars are the real ones (not shown unless
    ``others_shown``)."""
    bars = {}
    real = module.progress_bar

    def stand_in(total, enabled, name, **kw):
        if name != desc:
            return real(total, enabled and others_shown, name, **kw)
        bars[name] = CountingBar(total) if enabled else None
        return bars[name]

    monkeypatch.setattr(module, "progress_bar", stand_in)
    return bars
