"""Held-out views: how well each method predicts frames it was never given, on the built-in synthetic room and
the real sequences in ../shared/data, in one markdown table.

Every k-th frame of a sequence (positions p with p % k == k // 2) is held out; all methods map the other frames,
fed the same frames in the same run:

- `h2viz`: h2viz's Mapper (configured as `h2viz map --data <sequence>` with every --set), rendering its field;
- `h2viz-mesh`: the same mapper's final mesh, ray cast (no second mapping run; same per-frame times);
- `tsdf`: Open3D TSDF fusion (1 cm voxels by default), its coloured mesh ray cast;
- each `--variant NAME=key=value,...`: h2viz with these mapping overrides, rendering its field (and its mesh as
  NAME-mesh with --variant-mesh).

Each held-out camera is rendered by every method at 1/--downscale and compared with the captured frame shrunk
the same way, on two sets of pixels: the method's own (captured and rendered depth valid) and the common ones
(captured depth valid and every method of the sequence rendered a depth), so that methods that leave holes are
compared on the pixels they all predict.

    .venv/bin/python bench/heldout.py                                        # all four sequences, every frame
    .venv/bin/python bench/heldout.py --datasets synthetic --frames 60 --set source.downscale=2 \\
        --variant l2=mapping.losses.rgb_loss=l2 --images /tmp/heldout               # a quick look, with mosaics
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np
import trimesh
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import (  # noqa: E402
    DATASETS,
    Dataset,
    command_line,
    dataset_config,
    fmt,
    markdown_table,
    pick,
    write_doc,
)
from bench.tsdf_baseline import TsdfConfig, TsdfFusion  # noqa: E402
from h2viz.config import Config, apply_overrides, load_config, parse_yaml  # noqa: E402
from h2viz.errors import H2vizError  # noqa: E402
from h2viz.eval.mesh_render import MeshRenderer  # noqa: E402
from h2viz.eval.metrics import depth_l1_cm, psnr, ssim  # noqa: E402
from h2viz.eval.report import EvalView, Renderer, render_view, shrink_view, write_metrics  # noqa: E402
from h2viz.mapping.mapper import Mapper  # noqa: E402
from h2viz.sources.base import make_source  # noqa: E402
from h2viz.types import RgbdFrame  # noqa: E402

METHODS = ("h2viz", "h2viz-mesh", "tsdf")
"""The methods --methods picks from; variants come on top."""
KNOWN_METHODS: dict[str, object] = dict.fromkeys(METHODS)

BAD_DEPTH_M = 0.05
"""A rendered depth further than this from the captured one counts as wrong (the ">5 cm" columns)."""

COLUMNS = ["sequence", "method", "mapped", "held out", "PSNR (dB)", "SSIM", "depth L1 (cm)", ">5 cm (%)"]
COLUMNS += ["own PSNR (dB)", "own depth L1 (cm)", "own >5 cm (%)", "coverage (%)", "signed (cm)", "median s/frame"]

LEGEND = """\
- held out: the frames at positions p with p % {k} == {offset}, given to no method; mapped: the frames each method
  was given. Every held-out camera is rendered at 1/--downscale and compared with the captured frame shrunk the
  same way; each number is the mean over the held-out views.
- PSNR, SSIM, depth L1, >5 cm: on the common pixels, where the captured depth is valid and every method of the
  sequence rendered a depth; >5 cm = share of those pixels whose depth is off by more than 5 cm.
- own: the same on the method's own rendered pixels; coverage = own pixels / pixels with captured depth;
  signed = mean rendered minus captured depth on them (negative: in front of the captured surface).
- h2viz and its variants render their field, *-mesh and tsdf ray cast their final mesh; s/frame = mapping time
  (h2viz, shared by its mesh) or integration time (tsdf)."""
"""What the table's columns mean, printed under it."""

Rendered = tuple[np.ndarray, np.ndarray]
"""One method's image of one view: rgb (h,w,3) float32 in [0,1], depth (h,w) metres (0 = nothing rendered)."""

