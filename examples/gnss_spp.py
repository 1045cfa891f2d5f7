"""GNSS single-point positioning with RAIM, and a fault it catches.

The shipped GEONET excerpt (station 0759, GPS, RINEX 2 observation + navigation files):
first the plain solution, then the same epochs with +20 m added to satellite G11's
pseudoranges, to see what RAIM (B-method global test + w-test exclusion) makes of it:
how many epochs it excludes G11 in, and the statuses it gives.

    python examples/gnss_spp.py
"""

from importlib.resources import files

import robustloc

data = files("robustloc") / "data" / "gnss-geonet"
obs, nav = data / "07590920.05o", data / "07590920_0000-0400.05n"

clean = robustloc.spp(obs, nav, systems="G", raim=True)
faulty = robustloc.spp(obs, nav, systems="G", raim=True, inject={"G11": 20.0})
for label, sol in (("clean", clean), ("G11 +20 m", faulty)):
    s = sol.attrs["summary"]
    print(f"{label:10s} {s['solved']}/{s['epochs']} epochs, RMS horizontal "
          f"{s['rms_h_m']:.2f} m, 3-D {s['rms_3d_m']:.2f} m, exclusions in "
          f"{s['epochs_with_exclusion']} epochs, median HPL {s['median_hpl_m']:.1f} m")
print(faulty[["status", "excluded"]].value_counts().head())
