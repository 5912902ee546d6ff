"""The dashboard's control panel: playback, layer toggles, novel-view mode, export and live settings
(tabs Mapping / View / Export), plus the status panels and, when the run folder holds an earlier run, the offer to
resume it. Every control turns into a Command for the mapping worker or a change to a layer; shared by all
browsers (a late joiner sees the same state)."""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import viser

from h2viz.config import Config
from h2viz.types import MapSnapshot
from h2viz.viewer.comforts import CameraComforts
from h2viz.viewer.flythrough import FlythroughPanel
from h2viz.viewer.layers import LayerSet
from h2viz.viewer.render_loop import MODES, RenderLoop, render_png
from h2viz.viewer.status import StatusPanels, notify
from h2viz.worker import MappingWorker

log = logging.getLogger("h2viz.viewer")
COMMAND_TIMEOUT_S = 600.0
REFINE_STEPS = 500  # optimisation steps queued by one click of "Refine map" (20-40 s on a 2-core CPU)


def build_layer_controls(gui: viser.GuiApi, L: LayerSet, points: bool = True) -> None:
    """The Layers folder: a switch per layer, mesh opacity, octree levels (live dashboard and replay); `points`:
    also the current frame's point cloud (recordings keep no depth)."""
    with gui.add_folder("Layers"):
        mesh = gui.add_checkbox("Mesh", L.mesh.enabled)
        opacity = gui.add_slider("Mesh opacity", 0.1, 1.0, 0.05, L.mesh.opacity)
        leaves = gui.add_checkbox("Octree leaves", L.octree.enabled and L.octree.leaves)
        coarse = gui.add_slider("Coarser levels", 0, 3, 1, L.octree.coarse_levels if L.octree.enabled else 0)
        keyframes = gui.add_checkbox("Keyframes", L.keyframes.enabled, hint="orange: selected, blue: covered")
        trajectory = gui.add_checkbox("Trajectory", L.trajectory.enabled)
        camera = gui.add_checkbox("Current camera", L.camera.enabled)
        hint = "The current frame's depth points"
        cloud = gui.add_checkbox("Point cloud", L.camera.points, hint=hint) if points else None
    mesh.on_update(lambda _: L.mesh.set_enabled(mesh.value))
    opacity.on_update(lambda _: L.mesh.set_opacity(opacity.value))
    keyframes.on_update(lambda _: L.keyframes.set_enabled(keyframes.value))
    trajectory.on_update(lambda _: L.trajectory.set_enabled(trajectory.value))
    camera.on_update(lambda _: L.camera.set_enabled(camera.value))
    if cloud is not None:
        cloud.on_update(lambda _: L.camera.set_points(cloud.value))

    def octree(_: Any) -> None:
        L.octree.set_levels(leaves.value, int(coarse.value))
        L.octree.set_enabled(leaves.value or coarse.value > 0)

    leaves.on_update(octree)
    coarse.on_update(octree)


