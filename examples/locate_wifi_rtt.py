"""Locate a WiFi RTT log from Python and score it against the truth.

The shipped excerpt of the WiFi RTT data set (office, test file: five access points at
known positions, one scan per epoch): ranges in, one positions row per epoch and method
out, each with a status and a horizontal protection level ``hpl``; then the error
statistics against the surveyed reference points.

    python examples/locate_wifi_rtt.py
"""

from importlib.resources import files

import robustloc
from robustloc.datasets import wifi_rtt

excerpt = files("robustloc") / "data" / "wifi-rtt-rss"  # not the full data, even if present
room = wifi_rtt.load_room("office", "test", data_dir=excerpt)
measurements = room.ranges[["time", "tag", "anchor", "range"]]  # time, tag, anchor, range

# the default (auto), the paper's linearized LS and its favourite robust method (igg)
positions = robustloc.locate(measurements, room.anchors, ["auto", "ls", "igg"])
print(positions[["time", "method", "x", "y", "status", "hpl"]].head().round(2))
print(positions.groupby("method")["status"].value_counts().unstack(fill_value=0))

errors = robustloc.evaluate(positions, room.truth, baseline="ls")
print(errors[errors["tag"] == "all"][["method", "n", "rms", "p95", "rms_impr_pct"]].round(2))