Scores = dict[str, dict[str, float]]
"""One method on one view: {"own": metrics on its own pixels, "common": metrics on the pixels all methods rendered}."""


# --------------------------------------------------------------------------------------------- split


def is_heldout(position: int, k: int) -> bool:
    """Whether the frame at `position` of a sequence is held out: every k-th one, offset k // 2 (none for k <= 0)."""
    return k > 0 and position % k == k // 2


def heldout_split(n: int, k: int) -> tuple[list[int], list[int]]:
    """(mapped positions, held-out positions) of a sequence of n frames; together they are 0..n-1, once each."""
    held = [p for p in range(n) if is_heldout(p, k)]
    return [p for p in range(n) if not is_heldout(p, k)], held


def frame_view(frame: RgbdFrame) -> EvalView:
    """A captured frame as a view to score: (K, T_world_camera, rgb, depth_m)."""
    return frame.K, frame.T_world_camera, frame.rgb, frame.depth_m


# ------------------------------------------------------------------------------------------- scoring


def rendered_mask(depth: np.ndarray, gt_depth: np.ndarray) -> np.ndarray:
    """Pixels (h,w) where the captured depth and the rendered `depth` (h,w) are both valid."""
    return (gt_depth > 0) & (depth > 0) & np.isfinite(depth)


def common_mask(gt_depth: np.ndarray, depths: Iterable[np.ndarray]) -> np.ndarray:
    """Pixels (h,w) where the captured depth is valid and every one of `depths` (each (h,w)) rendered one."""
    mask = gt_depth > 0
    for depth in depths:
        mask = mask & rendered_mask(depth, gt_depth)
    return mask


def coverage_pct(mask: np.ndarray, gt_depth: np.ndarray) -> float:
    """Share (%) of the pixels with captured depth that `mask` (h,w) keeps; NaN when the capture has none."""
    captured = int(np.count_nonzero(gt_depth > 0))
    return 100.0 * np.count_nonzero(mask & (gt_depth > 0)) / captured if captured else math.nan


def pixel_scores(
    rgb: np.ndarray, depth: np.ndarray, gt_rgb: np.ndarray, gt_depth: np.ndarray, mask: np.ndarray
) -> dict[str, float]:
    """PSNR (dB), SSIM, depth L1 (cm), share of pixels whose depth is off by more than BAD_DEPTH_M (%) and mean
    signed depth error (cm, rendered minus captured: negative = in front of the captured surface) of one rendered
    view, rgb (h,w,3) and depth (h,w), over `mask` (h,w): pixels where both depths are valid (`rendered_mask` or
    `common_mask`); NaN where the mask is empty. coverage_pct: the mask's share of the captured pixels."""
    colour = np.clip(rgb, 0.0, 1.0)
    error_m = depth[mask].astype(np.float64) - gt_depth[mask].astype(np.float64)  # (P,)
    empty = len(error_m) == 0
    return {
        "psnr_db": psnr(colour, gt_rgb, mask),
        "ssim": ssim(colour, gt_rgb, mask),
        "depth_l1_cm": depth_l1_cm(depth, gt_depth, mask),
        "over_5cm_pct": math.nan if empty else 100.0 * float(np.mean(np.abs(error_m) > BAD_DEPTH_M)),
        "signed_cm": math.nan if empty else 100.0 * float(error_m.mean()),
        "coverage_pct": coverage_pct(mask, gt_depth),
    }


def score_rendered(images: Mapping[str, Rendered], gt_rgb: np.ndarray, gt_depth: np.ndarray) -> dict[str, Scores]:
    """Every method's scores on one view, gt rgb (h,w,3) float in [0,1] and depth (h,w): on its own pixels and on
    the pixels every method in `images` rendered (the same function for all methods)."""
    common = common_mask(gt_depth, (depth for _, depth in images.values()))
    return {
        name: {
            "own": pixel_scores(rgb, depth, gt_rgb, gt_depth, rendered_mask(depth, gt_depth)),
            "common": pixel_scores(rgb, depth, gt_rgb, gt_depth, common),
        }
        for name, (rgb, depth) in images.items()
    }


