"""Status codes written in the ``status`` column of every output row.

Every input epoch yields an output row; these strings say what became of it.
"""

OK = "ok"
#: Fewer usable observations than unknowns (or than the method's minimum).
INSUFFICIENT = "insufficient_anchors"
#: Geometry too poor for a stable solution (collinear anchors, singular normal matrix).
ILL_CONDITIONED = "ill_conditioned"
#: Iterations hit the limit before the step fell below the tolerance.
NOT_CONVERGED = "not_converged"
#: One or more observations were found faulty by a test and excluded; the fix is usable.
FAULT_EXCLUDED = "fault_excluded"
#: A fault was detected but could not be excluded (redundancy exhausted).
UNAVAILABLE = "unavailable"
#: The epoch's own input was unusable (all NaN/inf, malformed).
INVALID = "invalid_measurement"

ALL = (OK, INSUFFICIENT, ILL_CONDITIONED, NOT_CONVERGED, FAULT_EXCLUDED, UNAVAILABLE, INVALID)
#: Statuses whose position is a usable fix.
USABLE = (OK, FAULT_EXCLUDED, NOT_CONVERGED)
