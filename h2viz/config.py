"""Configuration: dataclasses with a docstring per field, strict YAML loading, dotted overrides.

Every field is documented by the string literal that follows it (read by `field_docs`). `mapping` is grouped by
stage (mapping.sampling.rays_per_iter); each name is unique across its groups. Loading is strict: an unknown key is
an error that names the key, the file and the closest valid key, and so is a key given twice in one mapping (which
PyYAML would silently take the last of). A flat mapping key of earlier versions (mapping.rays_per_iter) is still
read, with a FutureWarning naming its new place.
"""

from __future__ import annotations

import ast
import dataclasses
import difflib
import inspect
import textwrap
import typing
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import resources
from importlib.resources.abc import Traversable
from pathlib import Path
from typing import Any, TypeVar

import yaml

from h2viz.errors import ConfigError

T = TypeVar("T")

CONFIG_DIR: Traversable = resources.files("h2viz") / "configs"
"""The configuration files shipped inside the package (in a clone, `configs/` at the root is the same folder)."""
SOURCE_CONFIGS = ("synthetic", "replica", "scannet", "tum", "7scenes", "rosbag")
"""Formats with a per-source file in CONFIG_DIR (their intrinsics, depth range, keyframe IoU...)."""


@dataclass
class IntrinsicsConfig:
    fx: float = 0.0
    """Focal length x in pixels (0 = take from the data, or the format's default)."""
    fy: float = 0.0
    """Focal length y in pixels (0 = take from the data, or the format's default)."""
    cx: float = 0.0
    """Principal point x in pixels."""
    cy: float = 0.0
    """Principal point y in pixels."""

    def is_set(self) -> bool:
        return self.fx > 0 and self.fy > 0


@dataclass
class SyntheticConfig:
    seed: int = 0
    """Random seed of the procedural room, its textures and the trajectory."""
    width: int = 640
    """Rendered image width in pixels."""
    height: int = 480
    """Rendered image height in pixels."""
    n_frames: int = 300
    """Number of frames along the hand-held-like trajectory."""
    depth_noise_m: float = 0.0
    """Standard deviation of Gaussian noise added to every valid depth pixel, metres (0 = exact depth)."""
    fov_deg: float = 70.0
    """Horizontal field of view of the virtual camera, degrees."""
    prefetch: int = 4
    """Frames rendered ahead in a background thread (0 = render on demand)."""
    cache: bool = True
    """Keep rendered frames on disk (~0.36 MB a 640x480 frame) and read them back in later runs of the same room:
    reading takes ~4 ms, rendering ~0.2 s. Real-time playback renders the frames it will play first, once."""
    cache_dir: str = ""
    """Folder of the frame cache (empty = $H2VIZ_CACHE_DIR, else $XDG_CACHE_HOME/h2viz or ~/.cache/h2viz); safe to
    delete at any time."""
    recipe: str = ""
    """YAML file with the room's palettes (empty = assets/synthetic_room.yaml, shipped with h2viz: copy and edit it)."""


@dataclass
class TumConfig:
    preset: str = "auto"
    """Intrinsics preset: auto (from the folder name), fr1, fr2 or fr3."""
    max_time_gap_s: float = 0.02
    """Largest timestamp gap allowed when associating colour, depth and pose."""


@dataclass
class RosbagConfig:
    rgb_topic: str = ""
    """Colour image topic (empty = discover by message type and name)."""
    depth_topic: str = ""
    """Depth image topic (empty = discover)."""
    camera_info_topic: str = ""
    """CameraInfo topic (empty = discover; intrinsics from source.intrinsics when there is none)."""
    pose_topic: str = ""
    """PoseStamped / Odometry / TransformStamped topic (empty = discover, else the tf tree)."""
    world_frame: str = "world"
    """tf frame that poses are expressed in, when poses come from /tf."""
    camera_frame: str = ""
    """tf frame of the camera (empty = the depth image's header.frame_id)."""
    body_frame: str = ""
    """Frame the poses describe when it is not the camera optical frame (empty = poses are the camera's)."""
    T_body_camera: list[float] = field(default_factory=list)
    """Fixed body->camera transform, 16 numbers row-major (empty = look it up in /tf_static)."""
    max_time_gap_s: float = 0.03
    """Largest gap between colour and depth stamps, and how far poses may be extrapolated."""
    max_pose_gap_s: float = 0.5
    """Largest interval between two pose samples that a frame's pose is interpolated across."""
    depth_scale: float = 0.001
    """Metres per unit of 16UC1 depth images."""


