"""Recordings of a real run (the real Mapper, tiny configuration, on the analytic room): as many steps as mapped
frames with the live run's final mesh at the last step, replays in real headless chromium where scrubbing shows the
keyframes that existed at that step (each browser on its own timeline), a standalone HTML export that plays from
file:// with the network blocked, and no torch anywhere in replay."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from h2viz.config import Config
from h2viz.viewer.html_export import export_html
from h2viz.viewer.recording import Recording, RecordingError, voxel_changes
from h2viz.viewer.replay import ReplayServer
from h2viz.worker import MappingWorker
from tests.viewer.browser import WireRecorder, launch, wait_until
from tests.viewer.fakes import BoxRoomSource, recording_mapper, tiny_mapping_config

N_FRAMES = 8
REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, MappingWorker]]:
    """A finished run recorded by the live worker, with no browser connected (recording keeps the mesh live)."""
    folder = tmp_path_factory.mktemp("run") / "recording"
    worker = MappingWorker(
        BoxRoomSource(n=N_FRAMES, width=64, height=48), recording_mapper(tiny_mapping_config()), Config()
    )
    worker.set_viewers(0)
    worker.start_recording(folder, fps=4.0)
    worker.start()
    assert worker.wait_finished(120.0)
    worker.stop_recording()
    yield folder.parent, worker
    worker.stop()


def test_recording_has_a_step_per_frame_and_the_live_runs_final_mesh(recorded: tuple[Path, MappingWorker]) -> None:
    run_dir, worker = recorded
    rec = Recording(run_dir)
    _, live = worker.slot.get()
    assert live is not None and live.finished
    assert len(rec) == live.frames_done == N_FRAMES
    last = rec.snapshot(len(rec) - 1)
    assert last.finished and last.frames_done == N_FRAMES
    assert set(last.chunks) == set(live.chunks) and live.chunks
    for key, chunk in live.chunks.items():
        np.testing.assert_array_equal(last.chunks[key].faces, chunk.faces)
        np.testing.assert_allclose(last.chunks[key].vertices, chunk.vertices)
        np.testing.assert_array_equal(last.chunks[key].colors, chunk.colors)
    assert {tuple(v) for v in last.voxel_coords} == {tuple(v) for v in live.voxel_coords}
    assert [k.index for k in last.keyframes] == [k.index for k in live.keyframes]
    assert [k.state for k in last.keyframes] == [k.state for k in live.keyframes]
    np.testing.assert_allclose(last.trajectory, live.trajectory)
    assert [s.index for s in last.stats] == [s.index for s in live.stats]
    # each step holds its own frame: trajectory length, frames done and the current camera follow the steps
    for k in range(len(rec)):
        snap = rec.snapshot(k)
        assert snap.frames_done == len(snap.trajectory) == k + 1
        assert snap.current_frame is not None and snap.current_frame.index == live.stats[k].index


def test_steps_store_only_what_changed(recorded: tuple[Path, MappingWorker]) -> None:
    rec = Recording(recorded[0])
    new_chunks = [len(s.chunks) for s in rec.steps]
    final = len(rec.snapshot(len(rec) - 1).chunks)
    assert sum(new_chunks[1:-1]) < (len(rec) - 2) * final  # middle steps do not repeat every chunk
    assert all(len(s.trajectory_new) == 1 for s in rec.steps)
    assert sum(len(s.new_keyframes) for s in rec.steps) == len(rec.snapshot(len(rec) - 1).keyframes)


def test_voxel_changes_of_a_grown_and_of_a_shrunk_set() -> None:
    a = np.array([[0, 0, 0], [1, 0, 0]], np.int32)
    b = np.array([[0, 0, 0], [1, 0, 0], [5, 5, 5]], np.int32)
    added, removed = voxel_changes(a, b)
    assert added.tolist() == [[5, 5, 5]] and removed.shape == (0, 3)
    added, removed = voxel_changes(b, np.array([[5, 5, 5], [2, 2, 2]], np.int32))
    assert added.tolist() == [[2, 2, 2]] and sorted(removed.tolist()) == [[0, 0, 0], [1, 0, 0]]


def test_a_damaged_step_or_missing_recording_names_the_file(
    tmp_path: Path, recorded: tuple[Path, MappingWorker]
) -> None:
    with pytest.raises(RecordingError, match="no recording in"):
        Recording(tmp_path)
    broken = tmp_path / "recording"
    (broken / "steps").mkdir(parents=True)
    (broken / "recording.json").write_text(json.dumps({"format": "h2viz-recording", "fps": 4}))
    (broken / "steps" / "000000.npz").write_bytes(b"not a zip")
    with pytest.raises(RecordingError, match="000000.npz: damaged"):
        Recording(tmp_path)
    # a damaged later step: the steps before it still replay, and the problem names it
    shutil.copytree(recorded[0] / "recording", tmp_path / "copy" / "recording")
    (tmp_path / "copy" / "recording" / "steps" / "000005.npz").write_bytes(b"PK broken")
    rec = Recording(tmp_path / "copy")
    assert len(rec) == 5 and "000005.npz: damaged" in rec.problem
    assert rec.snapshot(4).frames_done == 5


def test_replay_imports_no_torch(recorded: tuple[Path, MappingWorker]) -> None:
    code = (
        "import sys; from h2viz.viewer.replay import ReplayServer; from h2viz.viewer.recording import Recording;"
        "from h2viz.viewer.html_export import export_html; import h2viz.cli;"
        f"r = Recording({str(recorded[0])!r}); r.snapshot(len(r) - 1);"
        "s = ReplayServer(r, port=0); s.stop();"
        "assert 'torch' not in sys.modules, 'torch was imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO, env={"PYTHONPATH": str(REPO)})


sync_api = pytest.importorskip("playwright.sync_api")


def _keyframes_shown(wire: WireRecorder) -> set[int]:
    return {int(n.rsplit("_", 1)[1]) for n in wire.names("CameraFrustumMessage", "/keyframes/")}


@pytest.mark.browser
def test_scrubbing_shows_the_keyframes_of_that_step_in_each_browser(recorded: tuple[Path, MappingWorker]) -> None:
    rec = Recording(recorded[0])
    expected = [{kf.index for kf in rec.snapshot(k).keyframes} for k in range(len(rec))]
    assert len(set(map(frozenset, expected))) > 2  # keyframes come and change over the run
    replay = ReplayServer(rec, port=0)
    try:
        with sync_api.sync_playwright() as playwright:
            browser = launch(playwright)
            pages, wires, sessions = [], [], []
            for n in (1, 2):  # one browser at a time, so that each page's session is known
                page = browser.new_page(viewport={"width": 800, "height": 600})
                wires.append(WireRecorder().attach(page))
                page.goto(replay.url)
                pages.append(page)
                wait_until(page, lambda n=n: len(replay.sessions) == n, what=f"replay session {n}")
                sessions.append(next(s for c, s in replay.sessions.items() if s not in sessions))
            first, second = sessions
            for k in (len(rec) - 1, 2, 0, 5):  # forwards and backwards
                first.show(k)
                wait_until(pages[0], lambda k=k: _keyframes_shown(wires[0]) == expected[k], what=f"step {k}")
            assert _keyframes_shown(wires[1]) == expected[0]  # the other browser stayed at the start
            second.set_playing(True)
            wait_until(pages[1], lambda: second.step == len(rec) - 1 and not second.playing, 30.0, "playback end")
            wait_until(pages[1], lambda: _keyframes_shown(wires[1]) == expected[-1], what="last step's keyframes")
            assert first.step == 5
            assert not wires[0].names("LineSegmentsMessage", "/octree/")  # layer switches are per browser too
            pages[0].get_by_role("checkbox", name="Octree leaves").check()
            wait_until(pages[0], lambda: wires[0].names("LineSegmentsMessage", "/octree/"), what="octree lines")
            assert not wires[1].names("LineSegmentsMessage", "/octree/")
            browser.close()
    finally:
        replay.stop()


@pytest.mark.browser
def test_exported_html_plays_offline_to_the_last_step(recorded: tuple[Path, MappingWorker], tmp_path: Path) -> None:
    rec = Recording(recorded[0])
    fps = 4.0
    html = export_html(recorded[0], tmp_path / "run.html", fps=fps)
    outside: list[str] = []

    def route(r: object) -> None:
        url = r.request.url  # type: ignore[attr-defined]
        if url.startswith(("file://", "data:", "blob:")):
            r.continue_()  # type: ignore[attr-defined]
        else:
            outside.append(url)
            r.abort()  # type: ignore[attr-defined]

    with sync_api.sync_playwright() as playwright:
        browser = launch(playwright)
        page = browser.new_page(viewport={"width": 800, "height": 600})
        page.route("**/*", route)
        page.goto(html.as_uri())
        # the playback bar's time field: note the largest time it showed (it loops back to 0 after the end)
        page.wait_for_selector("input")
        page.evaluate(
            "() => { window.__maxT = 0; setInterval(() => { const v = parseFloat(document.querySelector('input')"
            ".value); if (v > window.__maxT) window.__maxT = v; }, 5); }"
        )
        last_step_t = (len(rec) - 1) / fps
        wait_until(page, lambda: page.evaluate("() => window.__maxT") >= last_step_t, 60.0, "the last step")
        browser.close()
    assert outside == []
