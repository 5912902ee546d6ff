"""h2viz: live H2-Mapping (octree SDF priors + hash-grid residual field) streamed to the browser.

The public API (each name imported on first use, so that `import h2viz` loads neither torch nor NumPy):

- `Config`, `load_config`: the configuration (h2viz/config.py; defaults in h2viz/configs/default.yaml);
- `make_source`: frames from a dataset folder, a bag or the built-in synthetic room (h2viz/sources/);
- `Mapper`: H2-Mapping on posed RGB-D frames (h2viz/mapping/);
- `run_map`: a headless run: map, mesh, evaluate and write a run folder (what `h2viz map` does);
- `run_view`: the live dashboard (what `h2viz view` does).

Packages: `sources/` frame sources, `mapping/` the mapper and its stages, `eval/` metrics and reports, `worker/`
the dashboard's mapping thread, `viewer/` the dashboard; `pipeline.py` headless runs, `cli.py` the command line.
"""

import os
from typing import TYPE_CHECKING, Any

# Worker threads of OpenMP (torch) sleep at once when idle instead of spinning, and NumPy's BLAS stays on
# one thread (h2viz gives it only tiny products). On a small CPU shared with a browser or other programs,
# spinning threads waiting for a descheduled peer made every parallel op several times slower. Set before
# torch or NumPy load their thread pools; an explicit setting in the environment wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

__version__ = "0.1.0"

if TYPE_CHECKING:
    from h2viz.config import Config, load_config
    from h2viz.mapping.mapper import Mapper
    from h2viz.pipeline import run_map
    from h2viz.sources.base import make_source
    from h2viz.viewer.server import run_view

__all__ = ["Config", "Mapper", "load_config", "make_source", "run_map", "run_view"]


def __getattr__(name: str) -> Any:
    if name in ("Config", "load_config"):
        from h2viz import config as module
    elif name == "Mapper":
        from h2viz.mapping import mapper as module
    elif name == "make_source":
        from h2viz.sources import base as module
    elif name == "run_map":
        from h2viz import pipeline as module
    elif name == "run_view":
        from h2viz.viewer import server as module
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(module, name)


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
