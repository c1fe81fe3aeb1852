"""``optimize``: gradient-based planning through a differentiable simulator, multi-start, batched.

All starts of all problems run as ONE batch of ``N * S`` rollouts per
iteration: the variables are ``(N, S, size)`` tensors written into the
initial state (and the physical parameters), the rollout is differentiated,
and every start takes its own optimiser step. Each start's objective depends
on its own rollout only, so Adam (per-coordinate) optimises the starts
independently; L-BFGS shares one line search over all of them (the sum).

Box bounds are kept by projection: after each step the variables are clipped
into their box (and into a parameter's physical range, e.g. ``cor`` in
``[0, 1]``).
"""

from __future__ import annotations

import contextlib
import math
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from diffcontact.control.planner import Planner, as_planner
from diffcontact.control.variables import Parameter, Position, Variable, as_bounds
from diffcontact.threads import MIN_AUTO_STEPS, parse_threads, settled_on_one, thread_scope

__all__ = ["ControlError", "OptimizeResult", "optimize"]

OPTIMIZERS = ("adam", "lbfgs")


class ControlError(ValueError):
    """A planning problem that cannot go on: bad input, or a non-finite gradient or objective."""


@dataclass
class OptimizeResult:
    """What :func:`optimize` found. ``[N]`` is present when ``z0`` held ``N`` problems.

    Attributes:
        variables: the best start's values by variable name, ``([N,] size)``.
        objective: the best objective value, ``([N])``.
        z0: the best initial state, ``([N,] 2, P, dim)``.
        params: the best physical parameters (batched ``(N, ...)`` over
            problems when parameters were optimised; ``None`` for a planner
            without them).
        history: the objective of every start at every iteration, ``(I, [N,] S)``.
        start_objective: the best objective each start reached, ``([N,] S)``.
        start_variables: each start's best values, ``([N,] S, size)`` by name.
        best_start: the winning start, ``([N])`` long.
        iterations: the iterations run.
        stopped: ``"tolerance"`` (every problem reached it), ``"patience"`` (no
            improvement), or ``"iterations"``.
        seconds: wall time.
    """

    variables: dict[str, Tensor]
    objective: Tensor
    z0: Tensor
    params: Any
    history: Tensor
    start_objective: Tensor
    start_variables: dict[str, Tensor]
    best_start: Tensor
    iterations: int
    stopped: str
    seconds: float
    extra: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> str:
        """One line per problem: the objective and the variables."""
        lines = []
        obj = self.objective.reshape(-1)
        for i in range(obj.numel()):
            vals = ", ".join(
                f"{k} = {_fmt(v.reshape(obj.numel(), -1)[i])}" for k, v in self.variables.items()
            )
            lines.append(f"objective {obj[i].item():.6g}: {vals}")
        return "\n".join(lines)


def _fmt(t: Tensor) -> str:
    vals = [f"{x:.6g}" for x in t.tolist()]
    return vals[0] if len(vals) == 1 else "(" + ", ".join(vals) + ")"


