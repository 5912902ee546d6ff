"""Mapping speed of h2viz (fused numba hash-grid kernels, and the pure-torch reference path) and of an Open3D TSDF
fusion baseline on the same frames: per-frame time with its breakdown, meshing, peak memory and the quality
reached, in one markdown table.

Each method x dataset runs in a fresh subprocess, so its peak resident memory (ru_maxrss) is its own. The first
frame and the mesh update after it are the warm-up (numba compiles its kernels or loads them from its cache; the
first allocation): they are reported apart and left out of every other column. Frame loading is never timed;
the synthetic room's background prefetch is off so that rendering frames does not compete with mapping.

    .venv/bin/python bench/speed.py                                          # synthetic + redkitchen, 60 frames
    .venv/bin/python bench/speed.py --frames 0                               # every frame (synthetic: 300)
    .venv/bin/python bench/speed.py --datasets synthetic --frames 6 --set source.downscale=4   # a quick look
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import DATASETS, Dataset, command_line, dataset_config, fmt, markdown_table, pick  # noqa: E402
from bench.speed_run import STAGES, Run, child_main  # noqa: E402
from h2viz.config import Config, apply_overrides, dump_config, load_config  # noqa: E402
from h2viz.errors import H2vizError  # noqa: E402

METHODS: dict[str, list[str]] = {
    "h2viz": ["mapping.runtime.kernels=auto"],
    "h2viz-torch": ["mapping.runtime.kernels=torch"],
    "tsdf": [],
}
"""Method -> configuration switches applied after --set. tsdf: Open3D VoxelBlockGrid, 1 cm voxels, CPU."""

BENCH_DEFAULTS = ["source.synthetic.prefetch=0", "eval.n_interpolate=10", "eval.n_extrapolate=0"]
"""Applied before --set: no frame rendering in the background while mapping; 10 training views are evaluated
(bench/quality.py: 20, and 20 novel views), which keeps rendering them from outlasting the mapping."""

COLUMNS = ["method", "dataset", "frames", "iters/frame", "ms/frame", "p90 ms", "CPU ms/frame"]
COLUMNS += [f"{stage} ms" for stage in STAGES]
COLUMNS += ["mesh ms/update", "mesh ms/frame", "warm-up s map/mesh", "peak RSS MB", "RSS growth MB"]
COLUMNS += ["Acc cm", "Comp cm", "Comp ratio %", "depth L1 cm", "PSNR dB"]


def summary(run: Run) -> dict[str, float | None]:
    """The table's numbers: medians over the measured frames (warm-up excluded), p90, mean iterations."""
    med = lambda xs: float(np.median(xs)) if len(xs) else None  # noqa: E731
    out: dict[str, float | None] = {
        "median_frame_s": med(run.frame_s),
        "p90_frame_s": float(np.percentile(run.frame_s, 90)) if run.frame_s else None,
        "median_cpu_s": med(run.cpu_s),
        "mean_iterations": float(np.mean(run.iterations)) if run.iterations else None,
        "median_mesh_s": med(run.mesh_s),
        "mesh_s_per_frame": float(np.mean(run.mesh_s)) / run.mesh_every if run.mesh_s else None,
    }
    out.update({f"median_{stage}_s": med(run.stage_s.get(stage, [])) for stage in STAGES})
    return out


def cells(run: Run) -> list[str]:
    """One table row."""
    s = summary(run)
    ms = lambda v: fmt(v * 1e3 if v is not None else None, 0)  # noqa: E731
    mesh = run.metrics.get("mesh", {})
    interp = run.metrics.get("interpolate", {})
    frames = f"1+{len(run.frame_s)}" if run.warmup_map_s is not None else "-"
    warmup = "-" if run.warmup_map_s is None else f"{run.warmup_map_s:.2f}/{fmt(run.warmup_mesh_s, 2)}"
    growth = run.peak_rss_mb - run.start_rss_mb if run.peak_rss_mb is not None and run.start_rss_mb else None
    row = [run.method, run.dataset, frames, fmt(s["mean_iterations"], 1), ms(s["median_frame_s"])]
    row += [ms(s["p90_frame_s"]), ms(s["median_cpu_s"]), *(ms(s[f"median_{stage}_s"]) for stage in STAGES)]
    row += [ms(s["median_mesh_s"]), ms(s["mesh_s_per_frame"]), warmup, fmt(run.peak_rss_mb, 0), fmt(growth, 0)]
    row += [fmt(mesh.get("acc_cm"), 2), fmt(mesh.get("comp_cm"), 2), fmt(mesh.get("comp_ratio"), 1)]
    row += [fmt(interp.get("depth_l1_cm"), 2), fmt(interp.get("psnr_db"), 2)]
    return row


def pair_config(ds: Dataset, method: str, args: argparse.Namespace) -> Config:
    """The resolved configuration of one run (MissingData when the dataset is absent)."""
    overrides = [*BENCH_DEFAULTS, *args.set, *METHODS[method], "mapping.meshing.mesh_every=0"]  # meshing is timed here
    if args.threads > 0:
        overrides.append(f"mapping.runtime.threads={args.threads}")
    return dataset_config(ds, args.frames, overrides)


