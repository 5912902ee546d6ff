"""Neural dense mapping: octree, SDF priors, hash encoding, field, sampling, rendering, optimisation."""
