"""Which implementation each mapping stage runs, chosen once per mapper from `mapping.runtime.kernels` and the device.

- "numba": CPU tensors, with the compiled kernels (frame rays, band samples, hash grids, prior, decoders, losses,
  sparse Adam, colour prior) and the compiled NumPy-side kernels (voxel walks, the render search, marching cubes,
  observed-space tests, the frozen field's prior);
- "torch": CPU tensors through the pure-torch and NumPy reference code only; numba is never imported;
- "cuda": tensors on the GPU through the torch code; the NumPy-side kernels still run on the host copies when
  numba imports (and `mapping.runtime.kernels` is auto).

`resolve_backend` is the one place that makes this choice; the stages take the Backend and call the kernels it
holds, or their reference code where it holds none. The kernel modules are imported here, on first use, so that
numba stays a dependency of the fast CPU path only.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from types import ModuleType

import torch

from h2viz.errors import ConfigError

KERNEL_CHOICES: tuple[str, ...] = ("auto", "torch")
"""auto: the compiled numba kernels where they apply when numba imports, else torch; torch: always the reference."""


@dataclass(frozen=True)
class TensorKernels:
    """Compiled kernels on CPU float32 tensors (each module's parity test holds the torch reference)."""

    frame: ModuleType  # h2viz.mapping.kernels.frame_numba: a frame's rays and the ray batches
    band: ModuleType  # h2viz.mapping.kernels.band_numba: the training samples around measured depth
    hash: ModuleType  # h2viz.mapping.kernels.hash_numba: hash-grid encoding and its table gradient
    prior: ModuleType  # h2viz.mapping.kernels.prior_numba: trilinear corner priors
    decoder: ModuleType  # h2viz.mapping.kernels.decoder_numba: one-hidden-layer decoders
    loss: ModuleType  # h2viz.mapping.kernels.loss_numba: render weights and the four losses
    optim: ModuleType  # h2viz.mapping.kernels.optim_numba: row-sparse Adam
    color_prior: ModuleType  # h2viz.mapping.kernels.color_prior_numba: colour splats and blends
    fine_prior: ModuleType  # h2viz.mapping.kernels.fine_prior_numba: fine SDF prior blends


@dataclass(frozen=True)
class ArrayKernels:
    """Compiled kernels on host NumPy arrays (used on any device)."""

    walk: ModuleType  # h2viz.mapping.kernels.voxel_walk: voxel walks (voxel_walk_numba.py) and render lattices
    search: ModuleType  # h2viz.mapping.kernels.render_search: which render samples the networks evaluate
    marching: ModuleType  # h2viz.mapping.kernels.marching_numba: lattices, marching cubes, vertex matching
    support: ModuleType  # h2viz.mapping.kernels.observed_numba: observed-space tests of mesh faces
    prior: ModuleType  # h2viz.mapping.kernels.prior_numba: the frozen field's prior blend
    decoder: ModuleType  # h2viz.mapping.kernels.decoder_numba: the frozen field's decoder on CPU features
    fine_prior: ModuleType  # h2viz.mapping.kernels.fine_prior_numba: depth fusion into fine SDF priors, their blends
    octree: ModuleType  # h2viz.mapping.kernels.octree_numba: a frame's occupied cells, counts and mean points


@dataclass(frozen=True)
class Backend:
    name: str  # numba | torch | cuda (see the module docstring)
    device: torch.device
    tensor_kernels: TensorKernels | None = None  # None: the torch reference code
    array_kernels: ArrayKernels | None = None  # None: the NumPy / torch reference code

    def __deepcopy__(self, memo: dict[int, object]) -> Backend:
        return self  # immutable, and holds modules (a frozen field's deep copy shares it)

    def cpu_kernels(self, *tensors: torch.Tensor) -> TensorKernels | None:
        """The tensor kernels when every tensor lives on the CPU, else None (a GPU tensor handed to a CPU backend)."""
        k = self.tensor_kernels
        if k is None or any(t.device.type != "cpu" for t in tensors):
            return None
        return k

    def serial_thread(self) -> None:
        """Make the calling thread (a background one: meshing) run this backend's kernels on one thread, leaving
        the other cores to the mapping thread's parallel kernels (no-op without compiled kernels)."""
        if self.array_kernels is not None:
            from h2viz.mapping.kernels.jit import serial_kernels

            serial_kernels()


REFERENCE = Backend("torch", torch.device("cpu"))
"""The pure-torch CPU backend: what a stage built without a backend runs (the reference of every kernel)."""


@functools.cache
def _compiled() -> tuple[TensorKernels, ArrayKernels] | None:
    """Every kernel module, imported once; None when numba (or a kernel module) cannot be imported."""
    try:
        from h2viz.mapping.kernels import (
            band_numba,
            color_prior_numba,
            decoder_numba,
            fine_prior_numba,
            frame_numba,
            hash_numba,
            loss_numba,
            marching_numba,
            observed_numba,
            octree_numba,
            optim_numba,
            prior_numba,
            render_search,
            voxel_walk,
        )
    except ImportError:
        return None
    tensors = TensorKernels(
        frame_numba, band_numba, hash_numba, prior_numba, decoder_numba, loss_numba, optim_numba, color_prior_numba,
        fine_prior_numba,
    )  # fmt: skip
    arrays = ArrayKernels(
        voxel_walk, render_search, marching_numba, observed_numba, prior_numba, decoder_numba, fine_prior_numba,
        octree_numba,
    )  # fmt: skip
    return tensors, arrays


def pick_device(name: str) -> torch.device:
    """'auto' -> CUDA when present, else CPU."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def resolve_backend(kernels: str = "auto", device: str | torch.device = "cpu") -> Backend:
    """The backend for `mapping.runtime.kernels` (auto | torch) and a device (auto | cpu | cuda[:n] | torch.device)."""
    if kernels not in KERNEL_CHOICES:
        raise ConfigError(f"mapping.runtime.kernels: unknown {kernels!r}; use one of {KERNEL_CHOICES}")
    dev = pick_device(device) if isinstance(device, str) else device
    compiled = _compiled() if kernels == "auto" else None
    arrays = None if compiled is None else compiled[1]
    if dev.type != "cpu":
        return Backend(dev.type, dev, None, arrays)
    if compiled is None:
        return Backend("torch", dev)
    return Backend("numba", dev, compiled[0], arrays)
