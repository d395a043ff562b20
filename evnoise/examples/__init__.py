"""Runnable examples (``python -m evnoise.examples.<name>``)."""
