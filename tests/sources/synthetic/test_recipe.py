"""The synthetic room's palettes are data (assets/synthetic_room.yaml): an edited copy repaints the room without
moving it, and a broken one is a clear error naming the file and the entry."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from h2viz.config import SourceConfig, SyntheticConfig
from h2viz.errors import SourceError
from h2viz.sources.base import make_source
from h2viz.sources.synthetic.layout import RECIPE, load_recipe

ROOT = Path(__file__).resolve().parents[3]


def _last_frame(recipe: str = "") -> tuple[np.ndarray, np.ndarray]:
    synthetic = SyntheticConfig(width=96, height=72, n_frames=40, prefetch=0, recipe=recipe)
    frame = list(make_source(SourceConfig(format="synthetic", max_frames=3, stride=10, synthetic=synthetic)))[-1]
    return frame.rgb, frame.depth_m


def test_the_packaged_recipe_is_the_assets_file_and_loads() -> None:
    assert Path(str(RECIPE)).resolve() == (ROOT / "assets" / "synthetic_room.yaml").resolve()
    recipe = load_recipe()
    assert len(recipe.wall_paints) == 4 and len(recipe.sofas) == 4 and recipe.metal == (0.22, 0.22, 0.24)


def test_an_edited_recipe_repaints_the_room_and_keeps_its_geometry(tmp_path: Path) -> None:
    data = yaml.safe_load(Path(str(RECIPE)).read_text())
    # every wall pure red and the floor blue, as many entries as before (the seed's draws stay the same)
    data["wall_paints"] = [[[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]] * len(data["wall_paints"])
    data["floor_woods"] = [[0.0, 0.0, 1.0]] * len(data["floor_woods"])
    edited = tmp_path / "red_room.yaml"
    edited.write_text(yaml.safe_dump(data))
    rgb, depth = _last_frame()
    red_rgb, red_depth = _last_frame(str(edited))
    np.testing.assert_array_equal(red_depth, depth)  # the furniture did not move
    changed = np.abs(red_rgb.astype(int) - rgb.astype(int)).max(axis=2) > 30
    assert 0.2 < changed.mean() < 1.0  # walls and floor repainted, the rest not necessarily
    r, g, b = (red_rgb[..., k][changed].astype(float).mean() for k in range(3))
    assert max(r, b) > 2 * g  # the new pixels are red or blue, not green


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        ({"rugs": [[0.1, 0.2]]}, r"rugs\[0\] must be a colour \[r, g, b\]"),
        ({"sofas": [[0.1, 0.2, 1.5]]}, r"sofas\[0\] must be a colour"),
        ({"ceramics": [[0.1, 0.2, 0.3]]}, r"every entry of 'ceramics' is a pair of colours; entry 0"),
        ({"carpets": [[0.1, 0.2, 0.3]]}, r"unknown recipe key\(s\) carpets; the keys are wall_paints"),
        ({"chair_paints": []}, r"'chair_paints' must be a non-empty list"),
    ],
)
def test_a_broken_recipe_names_the_file_and_the_entry(tmp_path: Path, edit: dict, message: str) -> None:
    data = {**yaml.safe_load(Path(str(RECIPE)).read_text()), **edit}
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(data))
    with pytest.raises(SourceError, match=message) as e:
        load_recipe(str(bad))
    assert str(bad) in str(e.value)


def test_a_missing_recipe_file_says_what_to_pass(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match=r"nowhere.yaml cannot be read .*source.synthetic.recipe"):
        load_recipe(str(tmp_path / "nowhere.yaml"))