@dataclass
class SourceConfig:
    format: str = "auto"
    """auto | synthetic | replica | scannet | tum | 7scenes | rosbag."""
    path: str = ""
    """Dataset folder or bag file (empty = the built-in synthetic scene)."""
    stride: int = 1
    """Use every k-th frame."""
    max_frames: int = 0
    """Stop after this many frames (0 = all)."""
    depth_min_m: float = 0.05
    """Depth below this is treated as invalid."""
    depth_max_m: float = 10.0
    """Depth above this is treated as invalid."""
    downscale: int = 1
    """Integer factor to shrink colour, depth and intrinsics by (1 = full resolution)."""
    realtime: bool = False
    """Real-time mode: play the frames at their timestamps' own rate (a bag at its recorded rate), integrate every
    frame as it arrives and optimise in the time between frames (anytime.*), counting the frames integration cannot
    keep up with; `h2viz map --realtime` sets it, and the dashboard's Real-time toggle starts from it. Off: every
    frame is mapped with mapping.optimization.max_iters steps, as fast as mapping goes."""
    intrinsics: IntrinsicsConfig = field(default_factory=IntrinsicsConfig)
    """Camera intrinsics where the data has none (Replica) or to override them."""
    depth_scale: float = 0.0
    """Metres per depth unit in PNG files (0 = the format's default)."""
    synthetic: SyntheticConfig = field(default_factory=SyntheticConfig)
    """Built-in synthetic scene."""
    tum: TumConfig = field(default_factory=TumConfig)
    """TUM RGB-D specific options."""
    rosbag: RosbagConfig = field(default_factory=RosbagConfig)
    """ROS 1 / ROS 2 bag specific options."""


def _group(cls: Callable[[], T]) -> T:
    """A group of MappingConfig's settings, holding the group's defaults."""
    return field(default_factory=cls)


@dataclass(slots=True)
class RuntimeConfig:
    """Where and how the mapper runs: device, kernels, CPU threads and the random seed."""

    device: str = "auto"
    """auto (CUDA when present, else CPU) | cpu | cuda."""
    kernels: str = "auto"
    """auto: the fused numba kernels on the CPU (frame rays, samples, hash grids, prior, geometry decoder, rendering
    and losses) when numba imports, else pure torch; torch: always the pure-torch path (the reference)."""
    threads: int = 0
    """torch CPU threads (0 = all cores)."""
    seed: int = 0
    """Seed for ray sampling and parameter initialisation."""


@dataclass(slots=True)
class RepresentationConfig:
    """What the map is made of: octree voxels, SDF priors, the geometry hash grid and decoder
    (h2viz.mapping.field)."""

    voxel_size_m: float = 0.1
    """Edge of an octree leaf voxel."""
    truncation_m: float = 0.05
    """SDF truncation distance tr."""
    min_points_per_voxel: int = 10
    """A voxel is allocated only when more than this many depth points fall in it."""
    expansion: bool = True
    """Also allocate the neighbour across a face that a voxel's points hug (expanded voxels)."""
    priors: bool = True
    """Initialise corner SDF priors by projecting depth (off = zero priors, ablation)."""
    fine_priors: bool = True
    """Also fuse every frame's truncated projective SDF into a 1.25 cm lattice in each voxel (at 10 cm voxels;
    h2viz.mapping.field.fine_prior), which replaces the corner priors wherever frames reached it (false = the paper:
    corner priors written once). Held-out views, docs/heldout.md: +0.5 to +1.4 dB PSNR and 0.15-0.55 cm less depth
    error than the corner priors on all four sequences."""
    residual_bound: float = 2.0
    """Largest correction of the prior SDF by the hash grid, in truncation units: residual = b * tanh(r / b)
    (0 = unbounded; priors off = unbounded). The free-space loss pulls the SDF to tr in front of surfaces, and
    an unbounded residual carries that pull into unobserved parts of voxels as spurious surfaces."""
    hash_levels: int = 4
    """L: number of hash-grid levels."""
    hash_features: int = 2
    """F: features per level."""
    hash_log2_size: int = 19
    """log2 T: entries per level's hash table."""
    hash_scale: float = 2.0
    """Resolution ratio between adjacent levels."""
    hash_base_resolution_m: float = 0.1
    """Cell size of the coarsest level (the leaf voxel size by default)."""
    geo_hidden: int = 64
    """Width of the geometry decoder's hidden layer."""
    geo_layers: int = 1
    """Hidden layers of the geometry decoder."""


