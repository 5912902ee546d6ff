"""LatestSlot: a single-value mailbox between threads where the newest value wins."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")


class LatestSlot(Generic[T]):
    """A single-value mailbox: `put` replaces the value and bumps the version (newest wins)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._value: T | None = None
        self._version = 0

    def put(self, value: T) -> int:
        with self._cond:
            self._value, self._version = value, self._version + 1
            self._cond.notify_all()
            return self._version

    def get(self) -> tuple[int, T | None]:
        with self._cond:
            return self._version, self._value

    def wait_newer(self, version: int, timeout_s: float) -> tuple[int, T | None]:
        """Block until the version exceeds `version` or the timeout passes; return the current pair."""
        with self._cond:
            self._cond.wait_for(lambda: self._version > version, timeout=timeout_s)
            return self._version, self._value

    def wait_until(self, predicate: Callable[[T], bool], timeout_s: float) -> bool:
        """Block until the value satisfies `predicate` or the timeout passes; whether it does."""
        with self._cond:
            return self._cond.wait_for(lambda: self._value is not None and predicate(self._value), timeout=timeout_s)
