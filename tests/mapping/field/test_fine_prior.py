"""Fine SDF priors: the compiled kernels match the torch reference, a plane's truncated SDF comes back on the
lattice, space more than a truncation behind every surface stays unfused, a later view carves free space back
to positive, and the prior blends into the corner priors where no frame reached the lattice."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from h2viz.mapping.field.fine_prior import SUB, FinePrior
from tests.mapping.backends import FAST, REFERENCE

VS, TR = 0.1, 0.05
K = np.array([[200.0, 0.0, 80.0], [0.0, 200.0, 60.0], [0.0, 0.0, 1.0]])


def _voxels(x: range, y: range, z: range) -> torch.Tensor:
    """Origins (V,3) of the voxels on integer cells x * y * z."""
    return torch.tensor([[i * VS, j * VS, k * VS] for i in x for j in y for k in z], dtype=torch.float32)


def _prior(origins: torch.Tensor, fused: bool = True) -> FinePrior:
    prior = FinePrior(VS, TR, backend=FAST if fused else REFERENCE)
    prior.grow(origins.shape[0])
    return prior


def _voxel_of(origins: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Voxel ids (N,) of points (N,3) strictly inside the voxels with origins (V,3)."""
    cells = torch.floor(points / VS)
    match = (torch.round(origins / VS)[None] == cells[:, None]).all(dim=2)  # (N,V)
    return torch.where(match.any(1), match.float().argmax(1), torch.full((points.shape[0],), -1))


def test_a_plane_comes_back_as_its_truncated_sdf() -> None:
    origins = _voxels(range(-2, 2), range(-2, 2), range(7, 12))  # z from 0.7 to 1.2 m
    prior = _prior(origins)
    depth = np.full((120, 160), 0.93, np.float32)  # a wall facing the camera at the origin
    prior.fuse(origins, depth, K, np.eye(4))
    rng = np.random.default_rng(0)
    pts = torch.from_numpy(np.c_[rng.uniform(-0.05, 0.05, (4000, 2)), rng.uniform(0.7, 1.2, 4000)]).float()
    value, cover = prior.blend(origins, pts, _voxel_of(origins, pts))
    z = pts[:, 2].numpy()
    sdf = (0.93 - z) / TR
    lattice = VS / SUB
    linear = np.abs(sdf) < 1.0 - lattice / TR  # the 8 lattice points around it all inside the truncation band
    assert np.allclose(value[linear].numpy(), sdf[linear], atol=1e-4)
    assert np.allclose(cover[linear].numpy(), 1.0)
    free = sdf > 1.0 + lattice / TR
    assert np.allclose(value[free].numpy(), 1.0) and np.allclose(cover[free].numpy(), 1.0)
    hidden = sdf < -1.0 - lattice / TR  # more than tr behind the wall: no frame has seen it
    assert hidden.sum() > 500 and np.all(cover[hidden].numpy() == 0.0) and np.all(value[hidden].numpy() == 0.0)


def test_a_later_view_carves_free_space_behind_a_silhouette() -> None:
    origins = _voxels(range(0, 1), range(0, 1), range(9, 10))
    prior = _prior(origins)
    point = torch.tensor([[0.05, 0.05, 0.95]])
    T = np.eye(4)
    T[:3, 3] = [0.05, 0.05, 0.0]  # a camera right in front of the point
    near = np.full((120, 160), 0.925, np.float32)  # first view: an object 2.5 cm in front of the point
    far = np.full((120, 160), 2.0, np.float32)  # second view: open space to a wall behind it
    prior.fuse(origins, near, K, T)
    v1, c1 = prior.blend(origins, point, torch.tensor([0]))
    prior.fuse(origins, far, K, T)
    prior.fuse(origins, far, K, T)
    v3, c3 = prior.blend(origins, point, torch.tensor([0]))
    assert c1.item() == pytest.approx(1.0) and v1.item() == pytest.approx(-0.5, abs=1e-4)
    assert c3.item() == pytest.approx(1.0) and v3.item() == pytest.approx((-0.5 + 1.0 + 1.0) / 3, abs=1e-4)


def test_points_behind_the_camera_or_outside_the_image_are_left_alone() -> None:
    origins = _voxels(range(-1, 1), range(-1, 1), range(-3, 3))
    prior = _prior(origins)
    prior.fuse(origins, np.full((120, 160), 5.0, np.float32), K, np.eye(4))
    P = (SUB + 1) ** 3
    lattice = prior._lattice_points(origins)  # (V,P,3)
    z = lattice[..., 2]
    uv_x = K[0, 0] * lattice[..., 0] / z.clamp(min=1e-6) + K[0, 2]
    seen = prior.state[..., 1] > 0  # (V,P)
    assert seen.shape == (origins.shape[0], P)
    assert not seen[z <= 0].any()  # behind the camera
    assert not seen[(z > 0) & ((uv_x < -0.5) | (uv_x > 159.5))].any()  # off the image
    assert seen.any()


@pytest.mark.parametrize("seed", [0, 1])
def test_kernels_match_the_torch_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    origins = _voxels(range(-3, 3), range(-2, 2), range(4, 10))
    fused, reference = _prior(origins, fused=True), _prior(origins, fused=False)
    for _ in range(3):
        depth = rng.uniform(0.5, 1.0, (120, 160)).astype(np.float32)
        depth[rng.random(depth.shape) < 0.2] = 0.0  # holes
        T = np.eye(4)
        T[:3, 3] = rng.normal(0, 0.05, 3)
        fused.fuse(origins, depth, K, T)
        reference.fuse(origins, depth, K, T)
    assert fused.state[..., 1].sum() > 1000
    assert torch.allclose(fused.state, reference.state, atol=1e-5)
    pts = torch.from_numpy(rng.uniform([-0.3, -0.2, 0.4], [0.3, 0.2, 1.0], (3000, 3))).float()
    vox = _voxel_of(origins, pts)
    vox[::7] = -1  # outside the map
    for a, b in zip(fused.blend(origins, pts, vox), reference.blend(origins, pts, vox), strict=True):
        assert torch.allclose(a, b, atol=1e-5)


