"""What the worker does for viewer Commands: novel-view renders cut into row bands (so they can be
interleaved with mapping), mesh export to bytes, checkpoint saving and live settings changes."""

from __future__ import annotations

import time
from collections.abc import Callable, Generator
from concurrent.futures import Future, InvalidStateError
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from h2viz.errors import H2vizError
from h2viz.types import RenderMode, check_pose
from h2viz.worker.feed import WorkerSettings

if TYPE_CHECKING:
    from h2viz.mapping.mapper import Mapper

RENDER_BAND_PIXELS = 160 * 120  # renders are cut into row bands of about this many pixels
EXPORT_FORMATS = ("ply", "glb")
DEPTH_MODES = (RenderMode.DEPTH.value, RenderMode.PRIOR.value)


@dataclass(frozen=True)
class RenderedView:
    """Reply to a render Command: the image in the requested mode and, on request, its depth."""

    image: np.ndarray  # rgb | normal: (H,W,3) float32; depth | prior: (H,W) float32 metres
    depth_m: np.ndarray | None  # (H,W) float32 z-depth, 0 = nothing; None unless with_depth
    mode: str
    seconds: float  # mapper time spent on this render


def settle(future: Future[Any], value: Any = None, error: BaseException | None = None) -> None:
    """Resolve `future` unless it was cancelled meanwhile."""
    try:
        if error is not None:
            future.set_exception(error)
        else:
            future.set_result(value)
    except InvalidStateError:
        pass


def _bands(mapper: Mapper, K: np.ndarray, T: np.ndarray, height: int, width: int, mode: str, out: list) -> Any:
    """Render one image in row bands of about RENDER_BAND_PIXELS, appending each band to `out`;
    yields the seconds each band took."""
    rows = max(1, RENDER_BAND_PIXELS // width)
    for r0 in range(0, height, rows):
        t0 = time.perf_counter()
        K_band = K.copy()
        K_band[1, 2] -= r0  # the band is the image rows [r0, r0 + h)
        band = mapper.render(K_band, T, min(rows, height - r0), width, mode)
        out.append(np.asarray(band, dtype=np.float32))
        yield time.perf_counter() - t0


def scaled_intrinsics(K: np.ndarray, factor: int) -> np.ndarray:
    """K (3,3) of the same camera with images `factor` times smaller (pixel centres kept aligned)."""
    K = K.copy()
    K[:2, :2] /= factor
    K[:2, 2] = (K[:2, 2] + 0.5) / factor - 0.5
    return K


def render_bands(mapper: Mapper, args: dict[str, Any]) -> Generator[None, None, RenderedView]:
    """Render args K, T_world_camera, height, width, mode one row band per step. With `with_depth`,
    also the z-depth, at 1/`depth_downscale` resolution (default 1) upsampled by repetition."""
    K = np.asarray(args["K"], dtype=np.float64).reshape(3, 3)
    T_world_camera = check_pose(args["T_world_camera"], "render request")
    height, width = int(args["height"]), int(args["width"])
    mode = str(args.get("mode", RenderMode.RGB.value))
    modes = [m.value for m in RenderMode]
    if mode not in modes:
        raise H2vizError(f"render: unknown mode '{mode}'; use one of {', '.join(modes)}")
    if not (0 < height <= 8192 and 0 < width <= 8192):
        raise H2vizError(f"render: image size {width}x{height} must be between 1 and 8192 pixels a side")
    images: list[np.ndarray] = []
    spent = 0.0
    for seconds in _bands(mapper, K, T_world_camera, height, width, mode, images):
        spent += seconds
        yield
    image = np.concatenate(images, axis=0)
    depth_m = None
    if args.get("with_depth", False):
        depth_m = image if mode in DEPTH_MODES else None
        s = max(1, int(args.get("depth_downscale", 1)))
        if depth_m is None:
            h, w = -(-height // s), -(-width // s)
            depths: list[np.ndarray] = []
            for seconds in _bands(mapper, scaled_intrinsics(K, s), T_world_camera, h, w, "depth", depths):
                spent += seconds
                yield
            depth_m = np.repeat(np.repeat(np.concatenate(depths, axis=0), s, axis=0), s, axis=1)[:height, :width]
    return RenderedView(image, depth_m, mode, spent)


def export_mesh_bytes(mapper: Mapper, fmt: str, resolution: int | None = None) -> bytes:
    """The welded map mesh as PLY or GLB bytes, at `resolution` marching-cubes samples per voxel edge
    (default: the live mesh's)."""
    fmt = fmt.lower().lstrip(".")
    if fmt not in EXPORT_FORMATS:
        raise H2vizError(f"export: unknown mesh format '{fmt}'; use one of {', '.join(EXPORT_FORMATS)}")
    data = mapper.mesh(resolution).export(file_type=fmt)
    return data if isinstance(data, bytes) else str(data).encode()


def save_checkpoint(mapper: Mapper, path: str | Path, extra: dict[str, Any] | None = None) -> str:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if hasattr(mapper, "save_checkpoint"):
        mapper.save_checkpoint(path)
    else:
        from h2viz.mapping.checkpoint import save_checkpoint as save

        save(mapper, path, extra)
    return str(path)


def prepare_checkpoint(mapper: Mapper, extra: dict[str, Any] | None = None) -> Callable[[Path], object]:
    """`save_checkpoint` in two halves: the mapping state taken now, and what writes it on any thread (see
    h2viz.mapping.checkpoint.prepare_checkpoint)."""
    if hasattr(mapper, "save_checkpoint"):  # a mapper that writes itself
        return lambda path: save_checkpoint(mapper, path, extra)
    from h2viz.mapping.checkpoint import prepare_checkpoint as prepare

    return prepare(mapper, extra)


MAPPER_SETTINGS = {"mesh_resolution": int, "mesh_observed_only": bool}
"""Settings that live on the mapper (the live mesh's resolution and face filter); changing one re-meshes."""


def apply_settings(settings: WorkerSettings, mapper: Mapper, args: dict[str, Any]) -> bool:
    """Write `args` into `settings` (and MAPPER_SETTINGS into the mapper); True when the mesh must be
    re-extracted. Unknown keys or bad values raise H2vizError before anything changes."""
    types: dict[str, type] = {f.name: type(getattr(settings, f.name)) for f in fields(settings)}
    types.update(MAPPER_SETTINGS)
    for key in args:
        if key not in types:
            raise H2vizError(f"set: unknown setting '{key}'; valid settings: {', '.join(sorted(types))}")
    if any(types[k] is bool and not isinstance(v, bool) for k, v in args.items()):
        raise H2vizError(f"set: {', '.join(k for k in args if types[k] is bool)} must be true or false, got {args}")
    try:
        values = {k: types[k](v) for k, v in args.items()}
    except (TypeError, ValueError) as e:
        raise H2vizError(f"set: bad value in {args} ({e})") from e
    if values.get("stride", 1) < 1 or values.get("mesh_resolution", 2) < 2:
        raise H2vizError(f"set: stride must be >= 1 and mesh_resolution >= 2, got {args}")
    remesh = False
    for key, value in values.items():
        if key in MAPPER_SETTINGS:
            remesh |= value != getattr(mapper, key)
            setattr(mapper, key, value)
        else:
            setattr(settings, key, value)
    return remesh


def settings_reply(settings: WorkerSettings, mapper: Mapper) -> dict[str, Any]:
    return {**asdict(settings), **{k: t(getattr(mapper, k)) for k, t in MAPPER_SETTINGS.items()}}
