"""Gradient checkers for diffcontact's pieces (and yours).

``check_gradients`` compares autograd against central finite differences of a
scalar probe ``L(x) = sum(w * fn(x))`` (random fixed weights ``w``) along random
directions, one input at a time. Directional checks scale to large inputs
(a full finite-difference Jacobian of a 30-contact problem would need
thousands of solves) and still catch any wrong gradient component with
probability one.

Example::

    from diffcontact.testing import assert_gradients_close
    assert_gradients_close(lambda A, b: solve_cone_qp(A, b, mu, 2), (A, b))
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class GradientCheck:
    """Outcome of :func:`check_gradients` for one input.

    Attributes:
        index: position of the input in ``inputs``.
        autograd: (n_directions,) directional derivatives from autograd.
        finite_difference: (n_directions,) central differences.
        rel_error: max |autograd - fd| / max(|fd|, scale), scale = atol/rtol.
    """

    index: int
    autograd: Tensor
    finite_difference: Tensor
    rel_error: float


def check_gradients(
    fn: Callable[..., Tensor],
    inputs: Sequence[Tensor],
    *,
    wrt: Sequence[int] | None = None,
    directions: dict[int, Callable[[Tensor], Tensor]] | None = None,
    eps: float = 1e-6,
    rtol: float = 1e-4,
    atol: float = 1e-8,
    n_directions: int = 3,
    seed: int = 0,
) -> list[GradientCheck]:
    """Compare autograd with central finite differences along random directions.

    Args:
        fn: function of ``inputs`` returning a tensor (any shape).
        inputs: float64 tensors (the check casts nothing; use float64).
        wrt: indices of the inputs to check; default all floating-point ones.
        directions: optional per-input map turning a random tensor into an
            admissible direction (e.g. symmetrise for a symmetric matrix, zero
            the entries of a parameter that must stay >= 0 at 0).
        eps: finite-difference step.
        rtol, atol: tolerances used to scale the relative error.
        n_directions: random directions per input.
        seed: seed of the weights and directions.

    Returns:
        One :class:`GradientCheck` per checked input.
    """
    gen = torch.Generator().manual_seed(seed)
    directions = directions or {}
    bad = [i for i, x in enumerate(inputs) if not isinstance(x, Tensor)]
    if bad:
        raise ValueError(f"check_gradients: inputs {bad} are not torch tensors")
    inputs = [x.detach() for x in inputs]
    wrt = [i for i, x in enumerate(inputs) if x.is_floating_point()] if wrt is None else list(wrt)
    out_of_range = [i for i in wrt if not -len(inputs) <= i < len(inputs)]
    if out_of_range:
        n = len(inputs)
        raise ValueError(f"check_gradients: wrt {out_of_range} out of range for {n} inputs")
    if not wrt:  # (complex inputs only: it returned [] and a check passed without checking)
        raise ValueError(
            "check_gradients: no real floating-point input to check (give wrt= or float "
            "inputs; complex ones are not checked)"
        )
    not_real = [i for i in wrt if not inputs[i].is_floating_point()]
    if not_real:
        raise ValueError(f"check_gradients: inputs {not_real} are not real floating point")

    with torch.no_grad():
        out0 = fn(*inputs)
    w = torch.randn(out0.shape, generator=gen, dtype=torch.float64).to(out0)

    def probe(xs: Sequence[Tensor]) -> Tensor:
        return (w * fn(*xs)).sum()

    results = []
    for i in wrt:
        xs = [x.clone().requires_grad_(j == i) for j, x in enumerate(inputs)]
        value = probe(xs)
        grad = None  # fn may not depend on input i: a zero gradient then
        if value.requires_grad:
            (grad,) = torch.autograd.grad(value, xs[i], allow_unused=True)
        if grad is None:
            grad = torch.zeros_like(inputs[i])
        ad, fd = [], []
        for _ in range(n_directions):
            delta = torch.randn(inputs[i].shape, generator=gen, dtype=torch.float64).to(inputs[i])
            if i in directions:
                delta = directions[i](delta)
            with torch.no_grad():
                plus = [x + eps * delta if j == i else x for j, x in enumerate(inputs)]
                minus = [x - eps * delta if j == i else x for j, x in enumerate(inputs)]
                fd.append((probe(plus) - probe(minus)) / (2 * eps))
            ad.append((grad * delta).sum())
        ad_t, fd_t = torch.stack(ad).detach(), torch.stack(fd)
        scale = torch.clamp(fd_t.abs(), min=atol / rtol)
        rel = float(((ad_t - fd_t).abs() / scale).max())
        results.append(GradientCheck(i, ad_t, fd_t, rel))
    return results


def assert_gradients_close(
    fn: Callable[..., Tensor], inputs: Sequence[Tensor], *, rtol: float = 1e-4, **kwargs
) -> list[GradientCheck]:
    """Like :func:`check_gradients`, raising AssertionError on a mismatch."""
    results = check_gradients(fn, inputs, rtol=rtol, **kwargs)
    bad = [r for r in results if not r.rel_error <= rtol]
    if bad:
        lines = [
            f"input {r.index}: rel. error {r.rel_error:.3g} > {rtol:g}; autograd "
            f"{r.autograd.tolist()} vs finite differences {r.finite_difference.tolist()}"
            for r in bad
        ]
        raise AssertionError("gradient check failed:\n" + "\n".join(lines))
    return results


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    """``(exit status, stdout, stderr)`` of ``diffcontact ARGV`` run in-process (with capsys)."""
    from diffcontact.cli import main

    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def assert_usage_error(code: int, err: str, *needles: str) -> None:
    """Exit status 2 and ONE line on stderr, no traceback, containing every needle."""
    assert code == 2, (code, err)
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("diffcontact")
    for needle in needles:
        assert needle in lines[0], lines[0]


# operations that copy a value of a tensor to the host
_READS = ("aten._local_scalar_dense", "aten.nonzero", "aten.masked_select", "aten.is_nonzero")


def count_host_reads(fn: Callable[[], object], device: torch.device | str = "cpu") -> int:
    """How many times ``fn()`` reads a value of a tensor on ``device`` back to the host:
    ``.item()``, ``bool(tensor)``, ``nonzero``, ``.tolist()``, ``.numpy()``, a copy to
    the CPU. On CUDA each one waits for the work queued before it (a synchronisation), so
    counting them on the CPU shows, without a GPU, how often a loop would stall one.

    The count covers torch operations dispatched in this thread (a dispatch mode) and
    the two methods that dispatch nothing on the CPU (patched on ``torch.Tensor`` for the
    call).
    """
    from torch.utils._python_dispatch import TorchDispatchMode

    kind = torch.device(device).type
    reads = inside = 0  # inside: in a counted method (its own copy is not counted again)

    class Count(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            nonlocal reads
            first = args[0] if args and isinstance(args[0], Tensor) else None
            if not inside and first is not None and first.device.type == kind:
                to_host = (
                    func is torch.ops.aten._to_copy.default
                    and kind != "cpu"
                    and torch.device((kwargs or {}).get("device") or kind).type == "cpu"
                )
                reads += str(func).startswith(_READS) or to_host
            return func(*args, **(kwargs or {}))

    originals = {name: getattr(torch.Tensor, name) for name in ("tolist", "numpy")}

    def counted(name: str):
        def method(self, *args, **kwargs):
            nonlocal reads, inside
            reads += self.device.type == kind
            inside += 1
            try:
                return originals[name](self, *args, **kwargs)
            finally:
                inside -= 1

        return method

    try:
        for name in originals:
            setattr(torch.Tensor, name, counted(name))
        with Count():
            fn()
    finally:
        for name, original in originals.items():
            setattr(torch.Tensor, name, original)
    return reads