def render_methods(
    renders: Mapping[str, Renderer], view: EvalView, downscale: int
) -> tuple[np.ndarray, np.ndarray, dict[str, Rendered]]:
    """The captured view shrunk by `downscale` (rgb (h,w,3) float in [0,1], depth (h,w)) and every method's
    rendering of its camera at that size."""
    gt_rgb, gt_depth = shrink_view(np.asarray(view[2]), np.asarray(view[3]), downscale)
    images = {}
    for name, render in renders.items():
        rgb, depth, *_ = render_view(render, view, downscale)
        images[name] = (rgb, depth)
    return gt_rgb, gt_depth, images


ViewHook = Callable[[int, np.ndarray, np.ndarray, dict[str, Rendered]], None]
"""on_view(view number, gt rgb (h,w,3), gt depth (h,w), every method's images) after a view is scored."""


def score_views(
    renders: Mapping[str, Renderer], views: Sequence[EvalView], downscale: int, on_view: ViewHook | None = None
) -> dict[str, list[Scores]]:
    """Per-view scores (see `score_rendered`) of every method, method name -> one entry per view. One view is
    rendered at a time; `on_view` sees its images before they are dropped."""
    per_view: dict[str, list[Scores]] = {name: [] for name in renders}
    for i, view in enumerate(views):
        gt_rgb, gt_depth, images = render_methods(renders, view, downscale)
        for name, scores in score_rendered(images, gt_rgb, gt_depth).items():
            per_view[name].append(scores)
        if on_view is not None:
            on_view(i, gt_rgb, gt_depth, images)
    return per_view


def mean_scores(per_view: Sequence[Mapping[str, float]]) -> dict[str, float]:
    """Each score's mean over views, leaving out the views where it is NaN (NaN when none is left), and n_views."""
    out: dict[str, float] = {"n_views": float(len(per_view))}
    for key in dict.fromkeys(key for scores in per_view for key in scores):
        values = np.array([scores.get(key, math.nan) for scores in per_view], dtype=np.float64)
        values = values[np.isfinite(values)]
        out[key] = float(values.mean()) if len(values) else math.nan
    return out


def own_scores(render: Renderer, views: Sequence[EvalView], downscale: int) -> dict[str, float]:
    """One method's mean scores on its own pixels of `views`: what bench/quality.py reports for held-out frames."""
    return mean_scores([scores["own"] for scores in score_views({"method": render}, views, downscale)["method"]])


# ------------------------------------------------------------------------------------------- methods


class Run(Protocol):
    """One mapping run, fed the mapped frames one at a time."""

    frame_times_s: list[float]

    def integrate(self, frame: RgbdFrame) -> None: ...

    def frames(self) -> int: ...  # frames it was given

    def mesh(self) -> trimesh.Trimesh: ...  # the final mesh


class H2vizRun:
    """h2viz's Mapper; it renders its field, or its final mesh."""

    def __init__(self, cfg: Config) -> None:
        self.cfg = cfg
        self.mapper = Mapper(cfg.mapping)
        self.frame_times_s: list[float] = []
        self.refine_s = 0.0

    def integrate(self, frame: RgbdFrame) -> None:
        self.frame_times_s.append(self.mapper.integrate(frame).map_time_s)

    def frames(self) -> int:
        return self.mapper.frames_done

    def mesh(self) -> trimesh.Trimesh:
        return self.mapper.mesh()

    def finish(self) -> None:
        """mapping.optimization.refine_iters more steps after the last frame, as `h2viz map` does."""
        start = time.perf_counter()
        if self.cfg.mapping.optimization.refine_iters > 0:
            self.mapper.refine(self.cfg.mapping.optimization.refine_iters)
        self.refine_s = time.perf_counter() - start


class TsdfRun:
    """Open3D TSDF fusion; it renders its coloured mesh."""

    def __init__(self, cfg: TsdfConfig) -> None:
        self.tsdf = TsdfFusion(cfg)
        self.frame_times_s: list[float] = []

    def integrate(self, frame: RgbdFrame) -> None:
        self.frame_times_s.append(self.tsdf.integrate(frame))

    def frames(self) -> int:
        return self.tsdf.frames

    def mesh(self) -> trimesh.Trimesh:
        return self.tsdf.mesh()


