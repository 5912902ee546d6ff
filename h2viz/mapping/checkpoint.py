"""Checkpoints: everything a run needs to continue (octree, priors, field, optimiser, keyframes, trajectory)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from h2viz.config import MappingConfig, mapping_from_dict
from h2viz.errors import CheckpointError, ConfigError
from h2viz.mapping import checkpoint_format
from h2viz.mapping.backend import Backend
from h2viz.mapping.field.color_prior import compact_sums
from h2viz.mapping.field.color_views import StoredView
from h2viz.mapping.keyframes.budget import BudgetReport
from h2viz.mapping.mapper import Mapper
from h2viz.mapping.sampling.rays import FrameRays
from h2viz.types import RgbdFrame

FORMAT_VERSION = 2
"""2: only tensors, arrays and plain data, loaded with torch.load(weights_only=True); 1: pickled NumPy objects."""
REQUIRED_KEYS = (
    "format_version config octree priors_init priors field optim net_optim keyframes keyframe_frames thumbnails "
    "trajectory frames_done max_depth_m rng"
).split()


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
    """Write the whole mapping state to `path` (a .pt file), atomically; `extra` holds plain data only."""
    prepare_checkpoint(mapper, extra)(Path(path))


def prepare_checkpoint(mapper: Mapper, extra: dict[str, Any] | None = None) -> Callable[[Path], None]:
    """Take the mapping state as it is now (on the mapping thread) and return what writes it to a path, on any
    thread: an autosave while a live stream goes on writes in the background. Taking it copies no lattice, keyframe
    or network: what changes size (octree, corner priors, keyframe lists, lattices) is replaced when it grows, so
    the references taken stay as they are. The lattices' running sums and the networks' parameters are read when
    written: a write that overlaps later frames may hold some of their fusion and steps (a resumed run integrates
    those frames again, adding them to its averages twice); voxels, keyframes and frame counts are those of now."""
    color = None if mapper.field.color_prior is None else mapper.field.color_prior.sums  # (V,P,4), read later
    fine = None if mapper.field.fine_prior is None else mapper.field.fine_prior.state  # (V,P,2), read later
    views = tuple(mapper.color_views.views)  # immutable; JPEG-encoded by the write (once a view)
    state = {
        "format_version": FORMAT_VERSION,
        "config": dataclasses.asdict(mapper.cfg),
        "octree": mapper.octree.state_dict(),
        "priors_init": {k: np.array(v) for k, v in mapper.priors.state_dict().items()},  # written in place
        "observed": {k: np.array(v) for k, v in mapper.observed.state_dict().items()},  # written in place
        "priors": mapper.field.priors.detach().cpu().clone(),
        "field": {k: v.cpu() for k, v in mapper.field.state_dict().items()},
        "optim": mapper.optim.state_dict(),
        "net_optim": mapper.net_optim.state_dict(),
        "keyframes": mapper.keyframes.state_dict(),
        "keyframe_frames": [_keyframe_record(r) for r in mapper.keyframe_rays],
        "thumbnails": list(mapper.thumbnails),
        "keyframe_thinning": list(mapper.keyframe_budget.thinning),
        "keyframe_budget": dataclasses.asdict(mapper.keyframe_budget.report),
        "trajectory": np.asarray(mapper.trajectory).reshape(-1, 4, 4),
        "frames_done": mapper.frames_done,
        "max_depth_m": mapper.max_depth_m,
        "rng": mapper.rng.get_state(),
        "extra": extra or {},
    }

    def write(path: Path) -> None:
        lattices = {
            "color_prior": None if color is None else compact_sums(color),  # ~1 lattice point in 8 holds colour
            "fine_prior": None if fine is None else fine.cpu().clone(),  # its rows alone, not the storage behind
            "color_views": [view.record() for view in views],
        }
        checkpoint_format.write({**state, **lattices}, Path(path))

    return write


def load_checkpoint(path: Path, cfg: MappingConfig | None = None) -> tuple[Mapper, dict[str, Any]]:
    """Rebuild a Mapper from a checkpoint; returns it and the checkpoint's `extra` dict."""
    path = Path(path)
    state = _read_state(path)
    try:
        return _restore(state, cfg)
    except CheckpointError as e:
        raise CheckpointError(f"{path}: {e}") from None
    except (KeyError, TypeError, ValueError, IndexError, RuntimeError, AttributeError) as e:
        raise CheckpointError(
            f"{path} is damaged or inconsistent ({type(e).__name__}: {e}); resume from another checkpoint"
        ) from None


