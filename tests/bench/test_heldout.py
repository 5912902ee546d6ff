"""bench/heldout.py: which frames are held out, the own and common pixel masks, the scorer on renderers whose
errors are known exactly, and a tiny end-to-end run on the synthetic room in which no method sees a held-out
frame."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

import bench.common
from bench import heldout
from bench.heldout import common_mask, coverage_pct, heldout_split, is_heldout, rendered_mask, score_views
from h2viz.eval.mesh_render import MeshRenderer
from h2viz.eval.metrics import PSNR_MAX_DB
from h2viz.eval.report import EvalView
from h2viz.mapping.mapper import Mapper

HAVE_OPEN3D = importlib.util.find_spec("open3d") is not None

WIDTH, HEIGHT, PLANE_Z_M = 64, 48, 2.0
K = np.array([[60.0, 0.0, (WIDTH - 1) / 2], [0.0, 60.0, (HEIGHT - 1) / 2], [0.0, 0.0, 1.0]])
PLANE_RGB = np.array([200, 80, 30], dtype=np.uint8)


# --------------------------------------------------------------------------------------------- split


@pytest.mark.parametrize(
    ("n", "k", "held"),
    [(10, 10, [5]), (25, 10, [5, 15]), (12, 4, [2, 6, 10]), (7, 3, [1, 4]), (5, 2, [1, 3]), (4, 10, [])],
)
def test_every_kth_frame_from_k_half_is_held_out_and_the_rest_mapped(n: int, k: int, held: list[int]) -> None:
    mapped, scored = heldout_split(n, k)
    assert scored == held
    assert mapped == [p for p in range(n) if p not in held]  # in order, none both, none left out
    assert [is_heldout(p, k) for p in range(n)] == [p in held for p in range(n)]


def test_k_zero_holds_nothing_out() -> None:
    assert heldout_split(5, 0) == ([0, 1, 2, 3, 4], [])


# --------------------------------------------------------------------------------------------- masks


def test_common_mask_needs_the_capture_and_every_method() -> None:
    gt = np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 1.0]])
    a = np.array([[1.0, 0.0, 1.0], [1.0, 1.0, 1.0]])
    b = np.array([[1.0, 1.0, 1.0], [np.nan, 1.0, 0.0]])
    c = np.array([[2.0, 2.0, 2.0], [2.0, 2.0, np.inf]])
    assert common_mask(gt, [a, b, c]).tolist() == [[True, False, False], [False, True, False]]
    assert common_mask(gt, []).tolist() == (gt > 0).tolist()
    assert coverage_pct(rendered_mask(a, gt), gt) == pytest.approx(80.0)  # 4 of the 5 captured pixels
    assert coverage_pct(rendered_mask(b, gt), gt) == pytest.approx(60.0)  # NaN and 0 are not rendered
    assert coverage_pct(common_mask(gt, [a, b, c]), gt) == pytest.approx(40.0)
    assert math.isnan(coverage_pct(np.ones((2, 3), bool), np.zeros((2, 3))))


# ------------------------------------------------------------------------------------------- scoring


def _view(seed: int = 0) -> EvalView:
    """A textured wall at PLANE_Z_M seen straight on by the camera at the origin."""
    rgb = np.random.default_rng(seed).integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
    return K, np.eye(4), rgb, np.full((HEIGHT, WIDTH), PLANE_Z_M, dtype=np.float32)


def _offset_renderer(view: EvalView, offset_m: np.ndarray | float):
    """A renderer that returns the view's own colour and its depth + `offset_m` (scalar or (H,W))."""
    _, _, rgb, depth = view

    def render(K: np.ndarray, T: np.ndarray, h: int, w: int, mode: str) -> np.ndarray:
        assert (h, w) == depth.shape
        return rgb.astype(np.float32) / 255.0 if mode == "rgb" else (depth + offset_m).astype(np.float32)

    return render


