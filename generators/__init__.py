"""Dataset generators (importable as ``evnoise.generators``)."""
