"""What the map holds (config: mapping.representation, mapping.color).

- octree.py: the sparse voxel octree of leaf voxels, unbounded, and the allocation of a frame's voxels;
- corner_prior.py: SDF priors at voxel corners, projected from the first depth that sees them;
- fine_prior.py: every frame's truncated SDF averaged on a fine lattice inside each voxel;
- color_prior.py: every frame's colours averaged on a fine lattice inside each voxel;
- encoding.py: the multiresolution hash grids (geometry and colour);
- hybrid_field.py: sdf = priors + decoded hash-grid residual, colour = prior + decoded residual;
- tiled.py, bf16.py: how the decoders run fast on a CPU (cache-sized tiles, bfloat16 products);
- color_views.py: stored views whose images colour rendered surface points.
"""

from h2viz.mapping.field.color_prior import ColorPrior
from h2viz.mapping.field.color_views import ColorViews
from h2viz.mapping.field.corner_prior import PriorInitializer
from h2viz.mapping.field.encoding import HashGrid
from h2viz.mapping.field.fine_prior import FinePrior
from h2viz.mapping.field.hybrid_field import HybridField
from h2viz.mapping.field.octree import VoxelOctree

__all__ = ["ColorPrior", "ColorViews", "FinePrior", "HashGrid", "HybridField", "PriorInitializer", "VoxelOctree"]
