"""Frame sources: every dataset layout, ROS bags and the built-in synthetic scene behind one interface."""

from h2viz.sources.base import FORMATS, FrameSource, SkippedFrame, detect_format, make_source

__all__ = ["FORMATS", "FrameSource", "SkippedFrame", "detect_format", "make_source"]
