"""Onboard formation-flight service and its pure numerical core (planner, mapping)."""

import os as _os

# BLAS threads make the small dense operations of the planner an order of magnitude slower;
# this must be set before numpy is first imported, so it lives at the top of the package.
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

# numba's cache checks a compiled function against its own file only: caches compiled from
# other versions of the files it calls are cleared before any kernel is loaded (jitcache.py)
from onboard.jitcache import clear_stale as _clear_stale  # noqa: E402

try:
    _clear_stale()
except OSError:  # a source that vanished meanwhile: numba's own checks remain
    pass
