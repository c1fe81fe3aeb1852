"""The loops of :meth:`System.simulate <diffcontact.systems.System.simulate>`: a rollout
step by step, or as replays of one step captured in a CUDA graph.

A :class:`Rollout` holds what every step of one call uses (the system, its context of
parameters on the device, the initial states, the options) and runs the steps:

- :meth:`Rollout.eager`: step by step. With ``defer`` the fused solver's error flags are
  gathered on the device and read once after the last step; on CUDA every state then goes
  through the contact solve padded to :data:`GRAPH_CONTACTS` contacts (or more that the
  system remembers: :meth:`Rollout.contact_padding`) instead of a selection of the states
  in contact (a read of the device per step). Without ``defer`` each step reads the
  device and raises at once, naming the states.
- :meth:`Rollout.graphed`: one step with static shapes and no read of the device (the
  padded contacts, the deferred flags, the position projection read-free,
  :class:`~diffcontact.systems.projection.ReadFree`), captured in a CUDA graph and
  replayed; ``capture=False`` runs the same steps without a graph (on any device, for
  tests).

Both return the trajectory, its gaps (where kept) and, deferred, a ``()`` bool tensor on
the device that says whether a check failed (a solve, or padding that was too small):
``simulate`` reads it with its other checks and then runs the rollout again step by step
without ``defer``, which raises the error naming the states.
"""

from __future__ import annotations

import contextlib
import warnings
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, NamedTuple

import torch
from torch import Tensor

from diffcontact.contact.cone_qp import ConeQPError, SolverSettings, deferred_checks
from diffcontact.contact.fused import FLAGS as SOLVER_FLAGS
from diffcontact.contact.models import ContactModel
from diffcontact.systems.projection import ReadFree
from diffcontact.threads import thread_scope

if TYPE_CHECKING:
    from diffcontact.systems.system import System, _Context

__all__ = [
    "GRAPH_CONTACTS",
    "GRAPH_MAX_LIMIT_ROWS",
    "GRAPH_MAX_ROWS",
    "GRAPH_MIN_STEPS",
    "PROJECTION_ROWS",
    "Overflow",
    "Rollout",
    "RolloutOptions",
]

#: :meth:`System.simulate` with ``cuda_graph="auto"`` captures a CUDA graph for rollouts
#: of at least this many steps (the capture costs about two eager steps)
GRAPH_MIN_STEPS = 16
#: the contacts per state that a padded step (a captured one, or a step-by-step one on CUDA)
#: sends to the solve at first (no state of 4096 BP5 or BD5 rollouts of 100 steps had more
#: than 5 active at once: ``python benchmarks/run.py simulate --all-tasks --scenes 4096``,
#: column ``max contacts``); a rollout where a state has more is run again, and the system
#: remembers half as many more as it needed for its next rollouts
#: (:meth:`System._grow_contact_padding`)
GRAPH_CONTACTS = 8
#: the rows of each state's problem that a read-free position projection (a captured step,
#: or a step-by-step rollout on CUDA) pads to at first (enough for Rope's rollouts:
#: tests/systems/test_read_free_projection.py); a rollout where a state selects more is run
#: again, and the system remembers the larger count for its next rollouts
#: (:meth:`System._grow_projection_rows`)
PROJECTION_ROWS = 16
#: ``cuda_graph="auto"`` goes step by step once the read-free projection of a captured step
#: would pad each state's problem to more rows than this: a captured step projects every
#: state with every iteration at the padded size, where a step-by-step one selects the
#: states and rows it needs. Measured on an H200 with 4096 ropes, a second call of
#: ``python benchmarks/run.py simulate --device cuda --all-tasks --tasks Rope Rope-D400
#: --scenes 4096 --cuda-graph both --again`` (benchmarks/README.md): Rope at 16 rows, 0.28 s
#: graphed against 0.35 s step by step; Rope-D400 at 136 rows, 5.17 s against 1.89 s. Where
#: between the two the graph stops paying is not measured
GRAPH_MAX_ROWS = 32
#: ``cuda_graph="auto"`` goes step by step from the first call where the projection's
#: problem can have more rows than this (each side of each limit: Rope-D200 and Rope-D400,
#: not Rope or Rope-D100): such ropes select more than :data:`GRAPH_MAX_ROWS` rows within
#: their first steps, and the first call's graphed attempt was wasted (an H200, 4096
#: Rope-D400 ropes: 6.21 s under ``auto``, 4.17 s step by step; benchmarks/README.md,
#: 2026-11-27, ninth sitting)
GRAPH_MAX_LIMIT_ROWS = 256