@dataclass(frozen=True)
class Method:
    """One row of a sequence: the run it renders and whether it ray casts that run's mesh instead of its field."""

    name: str
    run: str  # "h2viz", "tsdf" or a variant's name
    mesh: bool = False


@dataclass(frozen=True)
class Variant:
    """h2viz with extra mapping overrides."""

    name: str
    overrides: tuple[str, ...]


def file_overrides(path: str) -> tuple[str, ...]:
    """The mapping section of a config file (e.g. configs/paper.yaml) as key=value overrides."""
    try:
        data = parse_yaml(Path(path).read_text()) or {}  # a key given twice is an error
    except (OSError, yaml.YAMLError) as e:
        raise SystemExit(f"--variant: cannot read {path} ({e}); pass a YAML config file") from e
    outside = sorted(set(data) - {"mapping"})
    if outside:
        raise SystemExit(f"--variant: {path} sets {', '.join(outside)}; a variant may only change mapping.*")
    dump = lambda v: yaml.safe_dump(v, default_flow_style=True).strip().removesuffix("...").strip()  # noqa: E731

    def dotted(prefix: str, values: dict) -> list[str]:  # one override a setting: mapping.sampling.free_samples=-1
        out: list[str] = []
        for k, v in values.items():
            out += dotted(f"{prefix}{k}.", v) if isinstance(v, dict) else [f"{prefix}{k}={dump(v)}"]
        return out

    return tuple(dotted("mapping.", data["mapping"]))


def parse_variant(text: str) -> Variant:
    """NAME=key=value,key=value or NAME=@config.yaml -> Variant; SystemExit naming what is wrong."""
    name, _, rest = text.partition("=")
    if rest.startswith("@"):
        overrides = file_overrides(rest[1:])
    else:
        overrides = tuple(item.strip() for item in rest.split(",") if item.strip())
    if not name.strip() or not overrides:
        raise SystemExit(f"--variant {text!r}: write NAME=key=value[,key=value...], e.g. l2=mapping.losses.rgb_loss=l2")
    if name.strip() in METHODS or name.strip().endswith("-mesh"):
        raise SystemExit(f"--variant {text!r}: the name must differ from {', '.join(METHODS)} and not end in -mesh")
    outside = [o for o in overrides if not o.startswith("mapping.")]
    if outside:
        raise SystemExit(f"--variant {text!r}: only mapping.* keys, since all methods map the same frames: {outside}")
    return Variant(name.strip(), overrides)


def pick_methods(methods: str, variants: Sequence[Variant], variant_mesh: bool) -> list[Method]:
    """The rows of each sequence, in the order --methods names them, then the variants."""
    picked = [Method(m, m if m == "tsdf" else "h2viz", m != "h2viz") for m in pick(methods, KNOWN_METHODS, "method")]
    for v in variants:
        picked.append(Method(v.name, v.name))
        if variant_mesh:
            picked.append(Method(f"{v.name}-mesh", v.name, True))
    names = [m.name for m in picked]
    if len(set(names)) != len(names):
        raise SystemExit(f"two methods share a name: {', '.join(names)}")
    return picked


def open_runs(
    ds: Dataset, methods: Sequence[Method], variants: Sequence[Variant], args: argparse.Namespace
) -> tuple[dict[str, Run], dict[str, str]]:
    """The mapping runs the methods need (run name -> run) and, for those that cannot start, why."""
    overrides = {"h2viz": (), **{v.name: v.overrides for v in variants}}
    runs: dict[str, Run] = {}
    notes: dict[str, str] = {}
    for name in dict.fromkeys(m.run for m in methods):
        try:
            cfg = dataset_config(ds, args.frames, [*args.set, *overrides.get(name, ())])
            if name == "tsdf":
                tsdf = TsdfConfig(args.tsdf_voxel_m, args.tsdf_trunc_voxels, depth_max_m=cfg.source.depth_max_m)
                runs[name] = TsdfRun(tsdf)
            else:
                runs[name] = H2vizRun(cfg)
        except H2vizError as e:  # open3d missing, a bad override: this run only
            notes[name] = str(e)
    return runs, notes


