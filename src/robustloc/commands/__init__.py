"""Subcommands of ``robustloc``, one module each (see :mod:`robustloc.cli`)."""

#: Order in ``robustloc --help``; commands not listed come after, alphabetically.
ORDER = [
    "simulate",
    "calibrate",
    "locate",
    "evaluate",
    "stats",
    "filter",
    "fuse",
    "spp",
    "reliability",
    "montecarlo",
    "reproduce",
]