@dataclass(slots=True)
class ColorConfig:
    """The map's colour: colour priors, the colour hash grid and decoder (h2viz.mapping.field)."""

    color_prior: bool = True
    """Explicit colour priors: every frame's pixel colours averaged on a fine lattice in each voxel
    (h2viz.mapping.field.color_prior), the colour network learning the residual of their logit, as the hash grid
    learns the residual of the SDF priors (false = the paper: the network learns colour alone)."""
    color_prior_cells: int = 12
    """Lattice cells per voxel edge of the colour priors (12 = 0.83 cm apart at 10 cm voxels); memory grows with
    (cells + 1)^3 x 16 B a voxel: 12 kB at 8, 35 kB at 12, 79 kB at 16 (held-out PSNR, one run: 8 -> 12 gains
    1.1 dB on the synthetic room and 0.4 dB on 7-Scenes redkitchen, 12 -> 16 a further 0.1)."""
    color_hash_levels: int = 0
    """Levels of the colour hash grid (same coarsest cell and scale as the geometry grid's; 0 =
    representation.hash_levels): each added level is twice as fine, for texture detail finer than the geometry needs."""
    color_hash_log2_size: int = 0
    """log2 T of the colour hash grid's tables (0 = representation.hash_log2_size)."""
    color_hidden: int = 64
    """Width of the colour decoder's hidden layers."""
    color_layers: int = 2
    """Hidden layers of the colour decoder."""
    color_precision: str = "auto"
    """Colour decoder matrix products on the CPU: auto = bfloat16 where the CPU has native bfloat16 dot products
    (AVX512-BF16 or AMX; ~2.5x faster, parameters stay float32), else float32; float32 | bfloat16 force one."""


@dataclass(slots=True)
class SamplingConfig:
    """Where the field is trained: rays per step and the samples along them (h2viz.mapping.sampling)."""

    rays_per_iter: int = 4096
    """Rays sampled per iteration across the current frame and selected keyframes."""
    step_m: float = 0.01
    """Distance between samples along a ray inside allocated voxels."""
    band_m: float = 0.15
    """Training samples from this far in front of the measured depth to band_behind_m behind it: every step_m from
    tr in front of the depth..."""
    band_behind_m: float = 0.02
    """...to this far behind it (the paper: tr, 0.05), where the SDF loss acts. Behind a surface, a ray's distance
    to its hit overstates how deep a sample lies, and at edges the samples a grazing ray calls "inside" lie outside
    the object: a short band keeps them from fattening silhouettes (held-out depth L1 1.10 -> 0.77 cm on 100
    synthetic frames)..."""
    band_front_step_m: float = 0.05
    """...and every this far (rounded to tile the span) from band_m to tr in front of it, where only the
    free-space loss acts..."""
    free_samples: int = 24
    """...plus this many stratified free-space candidates per ray, kept where they fall in allocated voxels
    (-1 = instead sample every step_m of every allocated voxel the ray crosses, as the paper does)."""


@dataclass(slots=True)
class LossesConfig:
    """What the field is trained on: the four losses and their weights (h2viz.mapping.rendering.losses)."""

    rgb_loss: str = "l2"
    """Colour loss per ray: l2 = mean squared error, which learns colour faster from the same rays (+0.9 dB PSNR
    on the synthetic sequence and +0.8 dB on redkitchen_50 with volume-rendered colour); l1 = mean absolute error
    over the channels (the reference implementation's)."""
    w_rgb: float = 0.5
    """Weight of the colour loss."""
    w_depth: float = 1.0
    """Weight of the depth L1 loss."""
    w_fs: float = 10.0
    """Weight of the free-space loss."""
    w_sdf: float = 50000.0
    """Weight of the SDF loss inside the truncation band."""
    color_supervision: str = "none"
    """How the colour network is trained: none = not at all, colour is the colour priors' (color.color_prior;
    measured best on held-out views: the network's residual learned what one view saw and another did not, -0.3 dB on
    ICL-NUIM and -1.6 dB on redkitchen); surface = the colour field at each ray's measured surface point (camera +
    depth along the ray) against the pixel's colour, on a batch of its own (experimental.color_rays_per_iter rays,
    one colour evaluation a ray, none in the geometry batch); volume = the paper's volume-rendered colour of the
    geometry batch's rays."""


@dataclass(slots=True)
class OptimizationConfig:
    """How long and how fast the field is trained: steps per frame, learning rate, refinement."""

    max_iters: int = 10
    """Largest number of optimisation iterations per frame."""
    lr: float = 1e-2
    """Adam learning rate for priors, hash tables and decoders."""
    early_ending: bool = True
    """Stop a frame's optimisation when the loss exceeds its running mean twice in a row."""
    refine_iters: int = 0
    """h2viz map: after the last frame, this many more optimisation steps, each over K + 1 keyframes drawn at
    random, before meshing and evaluation (0 = none: the paper's online protocol). Sharpens colour and depth of
    a finished map for export; not counted in the per-frame times."""