def _pads_contacts(device: torch.device) -> bool:
    """Whether a deferred step-by-step rollout on ``device`` sends every state to the
    contact model, padded, instead of selecting the states in contact: on CUDA, where the
    selection's read of the device stalls the queue and the padded work is cheap."""
    return device.type == "cuda"


def _projects_read_free(device: torch.device) -> bool:
    """Whether such a padded step-by-step rollout (:func:`_pads_contacts`) also runs the
    position projection read-free (:class:`~diffcontact.systems.projection.ReadFree`; a
    captured step always does). Not by default, as measured: read-free, the projection runs
    all its iterations, and a Rope training step dispatches 24,473 torch operations instead
    of 12,824 to save 23 of its 26 reads (``python benchmarks/run.py launches --tasks Rope
    [--read-free-projection]``, columns ``CUDA path`` and ``CUDA ops``); on an H200 a Rope
    training step took 0.376 s read-free and 0.221 s reading (``python benchmarks/run.py
    train --device cuda --tasks Rope [--read-free-projection]``, benchmarks/README.md,
    2026-11-27, fourth sitting: after the projection asked for any minimiser)."""
    return False


class RolloutOptions(NamedTuple):
    """The options of a rollout that every step uses."""

    model: ContactModel
    dynamics: str
    fraction: float
    iterations: int
    solver_settings: SolverSettings | None
    #: differentiate the penetration compensation target (False: a constant, as the
    #: paper's appendix G; :meth:`System.simulate`'s ``penetration_gradient``)
    target_gradient: bool = True


class _NeedsGradient(Exception):
    """A captured step's result requires grad (raised before the capture goes on)."""


#: what a rollout returns: ``(N, steps + 1, 2, P, dim)`` states, ``(N, steps + 1, K)``
#: gaps (or ``None``) and the deferred checks' ``()`` bool flag (or ``None``)
Result = tuple[Tensor, Tensor | None, Tensor | None]


class Overflow(NamedTuple):
    """A static rollout whose padding was too small: the most active contacts of a state,
    the most rows a state's position projection selected while the contacts fitted, up to
    the first step that overflowed (0 without a projection), the first step
    (1-based) where a state had more contacts or rows than the padding (its states before
    that step are the rollout's), and the attempt's :data:`Result` (its trajectory valid up
    to ``step - 1``)."""

    contacts: int
    rows: int
    step: int
    partial: Result


