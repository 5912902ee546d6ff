"""Where the field is trained (config: mapping.sampling).

- rays.py: each frame's valid pixels as training rays, kept on the device, and random ray batches over the
  current frame and its keyframes;
- samples.py: the samples along those rays inside allocated voxels: voxel traversal, fixed-step samples and the
  band around the measured depth (the torch reference of kernels/band_numba.py and kernels/voxel_walk.py).
"""

from h2viz.mapping.sampling.rays import FrameRays, RayBatch, sample_frames
from h2viz.mapping.sampling.samples import BandLayout, Samples, band_samples, sample_rays

__all__ = ["BandLayout", "FrameRays", "RayBatch", "Samples", "band_samples", "sample_frames", "sample_rays"]
