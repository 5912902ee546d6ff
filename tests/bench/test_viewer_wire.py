"""bench/viewer.py's mesh-arrival bookkeeping: when a chunk of a given version counts as in the browser."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from bench.viewer import Wire, node_name
from h2viz.types import MeshChunk


def chunk(key: tuple[int, int, int], version: int) -> MeshChunk:
    tri = np.zeros((1, 3), np.int32)
    return MeshChunk(key, np.zeros((3, 3), np.float32), tri, np.zeros((3, 3), np.uint8), version)


def snap(*chunks: MeshChunk) -> SimpleNamespace:
    return SimpleNamespace(chunks={c.key: c for c in chunks})


def test_a_chunk_arrives_with_its_first_glb_after_the_send() -> None:
    wire, a, b = Wire(), (0, 0, 0), (1, 0, -1)
    wire.on_sent(snap(chunk(a, 1), chunk(b, 1)), [a, b], 0)
    t_sent = wire.sends[-1][0]
    wire.arrivals += [
        (t_sent - 5.0, node_name(a), 10),
        (t_sent + 0.2, node_name(a), 11),
        (t_sent + 0.3, node_name(b), 12),
    ]
    assert wire.arrival(a, 1) == (t_sent + 0.2, 11)  # not the stale GLB from before the send
    assert wire.arrival(b, 1) == (t_sent + 0.3, 12)
    assert wire.arrival(a, 2) is None  # version 2 was never sent


def test_a_chunk_meshed_empty_counts_as_delivered_when_the_scene_drops_it() -> None:
    """The mesher drops a chunk whose surface vanished; the browser then has nothing to receive for it, and its
    next non-empty version (much later) must not count as this version's arrival."""
    wire, a, b = Wire(), (0, 0, 0), (2, 2, 2)
    wire.on_sent(snap(chunk(a, 1), chunk(b, 1)), [a, b], 0)
    wire.on_sent(snap(chunk(b, 2)), [b], 0)  # job 2 meshed a empty: it left the snapshot
    t_gone = wire.shown[-1][0]
    wire.on_sent(snap(chunk(a, 9), chunk(b, 9)), [a, b], 0)
    wire.arrivals.append((wire.sends[-1][0] + 0.1, node_name(a), 10))
    assert wire.arrival(a, 2) == (t_gone, 0)
    assert wire.arrival(a, 9) is not None and wire.arrival(a, 9)[1] == 10


def test_a_chunk_counts_as_sent_with_its_first_send_at_that_version_or_when_dropped() -> None:
    wire, a, b = Wire(), (0, 0, 0), (1, 1, 1)
    wire.on_sent(snap(chunk(a, 1), chunk(b, 1)), [a, b], 0)
    first = wire.sends[-1][0]
    wire.on_sent(snap(chunk(a, 3), chunk(b, 1)), [a], 0)
    third = wire.sends[-1][0]
    wire.on_sent(snap(chunk(a, 4)), [], 0)  # job 4 meshed b empty: the scene dropped it
    gone = wire.shown[-1][0]
    assert wire.sent(a, 1) == first
    assert wire.sent(a, 2) == third  # version 2 never went out on its own: the newer version 3 carried it
    assert wire.sent(b, 2) == gone
    assert wire.sent(a, 5) is None


def test_frames_are_timed_by_the_first_job_that_meshed_them_from_their_arrival() -> None:
    """Frames 1-2 go to job 1 (one pass); frame 3's job 2 ran no pass and was not cut short (no new voxel: nothing
    to time); frame 4's job 3 was cut short before its first pass, so frame 4 is timed by job 4."""
    from bench.viewer import Run, _measure
    from h2viz.worker.mesh_thread import JobRecord, PassRecord

    t0, a, b = 1000.0, (0, 0, 0), (1, 0, 0)
    passes = [PassRecord(1, 2, t0 + 0.10, t0 + 0.10, t0 + 0.20, (a,), True)]
    passes.append(PassRecord(4, 4, t0 + 0.60, t0 + 0.60, t0 + 0.70, (b,), True))
    jobs = [JobRecord(1, 2, t0 + 0.10, t0 + 0.20, 1, False), JobRecord(2, 3, t0 + 0.30, t0 + 0.31, 0, False)]
    jobs += [JobRecord(3, 4, t0 + 0.40, t0 + 0.41, 0, True), JobRecord(4, 4, t0 + 0.60, t0 + 0.70, 1, False)]
    worker = SimpleNamespace(
        meshing=SimpleNamespace(passes=passes, jobs=jobs, published=[t0 + 0.25, t0 + 0.75], busy_s=0.2),
        mapped_at={10: t0 + 0.00, 11: t0 + 0.05, 12: t0 + 0.25, 13: t0 + 0.35},  # frame index -> integrated
        _feed=SimpleNamespace(arrived_at={10: t0 - 0.10, 11: t0 - 0.05, 12: t0 + 0.20, 13: t0 + 0.30}),
    )
    wire = Wire()
    wire.sends = [(t0 + 0.30, {a: 1}), (t0 + 0.80, {b: 4})]
    wire.arrivals = [(t0 + 0.40, node_name(a), 100), (t0 + 0.90, node_name(b), 200)]
    run = Run(1, recorded=True, mapping_s=1.0)
    _measure(run, worker, wire)  # type: ignore[arg-type]
    assert run.unchanged == 1  # frame 12
    np.testing.assert_allclose(run.all_s, [0.40, 0.35, 0.55])  # frames 10, 11 (job 1) and 13 (job 4)
    np.testing.assert_allclose(run.arrived_all_s, [0.50, 0.45, 0.60])
    np.testing.assert_allclose(run.waited_s, [0.10, 0.10, 0.05, 0.05])  # every frame waited in the backlog
