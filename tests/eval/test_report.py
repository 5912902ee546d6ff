"""The eval back-end: image metrics through a renderer, mesh metrics from files, table and JSON."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from h2viz.config import EvalConfig
from h2viz.eval.mesh_render import MeshRenderer
from h2viz.eval.metrics import PSNR_MAX_DB, EvalError
from h2viz.eval.report import (
    evaluate_images,
    evaluate_mesh_files,
    format_table,
    image_metrics,
    write_metrics,
)
from h2viz.geometry import look_at
from h2viz.types import RgbdFrame
from tests.eval.scenes import grid_plane, plane_texture, render_textured_plane

H, W = 120, 160
K = np.array([[100.0, 0.0, 79.5], [0.0, 100.0, 59.5], [0.0, 0.0, 1.0]])
Y_DOWN = np.array([0.0, -1.0, 0.0])
POSES = [look_at(np.array([x, 0.1, 0.0]), np.array([0.0, 0.0, 2.0]), Y_DOWN) for x in (-0.3, 0.0, 0.4)]


def _views() -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Ground truth of the textured plane z = 2: colour as uint8, exact depth."""
    out = []
    for T in POSES:
        rgb = np.round(render_textured_plane(K, T, H, W, "rgb") * 255).astype(np.uint8)
        out.append((K, T, rgb, render_textured_plane(K, T, H, W, "depth")))
    return out


# ---------------------------------------------------------------------------------- image metrics


def test_exact_renderer_scores_perfectly_at_full_and_reduced_resolution() -> None:
    full = image_metrics(render_textured_plane, _views(), downscale=1)
    assert full["n_views"] == 3 and full["valid_pct"] == 100.0
    assert full["psnr_db"] > 55.0  # only the uint8 rounding of the ground truth remains
    assert full["ssim"] > 0.999 and full["depth_l1_cm"] < 1e-4
    # at half resolution the area-averaged ground truth must line up with the rendered pixel centres
    # (a half-pixel error in the scaled intrinsics drops this to about 32 dB)
    half = image_metrics(render_textured_plane, _views(), downscale=2)
    assert half["psnr_db"] > 50.0 and half["ssim"] > 0.999 and half["depth_l1_cm"] < 0.01


def test_noise_and_depth_offset_are_measured() -> None:
    rng = np.random.default_rng(0)

    def render(K: np.ndarray, T: np.ndarray, h: int, w: int, mode: str) -> np.ndarray:
        exact = render_textured_plane(K, T, h, w, mode)
        if mode == "depth":
            return exact + 0.02
        return exact + rng.normal(0.0, 0.01, exact.shape).astype(np.float32)  # texture stays in [0.1, 0.9]

    m = image_metrics(render, _views())
    assert m["psnr_db"] == pytest.approx(40.0, abs=0.2)
    assert m["depth_l1_cm"] == pytest.approx(2.0, abs=1e-3)
    assert 0.5 < m["ssim"] < 0.999