@dataclass(slots=True)
class RenderingConfig:
    """How rendered images are made (dashboard, evaluation, exports; h2viz.mapping.rendering)."""

    render_temperature: float = 0.05
    """tau in the rendering weights sigmoid(s/tau)*sigmoid(-s/tau), s in truncation units."""
    render_surface: bool = True
    """Rendered images (dashboard, evaluation, exports) show each ray's first zero crossing of the SDF, with the
    colour there, under the mesher's rules (meshing.mesh_prior_band, mesh_observed_only): silhouettes as sharp as the
    mesh and nothing drawn where no depth was observed. false = the paper's volume rendering (weighted mean depth and
    colour over the samples near the surface), which smears depth across silhouettes."""
    color_views: int = 8
    """Rendered colour (dashboard, evaluation, fly-throughs) blends the images of this many stored views nearest
    the camera where they see the surface point, with lumigraph weights (h2viz.mapping.field.color_views): as sharp as
    the frames, and view-dependent; the colour field where no view sees it (0 = the colour field alone, the paper).
    Held-out views, one run: 7-Scenes redkitchen 24.7 -> 29.1 dB. Surface renders only (render_surface)."""
    color_views_mb: float = 512.0
    """Memory the stored views may take (1.3 MB a 640x480 view: colour, its half-resolution copy and depth); past
    it the view nearest another is retired (0 = unbounded)."""
    color_views_field: float = 0.3
    """Weight of the colour field's colour in the blend where views see a point: it averages every frame, so it
    evens out what a few views keep of noise and aliasing (synthetic room +0.8 dB over 0; redkitchen -0.8)."""


@dataclass(slots=True)
class KeyframesConfig:
    """Which frames are kept and optimised again (h2viz.mapping.keyframes)."""

    n_keyframes: int = 10
    """K: keyframes optimised together with the current frame."""
    keyframe_iou: float = 0.85
    """Insert a keyframe when IoU(voxels seen now, at the last keyframe) falls below this."""
    keyframe_max_gap: int = 100
    """Insert a keyframe at least every this many frames."""
    keyframe_strategy: str = "coverage"
    """coverage | random | overlap."""
    keyframe_budget_mb: float = 1024.0
    """Memory the keyframes may take (rays at 11 bytes a valid pixel, voxel lists, thumbnails), MB; past it the most
    redundant keyframe whose voxels other keyframes also saw is retired, else the largest one keeps every other
    pixel (down to 1/8), so every voxel stays seen by a keyframe (0 = unbounded). 1024 MB holds ~300 full 640x480
    keyframes."""


@dataclass(slots=True)
class MeshingConfig:
    """The mesh extracted from the field (h2viz.mapping.meshing)."""

    mesh_resolution: int = 8
    """Marching-cubes samples per leaf voxel edge."""
    mesh_prior_band: float = 3.0
    """Meshing and surface renders keep the prior's sign where the corner priors put a point more than this many
    truncation distances from their surface (0 = off; no effect with priors off): the residual may move the surface
    that far only within the band. Behind observed surfaces and in free space nothing constrains the residual, and
    hash collisions there would leave spurious sheets 5-10 cm from the surface. 1.5 cut thin structures the
    10 cm corner priors cannot hold (held-out depth L1 on ICL-NUIM 0.62 -> 0.57 cm with 3; Acc unchanged)."""
    mesh_observed_only: bool = True
    """Meshing leaves out faces with no measured depth within about 1-4 cm (no observed voxel/8 cell in the 3x3x3
    cells around them): behind observed surfaces and in gaps nobody saw into, priors and residual can close the
    gap with surfaces 3-7 cm in front of the true ones. Voxels at the edge of the view (corners without a prior)
    are meshed too, keeping faces only where depth fell in their own cell (false = mesh every zero crossing of the
    voxels whose corners all hold priors)."""
    chunk_voxels: int = 8
    """Leaf voxels per mesh-chunk edge (chunks are re-meshed only when touched)."""
    mesh_every: int = 0
    """Headless runs: re-extract changed mesh chunks every this many frames (0 = only at the end; the
    dashboard meshes at its own rate, viewer.mesh_update_hz)."""


@dataclass(slots=True)
class ExperimentalConfig:
    """Settings kept to reproduce measurements of alternatives that lost; the defaults are the measured best, and
    nothing here is meant to be turned in normal use."""

    fine_prior_residual: bool = False
    """With fine priors, the hash-grid residual corrects them too (default false: it corrects only the corner priors,
    where no frame reached the fine lattice; over fine priors it fattens every silhouette on held-out views, ICL-NUIM
    27.89 -> 26.83 dB)."""
    color_rays_per_iter: int = 16384
    """Rays of the colour batch per iteration with losses.color_supervision: surface."""


