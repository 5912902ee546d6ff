"""The compiled (numba) fast paths of the mapping stages, for CPU tensors and host arrays.

Nothing here is imported unless `h2viz.mapping.backend` finds numba (with `mapping.runtime.kernels: auto`): the stages
take a `Backend` that holds these modules, and run their own torch / NumPy reference code where it holds none.
Each module is checked against that reference by its parity test (tests/mapping/kernels/ and the stage's tests).

- jit.py: numba compilation with an on-disk cache, and the lock every parallel kernel runs under;
- frame_numba.py: a frame's rays (reference: sampling/rays.py);
- band_numba.py: the training samples around measured depth (reference: sampling/samples.py band_samples);
- voxel_walk.py, voxel_walk_numba.py: ray walks through the allocated voxels and render lattices (reference:
  sampling/samples.py traverse);
- render_search.py, render_search_numba.py: which render samples the networks evaluate (reference: the
  exhaustive render, rendering/images.py render_rays_reference);
- hash_numba.py, prior_numba.py, decoder_numba.py: hash grids, corner priors and decoders (field/);
- color_prior_numba.py, fine_prior_numba.py, octree_numba.py: colour and fine SDF priors, voxel allocation (field/);
- loss_numba.py: render weights and the four losses with their gradients (rendering/);
- optim_numba.py: row-sparse Adam (optim.py);
- marching_numba.py, observed_numba.py: marching cubes and observed-space tests (meshing/).
"""