def renderer(method: Method, run: Run) -> Renderer:
    """What a method renders held-out cameras with: the run's field, or its final mesh ray cast."""
    if isinstance(run, H2vizRun) and not method.mesh:
        return run.mapper.render
    mesh = run.mesh()
    if len(mesh.faces) == 0:
        raise H2vizError(f"{method.run} produced an empty mesh; check the frames' depth and poses")
    return MeshRenderer(mesh)


# ---------------------------------------------------------------------------------------------- rows


@dataclass
class Row:
    """One method on one sequence."""

    sequence: str
    method: str
    mapped: int = 0
    heldout: int = 0
    frame_times_s: list[float] = field(default_factory=list)
    refine_s: float = 0.0
    common: dict[str, float] = field(default_factory=dict)
    own: dict[str, float] = field(default_factory=dict)
    per_view: list[dict[str, Any]] = field(default_factory=list)
    note: str = ""

    def median_frame_s(self) -> float | None:
        times = [t for t in self.frame_times_s if math.isfinite(t)]
        return float(np.median(times)) if times else None

    def cells(self) -> list[str]:
        c, o = self.common, self.own
        values = [c.get("psnr_db"), c.get("ssim"), c.get("depth_l1_cm"), c.get("over_5cm_pct"), o.get("psnr_db")]
        values += [o.get("depth_l1_cm"), o.get("over_5cm_pct"), o.get("coverage_pct"), o.get("signed_cm")]
        values.append(self.median_frame_s())
        digits = [2, 3, 2, 1, 2, 2, 1, 1, 2, 3]
        counts = [str(n) if n else "-" for n in (self.mapped, self.heldout)]
        return [self.sequence, self.method, *counts, *(fmt(v, d) for v, d in zip(values, digits, strict=True))]


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def feed(
    source: Iterable[RgbdFrame], runs: dict[str, Run], notes: dict[str, str], k: int, total: int
) -> list[tuple[int, RgbdFrame]]:
    """Give every mapped frame of `source` to every run and return the held-out (position, frame) pairs; a run
    that fails leaves `runs` with its reason in `notes`."""
    held: list[tuple[int, RgbdFrame]] = []
    for position, frame in enumerate(source):
        if is_heldout(position, k):
            held.append((position, frame))
            continue
        for name, run in list(runs.items()):
            try:
                run.integrate(frame)
            except H2vizError as e:
                notes[name] = f"failed on frame {frame.index}: {e}"
                del runs[name]
        if (position + 1) % 50 == 0:
            _log(f"    frame {position + 1}/{total}")
    return held


def finish_runs(runs: dict[str, Run], notes: dict[str, str]) -> None:
    """What `h2viz map` does after the last frame (mapping.optimization.refine_iters); a failed run leaves `runs`."""
    for name, run in list(runs.items()):
        try:
            if isinstance(run, H2vizRun):
                run.finish()
        except H2vizError as e:
            notes[name] = f"failed after the last frame: {e}"
            del runs[name]


