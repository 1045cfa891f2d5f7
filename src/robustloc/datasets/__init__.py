"""Loaders that turn the public real-data sets into the contract frames (anchors,
measurements, truth, survey).  Full data comes from ``--data DIR`` (default
``../shared/data``); small excerpts ship in ``robustloc/data/``."""
