"""`h2viz render-path RUN_DIR PATH.json`: a fly-through video rendered from a finished run's neural field."""

from __future__ import annotations

from pathlib import Path

from tqdm import tqdm

from h2viz.config import load_config
from h2viz.errors import CheckpointError
from h2viz.viewer.camera_path import load_path
from h2viz.viewer.video import render_path_video


def render_run_path(
    run_dir: Path,
    path_file: Path,
    out: Path | None = None,
    width: int | None = None,
    height: int | None = None,
    progress: bool = True,
) -> Path:
    """Render the camera path in `path_file` from RUN_DIR/checkpoint.pt to an MP4 (default: PATH.mp4)."""
    from h2viz.mapping.checkpoint import load_checkpoint

    run_dir, path_file = Path(run_dir), Path(path_file)
    checkpoint = run_dir / "checkpoint.pt"
    if not checkpoint.is_file():
        raise CheckpointError(f"{checkpoint} not found: render-path needs a run folder written by `h2viz map`")
    path = load_path(path_file)
    path.width, path.height = width or path.width, height or path.height
    path.check(str(path_file))
    config = run_dir / "config.yaml"
    cfg = load_config([config] if config.is_file() else [])
    mapper, _ = load_checkpoint(checkpoint, cfg.mapping)
    with tqdm(total=path.n_frames, disable=not progress, unit="frame", dynamic_ncols=True) as bar:
        return render_path_video(
            lambda K, T, h, w: mapper.render(K, T, h, w, "rgb"),
            path,
            out or path_file.with_suffix(".mp4"),
            on_frame=lambda done, _total: bar.update(done - bar.n),
        )