@pytest.mark.parametrize("fused", [True, False], ids=["kernels", "reference"])
def test_fusing_listed_voxels_writes_only_theirs_as_fusing_all_would(fused: bool) -> None:
    rng = np.random.default_rng(3)
    origins = _voxels(range(-3, 3), range(-2, 2), range(4, 10))
    depth = rng.uniform(0.5, 1.0, (120, 160)).astype(np.float32)
    listed = np.array([5, 0, 77, 140, 31])  # any order
    whole, part = _prior(origins, fused), _prior(origins, fused)
    whole.fuse(origins, depth, K, np.eye(4))
    part.fuse(origins, depth, K, np.eye(4), voxels=listed)
    others = np.setdiff1d(np.arange(origins.shape[0]), listed)
    assert part.state[listed, :, 1].sum() > 500
    assert torch.equal(part.state[listed], whole.state[listed])
    assert not part.state[others].any()
    part.fuse(origins, depth, K, np.eye(4), voxels=others)  # the rest in a second call: the same as all at once
    assert torch.equal(part.state, whole.state)
    part.fuse(origins, depth, K, np.eye(4), voxels=np.zeros(0, np.int64))  # none listed: nothing fused
    assert torch.equal(part.state, whole.state)


def test_voxels_at_the_image_border_far_off_axis_are_fused_like_the_reference() -> None:
    """Near the camera and far off its axis a voxel's image is stretched beyond its centre's distance times the
    radius over depth: culling by that circle skipped voxels whose corners still project into the image."""
    wide = np.array([[60.0, 0.0, 80.0], [0.0, 60.0, 60.0], [0.0, 0.0, 1.0]])  # ~106 x 90 degrees
    origins = _voxels(range(-15, 15), range(-10, 10), range(1, 8))  # 0.1-0.8 m deep, out to 1.5 m aside
    fused, reference = _prior(origins, fused=True), _prior(origins, fused=False)
    depth = np.full((120, 160), 1.0, np.float32)  # every voxel in front of it: free space, fused
    fused.fuse(origins, depth, wide, np.eye(4))
    reference.fuse(origins, depth, wide, np.eye(4))
    assert reference.state[..., 1].sum() > 1000
    assert torch.equal(fused.state[..., 1] > 0, reference.state[..., 1] > 0)
    assert torch.allclose(fused.state, reference.state, atol=1e-5)


def test_storage_grows_without_losing_lattices_and_loads_back() -> None:
    origins = _voxels(range(0, 2), range(0, 2), range(9, 10))
    prior = _prior(origins)
    prior.fuse(origins, np.full((120, 160), 0.97, np.float32), K, np.eye(4))
    before = prior.state.clone()
    prior.grow(1000)
    assert prior.state.shape[0] == 1000
    assert torch.equal(prior.state[: before.shape[0]], before) and prior.state[before.shape[0] :].abs().sum() == 0
    copy = FinePrior(VS, TR)
    copy.load(prior.state.clone())
    assert torch.equal(copy.state, prior.state)
    with pytest.raises(ValueError, match="expected"):
        copy.load(torch.zeros(3, 10, 2))


@pytest.mark.parametrize("share", [True, False])
def test_a_voxel_allocated_late_starts_its_shared_face_from_its_older_neighbour(share: bool) -> None:
    """Voxel A (z 0.9-1.0 m) sees three frames of open space; voxel B behind it (z 1.0-1.1) exists only from the
    fourth frame on, which puts a surface at 1.02 m. Shared, the face at z = 1 m holds the same average in both
    voxels, so the field is continuous there; not shared, B's side holds the fourth frame alone and the field
    jumps by 0.4 tr across the face (a spurious crossing for any render that samples both sides)."""
    origins = _voxels(range(0, 1), range(0, 1), range(9, 11))  # A = 0, B = 1
    T = np.eye(4)
    T[:3, 3] = [0.05, 0.05, 0.0]
    prior = _prior(origins[:1])
    for _ in range(3):
        prior.fuse(origins[:1], np.full((120, 160), 2.0, np.float32), K, T)
    prior.grow(2)
    if share:
        neighbours = np.array([[-1, -1, -1, -1, 0, -1]])  # B's -z face is A's +z face
        prior.share_faces(np.array([1]), neighbours)
    prior.fuse(origins, np.full((120, 160), 1.02, np.float32), K, T)
    face = torch.tensor([[0.03, 0.06, 1.0], [0.05, 0.05, 1.0], [0.09, 0.01, 1.0]])
    from_a, _ = prior.blend(origins, face, torch.zeros(3, dtype=torch.long))
    from_b, _ = prior.blend(origins, face, torch.ones(3, dtype=torch.long))
    expected_a = (3 * 1.0 + 0.4) / 4  # three frames of open space and the surface 2 cm behind the face
    assert from_a.numpy() == pytest.approx(np.full(3, expected_a), abs=1e-4)
    if share:
        assert from_b.numpy() == pytest.approx(from_a.numpy(), abs=1e-5)
    else:
        assert from_b.numpy() == pytest.approx(np.full(3, 0.4), abs=1e-4)