@dataclass
class Rollout:
    """One rollout of ``system`` from ``z0: (N, 2, P, dim)`` over ``steps`` steps.

    Attributes:
        system: the :class:`~diffcontact.systems.System` whose steps run.
        ctx: its parameters and static structure on ``z0``'s device (``System._context``).
        z0: the initial states.
        steps: the number of steps.
        options: :class:`RolloutOptions`.
        keep_gaps: also return every state's gaps (the contact resolution's own).
        progress: show a progress bar over the steps.
        threads: torch's CPU threads of a step-by-step rollout
            (:func:`~diffcontact.threads.thread_scope`).
    """

    system: System
    ctx: _Context
    z0: Tensor
    steps: int
    options: RolloutOptions
    keep_gaps: bool = False
    progress: bool = False
    threads: int | str | None = None
    #: the read-free projection of the last deferred :meth:`eager` call, if it ran one
    _read_free: ReadFree | None = field(default=None, init=False, repr=False)
    #: the contacts the last padded rollout sent per state; ``()`` int64 on the device:
    #: the most active contacts a state had in it, and the most rows its read-free
    #: projection needed while the contacts fit, up to the first step where a state had
    #: more contacts or rows than the padding (after it, the trajectory is not the
    #: rollout's and its rows would inflate the remembered padding beyond what the
    #: rollout needs)
    _padded: int | None = field(default=None, init=False, repr=False)
    _most: Tensor | None = field(default=None, init=False, repr=False)
    _rows_fitting: Tensor | None = field(default=None, init=False, repr=False)
    #: ``()`` int64 on the device: the steps counted, and the first (1-based) where a state
    #: had more active contacts than the padding or needed more rows (0: none)
    _step: Tensor | None = field(default=None, init=False, repr=False)
    _first_overflow: Tensor | None = field(default=None, init=False, repr=False)
    #: the rollout of the remaining steps that :meth:`graphed` went on with after an
    #: overflow (:meth:`_go_on`), if any
    _rest: Rollout | None = field(default=None, init=False, repr=False)

    def grow_padding(self) -> None:
        """After a deferred :meth:`eager` whose flag was set: if its padded contacts or its
        read-free projection's rows were too few, the system remembers more for its next
        rollouts (a read of the device each)."""
        if self._rest is not None:
            self._rest.grow_padding()
        rows = None if self._rows_fitting is None else int(self._rows_fitting)
        self.system._grow_contact_padding(self._most, self._padded)
        self.system._grow_projection_rows(self._read_free, rows)

    def contact_padding(self) -> int:
        """The contacts per state a padded step sends to the solve: :data:`GRAPH_CONTACTS`,
        or what the system remembers from a rollout that needed more, at most every
        candidate."""
        K = len(self.system.contact_names)
        return min(K, self.system._contact_padding or GRAPH_CONTACTS)

    def _track(self, like: Tensor, padded: int, read_free: ReadFree | None) -> None:
        """Start counting (on ``like``'s device) the most active contacts of a state and
        the rows the projection needed, in a rollout padded to ``padded`` contacts."""
        self._padded = padded
        self._most = torch.zeros((), dtype=torch.long, device=like.device)
        self._rows_fitting = None if read_free is None else torch.zeros_like(self._most)
        self._step = torch.zeros_like(self._most)
        self._first_overflow = torch.zeros_like(self._most)

    def _restart_count(self, read_free: ReadFree | None) -> None:
        """Zero the counts of :meth:`_track` in place (a captured graph keeps using them)."""
        for count in (self._most, self._step, self._first_overflow):
            count.zero_()
        if read_free is not None:
            read_free.needed.zero_()
            self._rows_fitting.zero_()

    def _count(self, gaps: Tensor, read_free: ReadFree | None, margin: float) -> None:
        """After a step's projection (``gaps: (N, K)``, the contact resolution's, active
        below ``margin``): update the counts of :meth:`_track` in place, without a read of
        the device."""
        if gaps.shape[0]:
            torch.maximum(self._most, (gaps < margin).sum(-1).amax(), out=self._most)
        over = self._most > self._padded
        if read_free is not None:
            # the rows needed while the contacts fit, up to the first step that overflowed
            # (after it, the states are not the rollout's)
            frozen = over | (self._first_overflow != 0)
            torch.where(frozen, self._rows_fitting, read_free.needed, out=self._rows_fitting)
            over = over | read_free.overflowed
        self._step.add_(1)
        first = over & (self._first_overflow == 0)
        torch.where(first, self._step, self._first_overflow, out=self._first_overflow)

    def _steps(self) -> Any:
        if not self.progress:
            return range(self.steps)
        from tqdm.auto import tqdm

        return tqdm(range(self.steps), desc=f"simulate {self.system.name}", unit="step")

    def eager(self, defer: bool = False) -> Result:
        """The rollout step by step (:data:`Result`; the flag only with ``defer``, True
        where a deferred check failed: then the caller runs the rollout again without
        ``defer``, which raises the error naming the states).

        ``defer``: the fused solver's error flags are gathered on the device
        (:func:`~diffcontact.contact.cone_qp.deferred_checks`) instead of read after each
        solve, and on CUDA each step sends every state to the contact model padded to
        :meth:`contact_padding` (a state with more active contacts sets the flag, and the
        system pads to more next time) instead of selecting the states in contact (a read
        of the device), and the position
        projection runs read-free where :func:`_projects_read_free` says so (a state
        needing more rows sets the flag too; :meth:`grow_padding`). Without ``defer``,
        each step reads the device (the selection, the solver's flags, the projection's
        rows and early stop) and raises at once."""
        system, ctx, z0, steps = self.system, self.ctx, self.z0, self.steps
        model, dynamics, fraction, iterations, solver_settings, target_gradient = self.options
        margin = system._contact_margin(iterations, ctx.dtype)
        device = z0.device
        flags = torch.zeros(len(SOLVER_FLAGS), dtype=torch.int32, device=device)
        overflow = torch.zeros((), dtype=torch.bool, device=device)
        padded = self.contact_padding() if defer and _pads_contacts(device) else None
        read_free = None
        if padded is not None and _projects_read_free(device):
            read_free = system._read_free_projection(device, iterations)
        self._read_free = read_free
        if padded is not None:
            self._track(z0, padded, read_free)
        states = [z0]
        gaps: list[Tensor] | None = [system.gaps(z0.detach()[:, 0])] if self.keep_gaps else None
        z = z0
        scope_defer = deferred_checks(flags) if defer else contextlib.nullcontext()
        rerun = False
        with thread_scope(self.threads, device, steps) as scope, scope_defer:
            for step in self._steps():
                with scope.step():
                    z1 = system._integrate(z, ctx, dynamics)
                    try:
                        res = system._resolve(
                            z1, ctx, model, fraction, solver_settings, padded,
                            target_gradient=target_gradient, margin=margin,
                        )  # fmt: skip
                        z = system._project(res, ctx, iterations, solver_settings, read_free)
                        if padded is not None:
                            self._count(res.gaps, read_free, margin)
                        if gaps is not None:
                            gaps.append(res.gaps)
                    except (ValueError, torch.linalg.LinAlgError) as err:
                        # a state that blew up inside the step fails in the first linear algebra
                        # that meets it (the solver's input check, or an SVD / factorisation of
                        # the penetration target): say which states and why
                        if defer:  # (the undeferred rollout names the first failure)
                            rerun = True
                            break
                        nonfinite = not bool(torch.isfinite(z1.detach()).all())
                        if "NaN or infinite" not in str(err) and not nonfinite:
                            raise
                        states.append(z1)
                        raise system._nonfinite_error(states, step + 1) from err
                    except ConeQPError as err:
                        failure = ConeQPError(
                            system._solver_failure_message(err, z0, z1, step + 1), err.status
                        )
                        failure.states = err.states  # trajectory indices, for callers that go on
                        raise failure from err
                    states.append(z)
        if rerun:
            return self.eager()
        traj = torch.stack(states, dim=1)
        gaps_all = None if gaps is None else torch.stack(gaps, 1)
        if padded is not None:
            overflow = self._most > padded
        if read_free is not None:
            overflow = overflow | read_free.overflowed
        pending = (flags.any() | overflow) if defer else None
        return traj, gaps_all, pending

    def graph_wanted(self, cuda_graph: bool | str) -> bool:
        """Whether ``simulate`` tries :meth:`graphed` (see its ``cuda_graph``)."""
        if cuda_graph not in (True, False, "auto"):
            raise ValueError(f"cuda_graph must be True, False or 'auto', got {cuda_graph!r}")
        if cuda_graph is False:
            return False
        z0, options = self.z0, self.options
        settings = (options.solver_settings or SolverSettings()).resolved(z0.dtype, z0.device)
        reasons = []
        if z0.device.type != "cuda":
            reasons.append(f"the states are on {z0.device}, not a CUDA device")
        if options.dynamics == "hamiltonian" and self.system.constraints is not None:
            reasons.append("constrained Hamiltonian dynamics solve with torch.linalg.solve")
        if settings.backend != "warp":
            reasons.append(f"the cone-QP backend is {settings.backend!r}, not 'warp'")
        if cuda_graph is True and reasons:
            raise ValueError("simulate: cuda_graph=True, but " + "; ".join(reasons))
        return not reasons and (cuda_graph is True or self._graph_pays())

    def _graph_pays(self) -> bool:
        """``cuda_graph="auto"``'s rule where a graph can be used: at least
        :data:`GRAPH_MIN_STEPS` steps, and a read-free projection (if on) padded to at most
        :data:`GRAPH_MAX_ROWS` rows (the rows the system remembers) of a problem of at most
        :data:`GRAPH_MAX_LIMIT_ROWS` rows."""
        system = self.system
        rows = min(system._projection_rows, system._projection_rows_all())
        many = system._projection_rows_all() > GRAPH_MAX_LIMIT_ROWS
        wide = bool(self.options.iterations) and (rows > GRAPH_MAX_ROWS or many)
        return self.steps >= GRAPH_MIN_STEPS and not wide

    def graphed(self, strict: bool = False, capture: bool = True) -> Result | None:
        """The rollout as replays of one step captured in a CUDA graph.

        The step is the eager one with static shapes and no read of the device: every state
        goes to the contact model with its active candidates padded to
        :meth:`contact_padding` (``System._resolve``'s ``static_contacts``), the position
        projection (if on) runs read-free with the rows the system remembers, and the fused
        solver's error flags are gathered on the device
        (:func:`~diffcontact.contact.cone_qp.deferred_checks`); all are read once after the
        last step. A state with more active contacts or projection rows than the padding
        records the step where that first happened; both paddings grow (the system
        remembers them), and the rollout goes on from the state before that step with the
        remaining steps (:meth:`_go_on`: graphed again, or step by step where the rest is
        too short for a capture to pay or the rows grew past :data:`GRAPH_MAX_ROWS` and not
        ``strict``); an overflow at the first step runs the rollout again. A replay launches
        the step's hundreds of kernels at once, where the eager step pays the host's time
        for each. Returns what :meth:`eager` does with ``defer`` (the flag: a solve failed,
        and the caller reruns step by step, which names the states and the cause), or None
        where the graph cannot be used (the step needs gradients, or the capture failed; a
        ``RuntimeWarning`` says why unless ``strict``, which raises; or, not ``strict``,
        the rows grew past :data:`GRAPH_MAX_ROWS` at the first step). ``capture=False``
        runs the same static, read-free steps without a graph (on any device; for tests)."""
        system = self.system
        needs_gradient = "the rollout needs gradients, which a graph replay does not record"

        def give_up(why: str) -> None:
            """Raise (strict) or warn, except that a rollout that needs gradients (a
            normal case) quietly goes step by step."""
            message = f"simulate {system.name}: no CUDA graph ({why}); running step by step"
            if strict:
                raise ValueError(message.replace("no CUDA graph", "cuda_graph=True failed"))
            if why != needs_gradient:
                warnings.warn(message, RuntimeWarning, stacklevel=4)

        tensors = [self.z0] + [t for t in vars(self.ctx).values() if isinstance(t, Tensor)]
        if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
            give_up(needs_gradient)
            return None
        while True:  # (ends: each overflow pads to more, up to every candidate and row)
            contacts = self.contact_padding()
            read_free = system._read_free_projection(self.z0.device, self.options.iterations)
            try:
                out = self._attempt(contacts, capture, read_free)
            except _NeedsGradient:
                give_up(needs_gradient)
                return None
            except Exception as err:  # the capture (CUDA's errors vary with the call)
                if not capture or isinstance(err, ValueError):
                    raise
                give_up(f"the capture failed: {type(err).__name__}: {err}")
                return None
            if not isinstance(out, Overflow):
                return out
            # both paddings grow from one attempt (an attempt that dropped contacts still
            # tells how many rows its projection needed: fewer wasted attempts)
            grew = system._grow_contact_padding(out.contacts, contacts)
            grew = system._grow_projection_rows(read_free, out.rows) or grew
            if not grew:  # (padded to every candidate and row: cannot happen)
                raise RuntimeError(
                    f"simulate {system.name}: the static rollout overflowed {tuple(out[:3])}"
                )
            if out.step > 1:
                return self._go_on(out, strict, capture)
            if not (strict or self._graph_pays()):
                return None  # (the projection's rows grew past GRAPH_MAX_ROWS)

    def _go_on(self, out: Overflow, strict: bool, capture: bool) -> Result:
        """The rollout after an attempt of :meth:`graphed` that overflowed at step
        ``out.step`` > 1: its states before that step are kept, and a rollout of the
        remaining steps from the last of them, with the grown padding, adds the rest (graphed
        where ``strict`` or :meth:`_graph_pays`, else step by step, deferred), so that the steps
        before the overflow are not run again. The deferred flag is the two parts' (the
        attempt's own may come from its states after the overflow; then ``simulate`` runs
        the whole rollout again step by step, as for any set flag)."""
        kept = out.step  # states 0 .. step - 1
        traj, gaps, flags = out.partial
        rest = replace(self, z0=traj[:, kept - 1], steps=self.steps - (kept - 1), progress=False)
        self._rest = rest
        result = rest.graphed(strict, capture) if strict or rest._graph_pays() else None
        if result is None:
            result = rest.eager(defer=True)
        traj_rest, gaps_rest, flags_rest = result
        traj = torch.cat([traj[:, :kept], traj_rest[:, 1:]], dim=1)
        if gaps is not None:
            gaps = torch.cat([gaps[:, :kept], gaps_rest[:, 1:]], dim=1)
        return traj, gaps, flags | flags_rest

    def _attempt(
        self, contacts: int, capture: bool, read_free: ReadFree | None
    ) -> Result | Overflow:
        """One try of :meth:`graphed` with the contacts padded to ``contacts`` and the
        position projection (if on) run ``read_free``: :data:`Result`, or an
        :class:`Overflow` where a state had more active contacts or its projection needed
        more rows; one read of the device."""
        system, ctx, z0, steps = self.system, self.ctx, self.z0, self.steps
        model, dynamics, fraction, iterations, solver_settings, target_gradient = self.options
        margin = system._contact_margin(iterations, ctx.dtype)
        device = z0.device
        flags = torch.zeros(len(SOLVER_FLAGS), dtype=torch.int32, device=device)
        self._track(z0, contacts, read_free)
        z_in = z0.detach().clone()

        def one_step() -> Tensor:  # the next state goes to z_in; returns its gaps
            with deferred_checks(flags):
                z1 = system._integrate(z_in, ctx, dynamics)
                res = system._resolve(
                    z1, ctx, model, fraction, solver_settings, contacts,
                    target_gradient=target_gradient, margin=margin,
                )  # fmt: skip
                if res.z.requires_grad:
                    raise _NeedsGradient
                z_in.copy_(system._project(res, ctx, iterations, solver_settings, read_free))
                self._count(res.gaps, read_free, margin)
            return res.gaps

        if capture:
            with torch.cuda.device(device):  # (the graph is captured on the current device)
                side = torch.cuda.Stream(device)
                side.wait_stream(torch.cuda.current_stream(device))
                with torch.cuda.stream(side):  # loads the kernels, records the launches
                    one_step()
                torch.cuda.current_stream(device).wait_stream(side)
                graph = torch.cuda.CUDAGraph()
                with torch.cuda.graph(graph, capture_error_mode="relaxed"):
                    g_out = one_step()
            advance = graph.replay
        else:
            g_out = one_step()

            def advance() -> None:
                g_out.copy_(one_step())

        z_in.copy_(z0)  # (the warm-up step moved it)
        flags.zero_()
        self._restart_count(read_free)
        N = z0.shape[0]
        traj = torch.empty((N, steps + 1, *z0.shape[1:]), dtype=z0.dtype, device=device)
        traj[:, 0] = z0.detach()
        gaps = None
        if self.keep_gaps:
            gaps = torch.empty((N, steps + 1, g_out.shape[-1]), dtype=z0.dtype, device=device)
            gaps[:, 0] = system.gaps(z0.detach()[:, 0])
        for step in self._steps():
            advance()
            traj[:, step + 1].copy_(z_in)
            if gaps is not None:
                gaps[:, step + 1].copy_(g_out)
        rows = torch.zeros_like(self._most) if read_free is None else self._rows_fitting
        most, rows, step = torch.stack([self._most, rows, self._first_overflow]).tolist()
        if step:
            return Overflow(most, rows, step, (traj, gaps, flags.any()))
        return traj, gaps, flags.any()  # (read by simulate with its other checks)