@dataclass(slots=True)
class MappingConfig:
    """H2-Mapping's settings, by stage. A key's name is unique across the groups (`updated` sets fields by name)."""

    runtime: RuntimeConfig = _group(RuntimeConfig)
    """Device, kernels, threads and seed."""
    representation: RepresentationConfig = _group(RepresentationConfig)
    """Voxels, SDF priors, the geometry hash grid and decoder."""
    color: ColorConfig = _group(ColorConfig)
    """Colour priors, the colour hash grid and decoder."""
    sampling: SamplingConfig = _group(SamplingConfig)
    """Training rays and samples."""
    losses: LossesConfig = _group(LossesConfig)
    """Loss terms and weights."""
    optimization: OptimizationConfig = _group(OptimizationConfig)
    """Optimisation steps, learning rate, refinement."""
    rendering: RenderingConfig = _group(RenderingConfig)
    """Rendered images: volume or surface, colour from stored views."""
    keyframes: KeyframesConfig = _group(KeyframesConfig)
    """Keyframe insertion, selection and memory budget."""
    meshing: MeshingConfig = _group(MeshingConfig)
    """Mesh extraction."""
    experimental: ExperimentalConfig = _group(ExperimentalConfig)
    """Alternatives that measured worse, kept for reproducing those measurements."""

    def updated(self, **fields: Any) -> MappingConfig:
        """A copy with the named fields changed, each found in its group: `cfg.updated(voxel_size_m=0.05,
        max_iters=3)`. TypeError names a field that no group has."""
        groups = {name: dataclasses.replace(getattr(self, name)) for name in _GROUP_NAMES}
        for name, value in fields.items():
            group = mapping_group(name)
            if group is None:
                raise TypeError(f"MappingConfig has no field {name!r}{_closest(name, sorted(_FIELD_GROUPS))}")
            setattr(groups[group], name, value)
        return MappingConfig(**groups)


def _group_fields() -> dict[str, str]:
    hints = typing.get_type_hints(MappingConfig)
    return {f.name: g.name for g in dataclasses.fields(MappingConfig) for f in dataclasses.fields(hints[g.name])}


_GROUP_NAMES = tuple(f.name for f in dataclasses.fields(MappingConfig))
_FIELD_GROUPS = _group_fields()
"""Each mapping field's group: {"voxel_size_m": "representation", ...} (the names are unique across the groups)."""


def mapping_group(name: str) -> str | None:
    """The group of MappingConfig that holds field `name` (None when no group has it)."""
    return _FIELD_GROUPS.get(name)


@dataclass
class EvalConfig:
    n_points: int = 200_000
    """Points sampled from each mesh for Acc / Comp."""
    threshold_m: float = 0.05
    """Distance under which a ground-truth point counts as completed."""
    cull_to_observed: bool = True
    """Keep only ground truth inside what the input frames observed."""
    n_interpolate: int = 20
    """Training views rendered for PSNR/SSIM/depth L1 ("interpolate"), spread over the frames the run mapped (with
    another stride, or frames dropped in real time, the views differ: compare such runs with bench/heldout.py)."""
    n_extrapolate: int = 20
    """Novel views away from the trajectory ("extrapolate"), placed from the poses of the frames the run mapped."""
    render_downscale: int = 2
    """Evaluate renders at 1/k of the input resolution."""
    cull_margin_m: float = 0.05
    """Ground truth further than this behind the measured depth of every frame counts as unobserved."""
    extrapolate_min_offset_m: float = 0.5
    """Shortest move of an extrapolated camera away from the trajectory camera it starts from."""
    extrapolate_max_offset_m: float = 1.0
    """Longest move of an extrapolated camera away from the trajectory camera it starts from."""
    extrapolate_min_distance_m: float = 0.4
    """Closest an extrapolated camera may be to any trajectory camera."""
    seed: int = 0
    """Seed of mesh point sampling and of extrapolated camera placement."""


@dataclass
class ViewerConfig:
    host: str = "127.0.0.1"
    """Address to bind; 127.0.0.1 keeps the dashboard local."""
    port: int = 8080
    """Port of the dashboard."""
    mesh_update_hz: float = 4.0
    """Largest rate of mesh updates sent to browsers (and, in real-time mode while frames arrive, of mesh jobs:
    at 2 Hz a mesh change reached the browser 0.61 s after its frame (median, p90 1.09 s), at 4 Hz 0.47 s (p90
    0.76 s), with as many frames integrated; docs/anytime.md)."""
    render_width: int = 640
    """Width of refined novel-view renders (moving renders use a quarter)."""
    live_mesh_resolution: int = 4
    """Marching-cubes samples per leaf voxel edge of the live mesh (2.5 cm cells: a quarter of the triangles
    and an eighth of the field evaluations of mapping.meshing.mesh_resolution = 8, which mesh downloads use)."""
    stream_mesh_resolution: int = 3
    """While a real-time stream arrives, the live mesh is extracted at most at this resolution (3.3 cm cells;
    0 = no cap): on two cores a live mesh job at 4 took ~2x as long, and mesh changes reached a client 0.95-1.4 s
    after their frame (median) instead of 0.6-0.95 s (docs/anytime.md). The live resolution (live_mesh_resolution,
    or the dashboard's slider) returns when the stream ends or pauses; each switch re-meshes every chunk once."""
    start_paused: bool = False
    """Open with mapping paused."""
    record_fps: float = 10.0
    """Recorded steps (mapped frames) per second of replay at 1x speed, and of exported HTML."""
    video_width: int = 640
    """Width of fly-through videos rendered from the map (the height follows the camera's aspect)."""
    video_fps: int = 30
    """Frames per second of fly-through videos."""


