"""h2viz: live H2-Mapping (octree SDF priors + hash-grid residual field) streamed to the browser."""

__version__ = "0.1.0"
