"""Classic TSDF fusion baseline: Open3D's VoxelBlockGrid (CPU) fusing the same posed RGB-D frames h2viz
maps, with colour, then marching cubes. Used by the benchmarks as the non-learned reference.

Open3D is an optional dependency: `.venv/bin/pip install -c constraints.txt open3d` (or the `bench` extra).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np
import trimesh

import h2viz  # noqa: F401  (thread-pool policy before OpenMP libraries load)
from h2viz.errors import H2vizError
from h2viz.types import RgbdFrame

INSTALL_HINT = ".venv/bin/pip install -c constraints.txt open3d  (or: pip install 'h2viz[bench]')"


class TsdfUnavailable(H2vizError):
    """Open3D is not installed, so the TSDF baseline cannot run."""


@dataclass
class TsdfConfig:
    """Parameters of the TSDF baseline."""

    voxel_size_m: float = 0.01
    """Edge of one TSDF voxel (1 cm)."""
    trunc_voxels: float = 5.0
    """Truncation distance in voxels (5 voxels = 5 cm, h2viz's truncation tr)."""
    depth_max_m: float = 10.0
    """Depth beyond this is not fused (sources already drop depth outside their range)."""
    weight_threshold: float = 0.5
    """Marching cubes keeps voxels whose fused weight (frames that saw them) exceeds this: 0.5 keeps all
    that was observed once, as h2viz meshes all it observed (Open3D's default, 3, drops surfaces seen
    by fewer than 4 frames, most of a sparse sequence)."""
    block_resolution: int = 8
    """Voxels per edge of one hashed block (8 -> 8 cm blocks at 1 cm voxels)."""
    initial_blocks: int = 4096
    """Initial capacity of the block hash map; it grows when a scene needs more."""


def import_open3d() -> ModuleType:
    """The open3d module, or TsdfUnavailable telling how to install it."""
    try:
        import open3d
    except ImportError as e:
        raise TsdfUnavailable(f"open3d is not installed ({e}); install it with {INSTALL_HINT}") from e
    return open3d


class TsdfFusion:
    """Incremental TSDF + colour fusion of RgbdFrames into an Open3D VoxelBlockGrid on the CPU."""

    def __init__(self, cfg: TsdfConfig | None = None) -> None:
        self.cfg = cfg or TsdfConfig()
        if self.cfg.voxel_size_m <= 0 or self.cfg.trunc_voxels <= 0:
            raise H2vizError("TSDF baseline: voxel_size_m and trunc_voxels must be > 0")
        self.o3d = import_open3d()
        o3c = self.o3d.core
        self.device = o3c.Device("CPU:0")
        self.grid = self.o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight", "color"),
            attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
            attr_channels=((1,), (1,), (3,)),
            voxel_size=self.cfg.voxel_size_m,
            block_resolution=self.cfg.block_resolution,
            block_count=self.cfg.initial_blocks,
            device=self.device,
        )
        self.frames = 0

    def integrate(self, frame: RgbdFrame) -> float:
        """Fuse one frame (depth and colour) and return the seconds it took (conversion included)."""
        start = time.perf_counter()
        o3c, image = self.o3d.core, self.o3d.t.geometry.Image
        depth = image(o3c.Tensor(np.ascontiguousarray(frame.depth_m, dtype=np.float32)))  # (H,W) metres
        rgb = np.ascontiguousarray(frame.rgb, dtype=np.float32) / np.float32(255.0)  # (H,W,3) in [0,1]
        color = image(o3c.Tensor(rgb))
        K = o3c.Tensor(np.asarray(frame.K, dtype=np.float64))
        T_camera_world = o3c.Tensor(np.linalg.inv(np.asarray(frame.T_world_camera, dtype=np.float64)))
        args: tuple[Any, ...] = (1.0, self.cfg.depth_max_m, self.cfg.trunc_voxels)  # depth scale, max, trunc
        blocks = self.grid.compute_unique_block_coordinates(depth, K, T_camera_world, *args)
        self.grid.integrate(blocks, depth, color, K, K, T_camera_world, *args)
        self.frames += 1
        return time.perf_counter() - start

    def mesh(self) -> trimesh.Trimesh:
        """The zero crossing as a vertex-coloured trimesh (empty when nothing was fused)."""
        if self.frames == 0:
            return trimesh.Trimesh()
        tmesh = self.grid.extract_triangle_mesh(weight_threshold=self.cfg.weight_threshold)
        if "positions" not in tmesh.vertex or "indices" not in tmesh.triangle:
            return trimesh.Trimesh()
        vertices = tmesh.vertex.positions.numpy().astype(np.float64)  # (N,3)
        faces = tmesh.triangle.indices.numpy().astype(np.int64)  # (M,3)
        colors = np.clip(tmesh.vertex.colors.numpy(), 0.0, 1.0)  # (N,3) in [0,1]
        rgba = np.concatenate([np.round(colors * 255.0), np.full((len(colors), 1), 255.0)], axis=1)
        return trimesh.Trimesh(vertices, faces, vertex_colors=rgba.astype(np.uint8), process=False)

    @property
    def n_blocks(self) -> int:
        """Allocated voxel blocks (memory grows with it)."""
        return int(self.grid.hashmap().size())
