"""Onboard formation-flight service and its pure numerical core (planner, mapping)."""

import os as _os

# BLAS threads make the small dense operations of the planner an order of magnitude slower;
# this must be set before numpy is first imported, so it lives at the top of the package.
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
