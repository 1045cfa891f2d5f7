"""robustloc: robust positioning from noisy radio measurements.

Batched estimators (linearized LS, WLS, Gauss-Newton, robust IRLS, LEGE), integrity
statistics (global test, w-test data snooping, B-method, reliability), Kalman filters and
GNSS single-point positioning, with a command line (``robustloc --help``).
"""

from robustloc.errors import InputError

__version__ = "0.1.0"
__all__ = ["InputError", "__version__"]
