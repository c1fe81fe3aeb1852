"""The Gram matrix ``J J^T`` of Jacobian rows kept as sparse entries, without the dense rows.

The position projection (:mod:`diffcontact.systems.projection`) needs, per state and
Gauss-Newton iteration, ``A = J_s J_s^T`` of its selected rows (``J_s = J M^-1/2`` with
point masses). Each row of a rope limit touches two or three points, but the dense rows
``(n, R, P dim)`` grow with the rope: for a 200-point rope with 78 selected rows, 128
states, their zeros alone are 32 MB per iteration, and the dense product ``J J^T`` and the
fill of those zeros were the projection's largest costs on the CPU (``torch.profiler`` on
``System("Rope-D400").simulate``; ``python benchmarks/run.py fastops`` times both ways).
From the entries,

    A[s, i, j] = sum_a sum_b [points[s, i, a] == points[s, j, b]] values[s, i, a] . values[s, j, b]

(:mod:`diffcontact.geometry.gram_kernels`, a Warp kernel, forward and backward). Where
Warp is not available (or the torch backend is asked for) :func:`dense_gram` computes the
same matrix from the dense rows (the reference the tests compare against).
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from diffcontact.contact.cone_qp import SolverSettings
from diffcontact.contact.fused import resolve_backend

from .base import SparseJacobian, assemble_jacobian

__all__ = ["DEVICES", "MIN_DENSE_SIZE", "dense_gram", "sparse_gram", "sparse_gram_available"]

MIN_DENSE_SIZE = 1 << 17
"""The projection takes :func:`sparse_gram` only where the dense rows would hold at least
this many numbers (``n R P dim``): below, their few products cost less than the kernels'
launches. ``python benchmarks/run.py fastops --threads 1`` (its ``gram`` rows; 2-core CPU,
float64), dense against sparse, forward / forward and backward, microseconds: 120 states x
8 rows x 10 points (19,200 numbers) 137 / 648 against 346 / 852; 1024 x 5 x 10 (102,400)
513 / 2330 against 826 / 2480; 1024 x 8 x 20 (327,680) 1227 / 6541 against 1171 / 2900;
128 x 20 x 50 (256,000) 652 / 4039 against 368 / 1316; 128 x 78 x 200 25,484 / 110,139
against 3180 / 11,425."""

DEVICES = {"cpu"}
"""The device types where the position projection (and the contact impulse of long ropes,
:class:`~diffcontact.geometry.sparse_contact.SparseContact`) use :func:`sparse_gram`. Not
CUDA yet:
the kernels run there (``tests/geometry/test_sparse_gram.py``, ``pytest -m cuda``), but
no GPU has timed them against the dense products; ``benchmarks/run.py simulate|train
--sparse-gram-cuda`` adds ``"cuda"`` for a run (``benchmarks/cuda_checks.sh``, part 7)."""


def sparse_gram_available(settings: SolverSettings | None, dtype: torch.dtype, device) -> bool:
    """Whether the projection uses :func:`sparse_gram` for tensors of ``dtype`` on
    ``device``: where the solver's backend (``settings.backend``, the environment variable
    ``DIFFCONTACT_SOLVER``) resolves to Warp, on a device type of :data:`DEVICES`."""
    if torch.device(device).type not in DEVICES:
        return False
    backend = (settings or SolverSettings()).backend
    return resolve_backend(backend, dtype, torch.device(device)) == "warp"


def dense_gram(points: Tensor, values: Tensor, n_points: int) -> Tensor:
    """``J J^T`` from the dense rows: ``points: (n, R, m)`` long, ``values: (n, R, m, dim)``
    -> ``(n, R, R)`` (the reference of :func:`sparse_gram`)."""
    n, R, _, dim = values.shape
    J = assemble_jacobian(SparseJacobian(points, values.unsqueeze(-3)), n_points)
    J = J.reshape(n, R, n_points * dim)
    A = J @ J.transpose(-1, -2)
    return 0.5 * (A + A.transpose(-1, -2))


def sparse_gram(points: Tensor, values: Tensor) -> Tensor:
    """``J J^T`` of rows given as sparse entries, by a Warp kernel (module docstring).

    Args:
        points: ``(n, R, m)`` long, the point of each entry (entries of a row may repeat
            a point; unused entries have zero values and any valid point, best one of the
            row's own: the kernel skips pairs of rows whose point ranges do not overlap).
        values: ``(n, R, m, dim)`` float32 or float64, on the CPU (or a CUDA device:
            the kernels run there, but the projection does not use them on CUDA yet).

    Returns:
        ``(n, R, R)``, exactly symmetric; differentiable in ``values`` (once).
    """
    return _SparseGram.apply(points, values)


@functools.cache
def _kernels(dtype: torch.dtype) -> tuple:
    """Warp and the kernels (``row_ranges``, and the forward and backward kernels'
    overloads for one float type), Warp initialised as the solver initialises it."""
    import typing

    from diffcontact.contact.fused import _load

    wp, _ = _load()
    from . import gram_kernels

    scalar = wp.float64 if dtype == torch.float64 else wp.float32
    out = [gram_kernels.row_ranges]
    for kernel in (gram_kernels.gram, gram_kernels.gram_backward):
        types = {}
        for arg in kernel.adj.args:
            if wp.types.is_array(arg.type) and arg.type.dtype is typing.Any:
                types[arg.label] = wp.array(dtype=scalar, ndim=arg.type.ndim)
        out.append(wp.overload(kernel, types))
    return wp, *out


def _launch(kernel, dim: tuple[int, ...], tensors: list[Tensor], wp) -> None:
    """Launch ``kernel`` over ``dim`` threads on the tensors' device (on CUDA, on torch's
    current stream), the tensors as Warp arrays."""
    from diffcontact.contact.fused import _ctype

    device = tensors[0].device
    stream = None
    if device.type == "cuda":
        stream = wp.stream_from_torch(torch.cuda.current_stream(device))
    inputs = [_ctype(t) for t in tensors]
    wp.launch(kernel, dim=dim, inputs=inputs, device=wp.device_from_torch(device), stream=stream)


class _SparseGram(torch.autograd.Function):
    @staticmethod
    def forward(ctx, points: Tensor, values: Tensor) -> Tensor:
        points = points.to(device=values.device, dtype=torch.int64).contiguous()
        values = values.contiguous()
        n, R, m = points.shape
        wp, ranges, forward, _ = _kernels(values.dtype)
        out = values.new_zeros(n, R, R)
        lo, hi = torch.empty(2, n, R, dtype=torch.int64, device=values.device)
        if out.numel() and m:
            _launch(ranges, (n, R), [points, lo, hi], wp)
            _launch(forward, (n, R), [points, values, lo, hi, out], wp)
        ctx.save_for_backward(points, values, lo, hi)
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out: Tensor) -> tuple[None, Tensor]:
        points, values, lo, hi = ctx.saved_tensors
        n, R, m = points.shape
        wp, _, _, backward = _kernels(values.dtype)
        grad_values = torch.zeros_like(values)
        if grad_values.numel() and m:
            grad = grad_out.to(values.dtype).contiguous()
            _launch(backward, (n, R), [points, values, lo, hi, grad, grad_values], wp)
        return None, grad_values
