"""Damaged bags and playback: files cut in half (ROS 1, ROS 2 sqlite3, ROS 2 mcap) still give the frames
before the cut, with a message naming the file; real-time mode paces frames at the bag's rate and
drops the older ones when the consumer is slow (driven by a fake clock, no wall-clock asserts)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from h2viz.config import SourceConfig
from h2viz.errors import SourceError
from h2viz.sources.rosbag import RosbagSource, bag_info
from tests.sources.rosbag.bagwriter import BagOptions, storage_file, synthetic_frames, write_bag

FRAMES, K = synthetic_frames()


def cut_in_half(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def source(path: Path, **rosbag: object) -> RosbagSource:
    cfg = SourceConfig(format="rosbag", path=str(path))
    for key, value in rosbag.items():
        setattr(cfg.rosbag, key, value)
    return RosbagSource(cfg)


@pytest.mark.parametrize(
    ("kind", "opt"),
    [
        ("ros1", BagOptions()),
        ("ros1", BagOptions(ros1_compression="lz4", chunk_bytes=150_000)),
        ("sqlite3", BagOptions()),
        ("mcap", BagOptions()),
    ],
    ids=["ros1", "ros1-lz4-chunks", "sqlite3", "mcap"],
)
def test_bag_cut_in_half_gives_the_frames_before_the_cut(
    tmp_path: Path, kind: str, opt: BagOptions, caplog: pytest.LogCaptureFixture
) -> None:
    bag = write_bag(tmp_path / ("b.bag" if kind == "ros1" else "b"), kind, FRAMES, K, opt)
    damaged = bag if kind == "ros1" else storage_file(bag)
    cut_in_half(damaged)
    with caplog.at_level(logging.WARNING, logger="h2viz.sources.rosbag"):
        src = source(bag)
    frames = list(src)
    assert 2 <= len(frames) <= 8, len(frames)
    for got, want in zip(frames, FRAMES, strict=False):
        np.testing.assert_array_equal(got.rgb, want.rgb)
        np.testing.assert_allclose(got.depth_m, want.depth_m, atol=1e-6)
        np.testing.assert_allclose(got.T_world_camera, want.T_world_camera, atol=1e-6)
    assert damaged.name in caplog.text and "could not be opened normally" in caplog.text
    damage = [s for s in src.skipped if s.key == str(bag)]
    assert len(damage) == 1 and damaged.name in damage[0].reason and "lost" in damage[0].reason
    assert "damaged" in bag_info(bag, SourceConfig().rosbag)


def test_garbage_file_is_a_source_error_naming_it(tmp_path: Path) -> None:
    path = tmp_path / "noise.bag"
    path.write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    with pytest.raises(SourceError, match=r"noise\.bag.*cannot be read as a ROS bag"):
        source(path)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(SourceError, match=r"empty\.mcap"):
        source(empty)


class FakeClock:
    """Wall clock that only moves when the source sleeps or the consumer works."""

    def __init__(self) -> None:
        self.now = 100.0
        self.slept: list[float] = []

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.slept.append(seconds)
        self.now += seconds


def paced_source(tmp_path: Path, clock: FakeClock) -> RosbagSource:
    src = source(write_bag(tmp_path / "b.bag", "ros1", FRAMES, K))
    src.cfg.realtime = True
    src.clock = clock  # type: ignore[method-assign]
    src.sleep = clock.sleep  # type: ignore[method-assign]
    return src


def test_realtime_waits_for_each_frame_when_the_consumer_keeps_up(tmp_path: Path) -> None:
    clock = FakeClock()
    src = paced_source(tmp_path, clock)
    stamps = [f.timestamp for f in src]
    assert len(stamps) == 10 and src.dropped == 0
    np.testing.assert_allclose(clock.slept, np.diff(stamps), atol=1e-6)  # the bag's own rhythm


def test_realtime_takes_the_newest_frame_when_the_consumer_is_slow(tmp_path: Path) -> None:
    clock = FakeClock()
    src = paced_source(tmp_path, clock)
    got = []
    for frame in src:
        got.append(frame.index)
        clock.now += 0.1001  # mapping one frame takes three frame periods
    assert got == [0, 3, 6, 9]
    assert src.dropped == 6 and src.skipped == []
