"""bench/gpu.py: its report on a tiny CPU run, and the clear stop when no CUDA device is there."""

from __future__ import annotations

import sys

import pytest
import torch

from bench import gpu

TINY = ["source.synthetic.width=96", "source.synthetic.height=72", "mapping.representation.hash_log2_size=14",
        "mapping.representation.min_points_per_voxel=1", "mapping.sampling.rays_per_iter=512",
        "mapping.optimization.max_iters=3"]  # fmt: skip


def test_the_report_names_the_backend_and_times_every_stage() -> None:
    report = gpu.run(3, "cpu", TINY)
    assert report.startswith("Backend ")
    rows = {line.split("|")[1].strip(): line.split("|")[2].strip() for line in report.splitlines() if "|" in line}
    for stage in ("mapping, first frame", "mapping, per frame (median)", "mesh, whole map",
                  "render rgb 96x72 (median of 3)", "render depth 96x72 (median of 3)"):  # fmt: skip
        assert float(rows[stage]) > 0.0, stage
    assert "Reproduce: `" in report


@pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA device is present")
def test_without_cuda_it_stops_and_says_how_to_check_the_script(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(sys, "argv", ["bench/gpu.py"])
    assert gpu.main() == 2
    assert "--device cpu" in capsys.readouterr().err