def test_only_pixels_with_both_depths_count() -> None:
    views = _views()
    for _, _, rgb, depth in views:
        rgb[:10] = 255 - rgb[:10]  # wrong ground-truth colour where the ground truth has no depth
        depth[:10] = 0.0

    def render(K: np.ndarray, T: np.ndarray, h: int, w: int, mode: str) -> np.ndarray:
        exact = render_textured_plane(K, T, h, w, mode)
        if mode == "depth":
            exact[:, : w // 2] = 0.0  # nothing rendered on the left half ...
        else:
            exact[:, : w // 2] = 1.0 - exact[:, : w // 2]  # ... where the colour is wrong
        return exact

    m = image_metrics(render, views)
    assert m["psnr_db"] > 55.0 and m["ssim"] > 0.999 and m["depth_l1_cm"] < 1e-4
    assert m["valid_pct"] == pytest.approx(100.0 * (H - 10) * (W // 2) / (H * W))


def test_renderer_with_wrong_shapes_is_an_error() -> None:
    with pytest.raises(EvalError, match="renderer returned"):
        image_metrics(lambda K, T, h, w, mode: np.zeros((h, w)), _views())


def test_evaluate_images_interpolated_and_extrapolated() -> None:
    plane = grid_plane(-4.0, 4.0, -4.0, 4.0, z=2.0, cells=200)
    colours = plane_texture(plane.vertices[:, 0], plane.vertices[:, 1])
    plane.visual.vertex_colors = np.round(colours * 255).astype(np.uint8)
    gt = MeshRenderer(plane)
    frames = []
    for i, x in enumerate(np.linspace(-0.5, 0.5, 8)):
        T = look_at(np.array([x, 0.0, 0.0]), np.array([x, 0.2, 2.0]), Y_DOWN)
        rgb = np.round(gt(K, T, H, W, "rgb") * 255).astype(np.uint8)
        frames.append(RgbdFrame(i, i / 30, rgb, gt(K, T, H, W, "depth"), K, T))
    cfg = EvalConfig(n_interpolate=4, n_extrapolate=3, render_downscale=2)
    out = evaluate_images(MeshRenderer(plane), frames, cfg, gt_render=gt)
    assert out["interpolate"]["n_views"] == 4 and out["extrapolate"]["n_views"] == 3
    assert out["interpolate"]["psnr_db"] > 45.0 and out["interpolate"]["ssim"] > 0.99
    assert out["interpolate"]["depth_l1_cm"] < 0.01
    # novel views are scored against the ground-truth renderer itself: a perfect map scores perfectly
    assert out["extrapolate"]["psnr_db"] == PSNR_MAX_DB and out["extrapolate"]["depth_l1_cm"] == 0.0
    assert out["extrapolate"]["valid_pct"] > 50.0
    assert "extrapolate" not in evaluate_images(MeshRenderer(plane), frames, cfg)


# ----------------------------------------------------------------------------------- mesh files


def test_evaluate_mesh_files_from_written_meshes(tmp_path: Path) -> None:
    gt = grid_plane(-0.15, 0.15, -0.15, 0.15, z=0.0, cells=30)
    rec = gt.copy()
    rec.apply_translation([0.0, 0.0, 0.01])
    gt.export(tmp_path / "gt.ply")
    rec.export(tmp_path / "rec.obj")
    cfg = EvalConfig(n_points=40_000)
    m = evaluate_mesh_files(tmp_path / "rec.obj", tmp_path / "gt.ply", cfg)
    assert m["acc_cm"] == pytest.approx(1.0, abs=0.05) and m["comp_cm"] == pytest.approx(1.0, abs=0.05)
    assert m["comp_ratio"] == 100.0
    culled = evaluate_mesh_files(tmp_path / "rec.obj", tmp_path / "gt.ply", cfg, lambda p: p[:, 0] < 0.0)
    assert culled["gt_kept_pct"] == pytest.approx(50.0, abs=1.5)


def test_evaluate_mesh_files_errors_name_the_file(tmp_path: Path) -> None:
    good = tmp_path / "good.ply"
    grid_plane(0.0, 1.0, 0.0, 1.0, cells=2).export(good)
    (tmp_path / "garbage.ply").write_text("garbage\n")
    (tmp_path / "empty.obj").write_text("")
    trimesh.PointCloud(np.random.default_rng(0).uniform(size=(50, 3))).export(tmp_path / "cloud.ply")
    cfg = EvalConfig(n_points=1000)
    cases = {"missing.ply": "does not exist", "garbage.ply": "cannot be read", "empty.obj": "no triangles"}
    cases["cloud.ply"] = "no triangles"
    for name, message in cases.items():
        with pytest.raises(EvalError, match=message) as err:
            evaluate_mesh_files(tmp_path / name, good, cfg)
        assert name in str(err.value)
    with pytest.raises(EvalError, match="missing.ply"):
        evaluate_mesh_files(good, tmp_path / "missing.ply", cfg)


# --------------------------------------------------------------------------------- presentation

METRICS = {
    "mesh": {
        "acc_cm": 1.23456789,
        "comp_cm": 2.5,
        "comp_ratio": 97.125,
        "fscore": 88.0,
        "n_gt_points": 200000.0,
    },
    "interpolate": {"psnr_db": 31.4159265, "ssim": 0.912345678, "depth_l1_cm": math.nan, "n_views": 20.0},
    "time_s": 12.0,
}


def test_format_table_lists_every_metric_with_value_and_unit() -> None:
    table = format_table(METRICS)
    lines = table.splitlines()
    assert lines[0].split() == ["metric", "value", "unit"]
    expected = {
        "mesh.acc_cm": ("1.2346", "cm"),
        "mesh.comp_cm": ("2.5000", "cm"),
        "mesh.comp_ratio": ("97.1250", "%"),
        "mesh.fscore": ("88.0000", "%"),
        "mesh.n_gt_points": ("200000", None),
        "interpolate.psnr_db": ("31.4159", "dB"),
        "interpolate.ssim": ("0.9123", None),
        "interpolate.depth_l1_cm": ("n/a", "cm"),
        "interpolate.n_views": ("20", None),
        "time_s": ("12.0000", "s"),
    }
    rows = {line.split()[0]: line.split()[1:] for line in lines[2:]}
    assert set(rows) == set(expected)
    for name, (value, unit) in expected.items():
        assert rows[name] == ([value, unit] if unit else [value]), name
    # columns are aligned: every value ends at the same column
    ends = {
        line.index(rows[n][0]) + len(rows[n][0])
        for n in expected
        for line in lines
        if line.startswith(n + " ")
    }
    assert len(ends) == 1


def test_metrics_json_round_trips(tmp_path: Path) -> None:
    path = write_metrics(METRICS, tmp_path)
    assert path == tmp_path / "metrics.json"
    back = json.loads(path.read_text())
    assert back["mesh"]["acc_cm"] == 1.23457 and back["interpolate"]["ssim"] == 0.912346
    assert back["interpolate"]["depth_l1_cm"] is None  # NaN is written as null
    assert back["mesh"]["n_gt_points"] == 200000 and back["time_s"] == 12.0
    assert set(back["mesh"]) == set(METRICS["mesh"]) and set(back) == set(METRICS)
    other = write_metrics(
        {"psnr_db": np.float32(40.5), "n": np.int64(3), "bad": math.inf}, tmp_path / "a" / "m.json"
    )
    assert json.loads(other.read_text()) == {"psnr_db": 40.5, "n": 3, "bad": None}
