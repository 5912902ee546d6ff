"""Checkpoints: everything a run needs to continue (octree, priors, field, optimiser, keyframes, trajectory)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import torch

from h2viz.config import MappingConfig
from h2viz.errors import CheckpointError
from h2viz.mapping.backend import Backend
from h2viz.mapping.mapper import Mapper
from h2viz.mapping.rays import FrameRays
from h2viz.types import RgbdFrame

FORMAT_VERSION = 1


def _keyframe_record(rays: FrameRays) -> dict[str, Any]:
    return {
        "index": rays.index,
        "K": rays.K,
        "T_world_camera": rays.T_world_camera,
        "shape": rays.shape,
        "valid": rays.valid.cpu(),
        "depth": rays.depth.cpu(),
        "rgb": rays.rgb.cpu(),
    }


def _keyframe_from_record(rec: dict[str, Any], backend: Backend) -> FrameRays:
    h, w = rec["shape"]
    depth = np.zeros(h * w, np.float32)
    rgb = np.zeros((h * w, 3), np.uint8)
    depth[rec["valid"].numpy()] = rec["depth"].numpy()
    rgb[rec["valid"].numpy()] = rec["rgb"].numpy()
    frame = RgbdFrame(rec["index"], 0.0, rgb.reshape(h, w, 3), depth.reshape(h, w), rec["K"], rec["T_world_camera"])
    return FrameRays(frame, backend)


def save_checkpoint(mapper: Mapper, path: Path, extra: dict[str, Any] | None = None) -> None:
    """Write the whole mapping state to `path` (a .pt file)."""
    state = {
        "format_version": FORMAT_VERSION,
        "config": dataclasses.asdict(mapper.cfg),
        "octree": mapper.octree.state_dict(),
        "priors_init": mapper.priors.state_dict(),
        "observed": mapper.observed.state_dict(),
        "priors": mapper.field.priors.detach().cpu(),
        "color_prior": None if mapper.field.color_prior is None else mapper.field.color_prior.sums.cpu().clone(),
        "fine_prior": None if mapper.field.fine_prior is None else mapper.field.fine_prior.state.cpu().clone(),
        "field": {k: v.cpu() for k, v in mapper.field.state_dict().items()},
        "optim": mapper.optim.state_dict(),
        "net_optim": mapper.net_optim.state_dict(),
        "keyframes": mapper.keyframes.state_dict(),
        "keyframe_frames": [_keyframe_record(r) for r in mapper.keyframe_rays],
        "thumbnails": mapper.thumbnails,
        "trajectory": np.asarray(mapper.trajectory).reshape(-1, 4, 4),
        "frames_done": mapper.frames_done,
        "max_depth_m": mapper.max_depth_m,
        "rng": mapper.rng.get_state(),
        "extra": extra or {},
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    try:
        torch.save(state, tmp)
        tmp.replace(path)
    except OSError as e:
        raise CheckpointError(f"cannot write checkpoint {path}: {e}; check the folder is writable") from e


def load_checkpoint(path: Path, cfg: MappingConfig | None = None) -> tuple[Mapper, dict[str, Any]]:
    """Rebuild a Mapper from a checkpoint; returns it and the checkpoint's `extra` dict."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist; pass the checkpoint.pt of an earlier run")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # noqa: BLE001 - any unpickling failure means the file is unusable
        raise CheckpointError(f"{path} is not a readable h2viz checkpoint ({e})") from e
    if state.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"{path} has checkpoint format {state.get('format_version')}, expected {FORMAT_VERSION}")
    saved = MappingConfig(**state["config"])
    if cfg is not None:  # runtime-only settings may change on resume; the map's geometry may not
        saved = dataclasses.replace(
            cfg,
            voxel_size_m=saved.voxel_size_m,
            truncation_m=saved.truncation_m,
            hash_levels=saved.hash_levels,
            hash_features=saved.hash_features,
            hash_log2_size=saved.hash_log2_size,
            hash_scale=saved.hash_scale,
            color_hash_levels=saved.color_hash_levels,
            color_hash_log2_size=saved.color_hash_log2_size,
            geo_hidden=saved.geo_hidden,
            geo_layers=saved.geo_layers,
            color_hidden=saved.color_hidden,
            color_layers=saved.color_layers,
            color_prior=saved.color_prior,
            fine_priors=saved.fine_priors,
            priors=saved.priors,
        )
    mapper = Mapper(saved)
    mapper.octree.load_state_dict(state["octree"])
    mapper.priors.load_state_dict(state["priors_init"])
    mapper.field.sync(mapper.octree)
    mapper.field.load_state_dict(state["field"])
    mapper.field.priors = state["priors"].to(mapper.device).requires_grad_(saved.priors)
    if mapper.field.color_prior is not None and state.get("color_prior") is not None:
        mapper.field.color_prior.load(state["color_prior"])
    if mapper.field.fine_prior is not None and state.get("fine_prior") is not None:
        mapper.field.fine_prior.load(state["fine_prior"])
    mapper.optim.load_state_dict(state["optim"])
    mapper.net_optim.load_state_dict(state["net_optim"])
    mapper.keyframes.load_state_dict(state["keyframes"])
    mapper.keyframe_rays = [_keyframe_from_record(r, mapper.backend) for r in state["keyframe_frames"]]
    if "observed" in state:
        mapper.observed.load_state_dict(state["observed"])
    else:  # saved before observed cells were kept: rebuild them from the keyframes' depth
        for rays in mapper.keyframe_rays:
            mapper.observed.add(mapper.octree, rays.voxel_points(1))
    mapper.thumbnails = list(state["thumbnails"])
    mapper.trajectory = list(state["trajectory"])
    mapper.frames_done = int(state["frames_done"])
    mapper.max_depth_m = float(state["max_depth_m"])
    mapper.rng.set_state(state["rng"])
    mapper.touched = np.ones(mapper.octree.n_voxels, dtype=bool)
    return mapper, state["extra"]
