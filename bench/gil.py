"""How much a thread that holds the GIL slows a thread of many small torch calls (as the mapping thread is).

One thread calls a function in a loop; the main thread counts the tiny torch calls (`x.add_(1)`, each of which
gives the GIL up and takes it back) it completes meanwhile. The functions: sleeping, undoing the synthetic room's
depth differencing with NumPy's row sums (which hold the GIL) and with torch's (which release it), and NumPy's
sums again under shorter switch intervals.

    .venv/bin/python bench/gil.py [--seconds 2]
"""

from __future__ import annotations

import argparse
import shlex
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from h2viz.sources.synthetic.frame_cache import undo_row_differences  # noqa: E402


def numpy_sums(second: np.ndarray) -> np.ndarray:
    """The frame cache's former decoding: NumPy's row sums, which hold the GIL."""
    bits = np.cumsum(second, axis=1, dtype=np.uint32)
    np.cumsum(bits, axis=1, dtype=np.uint32, out=bits)
    return bits


def calls_beside(work: Callable[[], object], seconds: float) -> int:
    """Tiny torch calls the calling thread completes in `seconds` while another thread loops over `work`."""
    stop = threading.Event()

    def loop() -> None:
        while not stop.is_set():
            work()

    thread = threading.Thread(target=loop, daemon=True)
    thread.start()
    x, n = torch.zeros(10), 0
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        x.add_(1)
        n += 1
    stop.set()
    thread.join()
    return n


def per_call_ms(work: Callable[[], object], repeats: int = 50) -> float:
    start = time.perf_counter()
    for _ in range(repeats):
        work()
    return (time.perf_counter() - start) / repeats * 1000


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=2.0, help="how long each row counts")
    args = parser.parse_args()
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    second = rng.integers(0, 2**32, (480, 640), dtype=np.uint64).astype(np.uint32)  # (H,W) a frame's differences
    assert np.array_equal(numpy_sums(second), undo_row_differences(second))
    rows: list[tuple[str, Callable[[], object], float | None]] = [
        ("time.sleep(0.001)", lambda: time.sleep(0.001), None),
        ("NumPy's row sums of a 640x480 frame, twice (hold the GIL)", lambda: numpy_sums(second), None),
        ("the same sums in torch (release the GIL)", lambda: undo_row_differences(second), None),
    ]
    rows += [(f"NumPy's sums, switch interval {s} s", lambda: numpy_sums(second), s) for s in (0.001, 0.0002, 5e-5)]
    default = sys.getswitchinterval()
    print(f"\n| the other thread loops over | ms a call | tiny torch calls in {args.seconds:g} s |\n|:--|--:|--:|")
    for name, work, interval in rows:
        sys.setswitchinterval(interval or default)
        n = calls_beside(work, args.seconds)
        sys.setswitchinterval(default)
        print(f"| {name} | {per_call_ms(work):.2f} | {n:,} |")
    print(f"\nReproduce: {shlex.join(['.venv/bin/python', 'bench/gil.py', *sys.argv[1:]])}")


if __name__ == "__main__":
    main()
