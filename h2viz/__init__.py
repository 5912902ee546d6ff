"""h2viz: live H2-Mapping (octree SDF priors + hash-grid residual field) streamed to the browser."""

import os

# Worker threads of OpenMP (torch) sleep at once when idle instead of spinning, and NumPy's BLAS stays on
# one thread (h2viz gives it only tiny products). On a small CPU shared with a browser or other programs,
# spinning threads waiting for a descheduled peer made every parallel op several times slower. Set before
# torch or NumPy load their thread pools; an explicit setting in the environment wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

__version__ = "0.1.0"
