"""ContactGeometry concatenation, sparse rows, devices and differentiability."""

import math

import pytest
import torch

from diffcontact.geometry import (
    CirclePairs,
    CircleWalls,
    ContactGeometry,
    Geometry,
    RimPlane,
    circles_2d,
    jacobian_matvec,
    rope_limits,
)

DT = torch.float64
BOX = [[1, 0, 0], [0, 1, 0], [-1, 0, 1], [0, -1, 1]]


def test_concatenation_keeps_numbering():
    kinds, radii = ["disk", "point", "disk"], [0.1, 0.2, 0.15]
    pairs = CirclePairs.build(kinds, radii)
    walls = CircleWalls.build(kinds, radii, BOX)
    geo = ContactGeometry((pairs, walls))
    assert isinstance(geo, Geometry) and isinstance(pairs, Geometry)
    assert geo.offsets == (0, 3) and geo.n_candidates == 15
    x = torch.rand(2, 7, 2, dtype=DT)
    torch.testing.assert_close(geo.gaps(x), torch.cat((pairs.gaps(x), walls.gaps(x)), -1))
    idx = torch.tensor([[4, 1, 14, 0], [2, 3, 3, 9]])
    J = geo.jacobian(x, idx)
    for b in range(2):
        for k, i in enumerate(idx[b].tolist()):
            part, local = (pairs, i) if i < 3 else (walls, i - 3)
            torch.testing.assert_close(J[b, k], part.jacobian(x[b], torch.tensor([local]))[0])
    # pair rows have 6 entries, wall rows 3: walls are padded with exact zeros
    jac = geo.jacobian_sparse(x, idx)
    assert jac.points.shape == (2, 4, 6)
    assert (jac.values[0, 0, :, 3:] == 0).all()


def test_parts_must_share_d():
    with pytest.raises(ValueError, match="share d"):
        ContactGeometry((CirclePairs.build(["point"] * 2, [0.1] * 2), RimPlane.build()))


def test_to_device_keeps_results():
    geo = rope_limits(5).to("cpu")
    x = torch.randn(5, 2, dtype=DT)
    torch.testing.assert_close(geo.gaps(x), rope_limits(5).gaps(x))


def _gradcheck_rows(geo, x, idx):
    v = torch.randn(x.shape, dtype=DT)

    def f(xx):
        return jacobian_matvec(geo.jacobian_sparse(xx, idx), v), geo.gaps(xx)

    assert torch.autograd.gradcheck(f, (x.requires_grad_(True),))


def test_jacobian_is_differentiable_in_x():
    gen = torch.Generator().manual_seed(0)
    circles = circles_2d(["disk", "point"], [0.2, 0.1], BOX)
    _gradcheck_rows(circles, torch.rand(4, 2, generator=gen, dtype=DT), torch.arange(9))
    rim = RimPlane.build()
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=DT))
    x0 = torch.randn(3, generator=gen, dtype=DT)
    _gradcheck_rows(rim, torch.cat((x0[None], x0 + q.T)), torch.tensor([0]))
    rope = rope_limits(4)
    x = torch.tensor([[0.003, -0.045], [0.01, -0.1], [0.0, -0.15], [0.02, -0.19]], dtype=DT)
    _gradcheck_rows(rope, x, torch.arange(7))


def _hanging_rope(n: int, points: int, gen: torch.Generator) -> torch.Tensor:
    """``(n, points, 2)`` ropes hanging from the anchor: segments of about the rest length
    (0.05) at angles near straight down. (Random points instead make segments of any
    length: the rows' conditioning then decides how far float32 results on two devices
    differ, not the devices.)"""
    angle = -math.pi / 2 + 0.05 * torch.randn(n, points, generator=gen, dtype=DT)
    length = 0.05 * (1 + 0.05 * torch.randn(n, points, generator=gen, dtype=DT))
    return (length[..., None] * torch.stack([angle.cos(), angle.sin()], -1)).cumsum(-2)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu():
    """The geometries on CUDA give the CPU's gaps and rows: to rounding in float64; in
    float32 about as close to the float64 result as the CPU's float32 is. (A fixed
    float32 tolerance failed on an H200 for 2 of 240 entries, 1.2e-4 relative, on
    disks at random, unseeded positions: near-degenerate frames amplify rounding on any
    device.)"""
    gen = torch.Generator().manual_seed(1)
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=DT))
    x_rim = torch.cat((torch.zeros(1, 3, dtype=DT), q.T)).expand(3, 4, 3)
    cases = [
        (
            circles_2d(["disk", "point"], [0.2, 0.1], BOX),
            torch.rand(3, 4, 2, generator=gen, dtype=DT),
            9,
        ),
        (RimPlane.build(), x_rim, 1),
        (rope_limits(6), _hanging_rope(3, 6, gen), 11),
    ]
    for geo, x, k in cases:
        idx = torch.randint(0, k, (3, 5), generator=gen)
        geo_gpu = geo.to("cuda")
        exact = geo.gaps(x), geo.jacobian(x, idx)
        for dtype in (DT, torch.float32):
            xc = x.to(dtype)
            gaps = geo_gpu.gaps(xc.cuda())
            J = geo_gpu.jacobian(xc.cuda(), idx.cuda())
            assert gaps.device.type == "cuda" and gaps.dtype == dtype
            for cuda, cpu, truth in zip(
                (gaps, J), (geo.gaps(xc), geo.jacobian(xc, idx)), exact, strict=True
            ):
                if dtype == DT:
                    torch.testing.assert_close(cuda.cpu(), cpu)
                    continue
                err_cuda = (cuda.cpu().double() - truth).abs().max()
                err_cpu = (cpu.double() - truth).abs().max()
                assert err_cuda <= 4 * err_cpu + 1e-6 * truth.abs().max(), (err_cuda, err_cpu)
            # the CPU-held geometry also works on CUDA inputs
            torch.testing.assert_close(geo.gaps(xc.cuda()).cpu(), geo.gaps(xc))
