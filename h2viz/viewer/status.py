"""Read-only panels refreshed from snapshots: progress and map statistics, live plots of the loss
terms and per-frame time, the current input images, metrics against ground truth and errors."""

from __future__ import annotations

from typing import Any

import numpy as np
import viser
import viser.uplot as uplot

from h2viz.types import MapSnapshot
from h2viz.viewer.shapes import colorize_depth

PHASE_TEXT = {
    "streaming": "every frame integrated, optimising between frames",
    "sharpening": "optimising until the loss stops improving",
    "settled": "the loss stopped improving",
}
"""How the progress panel names the real-time phases (h2viz.mapping.anytime.Phase)."""
PLOT_POINTS = 400  # newest frames shown in the plots
LOSS_COLORS = ["#ff8c00", "#28aaff", "#5ad45a", "#e04f5f", "#b77bff", "#f0d040"]
METRIC_LABELS = {
    "acc_cm": "Accuracy (cm)",
    "comp_cm": "Completion (cm)",
    "comp_ratio": "Completion ratio (%)",
    "fscore": "F-score (%)",
    "gt_kept_pct": "GT kept by culling (%)",
}


def progress_markdown(snap: MapSnapshot) -> str:
    """The progress panel's text: frames, timing, map size and memory."""
    last = snap.stats[-1] if snap.stats else None
    recent = [s.map_time_s for s in snap.stats[-20:]]
    state = "finished" if snap.finished else ("paused" if snap.paused else "mapping")
    if snap.refine_left and (snap.finished or snap.paused):
        state = f"refining ({snap.refine_left} steps left)"
    elif snap.refine_left:
        state += f", {snap.refine_left} refinement steps queued"
    elif snap.refined:
        state += f", refined {snap.refined} steps"
    if snap.preparing is not None:
        done, n = snap.preparing
        state += f" (real time: rendering the frames to play, {done} / {n}; once, they are cached)"
    elif snap.phase and not snap.paused:
        state += f" (real time: {PHASE_TEXT.get(snap.phase, snap.phase)})"
    total = snap.frames_total if snap.frames_total is not None else "?"
    rows = [
        ("State", state),
        ("Frames", f"{snap.frames_done} / {total}"),
        ("Integrated / dropped / skipped", f"{snap.frames_done} / {snap.dropped} / {snap.skipped}"),
        *([("Behind the stream", lag_text(snap))] if snap.phase == "streaming" else []),
        ("Time per frame", f"{1000 * float(np.mean(recent)):.0f} ms" if recent else "-"),
        ("Iterations", str(last.iterations) if last else "-"),
        *([("Optimisation steps", f"{snap.opt_steps:,}")] if snap.phase else []),
        ("Voxels", f"{len(snap.voxel_coords):,}"),
        ("Keyframes", str(len(snap.keyframes))),
        ("Mesh chunks", str(len(snap.chunks))),
        ("Memory", f"{snap.memory_mb:,.0f} MB"),
    ]
    return "\n".join(["| | |", "|:--|--:|", *(f"| {k} | {v} |" for k, v in rows)])


def lag_text(snap: MapSnapshot) -> str:
    """How far integration is behind a real-time stream: the newest integrated frame's wait after it arrived, and
    the frames waiting now (a full backlog, anytime.backlog_frames, drops the oldest)."""
    waiting = f"{snap.waiting} frame{'s' if snap.waiting != 1 else ''} waiting"
    return f"{snap.lag_s:.1f} s ({waiting})"


def metrics_markdown(metrics: dict[str, float], frames_done: int) -> str:
    if not metrics:
        return "Metrics appear after the first refresh."
    rows = [f"| {label} | {metrics[k]:.2f} |" for k, label in METRIC_LABELS.items() if k in metrics]
    return "\n".join([f"Against ground truth, at frame {frames_done}:", "", "| | |", "|:--|--:|", *rows])


def plot_data(snap: MapSnapshot, names: list[str]) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
    """x = frame index; (loss series for `names`), (per-frame time in ms)."""
    stats = snap.stats[-PLOT_POINTS:]
    x = np.array([s.index for s in stats], dtype=np.float64)
    losses = tuple(np.array([s.losses.get(n, np.nan) for s in stats], dtype=np.float64) for n in names)
    losses = tuple(np.where(v > 0, v, np.nan) for v in losses)  # the loss plot is logarithmic
    times = np.array([1000.0 * s.map_time_s for s in stats], dtype=np.float64)
    return (x, *losses), (x, times)