class Panels:
    """Builds the GUI on `server` and wires it to the worker, the layers and the render loop."""

    def __init__(
        self,
        server: viser.ViserServer,
        worker: MappingWorker,
        layers: LayerSet,
        renders: RenderLoop,
        cfg: Config,
    ) -> None:
        self.server, self.worker, self.layers, self.renders, self.cfg = server, worker, layers, renders, cfg
        self.out_dir = Path(cfg.out_dir or "outputs")
        self.downloads = 0
        gui = server.gui
        tabs = gui.add_tab_group()
        self._offer: viser.GuiFolderHandle | None = None
        self._offer_lock = threading.Lock()
        with tabs.add_tab("Mapping", icon=viser.Icon.PLAYER_PLAY):
            self._build_offer(gui)
            self._build_playback(gui)
            self.status = StatusPanels(gui)
        with tabs.add_tab("View", icon=viser.Icon.EYE):
            self._build_layers(gui)
            self._build_novel_view(gui)
            self.comforts = CameraComforts(server, worker)
        with tabs.add_tab("Export", icon=viser.Icon.DOWNLOAD):
            self._build_export(gui)
            self._build_recording(gui)
            v = cfg.viewer
            self.flythrough = FlythroughPanel(server, worker, self.out_dir, v.video_width, v.video_fps)
            self._build_settings(gui)

    # -- building ------------------------------------------------------------------------------
    def _build_playback(self, gui: viser.GuiApi) -> None:
        s = self.worker.settings
        self.pause = gui.add_button("Pause", icon=viser.Icon.PLAYER_PAUSE, hint="Stop taking new frames")
        self.resume = gui.add_button("Resume", icon=viser.Icon.PLAYER_PLAY, disabled=True)
        self.step = gui.add_button("Step one frame", icon=viser.Icon.PLAYER_TRACK_NEXT, hint="Map exactly one frame")
        self.realtime = gui.add_checkbox(
            "Real-time",
            s.realtime,
            hint="Play at the stream's rate: integrate every frame, optimise between frames and after the end",
        )
        self.stride = gui.add_number("Stride", int(s.stride), min=1, max=100, step=1, hint="Use every k-th frame")
        self.pause.on_click(lambda e: self._command(e, "pause"))
        self.resume.on_click(lambda e: self._command(e, "resume"))
        self.step.on_click(lambda e: self._command(e, "step"))
        self.realtime.on_update(lambda e: self._command(e, "set", realtime=self.realtime.value))
        self.stride.on_update(lambda e: self._command(e, "set", stride=int(self.stride.value)))

    def _build_offer(self, gui: viser.GuiApi) -> None:
        """The "Earlier run" folder: resume the run folder's earlier run, or dismiss the offer (nothing without one)."""
        offer = self.worker.resume_offer
        if offer is None:
            return
        with gui.add_folder("Earlier run") as self._offer:
            self.resume_earlier = gui.add_button(
                offer.label(),
                icon=viser.Icon.HISTORY,
                hint=f"Continue {offer.path} after its frame {offer.last_index} instead of this fresh run, whose map "
                "it replaces",
            )
            self.dismiss_earlier = gui.add_button("Dismiss", icon=viser.Icon.X, hint="Go on with this fresh run")
        self.resume_earlier.on_click(self._resume_earlier)
        self.dismiss_earlier.on_click(lambda _: self._drop_offer(dismiss=True))

    def _resume_earlier(self, event: Any) -> None:
        """Ask the worker to take over the offered run; say what happened (or why not) and drop the offer."""
        offer = self.worker.resume_offer
        if offer is None:
            self._drop_offer()
            return
        self.resume_earlier.disabled = self.dismiss_earlier.disabled = True
        try:
            message = self.worker.submit("resume_run", path=str(offer.path)).result(timeout=COMMAND_TIMEOUT_S)
        except Exception as e:
            log.warning("resuming %s failed: %s", offer.path, e)
            notify(event, "Cannot resume the earlier run", str(e), error=True)
        else:
            notify(event, "Earlier run resumed", str(message))
        finally:
            self._drop_offer()

    def _drop_offer(self, dismiss: bool = False) -> None:
        """Remove the "Earlier run" folder (once, whichever thread gets here first)."""
        if dismiss:
            self.worker.dismiss_resume_offer()
        with self._offer_lock:
            folder, self._offer = self._offer, None
        if folder is not None:
            folder.remove()

    def _build_layers(self, gui: viser.GuiApi) -> None:
        build_layer_controls(gui, self.layers)

    def _build_novel_view(self, gui: viser.GuiApi) -> None:
        with gui.add_folder("Novel view"):
            mode = gui.add_dropdown(
                "Render", MODES, initial_value=self.renders.mode, hint="Background rendered by the map"
            )
            button = gui.add_button(
                "Render this view", icon=viser.Icon.CAMERA, hint="Full resolution, downloaded as PNG"
            )
        mode.on_update(lambda _: self.renders.set_mode(mode.value))
        button.on_click(lambda e: self._download(e, "view"))
        self.mode_dropdown = mode

    def _build_export(self, gui: viser.GuiApi) -> None:
        with gui.add_folder("Export"):
            ply = gui.add_button("Download mesh (PLY)", icon=viser.Icon.DOWNLOAD)
            glb = gui.add_button("Download mesh (GLB)", icon=viser.Icon.DOWNLOAD)
            save = gui.add_button("Save checkpoint", icon=viser.Icon.DEVICE_FLOPPY, hint=f"Written to {self.out_dir}/")
            refine = gui.add_button(
                f"Refine map ({REFINE_STEPS} steps)",
                icon=viser.Icon.SPARKLES,
                hint="More optimisation over the keyframes, run while mapping is paused or finished: sharper "
                "colour and depth before an export",
            )
        refine.on_click(lambda e: self._command(e, "refine", steps=REFINE_STEPS))
        ply.on_click(lambda e: self._download(e, "ply"))
        glb.on_click(lambda e: self._download(e, "glb"))
        save.on_click(self._save)

    def _build_recording(self, gui: viser.GuiApi) -> None:
        with gui.add_folder("Recording"):
            self.record = gui.add_checkbox(
                "Record", self.worker.recording is not None, hint=f"One step per mapped frame, into {self.out_dir}/"
            )
            self.export_html = gui.add_button(
                "Download recording (HTML)",
                icon=viser.Icon.FILE_CODE,
                hint="One file that plays the recording in any browser, no server needed (ends the recording)",
            )
        self.record.on_update(self._toggle_record)
        self.export_html.on_click(self._download_html)
        self.recorded: Path | None = None  # the last finished recording

    def _toggle_record(self, event: Any) -> None:
        if self.record.value:
            folder = self.out_dir / f"run-{time.strftime('%Y%m%d-%H%M%S')}" / "recording"
            notify(event, "Recording", f"into {self.worker.start_recording(folder, self.cfg.viewer.record_fps)}")
        else:
            self.recorded = self.worker.stop_recording() or self.recorded
            if self.recorded is not None:
                notify(event, "Recording saved", f"{self.recorded}: replay it with `h2viz replay`")

    def _download_html(self, event: Any) -> None:
        from h2viz.viewer.html_export import export_html

        if self.worker.recording is not None:
            self.recorded = self.worker.stop_recording() or self.recorded
            self.record.value = False
        if self.recorded is None or event.client is None:
            notify(event, "Nothing recorded", "Switch Record on while mapping first", error=True)
            return
        note = event.client.add_notification("Preparing download", "HTML...", loading=True, with_close_button=False)
        try:
            out = export_html(self.recorded, self.recorded.parent / "recording.html")
            event.client.send_file_download(out.name, out.read_bytes(), save_immediately=True)
        except Exception as e:
            log.warning("HTML export failed: %s", e)
            notify(event, "Export failed", str(e), error=True)
        finally:
            note.remove()

    def _build_settings(self, gui: viser.GuiApi) -> None:
        s = self.worker.settings
        with gui.add_folder("Settings"):
            rate = gui.add_slider(
                "Mesh updates / s",
                0.0,
                5.0,
                0.1,
                float(np.clip(s.mesh_update_hz, 0.0, 5.0)),
                hint=f"0: no live mesh, re-meshed every {s.mesh_every} frames instead",
            )
            res = gui.add_slider("Marching cubes res.", 2, 16, 1, int(self.cfg.viewer.live_mesh_resolution))
            observed = gui.add_checkbox(
                "Observed surfaces only",
                bool(self.cfg.mapping.meshing.mesh_observed_only),
                hint="Mesh only within a few cm of measured depth; off: every zero crossing of the field",
            )
        rate.on_update(lambda e: self._command(e, "set", mesh_update_hz=float(rate.value)))
        res.on_update(lambda e: self._command(e, "set", mesh_resolution=int(res.value)))
        observed.on_update(lambda e: self._command(e, "set", mesh_observed_only=bool(observed.value)))

    # -- actions (run on viser's thread pool) --------------------------------------------------
    def _command(self, event: Any, kind: str, **args: Any) -> Any:
        try:
            return self.worker.submit(kind, **args).result(timeout=COMMAND_TIMEOUT_S)
        except Exception as e:
            log.warning("%s failed: %s", kind, e)
            notify(event, f"{kind} failed", str(e), error=True)
            return None

    def _download(self, event: Any, what: str) -> None:
        client = event.client
        if client is None:
            return
        note = client.add_notification(
            "Preparing download", f"{what.upper()}...", loading=True, with_close_button=False
        )
        try:
            if what == "view":
                data, name = render_png(self.worker, client.camera, self.renders.mode), "view.png"
            else:
                data = self.worker.submit("export", format=what).result(timeout=COMMAND_TIMEOUT_S)
                name = f"mesh.{what}"
            self.downloads += 1
            client.send_file_download(f"h2viz_{time.strftime('%Y%m%d-%H%M%S')}_{name}", data, save_immediately=True)
        except Exception as e:
            log.warning("download of %s failed: %s", what, e)
            notify(event, "Download failed", str(e), error=True)
        finally:
            note.remove()

    def _save(self, event: Any) -> None:
        path = self.out_dir / f"checkpoint_{time.strftime('%Y%m%d-%H%M%S')}.pt"
        saved = self._command(event, "save", path=str(path))
        if saved is not None:
            notify(event, "Checkpoint saved", str(saved))

    # -- refresh -------------------------------------------------------------------------------
    def update(self, snap: MapSnapshot) -> None:
        if self._offer is not None and self.worker.resume_offer is None:  # taken or dismissed elsewhere
            self._drop_offer()
        self.pause.disabled = snap.paused or snap.finished
        self.resume.disabled = not snap.paused or snap.finished
        self.step.disabled = snap.finished
        self.status.update(snap)
        self.comforts.update(snap)