def _check_int(name: str, value: Any, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ControlError(f"{name} must be an integer >= {low}, got {value!r}")
    return value


def _check_z0(z0: Any, planner: Planner) -> tuple[Tensor, bool]:
    if not isinstance(z0, Tensor) or not z0.is_floating_point():
        raise ControlError(f"z0 must be a floating-point tensor, got {type(z0).__name__}")
    shape = planner.state_shape
    single = z0.dim() == 3
    if tuple(z0.shape[-3:]) != shape or z0.dim() not in (3, 4):
        raise ControlError(
            f"z0 must have shape {shape} or (N, *{shape}) for {planner.name}, got {tuple(z0.shape)}"
        )
    if z0.dim() == 4 and z0.shape[0] == 0:
        raise ControlError(f"z0 holds no problem: shape {tuple(z0.shape)} (N = 0)")
    if not torch.isfinite(z0).all():
        raise ControlError("z0 holds NaN or infinite values")
    return (z0.unsqueeze(0) if single else z0), single


def _warn_outside(name: str, values: Tensor, box: tuple[Tensor, Tensor], what: str) -> None:
    """Warn that start ``values: (N, S, size)`` of variable ``name`` lie outside its
    ``box`` (they are clipped into it before the first iteration)."""
    low, high = (b.to(values) for b in box)
    outside = ((values < low) | (values > high)).any(-1)  # (N, S)
    if bool(outside.any()):
        warnings.warn(
            f"{what} of {name} lies outside its bounds in {int(outside.sum())} of "
            f"{outside.numel()} starts: clipped into them (low {low.tolist()}, high "
            f"{high.tolist()})",
            UserWarning,
            stacklevel=4,
        )


def _initial_values(
    variables: Sequence[Variable],
    bounds: list[tuple[Tensor, Tensor]],
    z0: Tensor,
    params: Any,
    planner: Planner,
    starts: int | Mapping[str, Any],
    seed: int,
) -> tuple[list[Tensor], int]:
    """``(N, S, size)`` start values per variable; start 0 is the current value."""
    N = z0.shape[0]
    current = [
        torch.stack([v.read(z0[n], params, planner) for n in range(N)]).to(z0)
        if not isinstance(v, Parameter)
        else v.read(z0[0], params, planner).to(z0).expand(N, -1)
        for v in variables
    ]
    if isinstance(starts, Mapping):
        unknown = set(starts) - {v.name for v in variables}
        if unknown:
            raise ControlError(f"starts: unknown variable(s) {sorted(unknown)}")
        given = {k: torch.as_tensor(s, dtype=z0.dtype, device=z0.device) for k, s in starts.items()}
        S = {t.shape[-2] if t.dim() >= 2 else -1 for t in given.values()}
        if len(S) != 1 or -1 in S:
            raise ControlError("starts: every tensor needs shape (S, size) or (N, S, size)")
        (S,) = S
        out = []
        for v, cur, box in zip(variables, current, bounds, strict=True):
            if v.name not in given:
                out.append(cur.unsqueeze(1).expand(N, S, -1).clone())
                _warn_outside(v.name, out[-1], box, "the current value")
                continue
            t = given[v.name]
            if t.dim() == 2:
                t = t.unsqueeze(0).expand(N, -1, -1)
            if t.shape != (N, S, cur.shape[-1]):
                raise ControlError(
                    f"starts[{v.name!r}] must have shape ({S}, {cur.shape[-1]}) or "
                    f"({N}, {S}, {cur.shape[-1]}), got {tuple(given[v.name].shape)}"
                )
            if not bool(torch.isfinite(t).all()):  # (named "z0 contains NaN" after a step)
                raise ControlError(f"starts[{v.name!r}] contains NaN or infinite values")
            out.append(t.clone())
            _warn_outside(v.name, out[-1], box, f"starts[{v.name!r}]")
        return out, S
    S = _check_int("starts", starts, 1)
    gen = torch.Generator().manual_seed(int(seed))
    out = []
    for v, cur, (low, high) in zip(variables, current, bounds, strict=True):
        _warn_outside(v.name, cur.unsqueeze(1), (low, high), "the current value (start 0)")
        size = cur.shape[-1]
        u = torch.rand(N, S, size, generator=gen, dtype=torch.float64)
        g = torch.randn(N, S, size, generator=gen, dtype=torch.float64)
        c = cur.detach().cpu().to(torch.float64).unsqueeze(1)
        finite = torch.isfinite(low) & torch.isfinite(high)
        spread = c + g * c.abs().clamp(min=1.0) * 0.5
        vals = torch.where(finite, low + u * (high - low), spread)
        vals[:, 0] = c[:, 0]  # start 0: the current value
        vals = torch.maximum(torch.minimum(vals, high), low)
        out.append(vals.to(z0))
    return out, S


def optimize(
    simulator: Any,
    z0: Tensor,
    objective: Callable[[Tensor], Tensor],
    *,
    variables: Sequence[Variable],
    steps: int | None = None,
    starts: int | Mapping[str, Any] = 1,
    optimizer: str = "adam",
    iterations: int = 100,
    lr: float = 0.05,
    tolerance: float | None = None,
    patience: int | None = None,
    seed: int = 0,
    progress: bool = True,
    contact_model: Any = None,
    threads: int | str | None = "auto",
) -> OptimizeResult:
    """Optimise parts of the initial state and/or physical parameters through ``simulate``.

    Args:
        simulator: a System, a trained model, a run directory, a task name or
            config file (:func:`~diffcontact.control.as_planner`).
        z0: ``(2, P, dim)`` one initial state, or ``(N, 2, P, dim)`` for ``N``
            independent problems solved in the same batch.
        objective: ``traj -> values``: ``traj`` is ``([N,] S, steps + 1, 2, P, dim)``
            (``N`` present when ``z0`` is batched), the result ``([N,] S)``,
            smaller is better. It must be differentiable.
        variables: what to change (:class:`Velocity`, :class:`Spin`,
            :class:`Position`, :class:`Parameter`): one, or a list with distinct names.
        steps: rollout steps (default: the task's ``horizon / dt - 1``).
        starts: ``S``: the number of starts per problem (start 0 is the value
            in ``z0``/the parameters, the others uniform in the box, or normal
            around the current value where a bound is open), or explicit start
            values ``{name: (S, size) or (N, S, size)}``.
        optimizer: ``"adam"`` or ``"lbfgs"``.
        iterations: at most this many optimiser iterations.
        lr: the learning rate (Adam) or step scale (L-BFGS).
        tolerance: stop when every problem's best objective is at or below it.
        patience: stop when no problem's best objective improved (by 1e-9
            relative) for this many iterations.
        seed: seeds the random starts.
        progress: show a progress bar.
        contact_model: the contact model of a System planner (``None``: the System's
            ``contact_model``, ``"CM"`` unless set).
        threads: torch's CPU threads during the iterations (put back afterwards):
            ``"auto"`` (default) times the iterations and runs them on one thread or
            on all available cores, whichever is faster now (from 24 iterations on;
            fewer leave it to each rollout); an integer fixes the count; ``None``
            leaves torch alone (:func:`diffcontact.threads.thread_scope`).

    Returns:
        :class:`OptimizeResult`.

    Raises:
        ControlError (a ``ValueError``): bad arguments, a variable that does
            not exist in the simulator, an objective of the wrong shape, or a
            gradient (named by its variable and start) or objective that is
            not finite.
    """
    import time

    try:
        planner = as_planner(simulator, contact_model=contact_model)
    except ValueError as err:
        raise ControlError(str(err)) from None
    z0b, single = _check_z0(z0, planner)
    if not callable(objective):
        raise ControlError("objective must be callable: traj -> ([N,] S) values")
    if isinstance(variables, Variable):
        variables = [variables]
    if isinstance(variables, (str, bytes)) or not isinstance(variables, Iterable):
        variables = [variables]  # not a variable either: the error below names its type
    variables = list(variables)
    if not variables or not all(isinstance(v, Variable) for v in variables):
        bad = [type(v).__name__ for v in variables if not isinstance(v, Variable)]
        raise ControlError(
            "variables: give a Velocity/Spin/Position/Parameter or a list of them"
            + (f", got {bad[0]}" if bad else ", got an empty list")
        )
    names = [v.name for v in variables]
    if len(set(names)) != len(names):
        raise ControlError(f"variables: names must be distinct, got {names}")
    if optimizer not in OPTIMIZERS:
        raise ControlError(f"optimizer must be one of {OPTIMIZERS}, got {optimizer!r}")
    try:
        threads = parse_threads(threads)
    except ValueError as err:
        raise ControlError(str(err)) from None
    iterations = _check_int("iterations", iterations, 1)
    steps = planner.system.default_steps if steps is None else _check_int("steps", steps, 1)
    if patience is not None:
        patience = _check_int("patience", patience, 1)
    if not (isinstance(lr, (int, float)) and math.isfinite(lr) and lr > 0):
        raise ControlError(f"lr must be a positive number, got {lr!r}")
    if tolerance is not None and not (
        isinstance(tolerance, (int, float)) and not isinstance(tolerance, bool)
        and math.isfinite(tolerance) and tolerance >= 0
    ):  # fmt: skip
        raise ControlError(f"tolerance must be a number >= 0 or None, got {tolerance!r}")
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ControlError(f"seed must be an integer, got {seed!r}")
    try:
        for v in variables:
            v.bind(planner)
    except ValueError as err:
        raise ControlError(str(err)) from None
    device, dtype = z0b.device, z0b.dtype
    bounds = []
    for v in variables:
        try:
            low, high = as_bounds(v.bounds, v.size(planner), v.name)
        except ValueError as err:
            raise ControlError(str(err)) from None
        if isinstance(v, Parameter):
            plo, phi = v.physical_bounds()
            low, high = low.clamp(min=plo), high.clamp(max=phi)
            if (low > high).any():  # (a made-up value inside neither range was returned)
                raise ControlError(
                    f"{v.name}: its bounds {v.bounds!r} lie outside the valid range of "
                    f"{v.field} [{plo:g}, {phi:g}]"
                )
        bounds.append((low, high))

    start = time.perf_counter()
    with planner.frozen():
        base = planner.parameters()
        if base is not None:
            base = _detached(base)
        values, S = _initial_values(variables, bounds, z0b, base, planner, starts, seed)
        N = z0b.shape[0]
        dev_bounds = [(lo.to(device, dtype), hi.to(device, dtype)) for lo, hi in bounds]
        for val, (lo, hi) in zip(values, dev_bounds, strict=True):
            val.copy_(torch.maximum(torch.minimum(val, hi), lo))
            val.requires_grad_(True)
        z_rep = z0b.unsqueeze(1).expand(N, S, *z0b.shape[1:]).reshape(N * S, *z0b.shape[1:])

        def build(vals: list[Tensor]) -> tuple[Tensor, Any]:
            z, p = z_rep, base
            for v, val in zip(variables, vals, strict=True):
                z, p = v.write(z, p, val.reshape(N * S, -1), planner)
            return z, p

        moves = [v.name for v in variables if isinstance(v, Position)]

        def overlapping(z: Tensor) -> Tensor:
            """``(N, S)`` bool: starts whose bodies overlap or cross a wall (a Position
            moved them there): no initial state, so never a plan."""
            if not moves:
                return torch.zeros(N, S, dtype=torch.bool, device=device)
            with torch.no_grad():
                gaps = planner.truth.gaps(z[..., 0, :, :].detach().to(torch.float64))
            return (gaps <= 0).any(-1).reshape(N, S).to(device)

        def evaluate(vals: list[Tensor], check: bool) -> tuple[Tensor, Tensor]:
            z, p = build(vals)
            bad = overlapping(z)
            if check and moves:
                # the caller's own state (start 0, where the starts are drawn) must hold no
                # overlap; another start a Position moved into one counts as infinite
                # (below), it does not stop the call
                check = False
                if not isinstance(starts, Mapping):
                    first = z.reshape(N, S, *z.shape[1:])[:, 0].detach().to(torch.float64)
                    try:
                        planner.truth._check_no_overlap(first, "z0")
                    except ValueError as err:  # simulate's hint (check_overlap) is not ours
                        text = str(err).split("\n(a state a simulation ended in")[0]
                        raise ControlError(
                            f"{text}\n(optimize starts from z0: move its bodies apart, or give "
                            "starts that place them)"
                        ) from None
            try:
                with warnings.catch_warnings():
                    if bool(bad.any()):  # the tunnelling check would blame dt for the overlap
                        warnings.filterwarnings("ignore", "(?s).*tunnel", RuntimeWarning)
                    traj = planner.simulate(z, steps, p, check_overlap=check)
            except ValueError as err:
                raise ControlError(f"simulation failed: {err}") from None
            traj = traj.reshape(N, S, *traj.shape[1:])
            out = objective(traj if not single else traj[0])
            if isinstance(out, Tensor) and not out.is_floating_point():
                raise ControlError(f"objective must return floating-point values, got {out.dtype}")
            if not isinstance(out, Tensor) or tuple(out.shape) != ((S,) if single else (N, S)):
                want = f"({S},)" if single else f"({N}, {S})"
                got = tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__
                raise ControlError(f"objective must return shape {want}, got {got}")
            return out.reshape(N, S), bad

        opt: torch.optim.Optimizer
        if optimizer == "adam":
            opt = torch.optim.Adam(values, lr=lr)
        else:
            opt = torch.optim.LBFGS(
                values, lr=lr, max_iter=1, history_size=20, line_search_fn="strong_wolfe"
            )

        best = torch.full((N, S), math.inf, dtype=dtype, device=device)
        best_vals = [v.detach().clone() for v in values]
        history: list[Tensor] = []
        stopped, since_improved = "iterations", 0
        bar: Any = None
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=iterations, desc=f"optimize ({planner.name})", unit="it")
        threads_held = contextlib.ExitStack()
        try:
            scope = threads_held.enter_context(thread_scope(threads, device, iterations))
            short = iterations < MIN_AUTO_STEPS  # (the rollouts govern their own steps)
            warned = False  # the zero-gradient warning, once per call
            warned_overlap = False  # and the one for starts moved into an overlap
            for it in range(iterations):
                last: dict[str, Tensor] = {}

                def closure(it: int = it, last: dict[str, Tensor] = last) -> Tensor:
                    opt.zero_grad()
                    obj, bad = evaluate(values, check=(it == 0 and not last))
                    if not torch.isfinite(obj).all():
                        bad = _where(~torch.isfinite(obj), single)
                        raise ControlError(f"objective is not finite at {bad} (iteration {it})")
                    if "obj" not in last:
                        last["obj"] = obj.detach()
                        last["vals"] = [v.detach().clone() for v in values]
                        last["overlap"] = bad
                    if not obj.requires_grad:
                        # no path from the variables to the objective (e.g. mu or e_P when
                        # no contact happens, or an objective that detaches): a zero
                        # gradient, which the optimiser's step leaves in place
                        last["no_gradient"] = obj
                        return obj.sum()
                    # a short loop is not governed: each rollout's forward steps are, and on
                    # a loaded CPU (they settled on one thread) the backward pass follows
                    one = threads == "auto" and short and settled_on_one(device)
                    with thread_scope(1, device) if one else contextlib.nullcontext():
                        obj.sum().backward()
                    for v, val in zip(variables, values, strict=True):
                        g = val.grad
                        if g is not None and not torch.isfinite(g).all():
                            bad = _where(~torch.isfinite(g).all(-1), single)
                            raise ControlError(
                                f"gradient of {v.name} is not finite at {bad} (iteration {it})"
                            )
                    if all(val.grad is None or not val.grad.any() for val in values):
                        # a simulator links parameters it did not use with a zero gradient
                        last["no_gradient"] = obj
                    return obj.sum()

                with scope.step():
                    opt.step(closure)
                if "no_gradient" in last and not warned:
                    warned = True
                    warnings.warn(
                        f"optimize: the objective does not depend on "
                        f"{', '.join(v.name for v in variables)} at iteration {it} (a "
                        "contact parameter without a contact to act in, a start whose "
                        "rollout never reaches what the objective measures, or an objective "
                        "that detaches its input): zero gradient",
                        stacklevel=2,
                    )
                with torch.no_grad():
                    for val, (lo, hi) in zip(values, dev_bounds, strict=True):
                        val.copy_(torch.maximum(torch.minimum(val, hi), lo))
                obj = last["obj"]
                history.append(obj)
                if bool(last["overlap"].any()):
                    if not warned_overlap:
                        warned_overlap = True
                        warnings.warn(
                            f"optimize: {', '.join(moves)} moved {_where(last['overlap'], single)}"
                            f" into an overlap with another body or a wall at iteration {it}: "
                            "such a start is no initial state, and is not taken as a plan",
                            stacklevel=2,
                        )
                    obj = torch.where(last["overlap"], math.inf, obj)  # never the best
                finite = torch.isfinite(best)
                improved = obj < torch.where(finite, best - 1e-9 * best.abs(), best)
                best = torch.where(improved, obj, best)
                for bv, lv in zip(best_vals, last["vals"], strict=True):
                    bv.copy_(torch.where(improved.unsqueeze(-1), lv, bv))
                since_improved = 0 if bool(improved.any()) else since_improved + 1
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(best=f"{best.min(-1).values.max().item():.4g}")
                if tolerance is not None and bool((best.min(-1).values <= tolerance).all()):
                    stopped = "tolerance"
                    break
                if patience is not None and since_improved >= patience:
                    stopped = "patience"
                    break
        finally:
            threads_held.close()
            if bar is not None:
                bar.close()
        for v in values:
            v.requires_grad_(False)

        winner = best.argmin(-1)  # (N,)
        rows = torch.arange(N, device=device)
        win_vals = [bv[rows, winner] for bv in best_vals]  # (N, size)
        z_best, p_best = z0b, base
        for v, val in zip(variables, win_vals, strict=True):
            z_best, p_best = v.write(z_best, p_best, val, planner)

    def squeeze(t: Tensor) -> Tensor:
        return t[0] if single else t

    return OptimizeResult(
        variables={v.name: squeeze(val) for v, val in zip(variables, win_vals, strict=True)},
        objective=squeeze(best[rows, winner]),
        z0=squeeze(z_best),
        params=p_best,
        history=torch.stack(history).squeeze(1) if single else torch.stack(history),
        start_objective=squeeze(best),
        start_variables={v.name: squeeze(b) for v, b in zip(variables, best_vals, strict=True)},
        best_start=squeeze(winner),
        iterations=len(history),
        stopped=stopped,
        seconds=time.perf_counter() - start,
    )


def _where(bad: Tensor, single: bool) -> str:
    """``start(s) [..]`` or ``(problem, start) pairs [..]`` of a boolean ``(N, S)`` mask."""
    idx = bad.nonzero().tolist()
    if single:
        return f"start(s) {[j for _, j in idx][:10]}"
    return f"(problem, start) {[tuple(p) for p in idx][:10]}"


def _detached(params: Any) -> Any:
    """``params`` with every tensor field detached (the potential module is kept)."""
    from diffcontact.control.variables import PARAMETER_FIELDS

    fields = {
        k: v.detach() for k in PARAMETER_FIELDS if isinstance(v := getattr(params, k, None), Tensor)
    }
    return params.replace(**fields)
