"""Layout detection: each folder layout is recognised by exactly one source, near misses by none, and
an unrecognised folder gets an error listing what was looked for."""

from __future__ import annotations

import importlib.util
from collections.abc import Callable
from pathlib import Path

import pytest

from h2viz.config import IntrinsicsConfig, SourceConfig
from h2viz.errors import SourceError
from h2viz.sources.base import FORMATS, detect_format, make_source
from h2viz.sources.replica import ReplicaSource
from h2viz.sources.scannet import ScanNetSource
from h2viz.sources.sevenscenes import SevenScenesSource
from h2viz.sources.tum import TumSource
from tests.conftest import shared_data
from tests.sources.fixtures import (
    Fixture,
    fixture_rgb,
    write_color,
    write_replica,
    write_scannet,
    write_sevenscenes,
    write_tum,
)

FOLDER_SOURCES = {
    "replica": ReplicaSource,
    "scannet": ScanNetSource,
    "tum": TumSource,
    "7scenes": SevenScenesSource,
}
WRITERS: dict[str, Callable[[Path], Fixture]] = {
    "replica": lambda p: write_replica(p, broken=False),
    "scannet": lambda p: write_scannet(p, broken=False),
    "tum": lambda p: write_tum(p, broken=False),
    "7scenes": lambda p: write_sevenscenes(p, broken=False),
}


def matching(path: Path) -> list[str]:
    return [name for name, cls in FOLDER_SOURCES.items() if cls.looks_like(path)]


@pytest.mark.parametrize("fmt", list(WRITERS))
def test_each_layout_is_detected_by_exactly_one_source(tmp_path: Path, fmt: str) -> None:
    fx = WRITERS[fmt](tmp_path / "data")
    assert matching(fx.root) == [fmt]
    assert detect_format(fx.root) == fmt
    assert detect_format(str(fx.root)) == fmt
    # Replica has no intrinsics file and the 64x48 fixture is not the default 1200x680 camera
    intrinsics = (
        IntrinsicsConfig(fx=50.0, fy=50.0, cx=31.5, cy=23.5) if fmt == "replica" else IntrinsicsConfig()
    )
    src = make_source(SourceConfig(path=str(fx.root), intrinsics=intrinsics))
    assert isinstance(src, FOLDER_SOURCES[fmt]) and src.format_name == fmt
    assert src.cfg.format == fmt and len(list(src)) == len(fx.poses)


def test_module_table_points_at_the_classes() -> None:
    for fmt, cls in FOLDER_SOURCES.items():
        assert (FORMATS[fmt].module, FORMATS[fmt].cls) == (cls.__module__, cls.__name__)


@pytest.mark.parametrize(
    ("name", "fmt"), [("redkitchen_50", "7scenes"), ("fountain_33", "7scenes"), ("tum_fr1_xyz_10", "tum")]
)
def test_real_sequences_are_detected(name: str, fmt: str) -> None:
    path = shared_data(name)
    if not path.is_dir():
        pytest.skip(f"real data {name} not found in ../shared/data")
    assert matching(path) == [fmt]
    assert detect_format(path) == fmt


def test_near_misses_match_nothing(tmp_path: Path) -> None:
    replica = tmp_path / "replica_no_depth"  # colour only in results/
    write_color(replica / "results" / "frame000000.jpg", fixture_rgb(0))
    scannet = write_scannet(tmp_path / "scannet_no_pose", broken=False).root
    for p in (scannet / "pose").iterdir():
        p.unlink()
    (scannet / "pose").rmdir()
    tum = tmp_path / "tum_rgb_only"
    tum.mkdir()
    (tum / "rgb.txt").write_text("# color images\n")
    seven = tmp_path / "seven_colour_only"
    write_color(seven / "frame-000000.color.png", fixture_rgb(0))
    padded = tmp_path / "seven_unpadded"  # 7-Scenes names carry six digits
    write_color(padded / "frame-0.depth.png", fixture_rgb(0))
    bag = tmp_path / "run.bag"
    bag.write_bytes(b"#ROSBAG V2.0\n")
    for path in (replica, scannet, tum, seven, padded, bag, tmp_path / "missing"):
        assert matching(path) == [], path


def test_unrecognised_folder_lists_what_was_looked_for(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    if importlib.util.find_spec("h2viz.sources.rosbag") is None:  # checked with the bag source when present
        monkeypatch.delitem(FORMATS, "rosbag")
    folder = tmp_path / "holiday_photos"
    write_color(folder / "IMG_0001.jpg", fixture_rgb(0))
    with pytest.raises(SourceError) as err:
        detect_format(folder)
    message = str(err.value)
    assert str(folder) in message and "--format" in message
    for fmt, info in FORMATS.items():
        if fmt != "synthetic":
            assert f"{fmt}: {info.looks_for}" in message


def test_missing_path_and_wrong_explicit_format(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="does not exist"):
        detect_format(tmp_path / "nope")
    fx = write_sevenscenes(tmp_path / "seq", n=2, broken=False)
    with pytest.raises(SourceError, match="rgb.txt"):  # a 7-Scenes folder opened as TUM
        make_source(SourceConfig(format="tum", path=str(fx.root)))
    with pytest.raises(SourceError, match="not a directory"):
        make_source(SourceConfig(format="7scenes", path=str(fx.root / "frame-000000.pose.txt")))
