"""Shape helpers cheap enough for the per-step hot paths."""

from __future__ import annotations

import operator
from collections.abc import Sequence


def broadcast_shapes(*shapes: Sequence[int]) -> tuple[int, ...]:
    """The broadcast of ``shapes``, as :func:`torch.broadcast_shapes` for shapes given as
    tuples (or ``torch.Size``), in a few microseconds instead of tens.

    Raises:
        RuntimeError: the shapes do not broadcast (the type ``torch.broadcast_shapes``
            raises).
    """
    out: list[int] = []
    for shape in shapes:
        shape = tuple(shape)
        if len(shape) > len(out):
            out[:0] = [1] * (len(shape) - len(out))
        offset = len(out) - len(shape)
        for i, size in enumerate(shape):
            current = out[offset + i]
            if size == current or size == 1:
                continue
            if current == 1:
                out[offset + i] = size
            else:
                raise RuntimeError(
                    f"shapes {[tuple(s) for s in shapes]} cannot be broadcast: size {size} "
                    f"against {current} at dimension {offset + i - len(out)}"
                )
    return tuple(out)


def contact_dimension(d: object, caller: str, allowed: tuple[int, ...] = (1, 2, 3)) -> int:
    """``d`` as a Python ``int`` in ``allowed``: an integer, or anything integral that
    converts exactly (``numpy.int64``, a 0-d integer tensor); a float, a bool or another
    value is a ``ValueError`` naming ``caller``. (A 0-d tensor ``d`` compared equal to 2
    but reached the fused solver as a tensor, where it corrupted memory.)"""
    try:
        value = None if isinstance(d, bool) else operator.index(d)  # type: ignore[arg-type]
    except TypeError:
        value = None
    if value not in allowed:
        names = ", ".join(map(str, allowed[:-1])) + f" or {allowed[-1]}"
        raise ValueError(f"{caller}: d must be {names} (an integer), got {d!r}")
    return int(value)