class StatusPanels:
    """Progress, plots, input images, metrics and errors; `update` refreshes them from a snapshot."""

    def __init__(self, gui: viser.GuiApi) -> None:
        self.gui = gui
        self.progress = gui.add_progress_bar(0.0, animated=False, color="blue")
        self.text = gui.add_markdown("Waiting for the first frame...")
        self.loss_plot: viser.GuiUplotHandle | None = None
        self.loss_names: list[str] = []
        self.plots = gui.add_folder("Plots", expand_by_default=True)
        with self.plots:
            self.time_plot = gui.add_uplot(
                (np.zeros(1), np.zeros(1)),
                (uplot.Series(label="frame"), uplot.Series(label="ms / frame", stroke="#28aaff", width=2)),
                title="Time per frame (ms, log)",  # log: the first frame (kernel warm-up) takes seconds
                scales={"x": {"time": False}, "y": {"distr": 3}},
                aspect=2.0,
            )
        with gui.add_folder("Input frame", expand_by_default=True):
            blank = np.zeros((48, 64, 3), dtype=np.uint8)
            self.rgb_image = gui.add_image(blank, label="colour", format="jpeg")
            self.depth_image = gui.add_image(blank, label="depth", format="jpeg")
        self.metrics_folder = gui.add_folder("Metrics", visible=False)  # shown once ground truth is scored
        with self.metrics_folder:
            self.metrics_text = gui.add_markdown("Metrics appear after the first refresh.")
        self.errors_text = gui.add_markdown("", visible=False)
        self._frame_index: int | None = None

    def update(self, snap: MapSnapshot) -> None:
        total = snap.frames_total or 0
        consumed = snap.frames_done + snap.dropped + snap.skipped
        self.progress.value = (
            100.0 if snap.finished else float(np.clip(100.0 * consumed / max(total, 1), 0, 100))
        )
        self.text.content = progress_markdown(snap)
        if snap.stats:
            self._update_plots(snap)
        if snap.current_frame is not None and snap.current_frame.index != self._frame_index:
            frame = snap.current_frame
            self._frame_index = frame.index
            step = max(1, frame.width // 320)
            self.rgb_image.image = np.ascontiguousarray(frame.rgb[::step, ::step])
            self.depth_image.image = colorize_depth(frame.depth_m[::step, ::step])
        if snap.metrics:
            self.metrics_folder.visible = True
            self.metrics_text.content = metrics_markdown(snap.metrics, snap.frames_done)

    def show_errors(self, errors: tuple[str, ...]) -> None:
        self.errors_text.content = "**Errors**\n\n" + "\n".join(f"- {e}" for e in errors[-5:])
        self.errors_text.visible = bool(errors)

    def _update_plots(self, snap: MapSnapshot) -> None:
        names = sorted(snap.stats[-1].losses)
        if names and names != self.loss_names:
            if self.loss_plot is not None:
                self.loss_plot.remove()
            series = [{"label": "frame"}] + [
                {"label": n, "stroke": LOSS_COLORS[i % len(LOSS_COLORS)], "width": 2}
                for i, n in enumerate(names)
            ]
            losses, _ = plot_data(snap, names)
            with self.plots:
                self.loss_plot = self.gui.add_uplot(
                    losses,
                    tuple(uplot.Series(**s) for s in series),  # type: ignore[typeddict-item]
                    title="Loss terms (log)",
                    scales={"x": {"time": False}, "y": {"distr": 3}},
                    aspect=2.0,
                    order=self.time_plot.order - 0.5,
                )
            self.loss_names = names
        losses, times = plot_data(snap, self.loss_names)
        if self.loss_plot is not None:
            self.loss_plot.data = losses
        self.time_plot.data = times


def notify(event: Any, title: str, body: str, error: bool = False) -> None:
    """A notification to the browser that caused a GUI event (green, or red for an error)."""
    client = getattr(event, "client", None)
    if client is not None:
        client.add_notification(title, body, auto_close_seconds=8.0, color="red" if error else "green")
