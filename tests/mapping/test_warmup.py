"""Kernels loaded before a live stream: after `warm_up`, mapping real frames (both modes, live steps, a mesh job)
loads or compiles no further kernel, in a fresh process where nothing was loaded before."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from h2viz.mapping.warmup import scratch_frame

ROOT = Path(__file__).resolve().parents[2]

CHECK = """
import sys
import numba
from numba.core.dispatcher import Dispatcher
from h2viz.mapping.mapper import Mapper
from tests.mapping.test_mapper import room_views, small_cfg

def loaded():
    return {
        (module.__name__, name): len(obj.overloads)
        for module in list(sys.modules.values())
        if getattr(module, "__name__", "").startswith("h2viz.")
        for name, obj in list(vars(module).items())
        if isinstance(obj, Dispatcher)
    }

cfg = small_cfg(max_iters=3)
seconds = Mapper(cfg).warm_up()
assert seconds > 0.0 and Mapper(cfg).warm_up() == 0.0, seconds
before = loaded()
assert sum(before.values()) >= 10, before  # the kernels of every stage, loaded
_, frames = room_views(4)
mapper = Mapper(cfg)
for frame in frames[:3]:
    mapper.add_frame(frame)
    mapper.live_step()
mapper.integrate(frames[3])
mapper.refine(2)
mapper.touched[:] = True
mapper.mesh_job(0.03).run()  # a live update
mapper.touched[:] = True
mapper.mesh_job(whole=True).run()  # an export's
after = loaded()
new = {k: (before.get(k, 0), v) for k, v in after.items() if v != before.get(k, 0)}
assert not new, f"kernels loaded after the warm-up: {new}"
print("ok", round(seconds, 2))
"""


def test_the_scratch_frame_is_a_valid_plane_in_view() -> None:
    frame = scratch_frame()
    assert frame.depth_m.shape == frame.rgb.shape[:2] == (120, 160)
    assert (frame.depth_m > 0.9).all() and (frame.depth_m < 2.5).all()
    assert len({tuple(c) for c in frame.rgb.reshape(-1, 3)[::97]}) > 10  # a gradient, not one colour


def test_after_the_warm_up_mapping_loads_no_further_kernel() -> None:
    done = subprocess.run(
        [sys.executable, "-c", CHECK], cwd=ROOT, capture_output=True, text=True, timeout=600, check=False
    )
    assert done.returncode == 0 and "ok" in done.stdout, done.stderr[-3000:]