@dataclass
class AutosaveConfig:
    every_frames: int = 50
    """Write the run folder's autosave.pt (h2viz map and the dashboard) after every this many mapped frames
    (0 = not by frames; real-time runs count time alone while their stream plays). A killed run loses at most this
    many frames: `h2viz map --resume RUN_FOLDER`."""
    every_s: float = 120.0
    """... or when this many seconds passed since the last autosave, whichever comes first (0 = not by time)."""


@dataclass
class AnytimeConfig:
    """Real-time mode (dashboard toggle, `h2viz map --realtime`, source.realtime): every frame that arrives
    is integrated (voxels, SDF and colour priors, keyframe decision) and optimisation runs in the time between
    frames, then goes on after the stream ends until the loss stops improving (h2viz.mapping.anytime)."""

    opt_share: float = 0.25
    """Least share of the mapping thread's time that optimisation keeps while frames wait to be integrated and
    integration is not catching up (see catch_up_frames; with no frame waiting, optimisation has all of it)."""
    backlog_frames: int = 60
    """Frames that may wait to be integrated; a frame arriving when this many wait is dropped and counted (the
    stream outruns integration itself). Two seconds at 30 Hz: where a camera first sees much of a room, integration
    on two cores with the dashboard can fall 40-50 frames behind before it catches up (the synthetic room's frames
    100-160), and a one-second backlog dropped 9-20 of them in some runs. A frame that waits is still integrated;
    under a load that never lets integration catch up, the map then lags the camera by up to this many frames."""
    catch_up_frames: int = 3
    """With this many frames waiting, integration takes every turn until fewer wait (optimisation's share waits),
    so that a stream integration alone keeps up with loses no frame; a frame then waits at most about this many
    frame times plus a step."""
    plateau_window: int = 50
    """After the stream: optimisation steps per window whose mean loss is compared with the best so far..."""
    plateau_patience: int = 3
    """...and windows in a row without improvement after which optimisation stops (the map has settled)..."""
    plateau_tol: float = 0.005
    """...where improving means a window mean below the best so far by this fraction."""
    sharpen_max_s: float = 600.0
    """Longest optimisation after the stream ends, seconds (0 = none: stop at the stream's end)."""
    color_points: int = 40_000
    """Pixels of each frame splatted into the colour prior (every k-th valid one; every-frame mode takes 160k):
    at 30 Hz consecutive frames see the same surfaces, so a quarter of each still fills the lattices, for ~10 ms
    a frame less."""
    observed_points: int = 30_000
    """Depth points of each frame that mark observed cells for meshing (every-frame mode takes 60k)."""
    fine_prior_stride: int = 4
    """While other frames wait to be integrated, a frame fuses its depth into the fine SDF prior lattices of the
    voxels it allocates only, and every fine_prior_stride-th frame into every lattice in view (1 = every frame
    into every lattice, as every-frame mode). With no frame waiting every frame is fused whole. At 30 Hz
    consecutive frames see nearly the same surfaces, and fine-prior fusion is about half of a frame's integration:
    integration that falls behind catches up ~40 % faster. At 4 rather than 2, `h2viz map --realtime` (224 of 300
    frames thinned instead of 149) ended with the same Acc / Comp (1.01 / 1.04 cm) and PSNR (32.67 vs 32.70 dB).
    In the dashboard, where the GIL limits integration more than its own work does, alternating runs on two cores
    integrated 99-103 of 150 frames at 4 against 77-88 at 2 in one set and 80-92 against 71-83 in another (with
    other changes, docs/anytime.md)."""


@dataclass
class Config:
    source: SourceConfig = field(default_factory=SourceConfig)
    """Where frames come from."""
    mapping: MappingConfig = field(default_factory=MappingConfig)
    """H2-Mapping's settings, grouped by stage (configs/paper.yaml: the paper's own)."""
    eval: EvalConfig = field(default_factory=EvalConfig)
    """Evaluation against ground truth."""
    viewer: ViewerConfig = field(default_factory=ViewerConfig)
    """The live dashboard."""
    autosave: AutosaveConfig = field(default_factory=AutosaveConfig)
    """Periodic checkpoints of a run, to resume after a crash."""
    anytime: AnytimeConfig = field(default_factory=AnytimeConfig)
    """Real-time mode's scheduling of integration and optimisation."""
    out_dir: str = ""
    """Output folder of a run (empty = outputs/<source>-<time>)."""


# --------------------------------------------------------------------------------------------- docs