def run_sequence(
    ds: Dataset, methods: Sequence[Method], variants: Sequence[Variant], args: argparse.Namespace
) -> list[Row]:
    """Map the sequence's mapped frames with every run, then score every method on every held-out view."""
    rows = {m.name: Row(ds.name, m.name) for m in methods}
    try:
        cfg = dataset_config(ds, args.frames, args.set)
        source = make_source(cfg.source)
    except H2vizError as e:  # missing data, unreadable source: every row says why
        for row in rows.values():
            row.note = str(e)
        return list(rows.values())
    runs, notes = open_runs(ds, methods, variants, args)
    total = len(source)
    mapped, held_out = heldout_split(total, args.k)
    _log(f"    mapping {len(mapped)} of {total} frames with {', '.join(runs) or 'nothing'}; {len(held_out)} held out")
    try:
        held = feed(source, runs, notes, args.k, total)
    finally:
        getattr(source, "close", lambda: None)()
    finish_runs(runs, notes)
    renders: dict[str, Renderer] = {}
    for m in methods:
        row, run = rows[m.name], runs.get(m.run)
        if run is None:
            row.note = notes.get(m.run, "not run")
            continue
        row.mapped, row.heldout, row.frame_times_s = run.frames(), len(held), list(run.frame_times_s)
        row.refine_s = getattr(run, "refine_s", 0.0)
        try:
            renders[m.name] = renderer(m, run)
        except H2vizError as e:
            row.note = str(e)
    downscale = args.downscale or cfg.eval.render_downscale
    _log(f"    rendering {len(held)} held-out views at 1/{downscale} with {', '.join(renders) or 'nothing'}")
    on_view = None
    if args.images:
        shown = spread(len(held), args.image_views)
        on_view = mosaic_writer(Path(args.images), ds.name, [p for p, _ in held], shown)
    per_view = score_views(renders, [frame_view(f) for _, f in held], downscale, on_view)
    for name, scores in per_view.items():
        row = rows[name]
        row.own = mean_scores([s["own"] for s in scores])
        row.common = mean_scores([s["common"] for s in scores])
        row.per_view = [{"position": p, **s} for (p, _), s in zip(held, scores, strict=True)]
    return list(rows.values())


# -------------------------------------------------------------------------------------------- images


def spread(n: int, count: int) -> set[int]:
    """`count` of the numbers 0..n-1, spread evenly from first to last (all of them when n <= count)."""
    if n <= 0 or count <= 0:
        return set()
    return {int(round(x)) for x in np.linspace(0, n - 1, min(count, n))}


def _bgr(rgb: np.ndarray) -> np.ndarray:
    """rgb (h,w,3) float in [0,1] -> (h,w,3) uint8 BGR."""
    return cv2.cvtColor(np.round(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.uint8), cv2.COLOR_RGB2BGR)


