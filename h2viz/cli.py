"""`h2viz` command line: the only place that prints and exits."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from h2viz.config import (
    Config,
    apply_file,
    apply_overrides,
    field_docs,
    load_config,
    source_config_file,
    to_dict,
)
from h2viz.errors import H2vizError

FORMAT_CHOICES = ["auto", "synthetic", "replica", "scannet", "tum", "7scenes", "rosbag"]


def _source_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", default="", help="dataset folder or bag file (default: the built-in synthetic scene)")
    p.add_argument("--format", default=None, choices=FORMAT_CHOICES, help="data layout (default: auto-detect)")
    p.add_argument("--config", action="append", default=[], help="YAML config file (repeatable, later wins)")
    p.add_argument("--frames", type=int, default=None, help="stop after N frames")
    p.add_argument("--stride", type=int, default=None, help="use every K-th frame")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override any config field, e.g. mapping.optimization.max_iters=5",
    )


def build_config(args: argparse.Namespace) -> Config:
    """defaults <- configs/default.yaml <- configs/<format>.yaml <- --config files <- flags <- --set."""
    cfg = load_config()
    fmt = args.format or "auto"
    if fmt == "auto":
        from h2viz.sources.base import detect_format

        fmt = detect_format(args.data)
    per_source = source_config_file(fmt)
    if per_source is not None:
        apply_file(cfg, per_source)
    for f in args.config:
        apply_file(cfg, f)
    cfg.source.path = args.data
    cfg.source.format = fmt
    if args.frames is not None:
        cfg.source.max_frames = args.frames
    if args.stride is not None:
        cfg.source.stride = args.stride
    if getattr(args, "out", None):
        cfg.out_dir = args.out
    if getattr(args, "host", None):
        cfg.viewer.host = args.host
    if getattr(args, "port", None):
        cfg.viewer.port = args.port
    if getattr(args, "realtime", False):
        cfg.source.realtime = True
    return apply_overrides(cfg, args.set)


def cmd_map(args: argparse.Namespace) -> int:
    from h2viz.pipeline import run_map

    cfg = build_config(args)
    result = run_map(
        cfg,
        resume=args.resume,
        gt_mesh=args.gt_mesh,
        progress=not args.quiet,
        realtime=cfg.source.realtime,
        record=args.record,
    )
    print(result.summary())
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    from h2viz.viewer.server import run_view

    run_view(
        build_config(args),
        on_ready=lambda url: print(f"h2viz dashboard: {url}  (Ctrl-C to stop)", flush=True),
        resume=args.resume,
    )
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from h2viz.viewer.replay import run_replay

    run_replay(
        args.run_dir,
        args.host,
        args.port,
        on_ready=lambda url: print(f"h2viz replay: {url}  (Ctrl-C to stop)", flush=True),
    )
    return 0


def cmd_export_html(args: argparse.Namespace) -> int:
    from h2viz.viewer.html_export import export_html

    out = export_html(args.run_dir, args.out, args.fps)
    print(f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB)")
    return 0


def cmd_render_path(args: argparse.Namespace) -> int:
    from h2viz.render_path import render_run_path

    out = render_run_path(args.run_dir, args.path, args.out, args.width, args.height, progress=not args.quiet)
    print(f"wrote {out}")
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from h2viz.eval.report import evaluate_mesh_files, format_table, write_metrics

    cfg = load_config(args.config, args.set)
    if args.points:
        cfg.eval.n_points = args.points
    metrics = evaluate_mesh_files(args.mesh, args.gt, cfg.eval)
    print(format_table(metrics))
    out = Path(args.out) if args.out else Path(args.mesh).with_name("metrics.json")
    write_metrics(metrics, out)
    print(f"wrote {out}")
    return 0


def cmd_bag_info(args: argparse.Namespace) -> int:
    from h2viz.sources.rosbag import bag_info

    cfg = load_config(args.config, args.set)
    print(bag_info(Path(args.path), cfg.source.rosbag))
    return 0


def cmd_upgrade_checkpoint(args: argparse.Namespace) -> int:
    from h2viz.mapping.checkpoint import upgrade_checkpoint

    out = upgrade_checkpoint(args.path, args.out)
    print(f"wrote {out}; resume from it with `h2viz map --resume {out}`")
    return 0


def cmd_config(args: argparse.Namespace) -> int:
    import yaml

    if args.docs:
        import dataclasses

        def walk(obj: object, prefix: str) -> None:
            docs = field_docs(type(obj))
            for f in dataclasses.fields(obj):  # type: ignore[arg-type]
                value = getattr(obj, f.name)
                if dataclasses.is_dataclass(value):
                    print(f"# {prefix}{f.name}: {docs.get(f.name, '')}")
                    walk(value, f"{prefix}{f.name}.")
                else:
                    print(f"{prefix}{f.name} = {value!r}\n    {docs.get(f.name, '')}")

        walk(Config(), "")
    else:
        print(yaml.safe_dump(to_dict(load_config(args.config, args.set)), sort_keys=False), end="")
    return 0


def make_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="h2viz", description="Live H2-Mapping of RGB-D frames, in the browser.")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("map", help="map a sequence headless and write mesh, checkpoint, stats and metrics")
    _source_args(p)
    p.add_argument("--out", default="", help="output folder (default: outputs/<format>-<time>)")
    p.add_argument(
        "--resume",
        type=Path,
        default=None,
        help="continue an earlier run: its folder (the newest checkpoint there; outputs go there too) or a .pt file",
    )
    p.add_argument("--gt-mesh", type=Path, default=None, help="ground-truth mesh for metrics.json")
    p.add_argument(
        "--realtime",
        action="store_true",
        help="play the source at its own frame rate: integrate every frame as it arrives, optimise between frames "
        "and, after the stream, until the loss stops improving (source.realtime, anytime.*)",
    )
    p.add_argument(
        "--record",
        action="store_true",
        help="also write a timeline recording (OUT/recording) for `h2viz replay` and `h2viz export-html`",
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_map)

    p = sub.add_parser("view", help="start the live dashboard (default: synthetic scene)")
    _source_args(p)
    p.add_argument("--host", default=None, help="address to bind (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=None, help="port (default 8080)")
    p.add_argument("--realtime", action="store_true", help="start in real-time mode (source.realtime)")
    p.add_argument("--out", default="", help="run folder for autosaves and checkpoints (default: outputs/)")
    p.add_argument("--resume", type=Path, default=None, help="continue a run: its folder or a checkpoint .pt")
    p.set_defaults(func=cmd_view)

    p = sub.add_parser("replay", help="serve a recorded run: play, pause, scrub, step, speed (no mapping)")
    p.add_argument("run_dir", type=Path, help="a run folder written by `h2viz map --record` (or its recording/)")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8080, help="port (default 8080)")
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser("export-html", help="write a recorded run as one HTML file that plays with no server")
    p.add_argument("run_dir", type=Path, help="a run folder written by `h2viz map --record`")
    p.add_argument(
        "--out", type=Path, default=None, help="output .html (or .viser) file (default RUN_DIR/recording.html)"
    )
    p.add_argument("--fps", type=float, default=None, help="steps per second at 1x (default: the recording's)")
    p.set_defaults(func=cmd_export_html)

    p = sub.add_parser("render-path", help="render a camera path JSON from a run's map to MP4")
    p.add_argument("run_dir", type=Path, help="a run folder with checkpoint.pt and config.yaml")
    p.add_argument("path", type=Path, help="camera path JSON (the dashboard's Save path writes one)")
    p.add_argument("--out", type=Path, default=None, help="output .mp4 (default: next to the path file)")
    p.add_argument("--width", type=int, default=None, help="video width (default: the path's)")
    p.add_argument("--height", type=int, default=None, help="video height (default: the path's)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_render_path)

    p = sub.add_parser("eval", help="Acc / Comp / Comp ratio of a mesh against ground truth")
    p.add_argument("--mesh", required=True, help="reconstructed mesh (PLY/OBJ/GLB)")
    p.add_argument("--gt", required=True, help="ground-truth mesh")
    p.add_argument("--points", type=int, default=0, help="points sampled per mesh (default 200000)")
    p.add_argument("--out", default="", help="metrics.json path (default: next to --mesh)")
    p.add_argument("--config", action="append", default=[], help="YAML config file")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("bag-info", help="list a bag's topics and what h2viz would use")
    p.add_argument("path", help=".bag file, ROS 2 bag folder, .mcap or .db3")
    p.add_argument("--config", action="append", default=[], help="YAML config file")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")
    p.set_defaults(func=cmd_bag_info)

    p = sub.add_parser(
        "upgrade-checkpoint", help="re-save a checkpoint of an older h2viz in this version's safe format"
    )
    p.add_argument("path", type=Path, help="the old checkpoint .pt (read without running code it might carry)")
    p.add_argument("--out", type=Path, default=None, help="where to write it (default: <name>.v2.pt next to it)")
    p.set_defaults(func=cmd_upgrade_checkpoint)

    p = sub.add_parser("config", help="print the resolved configuration (or every field's documentation)")
    p.add_argument("--config", action="append", default=[], help="YAML config file")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")
    p.add_argument("--docs", action="store_true", help="list every field with its documentation")
    p.set_defaults(func=cmd_config)
    return parser


def main(argv: list[str] | None = None) -> int:
    return _run(make_parser().parse_args(argv))


def app_main(argv: list[str]) -> int:
    """`python app.py`: `h2viz view` with the same flags, plus bare `section.key=value` overrides (as --set)."""
    parser = make_parser()
    args, extra = parser.parse_known_args(["view", *argv])
    wrong = [t for t in extra if t.startswith("-") or "=" not in t]
    if wrong:
        parser.error(f"app.py: unrecognised {' '.join(wrong)}; flags are those of `h2viz view --help`, overrides "
                     "look like section.key=value (e.g. viewer.port=8081)")  # fmt: skip
    args.set = [*extra, *args.set]
    return _run(args)


def _run(args: argparse.Namespace) -> int:
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s"
    )
    try:
        return int(args.func(args))
    except H2vizError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