def field_docs(cls: type) -> dict[str, str]:
    """Map each field of dataclass `cls` to the string literal written under it."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0].body  # type: ignore[attr-defined]
    docs: dict[str, str] = {}
    for stmt, nxt in zip(body, body[1:], strict=False):
        if isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name):
            if isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant):
                docs[stmt.target.id] = str(nxt.value.value)
    return docs


# ------------------------------------------------------------------------------------------ loading


def _closest(key: str, valid: list[str], nested: dict[str, str] | None = None, prefix: str = "") -> str:
    """A hint for an unknown key: the closest valid key, or the closest field of a group below (`nested`: each such
    field's name -> its dotted path, e.g. voxel_size_m -> mapping.representation.voxel_size_m); `prefix` is the
    dotted path of the valid keys' level."""
    nested = nested or {}
    match = difflib.get_close_matches(key, [*valid, *nested], n=1, cutoff=0.4)
    if match:
        return f"; did you mean '{nested.get(match[0], prefix + match[0])}'?"
    return f"; valid keys: {', '.join(sorted(valid))}"


def _nested_fields(obj: Any, prefix: str) -> dict[str, str]:
    """The fields of the dataclasses held by dataclass `obj`, by name -> dotted path (one level down)."""
    return {
        f.name: f"{prefix}{group.name}.{f.name}"
        for group in dataclasses.fields(obj)
        if dataclasses.is_dataclass(getattr(obj, group.name))
        for f in dataclasses.fields(getattr(obj, group.name))
    }


def _coerce(value: Any, typ: Any, where: str) -> Any:
    origin = typing.get_origin(typ)
    if typ is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false", "1", "0", "yes", "no", "on", "off"):
            return value.lower() in ("true", "1", "yes", "on")
        raise ConfigError(f"{where}: expected true/false, got {value!r}")
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, int | str):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        try:
            return int(value)
        except ValueError as e:
            raise ConfigError(f"{where}: expected an integer, got {value!r}") from e
    if typ is float:
        if isinstance(value, bool):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        try:
            return float(value)
        except (TypeError, ValueError) as e:
            raise ConfigError(f"{where}: expected a number, got {value!r}") from e
    if typ is str:
        if isinstance(value, dict | list):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return "" if value is None else str(value)
    if origin is list:
        if isinstance(value, str):
            value = yaml.safe_load(value)
        if not isinstance(value, list):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        (item,) = typing.get_args(typ)
        return [_coerce(v, item, f"{where}[{i}]") for i, v in enumerate(value)]
    raise ConfigError(f"{where}: unsupported field type {typ}")


def _merge(obj: Any, data: dict[str, Any], origin: str, prefix: str = "", moved: list[str] | None = None) -> None:
    """Write `data` into dataclass `obj` in place, strictly; `origin` names the file or override. A mapping key of
    the flat layout before the groups (mapping.color_views) is written to its group's field and listed in `moved` as
    "old -> new" (an error when `moved` is None)."""
    if not isinstance(data, dict):
        raise ConfigError(f"{origin}: '{prefix or '<top>'}' must be a mapping of keys to values, got {data!r}")
    hints = typing.get_type_hints(type(obj))
    names = [f.name for f in dataclasses.fields(obj)]
    for key, value in data.items():
        dotted = f"{prefix}{key}"
        group = mapping_group(str(key)) if isinstance(obj, MappingConfig) else None
        if key not in names and group is not None:
            new = f"{prefix}{group}.{key}"
            if moved is None:
                raise ConfigError(f"{origin}: '{dotted}' is now '{new}'")
            moved.append(f"{dotted} -> {new}")
            _merge(obj, {group: {key: value}}, origin, prefix, moved)
            continue
        if key not in names:
            hint = _closest(str(key), names, _nested_fields(obj, prefix), prefix)
            raise ConfigError(f"{origin}: unknown key '{dotted}'{hint}")
        current = getattr(obj, key)
        if dataclasses.is_dataclass(current):
            _merge(current, value or {}, origin, f"{dotted}.", moved)
        else:
            setattr(obj, key, _coerce(value, hints[key], f"{origin}: {dotted}"))


def _merge_warning_moved(obj: Any, data: dict[str, Any], origin: str) -> None:
    """_merge, with one FutureWarning per file or override that still uses flat mapping keys."""
    moved: list[str] = []
    _merge(obj, data, origin, moved=moved)
    if moved:
        warnings.warn(
            f"{origin}: mapping's settings are grouped now; read as {', '.join(moved)}. Flat keys will stop "
            "working in a later version: write the new keys (h2viz config --docs lists them)",
            FutureWarning,
            stacklevel=3,
        )


class _StrictLoader(yaml.SafeLoader):
    """yaml.safe_load that refuses a key repeated within one mapping (PyYAML keeps the last one silently)."""


class _RepeatedKey(yaml.YAMLError):
    pass


