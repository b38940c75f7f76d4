"""Offline commands: map building, evaluation, synthetic data, training, benchmarks and the
load test, one module or package per command. May import :mod:`sgvloc.server` and
:mod:`sgvloc.core`; nothing below imports this package."""
