"""Shapes, conventions and helpers of uncertsplat.render."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.reference.naive_render import look_at_cameras, random_scene
from uncertsplat.render import render, rgb_to_sh
from uncertsplat.render.project import quat_to_rotmat
from uncertsplat.render.sh import C0, sh_basis


def _sphere_quadrature(n_theta=16, n_phi=32):
    """Gauss-Legendre in cos(theta) x uniform phi: exact for polynomials of degree <= 2 n_theta - 1."""
    x, w = np.polynomial.legendre.leggauss(n_theta)
    phi = np.arange(n_phi) * 2 * np.pi / n_phi
    ct, ph = np.meshgrid(x, phi, indexing="ij")
    st = np.sqrt(1 - ct**2)
    dirs = np.stack([st * np.cos(ph), st * np.sin(ph), ct], -1).reshape(-1, 3)
    weights = (w[:, None] * np.full(n_phi, 2 * np.pi / n_phi)[None]).reshape(-1)
    return torch.from_numpy(dirs), torch.from_numpy(weights)


def test_sh_basis_is_orthonormal_on_the_sphere():
    dirs, w = _sphere_quadrature()
    Y = sh_basis(3, dirs)  # [Q,16]
    gram = (Y * w[:, None]).T @ Y
    assert torch.allclose(gram, torch.eye(16, dtype=gram.dtype), atol=1e-10)


def test_sh_degree1_follows_the_3dgs_sign_convention():
    d = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    Y = sh_basis(1, d)
    c1 = math.sqrt(3 / (4 * math.pi))
    assert torch.allclose(Y[0], torch.tensor([C0, 0, c1, 0], dtype=torch.float64))
    assert torch.allclose(Y[1], torch.tensor([C0, 0, 0, -c1], dtype=torch.float64))
    assert torch.allclose(Y[2], torch.tensor([C0, -c1, 0, 0], dtype=torch.float64))


def test_rgb_sh_roundtrip():
    rgb = torch.rand(10, 3, generator=torch.Generator().manual_seed(0))
    assert C0 == pytest.approx(0.28209479177387814)
    assert torch.allclose(rgb_to_sh(rgb) * C0 + 0.5, rgb, atol=1e-6)
    assert torch.allclose(rgb_to_sh(torch.full((3,), 0.5)), torch.zeros(3))


def test_quaternion_identity_and_orthonormality():
    q = torch.randn(50, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    R = quat_to_rotmat(q)
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=R.dtype).expand(50, 3, 3), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(50, dtype=R.dtype))
    assert torch.allclose(quat_to_rotmat(torch.tensor([[2.0, 0, 0, 0]])), torch.eye(3)[None])


def test_output_shapes_and_means2d_gradient(device):
    from dataclasses import replace

    s = random_scene(80, torch.Generator().manual_seed(1), sh_degree=3).to(device=device)
    means = s.means.clone().requires_grad_()
    s = replace(s, means=means, opacities=s.opacities.clone().requires_grad_())
    cams = look_at_cameras(2, 30, 20, focal=25.0).to(device=device)
    out = render(s, cams)
    assert out.rgb.shape == (2, 20, 30, 3)
    assert out.alpha.shape == out.depth.shape == out.depth_expected.shape == (2, 20, 30, 1)
    assert out.means2d.shape == (2, 80, 2) and out.radii.shape == (2, 80) and out.depths.shape == (2, 80)
    assert not out.means2d.is_leaf
    out.rgb.sum().backward()
    g = out.means2d.grad
    assert g is not None and g.shape == (2, 80, 2)
    visible = out.radii > 0
    assert (g[visible].abs().sum(-1) > 0).float().mean() > 0.5
    assert (g[~visible] == 0).all()
    assert (out.depth[out.alpha == 0] == 0).all()
    hit = out.alpha[..., 0] > 0
    assert torch.allclose(out.depth[hit], out.depth_expected[hit] / out.alpha[hit])


def test_means2d_is_the_pinhole_projection(device):
    s = random_scene(10, torch.Generator().manual_seed(2), sh_degree=0).to(device=device)
    cams = look_at_cameras(1, 30, 20, focal=25.0).to(device=device)
    out = render(s, cams)
    p = s.means @ cams.cam_from_world[0, :3, :3].T + cams.cam_from_world[0, :3, 3]
    uv = (p @ cams.K[0].T)[:, :2] / p[:, 2:]
    assert torch.allclose(out.means2d[0], uv, atol=1e-4)
    assert torch.allclose(out.depths[0], p[:, 2], atol=1e-5)


def test_no_gradients_needed_works(device):
    s = random_scene(30, torch.Generator().manual_seed(3), sh_degree=1).to(device=device)
    cams = look_at_cameras(1, 16, 16, focal=15.0).to(device=device)
    with torch.no_grad():
        out = render(s, cams)
    assert out.rgb.requires_grad is False and out.alpha.max() > 0


def test_the_near_plane_comes_nearer_only_for_a_surface_near_the_cameras():
    """1 % of the rig radius unless the sparse points' 1st-percentile depth is within 5x of it; then a fifth of
    that depth, floored at 0.1 % of the default (stray points at a lens)."""
    from uncertsplat.render import near_plane

    assert near_plane(2.0) == pytest.approx(0.02) and near_plane(2.0, torch.zeros(0)) == pytest.approx(0.02)
    far = torch.linspace(1.0, 5.0, 1000, dtype=torch.float64)
    assert near_plane(2.0, far) == pytest.approx(0.02)  # a surface well beyond it: unchanged
    close = torch.cat([torch.full((20,), 0.005), far])  # 2 % of the depths at 0.005
    assert near_plane(2.0, close) == pytest.approx(0.001)
    assert near_plane(2.0, torch.cat([torch.full((50,), 1e-12), far])) == pytest.approx(2e-5)
    assert near_plane(2.0, torch.full((9,), 1e-3)) == pytest.approx(0.02)  # too few to judge


def test_point_depths_are_the_in_view_camera_depths_in_chunks():
    """point_depths: the camera z of the points each camera has in front of it and inside its image, the same in
    chunks of cameras (40 here) as in one, and of every k-th point above max_points."""
    from uncertsplat.render.project import point_depths, project_points

    cams = look_at_cameras(40, 64, 48, focal=60.0, radius=3.0)
    pts = torch.randn(500, 3, generator=torch.Generator().manual_seed(0)) * 2
    uv, z = project_points(pts.double(), cams.cam_from_world, cams.K)
    inside = (z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < 64) & (uv[..., 1] >= 0) & (uv[..., 1] < 48)
    got = point_depths(pts, cams)
    assert got.dtype == torch.float64 and 0 < got.numel() < 40 * 500
    torch.testing.assert_close(got.sort().values, z[inside].sort().values)
    assert point_depths(pts, cams, max_points=100).numel() < got.numel() / 4


def test_camera_gradients_on_every_backend_and_bad_backends_refused():
    """The native projection has no camera gradient: a float32 CPU render by default gave cam_from_world.grad and
    K.grad of None (the PyTorch path gave them). A render whose cameras need grad takes the PyTorch projection, the
    same gradients; "native" asked for then is refused; a backend name that is none of the three ran the native
    kernels without a word."""
    import dataclasses

    s = random_scene(60, torch.Generator().manual_seed(3), sh_degree=1)
    cams = look_at_cameras(2, 30, 20, focal=25.0)
    grads = {}
    for backend in (None, "torch"):
        pose, K = cams.cam_from_world.clone().requires_grad_(), cams.K.clone().requires_grad_()
        out = render(s, dataclasses.replace(cams, cam_from_world=pose, K=K), backend=backend)
        (out.rgb.square().sum() + out.depth.sum()).backward()
        assert pose.grad is not None and K.grad is not None and float(pose.grad.abs().sum()) > 0
        grads[backend] = (pose.grad, K.grad)
    torch.testing.assert_close(grads[None][0], grads["torch"][0], rtol=1e-3, atol=1e-4)
    torch.testing.assert_close(grads[None][1], grads["torch"][1], rtol=1e-3, atol=1e-4)
    with pytest.raises(ValueError, match="no gradient for the cameras"):
        render(s, dataclasses.replace(cams, cam_from_world=cams.cam_from_world.clone().requires_grad_()),
               backend="native")
    for bad in ("Torch", "cuda", "pytorch"):
        with pytest.raises(ValueError, match="backend must be None, 'auto', 'native' or 'torch'"):
            render(s, cams, backend=bad)


def test_a_sample_with_rows_that_do_not_match_its_means_is_refused():
    """[1,3] scales beside [N,3] means: the native kernels read N rows of each and rendered memory past its end
    (images that changed from run to run); every per-Gaussian tensor must have the means' N rows."""
    from uncertsplat.types import GaussianSample

    s = random_scene(20, torch.Generator().manual_seed(4), sh_degree=1)
    import dataclasses

    for field, bad in (("scales", s.scales[:1]), ("opacities", s.opacities[:1]), ("sh", s.sh[:1]),
                       ("quats", s.quats[:, :3]), ("position_var", torch.zeros(3))):
        with pytest.raises(ValueError, match=f"GaussianSample.{field} must be"):
            dataclasses.replace(s, **{field: bad})
    assert len(GaussianSample(means=torch.zeros(0, 3), quats=torch.zeros(0, 4), scales=torch.zeros(0, 3),
                              opacities=torch.zeros(0), sh=torch.zeros(0, 1, 3))) == 0