def _mapping_without_repeats(loader: _StrictLoader, node: yaml.MappingNode) -> dict[Any, Any]:
    lines: dict[Any, int] = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node)  # type: ignore[no-untyped-call]
        line = key_node.start_mark.line + 1
        if key in lines:
            raise _RepeatedKey(f"key '{key}' is repeated (lines {lines[key]} and {line}); keep one of them")
        lines[key] = line
    return loader.construct_mapping(node)


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _mapping_without_repeats)


def parse_yaml(text: str) -> Any:
    """yaml.safe_load, except that a key repeated within one mapping is a yaml.YAMLError."""
    return yaml.load(text, Loader=_StrictLoader)  # noqa: S506 (a SafeLoader)


def load_yaml(path: str | Path | Traversable) -> dict[str, Any]:
    path = Path(path) if isinstance(path, str) else path
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist; pass an existing YAML file to --config")
    try:
        data = parse_yaml(path.read_text()) or {}
    except _RepeatedKey as e:
        raise ConfigError(f"{path}: {e}") from e
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML ({e})") from e
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: the top level must be a mapping of sections (source:, mapping:, ...)")
    return data


def apply_file(cfg: Config, path: str | Path | Traversable) -> Config:
    """Merge one YAML file into `cfg` (strict: unknown and repeated keys are errors naming the file)."""
    _merge_warning_moved(cfg, load_yaml(path), str(path))
    return cfg


def apply_overrides(cfg: Config, overrides: list[str]) -> Config:
    """Apply `section.key=value` overrides, e.g. `mapping.optimization.max_iters=5`."""
    for item in overrides:
        if "=" not in item:
            raise ConfigError(
                f"override '{item}' must look like section.key=value, e.g. mapping.optimization.max_iters=5"
            )
        dotted, raw = item.split("=", 1)
        parts = dotted.strip().split(".")
        try:
            nested: Any = parse_yaml(raw) if raw.strip() else ""
        except yaml.YAMLError as e:
            raise ConfigError(f"override '{item}': the value is not valid YAML ({e})") from e
        for part in reversed(parts):
            nested = {part: nested}
        _merge_warning_moved(cfg, nested, f"override '{item}'")
    return cfg


def packaged_config(name: str) -> Traversable:
    """A configuration file shipped with h2viz (e.g. "default", "paper", "replica"); ConfigError when it is missing
    (an incomplete installation)."""
    path = CONFIG_DIR / f"{name}.yaml"
    if not path.is_file():
        raise ConfigError(
            f"h2viz's configuration file {name}.yaml is missing from {CONFIG_DIR}; the installation is incomplete: "
            "reinstall h2viz (pip install --force-reinstall h2viz, or pip install -e . in a clone)"
        )
    return path


def source_config_file(fmt: str) -> Traversable | None:
    """The per-source override file shipped for a format (None for formats without one, e.g. auto)."""
    return packaged_config(fmt) if fmt in SOURCE_CONFIGS else None


def load_config(
    files: list[str | Path | Traversable] | None = None, overrides: list[str] | None = None
) -> Config:
    """Defaults <- the packaged default.yaml <- each file in order <- dotted overrides."""
    cfg = Config()
    apply_file(cfg, packaged_config("default"))
    for f in files or []:
        apply_file(cfg, f)
    return apply_overrides(cfg, overrides or [])


def to_dict(cfg: Any) -> dict[str, Any]:
    return dataclasses.asdict(cfg)


def dump_config(cfg: Config, path: str | Path) -> None:
    """Write the resolved configuration as YAML (loadable again with --config)."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(yaml.safe_dump(to_dict(cfg), sort_keys=False))


def from_dict(data: dict[str, Any]) -> Config:
    cfg = Config()
    _merge(cfg, data, "config")
    return cfg


def mapping_from_dict(data: dict[str, Any], origin: str = "checkpoint") -> MappingConfig:
    """The MappingConfig of `to_dict(cfg.mapping)`, or of the flat layout that came before the groups (checkpoints
    written by earlier versions), strictly otherwise."""
    cfg = MappingConfig()
    _merge(cfg, data, origin, "mapping.", moved=[])
    return cfg


DEFAULTS_HEADER = (
    "# h2viz defaults (configs/paper.yaml holds the paper's own settings). Every key is documented in\n"
    "# h2viz/config.py and listed by `h2viz config --docs`. Files passed with --config and per-source files in\n"
    "# this folder override it.\n"
    "# Regenerate after changing a default: python -c 'from h2viz.config import write_defaults; write_defaults()'\n"
)


def write_defaults(path: str | Path | None = None) -> None:
    """Write configs/default.yaml (the packaged defaults) from the dataclass defaults."""
    target = Path(str(CONFIG_DIR / "default.yaml") if path is None else path)
    target.write_text(DEFAULTS_HEADER + yaml.safe_dump(to_dict(Config()), sort_keys=False))
