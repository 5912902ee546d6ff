"""Checkpoints hold only tensors, arrays and plain data: a crafted file is refused without running its code, an old
(format 1) file gets a "re-save" message and `h2viz upgrade-checkpoint` converts it, and a damaged or incomplete file
is a clear error naming what is wrong."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch

from h2viz.cli import main
from h2viz.errors import CheckpointError
from h2viz.mapping import checkpoint_format
from h2viz.mapping.checkpoint import load_checkpoint, save_checkpoint, upgrade_checkpoint
from h2viz.mapping.mapper import Mapper
from tests.mapping.analytic import Scene, orbit
from tests.mapping.test_mapper import small_cfg

torch.set_num_threads(2)


class Payload:
    """Unpickling this creates the file `marker`: what a crafted checkpoint would do."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple:
        return (os.makedirs, (str(self.marker),))


@pytest.fixture(scope="module")
def saved(tmp_path_factory: pytest.TempPathFactory) -> tuple[Mapper, Path]:
    scene = Scene("sphere", radius=0.4)
    mapper = Mapper(small_cfg(max_iters=2))
    for i, T in enumerate(orbit(scene, 6, 1.4, 0.4, scene.center)[:2]):
        mapper.integrate(scene.frame(i, T))
    path = tmp_path_factory.mktemp("ck") / "checkpoint.pt"
    save_checkpoint(mapper, path, {"last_index": 1})
    return mapper, path


def test_plain_data_round_trips_and_anything_else_is_refused_on_save() -> None:
    state = {
        "a": np.arange(5, dtype=np.uint64),
        "b": (np.zeros((2, 3), bool), [np.float32(1.5), "x", None]),
        "c": {"t": torch.ones(2), "n": np.int64(7)},
    }
    back = checkpoint_format.decode(checkpoint_format.encode(state))
    assert back["a"].dtype == np.uint64 and back["a"].tolist() == [0, 1, 2, 3, 4]
    assert back["b"][0].shape == (2, 3) and back["b"][1] == [1.5, "x", None] and back["c"]["n"] == 7
    with pytest.raises(CheckpointError, match=r"checkpoint\.extra\.fn: a builtin_function_or_method cannot be saved"):
        checkpoint_format.encode({"extra": {"fn": print}})


def test_a_checkpoint_is_read_with_weights_only(saved: tuple[Mapper, Path]) -> None:
    data = torch.load(saved[1], weights_only=True)  # raises if anything but tensors and plain data is inside
    assert data["format_version"] == 2 and isinstance(data["trajectory"][checkpoint_format.ARRAY_TAG], torch.Tensor)


def test_a_crafted_checkpoint_is_refused_without_running_its_code(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    marker = tmp_path / "created_by_the_checkpoint"
    evil = tmp_path / "evil.pt"
    torch.save({"format_version": 2, "config": Payload(marker)}, evil)
    with pytest.raises(CheckpointError, match=r"refused: loading it would call os\.makedirs.*nothing in it was run"):
        load_checkpoint(evil)
    assert not marker.exists()
    assert main(["map", "--resume", str(evil), "--out", str(tmp_path / "run"), "-q"]) == 2
    assert "refused" in capsys.readouterr().err and not marker.exists()


def test_an_old_checkpoint_names_the_upgrade_and_the_upgrade_reproduces_the_map(
    saved: tuple[Mapper, Path], tmp_path: Path
) -> None:
    mapper, path = saved
    old = tmp_path / "old.pt"
    state = checkpoint_format.read(path)  # NumPy arrays again, pickled as objects as format 1 did
    torch.save({**state, "format_version": 1}, old)
    with pytest.raises(CheckpointError, match=r"older h2viz \(checkpoint format 1.*h2viz upgrade-checkpoint"):
        load_checkpoint(old)
    assert main(["upgrade-checkpoint", str(old)]) == 0
    again, extra = load_checkpoint(upgrade_checkpoint(old, tmp_path / "new.pt"))
    assert extra == {"last_index": 1} and (tmp_path / "old.v2.pt").is_file()
    T = mapper.trajectory[0]
    K = mapper.keyframe_rays[0].K
    np.testing.assert_allclose(again.render(K, T, 24, 32, "depth"), mapper.render(K, T, 24, 32, "depth"), atol=1e-6)


def test_an_incomplete_or_damaged_checkpoint_is_a_clear_error(saved: tuple[Mapper, Path], tmp_path: Path) -> None:
    state = torch.load(saved[1], weights_only=True)
    del state["octree"], state["rng"]
    torch.save(state, tmp_path / "partial.pt")
    with pytest.raises(CheckpointError, match=r"partial\.pt is incomplete: it lacks octree, rng"):
        load_checkpoint(tmp_path / "partial.pt")
    state = torch.load(saved[1], weights_only=True)
    state["octree"] = {"voxel_keys": state["octree"]["voxel_keys"]}
    torch.save(state, tmp_path / "inconsistent.pt")
    with pytest.raises(CheckpointError, match=r"inconsistent\.pt is damaged or inconsistent \(KeyError"):
        load_checkpoint(tmp_path / "inconsistent.pt")
    data = saved[1].read_bytes()
    (tmp_path / "cut.pt").write_bytes(data[: len(data) // 2])  # a copy cut short
    with pytest.raises(CheckpointError, match=r"cut\.pt is not a readable h2viz checkpoint"):
        load_checkpoint(tmp_path / "cut.pt")