def test_scores_of_renderers_with_known_errors() -> None:
    view = _view()
    half = np.zeros((HEIGHT, WIDTH), dtype=np.float32)
    half[:, : WIDTH // 2] = 0.10
    renders = {
        "exact": _offset_renderer(view, 0.0),
        "plus3": _offset_renderer(view, 0.03),
        "half10": _offset_renderer(view, half),
    }
    scores = {name: per_view[0] for name, per_view in score_views(renders, [view, view], 1).items()}
    exact, plus3, half10 = scores["exact"]["own"], scores["plus3"]["own"], scores["half10"]["own"]
    assert exact["depth_l1_cm"] == 0.0 and exact["over_5cm_pct"] == 0.0 and exact["signed_cm"] == 0.0
    assert exact["psnr_db"] == PSNR_MAX_DB and exact["ssim"] == pytest.approx(1.0)
    assert plus3["depth_l1_cm"] == pytest.approx(3.0, abs=1e-4) and plus3["signed_cm"] == pytest.approx(3.0, abs=1e-4)
    assert plus3["over_5cm_pct"] == 0.0 and plus3["psnr_db"] == PSNR_MAX_DB
    assert half10["over_5cm_pct"] == pytest.approx(50.0) and half10["depth_l1_cm"] == pytest.approx(5.0, abs=1e-4)
    for name in renders:  # all render every pixel: the common pixels are their own
        assert scores[name]["own"] == scores[name]["common"] and scores[name]["own"]["coverage_pct"] == 100.0


def test_field_and_mesh_renderers_are_scored_by_the_same_function() -> None:
    """An exact field-like renderer (a bound `render` method, depth 3 cm behind) and a ray cast mesh covering
    only the left half of the wall: the common pixels are that half, for both."""
    _, T, _, depth = view = _view()
    view = (K, T, np.broadcast_to(PLANE_RGB, (HEIGHT, WIDTH, 3)).copy(), depth)

    class FieldLike:
        render = staticmethod(_offset_renderer(view, 0.03))

    left = trimesh.Trimesh(
        [[-5.0, -5.0, PLANE_Z_M], [0.0, -5.0, PLANE_Z_M], [0.0, 5.0, PLANE_Z_M], [-5.0, 5.0, PLANE_Z_M]],
        [[0, 1, 2], [0, 2, 3], [0, 2, 1], [0, 3, 2]],  # both sides face the camera
        vertex_colors=np.tile(np.append(PLANE_RGB, 255), (4, 1)),
        process=False,
    )
    scores = score_views({"field": FieldLike().render, "mesh": MeshRenderer(left)}, [view], 1)
    field, mesh = scores["field"][0], scores["mesh"][0]
    assert field["own"]["coverage_pct"] == 100.0 and mesh["own"]["coverage_pct"] == pytest.approx(50.0, abs=1.0)
    assert field["common"]["coverage_pct"] == mesh["common"]["coverage_pct"] == mesh["own"]["coverage_pct"]
    assert mesh["own"]["depth_l1_cm"] < 1e-3 and mesh["own"]["psnr_db"] > 60.0 and mesh["own"]["over_5cm_pct"] == 0
    assert field["common"]["depth_l1_cm"] == pytest.approx(3.0, abs=1e-4)
    assert field["common"]["signed_cm"] == pytest.approx(3.0, abs=1e-4)


def test_means_leave_out_views_without_pixels() -> None:
    means = heldout.mean_scores([{"psnr_db": 20.0, "ssim": math.nan}, {"psnr_db": 30.0, "ssim": math.nan}])
    assert means["psnr_db"] == 25.0 and math.isnan(means["ssim"]) and means["n_views"] == 2.0


def test_variants_are_named_mapping_overrides() -> None:
    v = heldout.parse_variant("l2=mapping.losses.rgb_loss=l2,mapping.optimization.max_iters=3")
    assert v == heldout.Variant("l2", ("mapping.losses.rgb_loss=l2", "mapping.optimization.max_iters=3"))
    for bad in ("l2", "=mapping.losses.rgb_loss=l2", "tsdf=mapping.losses.rgb_loss=l2", "x=source.downscale=2"):
        with pytest.raises(SystemExit):
            heldout.parse_variant(bad)
    names = [m.name for m in heldout.pick_methods("tsdf,h2viz-mesh", [v], variant_mesh=True)]
    assert names == ["tsdf", "h2viz-mesh", "l2", "l2-mesh"]


def test_a_variant_takes_the_mapping_section_of_a_config_file(tmp_path: Path) -> None:
    v = heldout.parse_variant(f"paper=@{bench.common.ROOT / 'configs' / 'paper.yaml'}")
    assert "mapping.color.color_prior=false" in v.overrides and "mapping.sampling.free_samples=-1" in v.overrides
    cfg = bench.common.apply_overrides(bench.common.load_config(), list(v.overrides))
    assert cfg.mapping.rendering.render_surface is False and cfg.mapping.losses.rgb_loss == "l1"
    other = tmp_path / "other.yaml"
    other.write_text("source:\n  downscale: 2\n")
    with pytest.raises(SystemExit, match="only change mapping"):
        heldout.parse_variant(f"x=@{other}")
    with pytest.raises(SystemExit, match="cannot read"):
        heldout.parse_variant(f"x=@{tmp_path / 'missing.yaml'}")


def test_a_measurement_page_is_stamped_with_commit_and_cpu(tmp_path: Path) -> None:
    page = bench.common.write_doc(tmp_path / "docs" / "x.md", "Held-out views", "| a |\n|---|")
    text = page.read_text()
    assert text.startswith("# Held-out views\n") and "at commit " in text and " cores." in text
    assert text.rstrip().endswith("|---|")


# ---------------------------------------------------------------------------------------- end to end

TINY = [
    "source.synthetic.width=160",
    "source.synthetic.height=120",
    "mapping.optimization.max_iters=2",
    "mapping.representation.hash_log2_size=14",
    "mapping.runtime.threads=2",
]


@pytest.mark.slow
def test_heldout_run_scores_every_method_on_frames_none_of_them_mapped(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    monkeypatch.setattr(bench.common, "SHARED_DATA", tmp_path / "absent")  # the real sequences are "missing"
    given: list[tuple[str, int]] = []  # (run, frame index) of every frame a method was given

    def spy(cls: type, run: str) -> None:
        integrate = cls.integrate
        monkeypatch.setattr(cls, "integrate", lambda self, f: (given.append((run, f.index)), integrate(self, f))[1])

    spy(Mapper, "h2viz")
    methods = ["h2viz", "h2viz-mesh", "l2"]
    if HAVE_OPEN3D:
        from bench.tsdf_baseline import TsdfFusion

        spy(TsdfFusion, "tsdf")
        methods.insert(2, "tsdf")
    argv = ["--datasets", "synthetic,fountain", "--methods", ",".join(m for m in methods if m != "l2")]
    argv += ["--frames", "12", "--k", "4", "--variant", "l2=mapping.losses.rgb_loss=l2"]
    argv += [arg for item in TINY for arg in ("--set", item)]
    argv += ["--json", str(tmp_path / "rows.json"), "--images", str(tmp_path / "images")]
    assert heldout.main(argv) == 0

    out = capsys.readouterr().out
    table = [[c.strip() for c in line.strip("|").split("|")] for line in out.splitlines() if line.startswith("| ")]
    assert table[0][:4] == ["sequence", "method", "mapped", "held out"]
    assert [(r[0], r[1]) for r in table[1:]] == [(d, m) for d in ("synthetic", "fountain") for m in methods]
    assert "fountain did not run" in out and "command: .venv/bin/python bench/heldout.py" in out

    held = [2, 6, 10]
    assert sorted(i for run, i in given if run == "h2viz") == sorted(2 * [p for p in range(12) if p not in held])
    assert not HAVE_OPEN3D or sorted(i for run, i in given if run == "tsdf") == [p for p in range(12) if p not in held]
    rows = {(r["sequence"], r["method"]): r for r in json.loads((tmp_path / "rows.json").read_text())["rows"]}
    for method in methods:
        row = rows[("synthetic", method)]
        assert row["note"] == "" and row["mapped"] == 9 and row["heldout"] == 3 and len(row["frame_times_s"]) == 9
        assert [v["position"] for v in row["per_view"]] == held
        for part in ("own", "common"):
            for key in ("psnr_db", "ssim", "depth_l1_cm", "over_5cm_pct", "signed_cm", "coverage_pct"):
                assert math.isfinite(row[part][key]), (method, part, key)
        assert 0 < row["common"]["coverage_pct"] <= row["own"]["coverage_pct"] <= 100.0
        assert "not found" in rows[("fountain", method)]["note"]
    assert rows[("synthetic", "h2viz-mesh")]["frame_times_s"] == rows[("synthetic", "h2viz")]["frame_times_s"]
    assert sorted(p.name for p in (tmp_path / "images").iterdir()) == [f"synthetic_{p:05d}.png" for p in held]
