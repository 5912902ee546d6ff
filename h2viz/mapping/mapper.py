"""The H2-Mapping pipeline: one call of `Mapper.integrate` maps one posed RGB-D frame."""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np
import torch
import trimesh

from h2viz.config import MappingConfig
from h2viz.errors import ConfigError
from h2viz.mapping import warmup
from h2viz.mapping.backend import Backend, resolve_backend
from h2viz.mapping.field.color_views import ColorViews, StoredView
from h2viz.mapping.field.copy_pool import CopyPool
from h2viz.mapping.field.corner_prior import PriorInitializer
from h2viz.mapping.field.hybrid_field import HybridField
from h2viz.mapping.field.octree import Allocation, VoxelOctree
from h2viz.mapping.keyframes.budget import KeyframeBudget, keyframe_bytes
from h2viz.mapping.keyframes.keyframe_set import KeyframeSet
from h2viz.mapping.meshing.job import FrozenField, MeshJob
from h2viz.mapping.meshing.mesher import ChunkedMesher, export_mesh, merge_chunks
from h2viz.mapping.meshing.observed import ObservedCells
from h2viz.mapping.optim import GrowingAdam
from h2viz.mapping.rendering.images import RenderParams, SurfaceColor, locate, render_image
from h2viz.mapping.rendering.losses import check_color_settings, color_error, mapping_losses
from h2viz.mapping.rendering.volume import composite, live_samples, render_weights
from h2viz.mapping.sampling.rays import FrameRays, RayBatch, sample_frames
from h2viz.mapping.sampling.samples import BandLayout, Samples, band_samples, sample_rays
from h2viz.timing import StageTimer
from h2viz.types import FrameStats, KeyframeInfo, MeshChunk, RgbdFrame

AHEAD_KEPT = 32  # frames prepared ahead that wait for add_frame, at most (a full 30-frame backlog: ~220 MB)
OBSERVED_POINTS = 60_000
"""Depth points a frame marks observed cells with (every k-th valid one): a fifth of a 640x480 frame, which at
70 deg stays about as dense as the 1.25 cm cells up to 3 m away, for ~4 ms a frame instead of ~15."""

COLOR_POINTS = 160_000
"""Pixels a frame adds to the colour prior (every k-th valid one): about half of a 640x480 frame, still several
pixels a 1.25 cm lattice cell up to 4 m away at 70 deg, for ~15 ms a frame instead of ~30."""


ArrayT = TypeVar("ArrayT", np.ndarray, torch.Tensor)


INTEGRATION_STAGES = (
    "prepare", "voxels", "corner_priors", "fine_prior", "color_prior", "color_views", "observed", "keyframes",
)  # fmt: skip
"""The parts of integrating a frame that `FrameStats.timings` holds (seconds), in order: preparing it (`Mapper.prepare`;
~0 when a reader thread prepared it ahead), allocating its voxels (and growing the tables), projecting new corners'
priors, fusing the fine SDF lattices (with a fine prior), splatting the colour prior, storing its colour view,
marking observed cells, and the keyframe decision."""

THUMBNAIL_HEIGHT = 72
"""Keyframe thumbnails' height in pixels (the dashboard's keyframe frustums show them)."""


