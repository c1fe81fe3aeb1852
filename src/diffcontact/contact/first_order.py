"""Backward passes of the contact solvers: first derivatives only, and said so.

The solvers' autograd Functions differentiate their solution implicitly (through the
optimality conditions at the solution); that backward pass is not itself differentiable.
Under ``create_graph`` (a Hessian, ``torch.autograd.functional.hessian``, a gradient
penalty) autograd would still build a graph around it, with the solver's own curvature
missing: Hessians through a simulation came back wrong, without a word (on BP5 not even
the sign of ``d2L/dmu2`` agreed with finite differences of the gradient).
:func:`first_order_only` makes that case an error instead, while first derivatives under
a graph (``torch.func.grad``) still work.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

__all__ = ["SECOND_ORDER_MESSAGE", "first_order_only"]

SECOND_ORDER_MESSAGE = (
    "second derivatives through the contact solver are not implemented (its backward "
    "pass is the implicit first derivative only): differentiating a gradient again (a "
    "Hessian, a gradient penalty) would miss the solver's curvature. Take finite "
    "differences of the gradient instead, or keep contacts out of the second-order part"
)


class _SecondOrderTrap(torch.autograd.Function):
    """``0`` (a 0-d tensor) linked to ``anchor``; differentiating it raises."""

    @staticmethod
    def forward(anchor: Tensor) -> Tensor:
        return anchor.new_zeros(())

    @staticmethod
    def setup_context(ctx: Any, inputs: Any, output: Any) -> None:
        pass

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> Tensor:
        raise RuntimeError(SECOND_ORDER_MESSAGE)


def first_order_only(backward: Callable[..., Any]) -> Callable[..., Any]:
    """Decorate an autograd Function's ``backward``: it runs without a graph, and where
    autograd builds one (``create_graph=True``, ``torch.func.grad``) each gradient it
    returns is linked to the Function's saved tensors and incoming gradients through a
    node whose backward raises ``RuntimeError`` (:data:`SECOND_ORDER_MESSAGE`). First
    derivatives are unaffected; a second derivative through the solve is an error
    instead of a value without the solver's curvature. The Function must save a tensor
    that carries the graph (its output) for the link to exist."""

    @functools.wraps(backward)
    def wrapper(ctx: Any, *grads: Any) -> Any:
        if not torch.is_grad_enabled():
            return backward(ctx, *grads)
        with torch.no_grad():
            outputs = backward(ctx, *grads)
        anchors = [
            t for t in (*ctx.saved_tensors, *grads) if isinstance(t, Tensor) and t.requires_grad
        ]
        if not anchors:  # nothing the gradients could depend on
            return outputs
        trap = _SecondOrderTrap.apply(anchors[0])
        for anchor in anchors[1:]:
            trap = trap + _SecondOrderTrap.apply(anchor)
        return tuple(
            o + trap.to(o.dtype) if isinstance(o, Tensor) and o.is_floating_point() else o
            for o in outputs
        )

    return wrapper
