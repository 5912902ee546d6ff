"""The synthetic room's frame cache: frames read back bit for bit as rendered, one folder per room
configuration, damaged or unwritable caches handled, and real-time playback prepared by rendering only
the frames not cached yet."""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from h2viz.config import SourceConfig, SyntheticConfig
from h2viz.sources.synthetic import frame_cache
from h2viz.sources.synthetic.frame_cache import FrameCache, cache_root, room_key
from h2viz.sources.synthetic.source import SyntheticSource

W, H = 96, 72


def make(folder: Path, **kw: object) -> SyntheticSource:
    synth = SyntheticConfig(width=W, height=H, n_frames=12, prefetch=0, cache_dir=str(folder))
    return SyntheticSource(SourceConfig(format="synthetic", synthetic=replace(synth, **kw)))


def no_rendering(src: SyntheticSource) -> None:
    def fail(*args: object) -> None:
        raise AssertionError("rendered a frame the cache holds")

    src.scene = replace_render(src.scene, fail)


def replace_render(scene: object, render: object) -> object:
    """The scene with `render` in place of its own (the scene object is shared by every source of its seed)."""

    class Wrapped:
        def __getattr__(self, name: str) -> object:
            return getattr(scene, name)

    wrapped = Wrapped()
    wrapped.render = render  # type: ignore[attr-defined]
    return wrapped


def test_the_codec_is_lossless_for_any_float32_bits(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    cache = FrameCache(tmp_path, H, W)
    bits = rng.integers(0, 2**32, (H, W), dtype=np.uint64).astype(np.uint32)  # NaNs, infinities, denormals too
    depth = bits.view(np.float32)
    depth[:, :10] = 0.0  # no hit
    depth[5] = np.linspace(0.5, 9.0, W, dtype=np.float32)  # a plane seen along a row
    rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    cache.put(3, rgb, depth)
    got = cache.get(3)
    assert got is not None
    assert np.array_equal(got[0], rgb) and np.array_equal(got[1].view(np.uint32), depth.view(np.uint32))
    assert got[0].flags.writeable and got[1].dtype == np.float32 and got[1].shape == (H, W)
    assert cache.get(4) is None


def test_frames_read_from_the_cache_are_the_rendered_ones(tmp_path: Path) -> None:
    first = make(tmp_path, depth_noise_m=0.01)
    rendered = [first.load(i, i) for i in (0, 5, 11)]
    assert first.cache is not None and sorted(p.name for p in first.cache.folder.iterdir()) == [
        "00000.frame",
        "00005.frame",
        "00011.frame",
    ]
    again = make(tmp_path, depth_noise_m=0.01)  # a later run of the same room
    no_rendering(again)
    for frame in rendered:
        read = again.load(frame.index, frame.index)
        assert np.array_equal(read.rgb, frame.rgb) and np.array_equal(read.depth_m, frame.depth_m)  # noise too
        assert np.array_equal(read.T_world_camera, frame.T_world_camera) and np.array_equal(read.K, frame.K)
    plain = make(tmp_path, cache=False).load(5, 5)  # and both are what the renderer draws
    assert np.array_equal(plain.rgb, rendered[1].rgb)
    assert np.abs(plain.depth_m - rendered[1].depth_m).max() < 0.1 and (plain.depth_m > 0).mean() > 0.9


def test_each_room_configuration_has_its_own_folder(tmp_path: Path) -> None:
    base = SyntheticConfig(width=W, height=H, n_frames=12)
    keys = {
        room_key(c)
        for c in (
            base,
            replace(base, seed=1),
            replace(base, width=W + 8),
            replace(base, fov_deg=60.0),
            replace(base, n_frames=13),  # the trajectory spreads over the frames
        )
    }
    assert len(keys) == 5
    recipe = tmp_path / "recipe.yaml"
    recipe.write_text((Path(__file__).parents[3] / "assets" / "synthetic_room.yaml").read_text() + "\n# edited\n")
    assert room_key(replace(base, recipe=str(recipe))) not in keys
    assert room_key(replace(base, depth_noise_m=0.01, prefetch=0)) == room_key(base)  # added after reading


def test_an_install_without_the_renderer_sources_still_keys_its_cache(monkeypatch: pytest.MonkeyPatch) -> None:
    base = SyntheticConfig(width=W, height=H, n_frames=12)
    monkeypatch.setattr(frame_cache, "_CODE", (Path("/nonexistent/scene.py"),))
    assert room_key(base) == room_key(base) and room_key(replace(base, seed=1)) != room_key(base)


def test_the_cache_lives_where_configured_else_in_the_user_cache(monkeypatch: pytest.MonkeyPatch) -> None:
    assert cache_root("/data/h2viz-cache") == Path("/data/h2viz-cache")
    monkeypatch.setenv("H2VIZ_CACHE_DIR", "/tmp/elsewhere")
    assert cache_root() == Path("/tmp/elsewhere")
    monkeypatch.delenv("H2VIZ_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", "/tmp/xdg")
    assert cache_root() == Path("/tmp/xdg/h2viz")
    assert make(Path("/unused"), cache=False).cache is None


def test_a_damaged_frame_file_is_rendered_again_and_replaced(tmp_path: Path) -> None:
    src = make(tmp_path)
    frame = src.load(2, 2)
    assert src.cache is not None
    path = src.cache.path(2)
    path.write_bytes(path.read_bytes()[:100])  # a write cut short
    again = make(tmp_path).load(2, 2)
    assert np.array_equal(again.rgb, frame.rgb) and np.array_equal(again.depth_m, frame.depth_m)
    assert src.cache.get(2) is not None  # rewritten whole
    path.write_bytes(b"not a frame at all")
    assert src.cache.get(2) is None


def test_an_unwritable_cache_warns_once_and_frames_are_still_rendered(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    blocked = tmp_path / "file"
    blocked.write_text("a file where the cache folder would go")
    src = make(blocked)
    with caplog.at_level(logging.WARNING, logger="h2viz.sources"):
        frames = [src.load(i, i) for i in range(3)]
        src.prepare_playback(range(12))  # nothing to prepare into: frames are rendered as read
    assert [f.index for f in frames] == [0, 1, 2] and all(f.depth_m.max() > 0 for f in frames)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and str(blocked) in warnings[0] and "source.synthetic.cache_dir" in warnings[0]
    assert src.cache is not None and not src.cache.writable


def test_prepare_playback_renders_the_missing_frames_once_and_reports_progress(tmp_path: Path) -> None:
    src = make(tmp_path)
    src.load(4, 4)  # cached already
    progress: list[tuple[int, int]] = []
    src.prepare_playback([2, 4, 6, 8], lambda done, total: progress.append((done, total)))
    assert progress == [(1, 3), (2, 3), (3, 3)]
    assert src.cache is not None and all(src.cache.has(k) for k in (2, 4, 6, 8)) and not src.cache.has(3)
    no_rendering(src)
    src.prepare_playback([2, 4, 6, 8])  # all there: nothing rendered
    assert [src.load(k, k).index for k in (2, 6, 8)] == [2, 6, 8]


def test_prepare_playback_ends_when_told_to_stop(tmp_path: Path) -> None:
    src = make(tmp_path)
    progress: list[tuple[int, int]] = []
    src.prepare_playback(range(12), lambda done, total: progress.append((done, total)), stop=lambda: bool(progress))
    assert src.cache is not None
    assert progress[0][1] == 12 and len(progress) == 1 and sum(src.cache.has(k) for k in range(12)) < 12