def run_pair(ds: Dataset, method: str, args: argparse.Namespace, tmp: Path) -> Run:
    """Run one method on one dataset in a fresh interpreter and read back what it measured."""
    try:
        cfg = pair_config(ds, method, args)
        gt_mesh = ds.gt_mesh_path()
    except H2vizError as e:  # a missing dataset
        return Run(method, ds.name, note=str(e))
    config_path, result_path = tmp / f"{ds.name}-{method}.yaml", tmp / f"{ds.name}-{method}.json"
    dump_config(cfg, config_path)
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", str(config_path), "--result", str(result_path)]
    cmd += ["--method", method, "--dataset", ds.name, "--mesh-every", str(args.mesh_every)]
    cmd += ["--gt-mesh", str(gt_mesh) if gt_mesh is not None else ""] + (["--no-quality"] if args.no_quality else [])
    env = dict(os.environ)
    if args.threads > 0:
        # Open3D's OpenMP pool (torch and numba follow mapping.runtime.threads)
        env["OMP_NUM_THREADS"] = str(args.threads)
    proc = subprocess.run(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, check=False)
    if proc.returncode != 0 or not result_path.is_file():
        tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        return Run(method, ds.name, note=f"the run failed (exit {proc.returncode}): {tail}")
    return Run(**json.loads(result_path.read_text()))


def run_all(args: argparse.Namespace) -> list[Run]:
    pairs = [
        (DATASETS[d], m)
        for d in pick(args.datasets, DATASETS, "dataset")
        for m in pick(args.methods, METHODS, "method")
    ]
    runs = []
    with tempfile.TemporaryDirectory(prefix="h2viz-speed-") as tmp:
        for k, (ds, method) in enumerate(pairs, 1):
            print(f"[{k}/{len(pairs)}] {method} on {ds.name} ...", file=sys.stderr, flush=True)
            start = time.perf_counter()
            runs.append(run_pair(ds, method, args, Path(tmp)))
            phases = ", ".join(f"{k} {v:.0f} s" for k, v in runs[-1].phase_s.items())
            print(
                f"    done in {time.perf_counter() - start:.0f} s ({phases}) {runs[-1].note}",
                file=sys.stderr,
                flush=True,
            )
    return runs


def report(runs: list[Run], args: argparse.Namespace, load: tuple[float, float]) -> str:
    """The table, what its columns mean, the notes of runs that did not run, and the command."""
    lines = [markdown_table(COLUMNS, [cells(r) for r in runs]), ""]
    lines += [f"- {r.method} on {r.dataset} did not run: {r.note}" for r in runs if r.note]
    kernels = dict.fromkeys(f"{r.method} {r.kernels}" for r in runs if r.kernels)
    threads = sorted({r.threads for r in runs if r.threads})
    views = sorted({int(r.metrics["interpolate"]["n_views"]) for r in runs if "interpolate" in r.metrics})
    lines += [
        "- frames = warm-up + measured; ms/frame = Mapper.integrate (h2viz) or TSDF integration, loading excluded,"
        " median and p90;",
        "  CPU = median process CPU time of a frame (all threads; less sensitive to other jobs than wall time);",
        "  the stage columns are wall-time medians (they need not add up to the total; --json has every frame)",
        f"- mesh: Mapper.update_mesh() (changed chunks) or the TSDF's full extraction every {args.mesh_every} frames;"
        " ms/frame = mean update / interval",
        "- warm-up: the first frame's mapping and mesh update (numba compiles or loads its cache), in seconds",
        "- peak RSS: ru_maxrss of the run's own process up to the end of mapping and meshing (before evaluation);"
        " growth = peak minus the RSS after imports (open3d, numba) and opening the source",
        "- quality: bench/quality.py's evaluation; Acc/Comp/Comp ratio (5 cm) against the ground-truth mesh"
        f" (synthetic only), depth L1 and PSNR on {'/'.join(map(str, views)) or '-'} training views;"
        " h2viz renders its field, tsdf its mesh",
        f"- kernels: {' | '.join(kernels) or '-'}; torch/numba threads: {', '.join(map(str, threads)) or '-'};"
        f" 1-min load average {load[0]:.1f} before, {load[1]:.1f} after (other jobs on the machine inflate times)",
        "",
        f"command: {command_line('bench/speed.py')}",
    ]
    return "\n".join(lines)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--datasets", default="synthetic,redkitchen", help=f"any of {','.join(DATASETS)}")
    p.add_argument("--methods", default=",".join(METHODS), help=f"any of {','.join(METHODS)}")
    p.add_argument("--frames", type=int, default=60, help="frames per dataset, the warm-up one included (0 = all)")
    p.add_argument("--mesh-every", type=int, default=5, help="update the mesh every N frames (0 = never)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override for every run")
    p.add_argument("--threads", type=int, default=0, help="torch/numba/OpenMP threads (0 = the config's: all cores)")
    p.add_argument("--no-quality", action="store_true", help="skip the quality evaluation")
    p.add_argument("--json", default=None, help="also write every run (all per-frame times, metrics) to this file")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)  # config file of one run in a subprocess
    for hidden in ("--result", "--method", "--dataset", "--gt-mesh"):
        p.add_argument(hidden, default="", help=argparse.SUPPRESS)
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.child:
        return child_main(args)
    if args.frames == 1 or args.mesh_every < 0:
        raise SystemExit("--frames must be 0 (all) or >= 2 (one warm-up frame plus measured ones); --mesh-every >= 0")
    try:
        apply_overrides(load_config(), args.set)  # a mistyped --set fails here, not in every run
    except H2vizError as e:
        raise SystemExit(f"--set: {e}") from e
    load_before = os.getloadavg()[0]
    runs = run_all(args)
    print(report(runs, args, (load_before, os.getloadavg()[0])))
    if args.json:
        rows = [{**asdict(r), **summary(r)} for r in runs]
        Path(args.json).write_text(json.dumps({"command": command_line("bench/speed.py"), "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
