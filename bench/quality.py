"""Reconstruction and rendering quality of h2viz, its ablations and an Open3D TSDF fusion baseline, on the
built-in synthetic room and the real sequences in ../shared/data, in one markdown table.

Every method maps the same frames and goes through the same evaluation (`h2viz.pipeline.evaluate`):
mesh Acc / Comp / Comp ratio against the ground-truth mesh culled to what the frames observed, and depth L1 /
PSNR / SSIM on the same interpolated (training) and extrapolated (novel) views. Every --heldout-k-th frame is
not mapped: each method renders those cameras and is scored against the captured frames on its own rendered
pixels (bench/heldout.py's scoring; that benchmark also compares methods on their common pixels). h2viz renders
its field; the TSDF baseline renders its coloured mesh (ray casting). Times are per-frame mapping (h2viz) or
integration (TSDF) times, frame loading and final meshing excluded.

    .venv/bin/python bench/quality.py                                      # everything, every frame
    .venv/bin/python bench/quality.py --datasets synthetic --methods h2viz,tsdf --frames 8 \\
        --set source.downscale=4 --set mapping.optimization.max_iters=3                  # a quick look
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import trimesh

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
from bench.heldout import frame_view, heldout_split, is_heldout, own_scores  # noqa: E402
from bench.tsdf_baseline import TsdfConfig, TsdfFusion, import_open3d  # noqa: E402
from h2viz.config import Config, apply_file, apply_overrides, dump_config, load_config  # noqa: E402
from h2viz.errors import H2vizError  # noqa: E402
from h2viz.eval.mesh_render import MeshRenderer  # noqa: E402
from h2viz.eval.report import Renderer, load_mesh, write_metrics  # noqa: E402
from h2viz.mapping.mapper import Mapper  # noqa: E402
from h2viz.pipeline import EvalFrames, evaluate  # noqa: E402
from h2viz.sources.base import make_source  # noqa: E402
from h2viz.types import RgbdFrame  # noqa: E402

METHODS: dict[str, list[str]] = {
    "h2viz": [],
    "no-priors": ["mapping.representation.priors=false"],
    "no-expansion": ["mapping.representation.expansion=false"],
    "random-kf": ["mapping.keyframes.keyframe_strategy=random"],
    "overlap-kf": ["mapping.keyframes.keyframe_strategy=overlap"],
    "no-early-end": ["mapping.optimization.early_ending=false"],
    "tsdf": [],
    "gt": [],
}
"""Method name -> configuration switches applied after --set (the paper's ablations). "gt" evaluates the
ground-truth mesh itself: the floor of Comp set by the point sampling, and the image metrics of a perfect
mesh against the captured frames."""

COLUMNS = ["method", "dataset", "Acc (cm)", "Comp (cm)", "Comp ratio (%)", "depth L1 (cm)", "PSNR (dB)", "SSIM"]
COLUMNS += ["ext depth L1 (cm)", "ext PSNR (dB)", "held-out PSNR (dB)", "held-out depth L1 (cm)", "median s/frame"]
COLUMNS += ["frames"]


class Fusion(Protocol):
    """A method under test: fuses frames one at a time, then gives a mesh and a renderer."""

    def integrate(self, frame: RgbdFrame) -> float: ...  # seconds spent on this frame

    def result(self) -> tuple[trimesh.Trimesh, Renderer]: ...


class H2vizFusion:
    """h2viz's Mapper; it renders images from its field."""

    def __init__(self, cfg: Config) -> None:
        self.mapper = Mapper(cfg.mapping)

    def integrate(self, frame: RgbdFrame) -> float:
        return self.mapper.integrate(frame).map_time_s

    def result(self) -> tuple[trimesh.Trimesh, Renderer]:
        self.mapper.update_mesh()
        return self.mapper.mesh(), self.mapper.render


class TsdfMeshFusion:
    """Open3D TSDF fusion; it renders images from its coloured mesh."""

    def __init__(self, cfg: TsdfConfig) -> None:
        self.tsdf = TsdfFusion(cfg)

    def integrate(self, frame: RgbdFrame) -> float:
        return self.tsdf.integrate(frame)

    def result(self) -> tuple[trimesh.Trimesh, Renderer]:
        mesh = self.tsdf.mesh()
        if len(mesh.faces) == 0:
            raise H2vizError("the TSDF baseline produced an empty mesh; check the frames' depth and poses")
        return mesh, MeshRenderer(mesh)


class GroundTruthMesh:
    """The ground-truth mesh as if a method had built it (nothing is fused; no time per frame)."""

    def __init__(self, gt: trimesh.Trimesh | None) -> None:
        if gt is None:
            raise H2vizError("no ground-truth mesh for this dataset")
        self.gt = gt
        self.renderer = MeshRenderer(gt)

    def integrate(self, frame: RgbdFrame) -> float:
        return math.nan

    def result(self) -> tuple[trimesh.Trimesh, Renderer]:
        return self.gt, self.renderer

    def meaningful(self, metrics: dict[str, Any]) -> dict[str, Any]:
        """What a perfect mesh tells: Comp (the sampling floor) and the captured views, training and held out
        (their colour only when the mesh has colours). Its Acc counts the parts nobody observed; its novel views
        are their own reference."""
        keep = ("comp_cm", "comp_ratio", "recall", "n_gt_points", "gt_kept_pct")
        out: dict[str, Any] = {"mesh": {k: v for k, v in metrics.get("mesh", {}).items() if k in keep}}
        flat = np.ptp(self.renderer.vertex_rgb, axis=0).max() < 1e-6  # one flat colour: the mesh has none
        for part in ("interpolate", "heldout"):
            if part in metrics:
                out[part] = {k: v for k, v in metrics[part].items() if not (flat and k in ("psnr_db", "ssim"))}
        return out


@dataclass
class RenderOnly:
    """What `pipeline.evaluate` uses of a map: its `render(K, T_world_camera, height, width, mode)`."""

    render: Renderer


@dataclass
class Row:
    """One method on one dataset."""

    method: str
    dataset: str
    frames: int = 0
    frame_times_s: list[float] = field(default_factory=list)
    mesh_time_s: float | None = None
    metrics: dict[str, Any] = field(default_factory=dict)
    note: str = ""

    def median_frame_s(self) -> float | None:
        times = [t for t in self.frame_times_s if math.isfinite(t)]
        return float(np.median(times)) if times else None

    def cells(self) -> list[str]:
        mesh = self.metrics.get("mesh", {})
        interp = self.metrics.get("interpolate", {})
        ext = self.metrics.get("extrapolate", {})
        held = self.metrics.get("heldout", {})
        values = [mesh.get("acc_cm"), mesh.get("comp_cm"), mesh.get("comp_ratio"), interp.get("depth_l1_cm")]
        values += [interp.get("psnr_db"), interp.get("ssim"), ext.get("depth_l1_cm"), ext.get("psnr_db")]
        values += [held.get("psnr_db"), held.get("depth_l1_cm")]
        digits = [2, 2, 1, 2, 2, 3, 2, 2, 2, 2]
        cells = [fmt(v, d) for v, d in zip(values, digits, strict=True)]
        return [
            self.method,
            self.dataset,
            *cells,
            fmt(self.median_frame_s(), 3),
            str(self.frames) if self.frames else "-",
        ]


def _config(ds: Dataset, method: str, args: argparse.Namespace) -> Config:
    cfg = dataset_config(ds, args.frames, [*args.set, *METHODS[method]], args.config)
    cfg.out_dir = str(Path(args.out) / ds.name / method)
    return cfg


def _fusion(method: str, cfg: Config, args: argparse.Namespace, gt: trimesh.Trimesh | None) -> Fusion:
    if method == "gt":
        return GroundTruthMesh(gt)
    if method != "tsdf":
        return H2vizFusion(cfg)
    tsdf = TsdfConfig(args.tsdf_voxel_m, args.tsdf_trunc_voxels, depth_max_m=cfg.source.depth_max_m)
    return TsdfMeshFusion(tsdf)


def run_one(method: str, ds: Dataset, args: argparse.Namespace) -> Row:
    """Map (or fuse) the dataset's frames but the held-out ones with one method, evaluate, and keep the outputs."""
    row = Row(method, ds.name)
    if method == "tsdf":
        import_open3d()  # TsdfUnavailable with the install command, before any work
    cfg = _config(ds, method, args)
    gt_path = ds.gt_mesh_path()
    source = make_source(cfg.source)
    held: list[RgbdFrame] = []
    try:
        gt = load_mesh(gt_path) if gt_path is not None else source.ground_truth_mesh()
        fusion = _fusion(method, cfg, args, gt)
        mapped, _ = heldout_split(len(source), args.heldout_k)
        eval_frames = EvalFrames(len(mapped), cfg.eval.n_interpolate)  # training views among the mapped frames
        for position, frame in enumerate(source):
            if is_heldout(position, args.heldout_k):
                held.append(frame)
                continue
            eval_frames.add(len(row.frame_times_s), frame)
            row.frame_times_s.append(fusion.integrate(frame))
    finally:
        getattr(source, "close", lambda: None)()
    row.frames = len(row.frame_times_s)
    start = time.perf_counter()
    mesh, render = fusion.result()
    row.mesh_time_s = time.perf_counter() - start
    row.metrics = evaluate(RenderOnly(render), mesh, gt, eval_frames, cfg)  # type: ignore[arg-type]
    if held:
        row.metrics["heldout"] = own_scores(render, [frame_view(f) for f in held], cfg.eval.render_downscale)
    if isinstance(fusion, GroundTruthMesh):
        row.metrics = fusion.meaningful(row.metrics)
    _save(row, mesh, cfg)
    return row


def _save(row: Row, mesh: trimesh.Trimesh, cfg: Config) -> None:
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    dump_config(cfg, out / "config.yaml")
    mesh.export(out / "mesh.ply")
    write_metrics(row.metrics, out / "metrics.json")
    (out / "frame_times.json").write_text(json.dumps({"frame_times_s": row.frame_times_s}))


def run_all(args: argparse.Namespace) -> list[Row]:
    """Every (dataset, method) pair; a pair that cannot run becomes a row with a note."""
    pairs = [
        (DATASETS[d], m)
        for d in pick(args.datasets, DATASETS, "dataset")
        for m in pick(args.methods, METHODS, "method")
    ]
    rows = []
    for k, (ds, method) in enumerate(pairs, 1):
        print(f"[{k}/{len(pairs)}] {method} on {ds.name} ...", file=sys.stderr, flush=True)
        start = time.perf_counter()
        try:
            row = run_one(method, ds, args)
        except H2vizError as e:  # missing data, missing open3d, unusable frames: note it, run the rest
            row = Row(method, ds.name, note=str(e))
        print(f"    done in {time.perf_counter() - start:.0f} s {row.note}", file=sys.stderr, flush=True)
        rows.append(row)
    return rows


def report(rows: list[Row]) -> str:
    """The table, the notes on datasets and skipped rows, and the command."""
    lines = [markdown_table(COLUMNS, [r.cells() for r in rows]), ""]
    lines += [f"- {d}: {DATASETS[d].note}" for d in dict.fromkeys(r.dataset for r in rows)]
    lines += [f"- {r.method} on {r.dataset} did not run: {r.note}" for r in rows if r.note]
    lines.append("- Acc/Comp/Comp ratio: mesh vs ground truth culled to what the frames observed, Comp ratio at 5 cm;")
    lines.append("  depth L1/PSNR/SSIM on interpolated (training) views, ext = extrapolated novel views;")
    lines.append("  held-out = the captured frames left out of mapping (--heldout-k), on each method's own rendered")
    lines.append("  pixels (bench/heldout.py compares methods on their common pixels);")
    lines.append("  h2viz renders its field, tsdf and gt their mesh; s/frame = mapping (h2viz) or integration (tsdf);")
    lines.append("  gt = the ground-truth mesh itself: its Comp is the floor set by sampling eval.n_points points,")
    lines.append("  its images the best a mesh does against the captured frames.")
    lines += ["", f"command: {command_line('bench/quality.py')}"]
    return "\n".join(lines)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--datasets", default="synthetic,fountain,redkitchen", help=f"any of {','.join(DATASETS)}")
    p.add_argument("--methods", default=",".join(METHODS), help=f"any of {','.join(METHODS)}")
    p.add_argument("--frames", type=int, default=None, help="at most N frames per dataset (default: all)")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="config override for every run (mapping.* only affects h2viz)",
    )
    p.add_argument(
        "--config",
        action="append",
        default=[],
        metavar="FILE",
        help="config file for every run, after the per-format one (e.g. configs/paper.yaml for the paper's settings)",
    )
    p.add_argument("--out", default=None, help="keep each run's mesh, metrics and config in OUT/<dataset>/<method>")
    p.add_argument("--doc", default=None, help="also write the table, with commit and CPU, to this page")
    p.add_argument("--json", default=None, help="also write every row (all metrics, per-frame times) to this file")
    p.add_argument("--tsdf-voxel-m", type=float, default=0.01, help="TSDF voxel size (default 1 cm)")
    p.add_argument("--tsdf-trunc-voxels", type=float, default=5.0, help="TSDF truncation in voxels (default 5)")
    p.add_argument(
        "--heldout-k",
        type=int,
        default=10,
        help="leave every k-th frame (from position k // 2) out of mapping and score it (default 10; 0 = map all)",
    )
    args = p.parse_args(argv)
    if args.heldout_k == 1 or args.heldout_k < 0:
        p.error(f"--heldout-k {args.heldout_k}: use 0 (map every frame) or k >= 2")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        cfg = load_config()
        for path in args.config:
            apply_file(cfg, path)
        apply_overrides(cfg, args.set)  # a mistyped --set or config key fails here, not in every row
    except H2vizError as e:
        raise SystemExit(f"--config / --set: {e}") from e
    with tempfile.TemporaryDirectory(prefix="h2viz-quality-") as tmp:
        args.out = args.out or tmp
        rows = run_all(args)
    text = report(rows)
    print(text)
    if args.doc:
        write_doc(args.doc, "Quality: h2viz, its ablations and TSDF fusion", text)
    if args.json:
        table = [{**asdict(r), "median_frame_s": r.median_frame_s()} for r in rows]
        write_metrics({"command": command_line("bench/quality.py"), "rows": table}, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
