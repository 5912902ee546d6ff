"""From field values to pixels, and the losses that compare them with the frames (config: mapping.losses).

- volume.py: SDF-based volume rendering over ragged samples (weights, composites, first surface crossings);
- losses.py: the four H2-Mapping losses (colour, depth, free space, SDF);
- images.py: rendered images at any camera (colour, depth, normals) without gradients, volume or surface
  renders, searching only the samples that can carry weight (kernels/render_search.py on the CPU).
"""

from h2viz.mapping.rendering.images import RenderParams, render_image
from h2viz.mapping.rendering.losses import mapping_losses
from h2viz.mapping.rendering.volume import composite, render_weights

__all__ = ["RenderParams", "composite", "mapping_losses", "render_image", "render_weights"]
