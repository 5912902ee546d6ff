"""Neural dense mapping (H2-Mapping): one `Mapper` turns posed RGB-D frames into a map, stage by stage.

- `field/`: what the map holds: the sparse voxel octree, its SDF priors (corner, fine) and colour priors, the
  hash-grid encodings and decoders that form the hybrid field, and the stored colour views;
- `sampling/`: training rays from frames and keyframes, and the samples along them inside allocated voxels;
- `rendering/`: volume rendering of samples, the four losses, and rendered images at any camera;
- `keyframes/`: which frames are kept, which are optimised together, and the keyframes' memory budget;
- `meshing/`: chunked marching cubes of the field, the mesh jobs that run beside mapping, observed cells;
- `kernels/`: the compiled (numba) fast paths of those stages, each checked against its stage's reference code;
- here: the `Mapper` (mapper.py), the `Backend` that picks each stage's kernels once (backend.py), the optimiser
  (optim.py), real-time scheduling (anytime.py), checkpoints (checkpoint.py, checkpoint_format.py), autosave
  and the kernel warm-up before a live stream (warmup.py).

The public names below are imported on first use: anytime.py and autosave.py, which the dashboard's worker
imports, stay free of torch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from h2viz.mapping.backend import Backend, resolve_backend
    from h2viz.mapping.checkpoint import load_checkpoint, save_checkpoint
    from h2viz.mapping.mapper import Mapper

__all__ = ["Backend", "Mapper", "load_checkpoint", "resolve_backend", "save_checkpoint"]


def __getattr__(name: str) -> Any:
    if name == "Mapper":
        from h2viz.mapping import mapper as module
    elif name in ("Backend", "resolve_backend"):
        from h2viz.mapping import backend as module
    elif name in ("load_checkpoint", "save_checkpoint"):
        from h2viz.mapping import checkpoint as module
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(module, name)


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
