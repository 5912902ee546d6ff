"""Shared helpers of the benchmarks: the benchmark datasets (built-in synthetic room and the real
sequences in ../shared/data), their configurations, and markdown tables."""

from __future__ import annotations

import datetime
import math
import os
import platform
import shlex
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import h2viz  # noqa: F401  (thread-pool policy before NumPy and torch load)
from h2viz.config import Config, apply_file, apply_overrides, load_config, source_config_file
from h2viz.errors import H2vizError

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"


class MissingData(H2vizError):
    """A benchmark dataset is not on this machine."""


@dataclass(frozen=True)
class Dataset:
    """One benchmark sequence."""

    name: str
    folder: str  # under ../shared/data; "" = the built-in synthetic room
    fmt: str  # source format
    gt_mesh: str  # file in the folder with the reference mesh; "" = the source's own (or none)
    note: str

    def path(self) -> Path | None:
        """Folder of the sequence (None for the synthetic room); MissingData when it is absent."""
        if not self.folder:
            return None
        path = SHARED_DATA / self.folder
        if not path.is_dir():
            raise MissingData(f"{path} not found; put the real sequences in ../shared/data next to the project")
        return path

    def gt_mesh_path(self) -> Path | None:
        path = self.path()
        return path / self.gt_mesh if path is not None and self.gt_mesh else None


DATASETS: dict[str, Dataset] = {
    "synthetic": Dataset("synthetic", "", "synthetic", "", "built-in room, exact depth, exact ground-truth mesh"),
    "fountain": Dataset(
        "fountain",
        "fountain_33",
        "7scenes",
        "reference_mesh.ply",
        "33 far-apart keyframes (not a video); the ground truth is a reference reconstruction 1.5-3 cm from "
        "the depth, covering only a 1.5 m cube around the fountain while the frames see more: Acc counts "
        "the surfaces outside it, and Acc/Comp below ~2 cm mean little",
    ),
    "redkitchen": Dataset(
        "redkitchen", "redkitchen_50", "7scenes", "", "7-Scenes, Kinect v1; no ground-truth mesh: image metrics only"
    ),
    "icl": Dataset(
        "icl",
        "icl_livingroom1_211",
        "7scenes",
        "",
        "Augmented ICL-NUIM livingroom1, 211 frames of a rendered living room with clean synthetic depth; "
        "no ground-truth mesh: image metrics only",
    ),
}


def pick(names: str, known: dict[str, object], what: str) -> list[str]:
    """Comma-separated names checked against `known` (error listing the valid ones)."""
    picked = [n.strip() for n in names.split(",") if n.strip()]
    unknown = [n for n in picked if n not in known]
    if unknown or not picked:
        raise SystemExit(f"unknown {what} {', '.join(unknown) or '(none given)'}; choose from {', '.join(known)}")
    return picked


def dataset_config(
    ds: Dataset, frames: int | None, overrides: list[str], config_files: Sequence[str | Path] = ()
) -> Config:
    """Configuration as `h2viz map --data <dataset> --config FILE...` resolves it: defaults <- configs/<format>.yaml
    <- each of `config_files` <- the frame cap <- `overrides` (section.key=value)."""
    cfg = load_config()
    per_source = source_config_file(ds.fmt)
    if per_source is not None:
        apply_file(cfg, per_source)
    for path in config_files:
        apply_file(cfg, path)
    path = ds.path()
    cfg.source.path = str(path) if path is not None else ""
    cfg.source.format = ds.fmt
    if frames is not None:
        cfg.source.max_frames = frames
    return apply_overrides(cfg, overrides)


def fmt(value: float | None, digits: int = 2) -> str:
    """A table cell: the value rounded, or "-" when it is missing or not finite."""
    if value is None or not math.isfinite(value):
        return "-"
    return f"{value:.{digits}f}"


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A markdown table with columns padded to line up in a terminal."""
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    line = lambda cells: "| " + " | ".join(c.ljust(w) for c, w in zip(cells, widths, strict=True)) + " |"
    rule = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    return "\n".join([line(header), rule, *(line(r) for r in rows)])


def command_line(script: str) -> str:
    """The command that reproduces this run, from the project root."""
    return " ".join([".venv/bin/python", script, *map(shlex.quote, sys.argv[1:])])


def machine() -> str:
    """The CPU model and core count, e.g. "AMD EPYC 7B13, 2 cores"."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{model}, {os.cpu_count()} cores"


def commit() -> str:
    """The checkout's commit (short), with "+changes" when the work tree differs from it; "unknown" outside git."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True)  # fmt: skip
    except OSError:
        return "unknown"
    if head.returncode != 0:
        return "unknown"
    return head.stdout.strip() + ("+changes" if dirty.stdout.strip() else "")


def write_doc(path: str | Path, title: str, body: str) -> Path:
    """Write a measurement page: a title, the stamp (date, commit, CPU) and the benchmark's report."""
    stamp = f"Measured {datetime.date.today().isoformat()} at commit {commit()} on {machine()}."
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"# {title}\n\n{stamp}\n\n{body}\n")
    return path
