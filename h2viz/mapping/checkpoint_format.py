"""The checkpoint file format: plain data (dicts, lists, tuples, str, int, float, bool, None), torch tensors and NumPy
arrays written with `torch.save` and read back with `torch.load(weights_only=True)`, so opening a checkpoint never
runs code it carries. NumPy arrays travel as tensors tagged with ARRAY_TAG; NumPy scalars as Python numbers.

Files of checkpoint format 1 pickled NumPy arrays as objects: they are refused with a message that says how to
re-save them (`upgrade_legacy`, which still loads them without running code: only NumPy's array reconstruction is
allowed)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import torch

from h2viz.errors import CheckpointError

ARRAY_TAG = "__ndarray__"
_GLOBAL = re.compile(r"GLOBAL ([\w.]+)")


def encode(obj: Any, where: str = "checkpoint") -> Any:
    """`obj` with every NumPy array replaced by {ARRAY_TAG: tensor} and NumPy scalars by Python numbers; anything
    other than plain data, tensors and arrays raises CheckpointError naming where it sits."""
    if isinstance(obj, np.ndarray):
        if obj.dtype == object:
            raise CheckpointError(f"{where}: an object array cannot be saved; only numeric arrays can")
        return {ARRAY_TAG: torch.from_numpy(np.ascontiguousarray(obj).copy())}
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, torch.Tensor):
        return obj.detach().cpu()
    if isinstance(obj, dict):
        return {k: encode(v, f"{where}.{k}") for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return type(obj)(encode(v, f"{where}[{i}]") for i, v in enumerate(obj))
    if obj is None or isinstance(obj, str | int | float | bool):
        return obj
    raise CheckpointError(f"{where}: a {type(obj).__name__} cannot be saved in a checkpoint (only plain data)")


def decode(obj: Any) -> Any:
    """The inverse of `encode`: tagged tensors become NumPy arrays again."""
    if isinstance(obj, dict):
        if len(obj) == 1 and ARRAY_TAG in obj:
            return obj[ARRAY_TAG].numpy()
        return {k: decode(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return type(obj)(decode(v) for v in obj)
    return obj


def write(state: dict[str, Any], path: Path) -> None:
    """Encode `state` and write it to `path` atomically (a temporary file renamed over it)."""
    path = Path(path)
    data = encode(state)
    tmp = path.with_suffix(path.suffix + ".tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save(data, tmp)
        tmp.replace(path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise CheckpointError(f"cannot write checkpoint {path}: {e}; check the folder is writable and has room") from e


def read(path: Path, mmap: bool = False) -> dict[str, Any]:
    """Load a checkpoint without running any code it carries; a file that would need code is refused. `mmap`: its
    tensors are mapped from the file, read only when used (a quick look at its plain data)."""
    return decode(_load(Path(path), mmap))


def _load(path: Path, mmap: bool = False) -> dict[str, Any]:
    """torch.load with weights_only=True (and the safe globals in effect), as a dict, or a CheckpointError."""
    try:
        data = torch.load(path, map_location="cpu", weights_only=True, mmap=mmap)
    except Exception as e:  # noqa: BLE001 - any failure means the file is unusable as it is
        raise _refusal(path, e) from None
    if not isinstance(data, dict):
        raise CheckpointError(f"{path} is not an h2viz checkpoint (it holds a {type(data).__name__}, not a dict)")
    return data


def _refusal(path: Path, e: Exception) -> CheckpointError:
    """The message for a checkpoint torch's safe loader refused: an old h2viz one, a crafted one or a broken one."""
    found = _GLOBAL.search(str(e))
    if found is None:
        return CheckpointError(f"{path} is not a readable h2viz checkpoint ({type(e).__name__}: {e})")
    name = found.group(1)
    if name.startswith("numpy."):
        return CheckpointError(
            f"{path} was written by an older h2viz (checkpoint format 1, which pickled NumPy objects); re-save it "
            f"with this version: `h2viz upgrade-checkpoint {path}` (only use it on a file you trust)"
        )
    return CheckpointError(
        f"{path} was refused: loading it would call {name}, which an h2viz checkpoint never contains (it may have "
        "been crafted to run code); nothing in it was run. Resume only from checkpoints h2viz wrote"
    )


def _numpy_globals() -> list[Any]:
    """What format-1 checkpoints need to rebuild their NumPy arrays and scalars: data, no code."""
    core = np._core.multiarray  # type: ignore[attr-defined]
    dtypes = [type(np.dtype(c)) for c in "?bBhHiIlLqQefdgFDGSU"]
    names: list[Any] = [np.ndarray, np.dtype, *dtypes]
    for module in ("numpy.core.multiarray", "numpy._core.multiarray"):
        names += [(core._reconstruct, f"{module}._reconstruct"), (core.scalar, f"{module}.scalar")]
    return names


def read_legacy(path: Path) -> dict[str, Any]:
    """A format-1 checkpoint's state, loaded with only NumPy's array reconstruction allowed besides torch's own."""
    with torch.serialization.safe_globals(_numpy_globals()):
        return _load(Path(path))
