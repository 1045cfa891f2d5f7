"""Workflows: the one implementation of each command, under every front end.

A pipeline takes its inputs as paths or in-memory frames, its settings as one typed,
frozen dataclass (scikit-learn style: settings in the constructor, data in the call;
every value checked by :func:`robustloc.options.check_settings` with the command line's
wording), and writes its output to a path (atomically) or returns it as a frame.  It
returns the run summary (what ``--json`` prints).

Front ends over it, never beside it:

* the Python API (:mod:`robustloc.api`: ``robustloc.locate(...)`` & co.);
* the command line (:mod:`robustloc.commands`: parse the options into the settings,
  call the pipeline, print the summary);
* the Dask engine (:mod:`robustloc.engines`: the same pipeline per partition) and the
  live service (:mod:`robustloc.service`: the same locators and log-scale pass).

Layering: ``io -> models -> robust -> estimators -> integrity -> filters -> tracking ->
pipelines -> service/engines -> api -> commands``.

Modules: :mod:`~robustloc.pipelines.locate`, :mod:`~robustloc.pipelines.track`.
"""