def _colour_map(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """values (h,w) in [0,1] (clipped) as a turbo colour map (h,w,3) uint8 BGR, mid-grey where not `valid`."""
    levels = np.round(np.clip(np.nan_to_num(values), 0.0, 1.0) * 255.0).astype(np.uint8)
    image = cv2.applyColorMap(levels, cv2.COLORMAP_TURBO)
    image[~valid] = 128
    return image


def _label(image: np.ndarray, text: str) -> np.ndarray:
    """The image (h,w,3) uint8 with `text` in its top left corner, white on a dark outline."""
    image = image.copy()
    scale = max(0.25, image.shape[1] / 700.0)
    origin = (4, int(4 + 22 * scale))
    cv2.putText(image, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(image, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return image


def mosaic(gt_rgb: np.ndarray, gt_depth: np.ndarray, images: Mapping[str, Rendered]) -> np.ndarray:
    """One held-out view side by side, (2h, (1+M)w, 3) uint8 BGR: the captured colour then each method's on top;
    below, the captured depth (near blue, far red) then each method's |depth error| from 0 (blue) to BAD_DEPTH_M
    and beyond (red), grey where the capture or the method has no depth."""
    top = [_label(_bgr(gt_rgb), "captured")]
    top += [_label(_bgr(rgb), name) for name, (rgb, _) in images.items()]
    far = max(float(gt_depth.max(initial=0.0)), 1e-6)
    bottom = [_label(_colour_map(gt_depth / far, gt_depth > 0), f"depth 0-{far:.1f} m")]
    legend = f"|error| 0-{BAD_DEPTH_M * 100:.0f} cm"
    for _, depth in images.values():
        error = np.abs(depth - gt_depth) / BAD_DEPTH_M  # (h,w) in units of the threshold
        bottom.append(_label(_colour_map(error, rendered_mask(depth, gt_depth)), legend))
    return np.vstack([np.hstack(top), np.hstack(bottom)])


def mosaic_writer(folder: Path, sequence: str, positions: Sequence[int], shown: set[int]) -> ViewHook:
    """An `on_view` hook writing the mosaic of the views numbered in `shown` to folder/<sequence>_<position>.png."""

    def write(i: int, gt_rgb: np.ndarray, gt_depth: np.ndarray, images: dict[str, Rendered]) -> None:
        if i in shown:
            folder.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(folder / f"{sequence}_{positions[i]:05d}.png"), mosaic(gt_rgb, gt_depth, images))

    return write


# ------------------------------------------------------------------------------------------------ cli


def report(rows: list[Row], k: int) -> str:
    """The table, what its columns mean, the notes on sequences and rows that did not run, and the command."""
    lines = [markdown_table(COLUMNS, [r.cells() for r in rows]), ""]
    lines += LEGEND.format(k=k, offset=k // 2).splitlines()
    lines += [f"- {d}: {DATASETS[d].note}" for d in dict.fromkeys(r.sequence for r in rows)]
    lines += [f"- {r.method} on {r.sequence} did not run: {r.note}" for r in rows if r.note]
    lines += ["", f"command: {command_line('bench/heldout.py')}"]
    return "\n".join(lines)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--k", type=int, default=10, help="hold out every k-th frame, from position k // 2 (default 10)")
    p.add_argument("--datasets", default="synthetic,icl,redkitchen,fountain", help=f"any of {','.join(DATASETS)}")
    p.add_argument("--methods", default=",".join(METHODS), help=f"any of {','.join(METHODS)}")
    p.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="NAME=KEY=VALUE[,KEY=VALUE]",
        help="one more h2viz row with these mapping overrides (repeatable), e.g. l2=mapping.losses.rgb_loss=l2, or "
        "those of a config file's mapping section: paper=@configs/paper.yaml",
    )
    p.add_argument("--variant-mesh", action="store_true", help="also ray cast each variant's mesh (NAME-mesh)")
    p.add_argument("--frames", type=int, default=None, help="at most N frames per sequence, before the split")
    p.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="config override for every run (and the frames)"
    )
    p.add_argument("--downscale", type=int, default=None, help="render at 1/N (default: eval.render_downscale)")
    p.add_argument("--json", default=None, help="also write every row, with its per-view numbers, to this file")
    p.add_argument("--doc", default=None, help="also write the table, with commit and CPU, to this page")
    p.add_argument("--images", default=None, help="write mosaics of a few held-out views per sequence to this folder")
    p.add_argument("--image-views", type=int, default=3, help="held-out views per sequence with a mosaic (default 3)")
    p.add_argument("--tsdf-voxel-m", type=float, default=0.01, help="TSDF voxel size (default 1 cm)")
    p.add_argument("--tsdf-trunc-voxels", type=float, default=5.0, help="TSDF truncation in voxels (default 5)")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.k < 2:
        raise SystemExit(f"--k {args.k}: use k >= 2 (every k-th frame is held out, the others are mapped)")
    if args.downscale is not None and args.downscale < 1:
        raise SystemExit(f"--downscale {args.downscale}: use 1 or more")
    variants = [parse_variant(v) for v in args.variant]
    methods = pick_methods(args.methods, variants, args.variant_mesh)
    for overrides in [(), *(v.overrides for v in variants)]:
        try:
            apply_overrides(load_config(), [*args.set, *overrides])  # a mistyped key fails here, not in every row
        except H2vizError as e:
            raise SystemExit(f"--set / --variant: {e}") from e
    names = pick(args.datasets, DATASETS, "dataset")
    rows: list[Row] = []
    for i, name in enumerate(names, 1):
        _log(f"[{i}/{len(names)}] {name}: {', '.join(m.name for m in methods)} ...")
        start = time.perf_counter()
        rows += run_sequence(DATASETS[name], methods, variants, args)
        _log(f"    done in {time.perf_counter() - start:.0f} s")
    table_md = report(rows, args.k)
    print(table_md)
    if args.doc:
        write_doc(args.doc, "Held-out views", table_md)
    if args.json:
        table = [{**asdict(r), "median_frame_s": r.median_frame_s()} for r in rows]
        meta = {"command": command_line("bench/heldout.py"), "k": args.k, "downscale": args.downscale}
        write_metrics({**meta, "rows": table}, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
