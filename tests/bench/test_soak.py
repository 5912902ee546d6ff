"""bench/soak.py on a handful of tiny frames: three wire clients connect, samples and the plot are written, the
killed run loses at most one autosave interval and, resumed, ends with the uninterrupted run's mesh."""

from __future__ import annotations

from pathlib import Path

import cv2

from bench import soak

TINY = [
    "--set", "mapping.representation.min_points_per_voxel=1", "--set", "mapping.representation.hash_log2_size=14",
    "--set", "mapping.sampling.rays_per_iter=1024", "--set", "mapping.optimization.max_iters=2", "--set",
    "mapping.runtime.device=cpu",
]  # fmt: skip


def test_a_tiny_soak_samples_memory_and_recovers_from_sigkill(tmp_path: Path) -> None:
    out = tmp_path / "soak"
    argv = ["--frames", "16", "--laps", "2", "--width", "96", "--sample-every", "4", "--autosave-every", "3",
            "--budget-mb", "0.4", "--no-explore", "--seed", "3", "--out", str(out), "--doc", str(tmp_path / "soak.md"),
            "--side-by-side",
            *TINY]  # fmt: skip
    text = soak.main(argv)
    revisit = soak.read_samples(out / "revisit")
    assert [s["frame"] for s in revisit] == [1, 4, 8, 12, 16]  # the first frame, then every 4
    assert all(s["clients"] == 3 for s in revisit) and all(s["rss_mb"] > 100 for s in revisit)
    assert max(s["keyframe_mb"] for s in revisit) <= 0.4
    rows = {line.split("|")[1].strip(): line for line in text.splitlines() if line.startswith("| ")}
    crash = next(v for k, v in rows.items() if k.startswith("SIGKILL at frame"))
    assert crash.rstrip(" |").endswith("yes")  # at most one autosave interval lost
    lost = int(crash.split("|")[3].split()[0])
    assert 0 <= lost <= 3
    for key in ("resumed vs uninterrupted mesh: faces differ", "resumed vs uninterrupted mesh: vertex distance"):
        assert next(v for k, v in rows.items() if k.startswith(key)).rstrip(" |").endswith("yes"), text
    crash_samples = soak.read_samples(out / "crash")
    assert crash_samples[-1]["frame"] == 16  # resumed to the end, frames counted on from the checkpoint
    image = cv2.imread(str(tmp_path / "soak.png"))
    assert image is not None and image.shape[1] > 1000
    assert "Measured" in (tmp_path / "soak.md").read_text() and "soak.png" in (tmp_path / "soak.md").read_text()
