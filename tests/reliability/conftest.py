"""Hypothesis profile for the reliability tests: bounded examples, no per-example deadline (numba
compiles on first call), derandomized so CI is reproducible."""

from hypothesis import settings

settings.register_profile("reliability", max_examples=60, deadline=None, derandomize=True)
settings.load_profile("reliability")
