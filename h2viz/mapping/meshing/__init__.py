"""The field as a triangle mesh, re-meshed chunk by chunk while mapping goes on (config: mapping.meshing).

- mesher.py: the chunked mesher: which chunks to re-mesh, merging and export;
- job.py: a frozen copy of the field and a mesh job that runs on any thread beside mapping;
- passes.py: what one update works on (voxels by chunk, work items cut into passes) and each chunk's surface;
- field_values.py: field values at the lattice points of a set of chunks, each point evaluated once;
- value_cache.py: each chunk's lattice values kept between updates;
- marching.py, case_table.py: masked marching cubes on a chunk's lattice, and its case table;
- observed.py: where depth was observed, so that faces nobody measured are left out (surface renders too).
"""

from h2viz.mapping.meshing.field_values import MeshingError
from h2viz.mapping.meshing.job import FrozenField, MeshJob
from h2viz.mapping.meshing.mesher import ChunkedMesher, export_mesh, merge_chunks
from h2viz.mapping.meshing.observed import ObservedCells, ObservedSupport

__all__ = [
    "ChunkedMesher",
    "FrozenField",
    "MeshJob",
    "MeshingError",
    "ObservedCells",
    "ObservedSupport",
    "export_mesh",
    "merge_chunks",
]