def keyframe_thumbnail(rgb: np.ndarray) -> np.ndarray:
    """(THUMBNAIL_HEIGHT,w,3) uint8 area-averaged picture of rgb (H,W,3), w keeping its aspect. Halved 2x2 first
    while at least twice the size (exact box averages: ~0.5 ms for 640x480 instead of ~1.8 in one resize)."""
    h = THUMBNAIL_HEIGHT
    w = max(1, round(rgb.shape[1] * h / rgb.shape[0]))
    while rgb.shape[0] >= 2 * h and rgb.shape[1] >= 2 * w:
        rgb = cv2.resize(rgb, (rgb.shape[1] // 2, rgb.shape[0] // 2), interpolation=cv2.INTER_AREA)
    return cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)


def every_kth(rows: ArrayT, n: int, frame_index: int) -> ArrayT:
    """At most `n` of a frame's per-pixel rows (P,...) (points, colours): every k-th, starting at frame_index mod k.
    Frames in a row start at other pixels: with a fixed start, every frame of a 640-pixel-wide image would sample
    the same columns."""
    k = max(1, -(-len(rows) // max(1, n)))
    return rows[frame_index % k :: k]


@dataclass(frozen=True)
class PreparedFrame:
    """What integrating a frame computes from the frame alone, before it touches the map: a reader thread may
    compute it while the mapping thread integrates the frame before (`Mapper.prepare_ahead`)."""

    frame: RgbdFrame
    rays: FrameRays  # its valid pixels, for training
    points: np.ndarray  # (P,3) float32 their world points
    voxel_keys: np.ndarray  # (n,) int64 voxels to allocate (> min_points points, and expanded neighbours)
    hit_keys: np.ndarray  # (m,) int64 every voxel a point falls in
    thumbnail: np.ndarray  # (THUMBNAIL_HEIGHT,w,3) uint8 its picture, should it become a keyframe
    view: StoredView | None  # its colour as the view store keeps it (None: no store)


class Mapper:
    """Octree SDF priors + hash-grid residual field, optimised frame by frame with coverage keyframes."""

    def __init__(self, cfg: MappingConfig) -> None:
        check_color_settings(cfg.losses.rgb_loss, cfg.losses.color_supervision, cfg.color.color_prior)
        self.cfg = cfg
        self.surface_color = cfg.losses.color_supervision == "surface"  # colour learned on a batch of its own
        self.volume_color = cfg.losses.color_supervision == "volume"  # colour learned in the geometry batch
        self.geometry_cfg = cfg if self.volume_color else cfg.updated(w_rgb=0.0)  # the geometry batch's losses
        self.backend: Backend = resolve_backend(cfg.runtime.kernels, cfg.runtime.device)  # chosen once, for every stage
        self.device = self.backend.device
        if cfg.runtime.threads > 0:
            torch.set_num_threads(cfg.runtime.threads)
        torch.manual_seed(cfg.runtime.seed)
        self.rng = torch.Generator().manual_seed(cfg.runtime.seed)
        rep, kf, views, mesh = cfg.representation, cfg.keyframes, cfg.rendering, cfg.meshing
        self.voxel_size_m = rep.voxel_size_m
        arrays = self.backend.array_kernels
        cells = None if arrays is None else arrays.octree.cell_stats
        self.octree = VoxelOctree(rep.voxel_size_m, rep.min_points_per_voxel, rep.expansion, cells)
        self.priors = PriorInitializer(rep.truncation_m, rep.priors)
        self.observed = ObservedCells(rep.voxel_size_m, self.backend)  # where depth was measured, for meshing
        self.field = HybridField(cfg, self.backend).to(self.device)
        self.field.priors = self.field.priors.to(self.device).requires_grad_(rep.priors)
        self.optim = self._make_optimiser()
        self.keyframes = KeyframeSet(
            kf.n_keyframes, kf.keyframe_iou, kf.keyframe_max_gap, kf.keyframe_strategy, cfg.runtime.seed
        )
        self.keyframe_rays: list[FrameRays] = []
        self.thumbnails: list[np.ndarray] = []
        self.keyframe_budget = KeyframeBudget(kf.keyframe_budget_mb)  # retires / thins keyframes past the budget
        self.color_views = ColorViews(views.color_views, views.color_views_mb, views.color_views_field)  # rendering
        self.copy_pool = CopyPool()  # memory for the frozen fields of mesh jobs, reused job after job
        self.mesher = ChunkedMesher(rep.voxel_size_m, mesh.mesh_resolution, mesh.chunk_voxels, self.backend)
        self._mesh_resolution, self._mesh_resolution_cap = self.mesher.resolution, 0  # see mesh_resolution
        self.touched = np.zeros(0, dtype=bool)  # (V,) voxels allocated or observed since the last mesh job
        self.trajectory: list[np.ndarray] = []
        self.frames_done = 0
        self.version = 0
        self.max_depth_m = 0.0
        self._live: tuple[int, FrameRays, np.ndarray, list[FrameRays] | None] | None = None
        """The newest frame `add_frame` integrated: index, rays, observed voxels and, once selected, the frames its
        live steps sample (it and its keyframes)."""
        self._live_timer = StageTimer()  # stage seconds of live and refinement steps
        self.on_iteration: Callable[[], None] | None = None
        """Called on the mapping thread after every optimisation step, where the field is consistent: the
        dashboard hands a waiting mesh update over there instead of at the end of the frame."""
        self._ahead: OrderedDict[int, PreparedFrame] = OrderedDict()  # frames prepared ahead, by index
        self._ahead_lock = threading.Lock()

    def _make_optimiser(self) -> GrowingAdam:
        """Adam for the growing corner priors (ours) and for hash tables and decoders (torch's fused one:
        a dense step over both 2^19-entry tables costs ~4 ms on CPU, less than a lazy update of the few
        hundred thousand rows a step touches, whose random accesses cost ~15x more per row)."""
        opt = GrowingAdam(self.cfg.optimization.lr, backend=self.backend)
        if self.cfg.representation.priors:
            opt.add("priors", lambda: self.field.priors, sparse=True)  # only corners with gradient move
        one_pass = {"fused": True} if self.device.type in ("cpu", "cuda") else {}  # torch's single-kernel Adam
        self.net_optim = torch.optim.Adam(
            self.field.parameters(), lr=self.cfg.optimization.lr, betas=(0.9, 0.99), eps=1e-15, **one_pass
        )
        return opt

    # ----------------------------------------------------------------------------------- pipeline
    def integrate(self, frame: RgbdFrame) -> FrameStats:
        """Map one frame (every-frame mode, the paper's protocol): integrate it, then up to max_iters steps on it
        and its coverage-selected keyframes."""
        start = time.perf_counter()
        timer = StageTimer()
        rays, alloc = self._integrate_frame(frame, timer)
        with timer("keyframes"):
            selected = self.keyframes.select(alloc.observed, frame.index)  # coverage-maximising K keyframes
        frames = [rays, *(self.keyframe_rays[i] for i in selected)]
        iters, losses = self._optimise(frames, timer)  # at most max_iters, early ending
        self._finish_frame(frame, alloc)
        return self._frame_stats(frame, start, iters, losses, timer)

    def add_frame(
        self,
        frame: RgbdFrame,
        color_points: int = COLOR_POINTS,
        observed_points: int = OBSERVED_POINTS,
        fuse_all: bool = True,
    ) -> FrameStats:
        """Integrate one frame without optimising (real-time mode): rays, voxel allocation, SDF priors, colour
        prior (from up to `color_points` of its pixels), observed cells (up to `observed_points`) and the keyframe
        decision. Its geometry is in the map when this returns; `live_step` optimises it afterwards, as often as
        time allows. `fuse_all=False` fuses its depth into the fine lattices of the voxels it allocates only (see
        anytime.fine_prior_stride)."""
        start = time.perf_counter()
        timer = StageTimer()
        rays, alloc = self._integrate_frame(frame, timer, color_points, observed_points, fuse_all)
        self._live = (frame.index, rays, alloc.observed, None)  # keyframes selected at its first step
        self._finish_frame(frame, alloc)
        return self._frame_stats(frame, start, 0, {}, timer)

    def prepare(self, frame: RgbdFrame) -> PreparedFrame:
        """The part of integrating `frame` that depends on it alone: rays, world points, voxels to allocate, its
        keyframe thumbnail and the view the colour store would keep."""
        rays, points = FrameRays.with_points(frame, self.backend)  # valid depth -> rays, world points (P,3)
        keys, hit_keys = self.octree.candidate_voxels(points)  # voxels with > min_points points (+ neighbours)
        view = self.color_views.view_of(frame) if self.color_views.enabled else None
        return PreparedFrame(frame, rays, points, keys, hit_keys, keyframe_thumbnail(frame.rgb), view)

    def prepare_ahead(self, frame: RgbdFrame) -> None:
        """(a reader thread) `prepare` the frame now, for `add_frame` to take (the newest `AHEAD_KEPT` are kept),
        so that the mapping thread integrates it ~25 % faster while a core is free. The calling thread runs its
        kernels on one core from then on (`Backend.serial_thread`): it is not the mapping thread."""
        self.backend.serial_thread()  # a thread-local setting: cheap to repeat
        prepared = self.prepare(frame)
        with self._ahead_lock:
            self._ahead[frame.index] = prepared
            while len(self._ahead) > AHEAD_KEPT:  # frames dropped from the backlog are never taken
                self._ahead.popitem(last=False)

    def _prepared(self, frame: RgbdFrame) -> PreparedFrame:
        """The frame prepared ahead, else prepared now."""
        with self._ahead_lock:
            ahead = self._ahead.pop(frame.index, None)
        return ahead if ahead is not None and ahead.frame is frame else self.prepare(frame)

    def warm_up(self) -> float:
        """Load the compiled kernels this map's configuration runs (see `warmup`), before a live stream starts;
        the seconds it took (0 when they were loaded before). The map itself is not touched."""
        return warmup.once(repr(self.cfg), lambda: Mapper(self.cfg)._run_every_stage(warmup.scratch_frame()))

    def _run_every_stage(self, frame: RgbdFrame) -> None:
        """Integrate `frame` in both modes, take a live step, mesh the map whole and update that mesh."""
        self.add_frame(frame)
        self.live_step()
        self.integrate(frame)  # every-frame mode: the same stages with its own steps
        for whole in (True, False):  # a whole mesh, then a live update against it
            self.touched[:] = True
            job = self.mesh_job(0.03, whole=whole)
            assert job is not None  # voxels were touched
            job.run()

    def live_step(self) -> float:
        """One optimisation step on the newest frame `add_frame` integrated plus the K keyframes coverage selects
        for it (selected at its first step); its voxels are marked for re-meshing. Without a frame from `add_frame`
        (a map built in every-frame mode, or restored), a `refine_step`. Returns the loss (NaN without keyframes)."""
        if self._live is None:
            return self.refine_step()
        index, rays, observed, frames = self._live
        if frames is None:
            selected = self.keyframes.select(observed, index)
            frames = [rays, *(self.keyframe_rays[i] for i in selected)]
            self._live = (index, rays, observed, frames)
        loss = float(self._step(frames, self._live_timer)["total"])
        self.touched[observed] = True
        return loss

    def refine_step(self) -> float:
        """One step on rays from K + 1 keyframes drawn at random (what `refine` runs, and real-time mode after the
        stream); marks every voxel for re-meshing. Returns the loss (NaN without keyframes)."""
        n_keyframes = len(self.keyframe_rays)
        n_frames = min(self.cfg.keyframes.n_keyframes + 1, n_keyframes)
        if n_frames == 0:
            return float("nan")
        picked = torch.randperm(n_keyframes, generator=self.rng)[:n_frames]  # the ray sampler's generator
        loss = float(self._step([self.keyframe_rays[i] for i in picked.tolist()], self._live_timer)["total"])
        self.touched[:] = True
        return loss

    def refine(self, iterations: int, on_step: Callable[[], None] | None = None) -> int:
        """Optimise the finished map `iterations` more steps, each on rays from K + 1 keyframes drawn at random
        (no early ending; `on_step` after each), and mark every voxel for re-meshing. Returns the steps taken (0
        without keyframes)."""
        done = 0
        while done < iterations and self.keyframe_rays:
            self.refine_step()
            done += 1
            if on_step is not None:
                on_step()
        return done

    def _integrate_frame(
        self,
        frame: RgbdFrame,
        timer: StageTimer,
        color_points: int = COLOR_POINTS,
        observed_points: int = OBSERVED_POINTS,
        fuse_all: bool = True,
    ) -> tuple[FrameRays, Allocation]:
        """What a frame adds to the map before any optimisation; inserts it as a keyframe when the rule says so.
        The timer gets each part's seconds (INTEGRATION_STAGES)."""
        with timer("prepare"):
            prepared = self._prepared(frame)  # rays, world points (P,3) and the voxels they fill
            rays, points = prepared.rays, prepared.points
        with timer("voxels"):
            alloc = self.octree.allocate_candidates(prepared.voxel_keys, prepared.hit_keys)
            self._grow(alloc.new_voxels)  # corners, priors and tables follow the octree
        # project new corners and the fine lattices (all in view, or the new voxels') into the depth image
        self._init_priors(frame, timer, None if fuse_all else alloc.new_voxels)
        with timer("color_prior"):
            self._add_colors(points, rays, color_points, frame.index)  # averages of pixel colours
        with timer("color_views"):
            self.color_views.add(frame, prepared.view)  # renders take colour from the nearest stored views
        with timer("observed"):
            self.observed.add(self.octree, every_kth(points, observed_points, frame.index))  # meshing
        with timer("keyframes"):
            if self.keyframes.should_insert(frame.index, alloc.observed):  # IoU / max-gap rule
                self._add_keyframe(frame, rays, alloc.observed, prepared.thumbnail)
        return rays, alloc

    def _finish_frame(self, frame: RgbdFrame, alloc: Allocation) -> None:
        self.touched[np.concatenate([alloc.new_voxels, alloc.observed])] = True  # re-meshed by the next mesh job
        self.trajectory.append(frame.T_world_camera)
        self.frames_done += 1
        self.max_depth_m = max(self.max_depth_m, float(frame.depth_m.max(initial=0.0)))
        if self.cfg.meshing.mesh_every > 0 and self.frames_done % self.cfg.meshing.mesh_every == 0:
            self.update_mesh()

    def _frame_stats(
        self, frame: RgbdFrame, start: float, iters: int, losses: dict[str, float], timer: StageTimer
    ) -> FrameStats:
        return FrameStats(
            index=frame.index,
            map_time_s=time.perf_counter() - start,
            iterations=iters,
            n_voxels=self.octree.n_voxels,
            n_keyframes=len(self.keyframes),
            keyframe_mb=self.keyframe_mb,
            view_mb=self.color_views.nbytes / 1e6,
            losses=losses,
            timings=timer.seconds,
        )

    def _grow(self, new_voxels: np.ndarray) -> None:
        self.field.sync(self.octree)
        if self.field.fine_prior is not None:  # new voxels' faces start from their older neighbours'
            self.field.fine_prior.share_faces(new_voxels, self.octree.face_neighbours(new_voxels))
        self.priors.grow(self.octree.n_corners, new_voxels)
        self.touched = np.concatenate([self.touched, np.zeros(self.octree.n_voxels - self.touched.size, bool)])

    def _add_colors(self, points: np.ndarray, rays: FrameRays, color_points: int, frame_index: int) -> None:
        """Splat the colours of up to `color_points` of the frame's valid pixels (every k-th, see `every_kth`)
        into the colour prior."""
        if self.field.color_prior is None:
            return
        rgb_u8 = every_kth(rays.rgb, color_points, frame_index).cpu().numpy()  # (P/k,3) uint8 (NumPy: ~10x faster)
        rgb = torch.from_numpy(rgb_u8.astype(np.float32) / np.float32(255.0)).to(self.device)
        self.field.add_colors(torch.from_numpy(every_kth(points, color_points, frame_index)).to(self.device), rgb)

    @torch.no_grad()
    def _init_priors(self, frame: RgbdFrame, timer: StageTimer, fine_voxels: np.ndarray | None = None) -> None:
        with timer("corner_priors"):
            cids, vals = self.priors.initialize(self.octree, frame.depth_m, frame.K, frame.T_world_camera)
            if cids.size:
                self.field.priors[torch.from_numpy(cids).to(self.device)] = torch.from_numpy(vals).to(self.device)
        if self.field.fine_prior is not None:
            with timer("fine_prior"):
                self.field.fine_prior.fuse(
                    self.field.voxel_origin, frame.depth_m, frame.K, frame.T_world_camera, fine_voxels
                )

    def _add_keyframe(self, frame: RgbdFrame, rays: FrameRays, observed: np.ndarray, thumbnail: np.ndarray) -> None:
        self.keyframes.insert(frame.index, observed)
        self.keyframe_rays.append(rays)
        self.thumbnails.append(thumbnail)
        self.keyframe_budget.fit(self.keyframes, self.keyframe_rays, self.thumbnails)

    @property
    def keyframe_mb(self) -> float:
        """Memory of the keyframes (rays, voxel lists, thumbnails), MB."""
        return keyframe_bytes(self.keyframes, self.keyframe_rays, self.thumbnails) / 1e6

    def _batch(self, frames: list[FrameRays]) -> RayBatch:
        n = max(1, self.cfg.sampling.rays_per_iter // len(frames))
        return sample_frames(frames, n, self.rng, self.backend)

    def _optimise(self, frames: list[FrameRays], timer: StageTimer) -> tuple[int, dict[str, float]]:
        """Up to max_iters Adam steps; stop when the loss exceeds its running mean twice in a row."""
        history: list[float] = []
        above = 0
        terms: dict[str, torch.Tensor] = {}
        for it in range(self.cfg.optimization.max_iters):
            terms = self._step(frames, timer)
            if self.on_iteration is not None:
                self.on_iteration()
            loss = float(terms["total"])
            above = above + 1 if history and loss > float(np.mean(history)) else 0
            history.append(loss)
            if self.cfg.optimization.early_ending and above >= 2:
                return it + 1, {k: float(v) for k, v in terms.items()}
        return self.cfg.optimization.max_iters, {k: float(v) for k, v in terms.items()}

    def _samples(self, frames: list[FrameRays]) -> tuple[Samples, RayBatch]:
        """A batch of rays and their samples: the truncation band plus free space, or the paper's dense march."""
        c = self.cfg
        batch = self._batch(frames)
        if c.sampling.free_samples < 0:  # every 1 cm of every allocated voxel the ray crosses
            far = batch.depth + c.sampling.band_behind_m
            return sample_rays(
                self.octree, batch.origins, batch.dirs, far, c.sampling.step_m, True, backend=self.backend
            ), batch
        layout = BandLayout(
            c.sampling.band_m,
            c.representation.truncation_m,
            c.sampling.step_m,
            c.sampling.band_front_step_m,
            c.sampling.free_samples,
            c.sampling.band_behind_m,
        )
        samples = band_samples(self.octree, batch.origins, batch.dirs, batch.depth, layout, self.rng, self.backend)
        return samples, batch

    def _step(self, frames: list[FrameRays], timer: StageTimer) -> dict[str, torch.Tensor]:
        """One Adam step on the four losses over a batch of rays from `frames`; colour is evaluated only where the
        render weights matter."""
        with timer("sampling"):
            samples, batch = self._samples(frames)
        if samples.t.numel() == 0:
            return {"total": torch.zeros(())}
        with timer("forward"):
            sdf = self.field.sdf(samples.points, samples.voxel)  # (S,) truncation units
            terms = self._losses(samples, sdf, batch)
            if self.surface_color:
                terms["rgb"] = self._surface_color_loss(frames)
                terms["total"] = terms["total"] + terms["rgb"]
        with timer("backward"):
            self.optim.zero_grad()
            self.net_optim.zero_grad()
            terms["total"].backward()
        with timer("optimiser"):
            self.optim.step()
            self.net_optim.step()
        return {k: v.detach() for k, v in terms.items()}

    def _surface_color_loss(self, frames: list[FrameRays]) -> torch.Tensor:
        """The colour loss of a batch of its own: the colour field at each ray's measured surface point (camera +
        depth along the z-normalised ray) against the pixel's colour; gradients reach only the colour branch."""
        n = max(1, self.cfg.experimental.color_rays_per_iter // len(frames))
        batch = sample_frames(frames, n, self.rng, self.backend)
        points = batch.origins + batch.dirs * batch.depth[:, None]  # (R,3)
        rgb = self.field.color(points)  # (R,3)
        return self.cfg.losses.w_rgb * color_error(rgb, batch.rgb, self.cfg.losses.rgb_loss == "l2")

    def _losses(self, samples: Samples, sdf: torch.Tensor, batch: RayBatch) -> dict[str, torch.Tensor]:
        """Render the batch and take the four losses (colour evaluated only where the weights matter, not at all when
        colour has a batch of its own): the backend's fused kernels (h2viz.mapping.kernels.loss_numba), else the torch
        functions they reproduce."""
        cfg = self.geometry_cfg
        color = self.field.color if self.volume_color else self._no_color
        kernels = self.backend.cpu_kernels(sdf)
        if kernels is not None:
            return kernels.loss.mapping_losses(samples, sdf, color, batch.rgb, batch.depth, cfg)
        tr, tau = cfg.representation.truncation_m, cfg.rendering.render_temperature
        weights = render_weights(samples, sdf, tr, tau)  # (S,)
        live = live_samples(samples, weights)  # (S',)
        render = composite(samples, weights, color(samples.points[live]), live)  # colour (S',3) of the live samples
        return mapping_losses(samples, sdf, render, batch.rgb, batch.depth, cfg)

    @staticmethod
    def _no_color(points: torch.Tensor) -> torch.Tensor:
        """A constant colour (N,3) without gradient, for a geometry batch whose colour is not learned."""
        return torch.zeros(points.shape[0], 3, device=points.device)

    # ------------------------------------------------------------------------------------- outputs
    @torch.no_grad()
    def sdf_m(self, points: np.ndarray) -> np.ndarray:
        """SDF in metres (N,) at world points (N,3) inside allocated voxels (NaN elsewhere)."""
        out = np.full(points.shape[0], np.nan, dtype=np.float32)
        for i in range(0, points.shape[0], 65536):
            p = torch.from_numpy(np.ascontiguousarray(points[i : i + 65536], dtype=np.float32)).to(self.device)
            vid = locate(self.octree, p)
            ok = vid >= 0
            s = torch.full((p.shape[0],), float("nan"), device=self.device)
            s[ok] = self.field.sdf(p[ok], vid[ok]) * self.cfg.representation.truncation_m
            out[i : i + 65536] = s.cpu().numpy()
        return out

    @torch.no_grad()
    def color_u8(self, points: np.ndarray) -> np.ndarray:
        """Colour (N,3) uint8 of the field at world points (N,3)."""
        parts = []
        for i in range(0, points.shape[0], 65536):
            p = torch.from_numpy(np.ascontiguousarray(points[i : i + 65536], dtype=np.float32)).to(self.device)
            parts.append((self.field.color(p) * 255.0).round().clamp(0, 255).to(torch.uint8).cpu().numpy())
        return np.concatenate(parts) if parts else np.zeros((0, 3), np.uint8)

    @property
    def mesh_observed_only(self) -> bool:
        """Mesh only near measured depth (mapping.meshing.mesh_observed_only); changing it re-meshes every chunk."""
        return self.cfg.meshing.mesh_observed_only

    @mesh_observed_only.setter
    def mesh_observed_only(self, value: bool) -> None:
        self.cfg.meshing.mesh_observed_only = bool(value)

    @property
    def mesh_resolution(self) -> int:
        """Marching-cubes cells per voxel edge of the live mesh, as chosen (the mesher works at
        min(it, `mesh_resolution_cap`) while a cap is set)."""
        return self._mesh_resolution

    @mesh_resolution.setter
    def mesh_resolution(self, value: int) -> None:
        self._set_mesh_resolution(int(value), self._mesh_resolution_cap)

    @property
    def mesh_resolution_cap(self) -> int:
        """Largest resolution the live mesh is extracted at for now (0 = none; a real-time stream's)."""
        return self._mesh_resolution_cap

    @mesh_resolution_cap.setter
    def mesh_resolution_cap(self, value: int) -> None:
        self._set_mesh_resolution(self._mesh_resolution, int(value))

    @property
    def meshing_resolution(self) -> int:
        """The resolution the live mesh is extracted at now (`mesh_resolution` under its cap)."""
        return self.mesher.resolution

    def _set_mesh_resolution(self, resolution: int, cap: int) -> None:
        if cap < 0:
            raise ConfigError(f"mesh resolution cap must be >= 0 (0 = none), got {cap}")
        self.mesher.resolution = min(resolution, cap) if cap > 0 else resolution  # checks the range first
        self._mesh_resolution, self._mesh_resolution_cap = resolution, cap

    def mesh_job(self, refresh_s: float = 0.0, whole: bool = False) -> MeshJob | None:
        """Freeze what a mesh update needs, to run on any thread while mapping goes on: new voxels first, then
        for up to `refresh_s` seconds the voxels allocated or observed since the last job and the stalest
        chunks; `whole` re-meshes every chunk from the field now instead. None when nothing changed since
        everything was last meshed. A voxel at the edge of the view, whose corners do not all hold priors, would
        close the surface with a skirt where its unobserved corners meet observed ones: with `mesh_observed_only`
        its faces are kept only where depth was measured in their own 1.25 cm cell (measured surfaces there are
        kept, skirts are not), otherwise such voxels are not meshed."""
        if not self.touched.any() and self.mesher.stale(self.frames_done, self.cfg.meshing.mesh_observed_only) == 0:
            return None
        self.version += 1
        job = self._frozen_job(self.mesher, refresh_s, whole)
        self.touched[:] = False
        return job

    def _frozen_job(self, mesher: ChunkedMesher, refresh_s: float, whole: bool) -> MeshJob:
        initialised = self.priors.initialised(self.octree.n_voxels)  # (V,)
        support = None
        # every voxel; where priors are missing, faces need depth in their own cell
        if self.cfg.meshing.mesh_observed_only:
            meshable = np.arange(self.octree.n_voxels)
            support = self.observed.snapshot(self.octree, strict=~initialised)
        else:
            meshable = np.flatnonzero(initialised)  # (V',) voxel ids
        dirty = self.touched[meshable] & (not whole)
        band = self.cfg.meshing.mesh_prior_band if self.cfg.representation.priors else 0.0
        field = FrozenField(self.field, self.cfg.representation.truncation_m, band, self.backend, self.copy_pool)
        coords = self.octree.voxel_coords()[meshable]
        return MeshJob(
            mesher, coords, meshable, dirty, field, self.version, self.frames_done, refresh_s, whole, support
        )

    def update_mesh(self) -> None:
        """Re-mesh every chunk from the field now, on this thread, when anything changed since the last time."""
        job = self.mesh_job(whole=True)
        if job is not None:
            job.run()

    def mesh_chunks(self) -> dict[tuple[int, int, int], MeshChunk]:
        """The current mesh chunks (safe to call while a mesh job runs on another thread)."""
        return self.mesher.chunks

    def mesh(self, resolution: int | None = None) -> trimesh.Trimesh:
        """Welded mesh of the whole map, every chunk re-meshed from the current field first when needed.

        A `resolution` other than the live mesher's meshes the map once with a mesher of its own, leaving the
        live chunks as they are (a coarse live mesh, a full-resolution download)."""
        if resolution is None or int(resolution) == self.mesher.resolution:
            self.update_mesh()
            return merge_chunks(self.mesher.chunks)
        mesher = ChunkedMesher(
            self.cfg.representation.voxel_size_m, int(resolution), self.cfg.meshing.chunk_voxels, self.backend
        )
        return merge_chunks(self._frozen_job(mesher, 0.0, whole=True).run())

    def export_mesh(self, path: Path) -> None:
        export_mesh(self.mesh(), Path(path))

    def voxel_coords(self) -> np.ndarray:
        return self.octree.voxel_coords().astype(np.int32)

    def octree_levels(self, level: int) -> np.ndarray:
        return self.octree.level_coords(level).astype(np.int32)

    def keyframe_infos(self) -> tuple[KeyframeInfo, ...]:
        return tuple(
            KeyframeInfo(r.index, r.T_world_camera, r.K, r.shape[1], r.shape[0], thumb, state)
            for r, thumb, state in zip(self.keyframe_rays, self.thumbnails, self.keyframes.states(), strict=True)
        )

    def render(
        self, K: np.ndarray, T_world_camera: np.ndarray, height: int, width: int, mode: str = "rgb"
    ) -> np.ndarray:
        """Render any camera: rgb (H,W,3) [0,1], depth/prior (H,W) metres, normal (H,W,3) [-1,1]."""
        params = RenderParams.from_config(self.cfg, self.max_depth_m)
        trusted = None  # voxels whose 8 corners all hold a measured prior: there the priors locate the surface
        # the corner priors miss what only the fine one holds
        if self.cfg.representation.priors and self.field.fine_prior is None:
            trusted = torch.ones(self.octree.n_voxels, dtype=torch.bool)  # (V,) host-side: the walks read it
            trusted[torch.from_numpy(self.priors.pending)] = False
        support = self.drawable() if params.surface else None
        color = self._view_color(K, T_world_camera) if params.surface and mode == "rgb" else None
        args = (self.field, self.octree, K, T_world_camera, height, width, mode, params, trusted)
        return render_image(*args, support=support, backend=self.backend, surface_color=color)

    def _view_color(self, K: np.ndarray, T_world_camera: np.ndarray) -> SurfaceColor | None:
        """Colour of a render's surface points from the stored views nearest its camera (None: no views)."""
        views = self.color_views
        if not views.enabled or not views.views:
            return None

        def color(points: torch.Tensor, field_rgb: torch.Tensor) -> torch.Tensor:
            rgb = views.blend(points.cpu().numpy(), field_rgb.cpu().numpy(), T_world_camera, K)  # (N,3)
            return torch.from_numpy(rgb).to(field_rgb.device)

        return color

    def drawable(self) -> Callable[[np.ndarray], np.ndarray]:
        """Which world points (N,3) the mesher would draw a face at, (N,) bool: near observed depth (strictly in
        its own cell where a voxel's priors are incomplete) with mesh_observed_only, else in voxels whose corners
        all hold priors."""
        initialised = self.priors.initialised(self.octree.n_voxels)  # (V,)
        if self.cfg.meshing.mesh_observed_only:
            return self.observed.snapshot(self.octree, strict=~initialised).contains
        octree = self.octree

        def in_initialised(points: np.ndarray) -> np.ndarray:
            vid = locate(octree, torch.from_numpy(np.ascontiguousarray(points, dtype=np.float32))).cpu().numpy()
            return (vid >= 0) & initialised[np.maximum(vid, 0)]

        return in_initialised