def peek_checkpoint(path: Path) -> tuple[int, dict[str, Any]]:
    """A checkpoint's frames mapped and its `extra`, checked as load_checkpoint checks them but without rebuilding
    the map (its tensors stay in the file): what the dashboard's offer to resume an earlier run shows."""
    state = _read_state(Path(path), mmap=True)
    try:
        return int(state["frames_done"]), dict(state.get("extra") or {})
    except (TypeError, ValueError) as e:
        raise CheckpointError(f"{path} is damaged ({type(e).__name__}: {e}); resume from another checkpoint") from None


def _read_state(path: Path, mmap: bool = False) -> dict[str, Any]:
    """A checkpoint's decoded state, of this format and with every part a map needs, or a CheckpointError."""
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist; pass the checkpoint.pt of an earlier run")
    state = checkpoint_format.read(path, mmap)
    version = state.get("format_version")
    if version != FORMAT_VERSION:
        raise CheckpointError(f"{path} has checkpoint format {version}, expected {FORMAT_VERSION}; map the run again")
    missing = [key for key in REQUIRED_KEYS if key not in state]
    if missing:
        raise CheckpointError(f"{path} is incomplete: it lacks {', '.join(missing)}; resume from another checkpoint")
    return state


def _restore(state: dict[str, Any], cfg: MappingConfig | None) -> tuple[Mapper, dict[str, Any]]:
    """A Mapper rebuilt from a checkpoint's decoded state."""
    try:
        saved = mapping_from_dict(state["config"])
    except ConfigError as e:
        raise CheckpointError(f"its settings do not load in this version ({e})") from None
    if cfg is not None:  # runtime-only settings may change on resume; the map's geometry may not
        rep, col = saved.representation, saved.color
        saved = cfg.updated(
            voxel_size_m=rep.voxel_size_m,
            truncation_m=rep.truncation_m,
            hash_levels=rep.hash_levels,
            hash_features=rep.hash_features,
            hash_log2_size=rep.hash_log2_size,
            hash_scale=rep.hash_scale,
            color_hash_levels=col.color_hash_levels,
            color_hash_log2_size=col.color_hash_log2_size,
            geo_hidden=rep.geo_hidden,
            geo_layers=rep.geo_layers,
            color_hidden=col.color_hidden,
            color_layers=col.color_layers,
            color_prior=col.color_prior,
            fine_priors=rep.fine_priors,
            priors=rep.priors,
        )
    mapper = Mapper(saved)
    mapper.octree.load_state_dict(state["octree"])
    mapper.priors.load_state_dict(state["priors_init"])
    mapper.field.sync(mapper.octree)
    mapper.field.load_state_dict(state["field"])
    mapper.field.priors = state["priors"].to(mapper.device).requires_grad_(saved.representation.priors)
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
    if mapper.color_views.enabled:  # saved before views were kept: renders use the colour field alone
        mapper.color_views.replace(tuple(StoredView.from_record(r) for r in state.get("color_views", [])))
    budget = mapper.keyframe_budget
    budget.thinning = [int(t) for t in state.get("keyframe_thinning", [0] * len(mapper.keyframe_rays))]
    budget.report = BudgetReport(**state.get("keyframe_budget", {}))
    mapper.trajectory = list(state["trajectory"])
    mapper.frames_done = int(state["frames_done"])
    mapper.max_depth_m = float(state["max_depth_m"])
    mapper.rng.set_state(state["rng"])
    mapper.touched = np.ones(mapper.octree.n_voxels, dtype=bool)
    return mapper, dict(state.get("extra") or {})


def upgrade_checkpoint(path: Path, out: Path | None = None) -> Path:
    """Re-save a format-1 checkpoint in this format (default: next to it, as <name>.v2.pt); returns the new path.
    The old file is read without running code: only NumPy's array reconstruction is allowed besides tensors."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    state = checkpoint_format.read_legacy(path)
    if state.get("format_version") not in (1, FORMAT_VERSION):
        raise CheckpointError(f"{path} has checkpoint format {state.get('format_version')}, which cannot be upgraded")
    out = Path(out) if out is not None else path.with_suffix(".v2.pt")
    checkpoint_format.write({**state, "format_version": FORMAT_VERSION}, out)
    load_checkpoint(out)  # it must load now
    return out
