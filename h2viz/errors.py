"""Typed errors. Every message says what is wrong and what to do about it; only cli.py prints them."""

from __future__ import annotations


class H2vizError(Exception):
    """Base class of every error h2viz raises on purpose."""


class ConfigError(H2vizError):
    """A configuration file or override is invalid (unknown key, wrong type, bad value)."""


class SourceError(H2vizError):
    """A frame source cannot be opened at all (missing folder, unrecognised layout, no intrinsics...)."""


class FrameError(H2vizError):
    """One frame cannot be read; the source skips it, counts it and goes on."""


class CheckpointError(H2vizError):
    """A checkpoint cannot be written or read back."""
