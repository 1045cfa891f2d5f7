"""Self-calibrate WiFi RTT access points from a log without truth, then locate with them.

WiFi RTT ranges are biased and scaled per access point.  `calibrate(self_log=...)`
estimates each AP's bias, scale and noise sigma jointly with every scan's position (no
truth needed); `locate` then applies them (range_corrected = (range - bias) / scale, each
AP weighted by its sigma).  The shipped office excerpt, train file for the calibration and
test file to score it.

    python examples/selfcal_then_locate.py
"""

from importlib.resources import files

import robustloc
from robustloc.datasets import wifi_rtt

excerpt = files("robustloc") / "data" / "wifi-rtt-rss"  # not the full data, even if present
train = wifi_rtt.load_room("office", "train", data_dir=excerpt)
test = wifi_rtt.load_room("office", "test", data_dir=excerpt)
ranges = ["time", "tag", "anchor", "range"]

calibrated = robustloc.calibrate(anchors=train.anchors, self_log=train.ranges[ranges])
print(calibrated[["anchor", "bias", "scale", "sigma"]].round(3))

for label, anchors in (("as surveyed", test.anchors), ("self-calibrated", calibrated)):
    positions = robustloc.locate(test.ranges[ranges], anchors)
    e = robustloc.evaluate(positions, test.truth, baseline="auto")
    rms = float(e.loc[e["tag"] == "all", "rms"].iloc[0])
    print(f"{label:16s} RMS {rms:.2f} m over {len(positions)} scans")
