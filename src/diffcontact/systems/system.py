"""``System``: a validated config turned into a batched, differentiable simulator.

A :class:`System` holds the static structure of a task (points, equality
constraints, contact geometry, time step) and its physical parameters as
float64 tensors (``mass``, ``second_moments``, ``mu``, ``cor``, ``gravity``
and, for the rope, ``stiffness`` and ``rest_length``). Set ``requires_grad``
on any of them (or replace them with tensors that carry a graph) and every
quantity :meth:`System.simulate` returns is differentiable with respect to
them and to the initial state.

One step of :meth:`System.simulate` (paper-facts.md, "Time stepping"):

1. RK4 over ``dt`` of the smooth constrained dynamics (the config's ``integrator``:
   classic ``rk4`` or the 3/8 rule ``rk4_38``): the Lagrangian vector field (S.2)
   by default, or the Hamiltonian one (S.4-S.7);
2. collision detection on the new positions: the gaps of all candidates;
3. for the states with an active candidate (gap < 0) only: the active
   candidates are gathered and padded to the largest count in the batch (a
   mask marks real ones; padded rows of ``J_C`` are exact zeros),
   ``J_C: (n, Ka*d, D)``, ``Mhat^-1`` (S.12), the penetration-compensation
   target (appendix G, ``fraction * depth / dt``) and the two-phase impulse
   (CM or CMr) give the post-impact velocities;
4. with ``position_projection > 0`` (the config's key; default for the rope only),
   the positions of the states that violate a candidate are projected onto the
   admissible set, and (``velocity_projection``, default on) their velocities,
   inelastically, onto the limits closed at the projected positions
   (:func:`~diffcontact.systems.projection.project_state`).

States are ``z: (N, 2, P, dim)``: positions then velocities of the P points
(``docs/conventions.md``); trajectories are ``(N, T, 2, P, dim)``.
"""

from __future__ import annotations

import math
import operator
import os
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from dataclasses import field as dataclass_field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from diffcontact.contact.cone_qp import (
    ConeQPError,
    SolverSettings,
    settings_or_default,
)
from diffcontact.contact.impulse import _penetration_target
from diffcontact.contact.models import ContactModel, ContactParams, ContactState
from diffcontact.contact.registry import create_contact_model
from diffcontact.fastops import spd_solve
from diffcontact.geometry import RimPlane, circles_2d, jacobian_matvec, rope_limits
from diffcontact.geometry.base import SparseJacobian
from diffcontact.geometry.sparse_contact import SparseContact
from diffcontact.geometry.sparse_gram import MIN_DENSE_SIZE, sparse_gram_available
from diffcontact.io import parse_device
from diffcontact.mechanics import (
    INTEGRATORS,
    EqualityConstraints,
    Mhat_inv,
    assemble_mass_matrix,
    ball_joint,
    block_diagonal,
    body_inverse_mass_matrix,
    body_mass_matrix,
    chain_constraints,
    concat_constraints,
    hamiltonian_flow,
    kron_identity,
    lagrangian_vector_field,
    potential_gradient,
    rigid_body_constraints,
)
from diffcontact.systems import initial_conditions as ics
from diffcontact.systems.config import (
    MAX_PROJECTION_ITERATIONS,
    BouncingDisksConfig,
    BouncingMassesConfig,
    ChainPendulumConfig,
    GyroscopeConfig,
    RopeConfig,
    parse_config,
    rollout_size_error,
)
from diffcontact.systems.config_file import read_config_file
from diffcontact.systems.graph import ENVIRONMENT, Body, BodyGraph, Edge
from diffcontact.systems.params import PhysicalParams
from diffcontact.systems.projection import (
    ReadFree,
    _minv_rows,
    _project,
    closed_below,
    keep_constraint_rates,
    warn_unconverged,
)
from diffcontact.systems.rollout import PROJECTION_ROWS, Rollout, RolloutOptions

__all__ = [
    "ConstraintDriftWarning",
    "ContactResult",
    "RolloutWarning",
    "System",
    "TunnellingWarning",
    "list_tasks",
    "load_config",
    "load_system",
]

_F = torch.float64
_TASK_DIR = Path(__file__).parent / "tasks"
DYNAMICS = ("lagrangian", "hamiltonian")
ROPE_RESTITUTION_WARNING = (
    "rope limits with cor > 0 and the position projection: with an end much heavier than "
    "the other points and cor near 1 the limits break and the energy rises (docs/config.md, "
    "rope, 'Restitution'); cor 0, the rope's default, keeps both"
)
"""Warned when a rope is loaded with restitution on its limits and the position
projection on."""
TUNNELLING_FRACTION = 1.0
"""Penetration deeper than this fraction of the smaller body's radius counts as tunnelling
(the centre has crossed the other surface; the built-in tasks at their own step reach about
0.75 for BP5's smallest body, 0.46 for BD5)."""
ON_TUNNELLING = ("warn", "raise", "ignore")
CONSTRAINT_DRIFT_TOL = 0.25
"""A rollout whose equality constraints are off by more than this (relative,
:meth:`~diffcontact.mechanics.EqualityConstraints.relative_residual`: a squared link
length 25 % off) has drifted off them: :class:`ConstraintDriftWarning`. The built-in
tasks at their own step stay within a quarter of it
(``tests/learning/data/test_constraint_check.py``); a chain with a light inner link
whipped by a heavy outer one at a step too large for it exceeded 0.8 (a link's length
halved, the energy quadrupled: ``tests/systems/test_simulate.py``). Recorded data off by
more do not belong to their config (``diffcontact.learning.data.checks.CONSTRAINT_TOL``,
the same number)."""
BLOW_UP = 1e12
"""A rollout whose largest ``|value|`` exceeds ``BLOW_UP`` times its initial state's (at
least 1) has blown up, finite or not (Gyro at ``dt = 0.5`` reached 1e38 in 3 steps and
overflowed later): :class:`NonFiniteRolloutError`, not a tunnelling report."""
SPARSE_CONTACT_COLUMNS = 200
"""The contact impulse of point masses takes its products from the rows' sparse entries
(:class:`~diffcontact.geometry.sparse_contact.SparseContact`) only where a dense row of
``J_C`` has at least this many columns (``P dim``: a rope of 100 points or more), on top
of the size rule of :data:`~diffcontact.geometry.sparse_gram.MIN_DENSE_SIZE`: shorter rows
are few numbers, and their dense products cost less than the kernel's launches.
``python benchmarks/run.py simulate --all-tasks --tasks BP5 Rope Rope-D200 Rope-D400
--threads 1 --contact-rows dense`` (then ``sparse``; 2-core CPU, 1024 scenes, two runs
each, seconds): BP5 (10 columns) 0.34-0.41 dense against 0.47-0.75 sparse; Rope (20)
0.64-0.75 against 0.66-0.72; Rope-D200 (200) 6.36-7.19 against 5.48-5.97; Rope-D400
(400) 21.3-21.7 against 15.2-16.2."""


TUNNELLING_HINT = " (on_tunnelling='ignore' silences this)"  # the end of its message


class RolloutWarning(RuntimeWarning):
    """A rollout finished, but its trajectory is not to be trusted: bodies tunnelled
    (:class:`TunnellingWarning`) or the equality constraints drifted
    (:class:`ConstraintDriftWarning`). Its own category, so that callers can filter or
    count them (training reports one line per epoch instead of one warning per batch)."""


class TunnellingWarning(RolloutWarning):
    """Bodies passed into each other or a wall deeper than ``TUNNELLING_FRACTION`` of the
    smaller radius during a rollout (``simulate(on_tunnelling="warn")``)."""


class ConstraintDriftWarning(RolloutWarning):
    """The equality constraints (link lengths, pivots, rigid bodies) drifted by more than
    :data:`CONSTRAINT_DRIFT_TOL` during a rollout: the integration error of the step is
    too large for the motion (``warnings.filterwarnings("ignore",
    category=ConstraintDriftWarning)`` silences it)."""


class NonFiniteRolloutError(ValueError):
    """A rollout reached NaN or infinite states, or blew up (:data:`BLOW_UP`).

    Attributes:
        states: the indices of the trajectories (of the call's batch) that did, where
            known; a caller can go on without them (``diffcontact evaluate`` counts them
            as diverged).
    """

    def __init__(self, message: str, states: list[int] | None = None) -> None:
        super().__init__(message)
        self.states = states


class _ZeroGradient(torch.autograd.Function):
    """``traj`` unchanged, linked to ``inputs`` it does not depend on: their gradient is zero."""

    @staticmethod
    def forward(ctx: Any, traj: Tensor, *inputs: Tensor) -> Tensor:
        ctx.inputs = [(t.shape, t.dtype, t.device) for t in inputs]
        return traj.clone()

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:
        zeros = (torch.zeros(shape, dtype=dt, device=dev) for shape, dt, dev in ctx.inputs)
        return (None, *zeros)


def _integer(value: Any) -> int | None:
    """``value`` as an ``int`` where it is integral (``numpy.int64`` too), else ``None``
    (floats and bools included)."""
    if isinstance(value, bool):
        return None
    try:
        return operator.index(value)
    except TypeError:
        return None


def list_tasks() -> list[str]:
    """Names of the built-in tasks (the YAML files in ``systems/tasks``)."""
    return sorted(p.stem for p in _TASK_DIR.glob("*.yaml"))


def load_config(spec: Any, **overrides: Any):
    """Validated config from a built-in task name, a ``.yaml``/``.json`` path or a mapping.

    Args:
        spec: task name (see :func:`list_tasks`), path, mapping, or a config model.
        overrides: top-level keys replacing those of ``spec`` (e.g. ``dt=0.005``).

    Raises:
        ValueError: unknown task name (the message lists the known ones), an
            unreadable file or an invalid config (the message names the key).
    """
    source = ""
    if isinstance(spec, (str, os.PathLike)):
        name = spec if isinstance(spec, str) else os.fsdecode(os.fspath(spec))
        builtin = _TASK_DIR / f"{name}.yaml"
        path = Path(name)
        if builtin.is_file() and "/" not in name and "\\" not in name:
            data, source = read_config_file(builtin), f" of built-in task {name!r}"
        elif path.is_dir():  # ("does not exist" for dir.yaml, "unknown task" for others)
            raise ValueError(
                f"{str(path)!r} is a directory, not a config file (a .yaml, .yml or .json "
                "file, a built-in task name, or a dict)"
            )
        elif path.suffix.lower() in (".yaml", ".yml", ".json"):
            if not path.is_file():
                raise ValueError(f"config file {str(path)!r} does not exist")
            data, source = read_config_file(path), f" in {path}"
        elif path.is_file():
            raise ValueError(
                f"{str(path)!r} is not a config file: a config is a .yaml, .yml or .json file "
                "(or a built-in task name, or a dict)"
            )
        else:
            raise ValueError(
                f"unknown task {name!r}; known tasks: {', '.join(list_tasks())} "
                "(or pass a path to a .yaml/.json file, or a dict)"
            )
    elif isinstance(spec, Mapping):
        data = dict(spec)
    elif hasattr(spec, "model_dump"):
        data = spec.model_dump()
    else:
        raise ValueError(
            f"load_system expects a task name, a path or a dict; got {type(spec).__name__}"
        )
    if overrides:
        if not isinstance(data, dict):
            raise ValueError(f"invalid system config{source}: expected a mapping of keys")
        data = {**data, **overrides}
    return parse_config(data, source)


def _grown(needed: int) -> int:
    """A padding remembered after a rollout needed ``needed``: half as much more, rounded
    up to a multiple of 8 (and more than ``needed``)."""
    return max(needed + 1, -(-3 * needed // 2 // 8) * 8)


def _per_body(device: torch.device) -> bool:
    """Whether bodies constrained each on its own (BD5's disks) run the constrained dynamics
    and the contact's ``Mhat^-1`` as a batch of bodies (``EqualityConstraints.split``) on
    ``device``, instead of over all points at once: on the CPU, where it is faster
    (docs/architecture.md), not on CUDA, where its many smaller matrix products made 4096
    BD5 scenes x 100 graphed steps slower on an H200 (``python benchmarks/run.py simulate
    --device cuda --all-tasks --scenes 4096``, before and after this choice:
    benchmarks/README.md, 2026-11-27, fourth sitting). Both give the same trajectories."""
    return device.type != "cuda"


def load_system(spec: Any, **overrides: Any) -> System:
    """A :class:`System` from a built-in task name, a ``.yaml``/``.json`` path or a dict.

    Example::

        system = load_system("BP5")
        z0 = system.sample_initial_conditions(16, seed=0)
        traj = system.simulate(z0, steps=100)
        E = system.energy(traj)
    """
    return System(load_config(spec, **overrides))


@dataclass
class ContactResult:
    """Outcome of one contact resolution (:meth:`System.resolve_contacts`).

    Attributes:
        z: ``(N, 2, P, dim)`` the state with post-impact velocities.
        gaps: ``(N, K)`` gaps of all candidates at the state's positions.
        batch_index: ``(n,)`` long, the states that had an active contact.
        contact_index: ``(n, Ka)`` long, their candidate indices, active ones
            first in candidate order, padded with inactive candidates.
        active: ``(n, Ka)`` bool, the real (active) entries.
        f_c: ``(n, Ka, d)`` compression impulses (contact space; zero where padded).
        f_r: ``(n, Ka, d)`` restitution impulses.
        J_C: ``(n, Ka*d, D)`` contact Jacobian (padded rows zero). (Inside a rollout,
            where a long rope's impulse took the rows' sparse entries, ``None``;
            :meth:`System.resolve_contacts` always returns it.)
        v_C_star: ``(n, Ka*d)`` penetration-compensation target (zeros when off).
    """

    z: Tensor
    gaps: Tensor
    batch_index: Tensor
    contact_index: Tensor
    active: Tensor
    f_c: Tensor
    f_r: Tensor
    J_C: Tensor | None
    v_C_star: Tensor


@dataclass
class _Context:
    """Parameters and static structure resolved for one dtype and device.

    Parameter fields have their unbatched shapes, or one leading dimension N
    more when the :class:`PhysicalParams` carry one set per trajectory.
    """

    dtype: torch.dtype
    device: torch.device
    batched: bool
    geometry: Any
    constraints: EqualityConstraints | None
    M: Tensor  # (P, P) or (N, P, P)
    M_inv: Tensor  # (P, P) or (N, P, P)
    # bodies whose constraints act on each body alone (EqualityConstraints.split): the
    # constraints of one body and the bodies' inverse mass blocks, (B, q, q) or (N, B, q, q);
    # the constrained dynamics then run per body (``None``: over all points at once)
    groups: EqualityConstraints | None
    M_inv_groups: Tensor | None
    weights: Tensor  # (P,) or (N, P): gravity weights (masses at centres of mass)
    g_vec: Tensor  # (dim,) or (N, dim)
    mu: Tensor  # (K,) or (N, K)
    cor: Tensor  # (K,) or (N, K)
    eps: Tensor  # () or (N,)
    stiffness: Tensor | None  # () or (N,)
    rest_length: Tensor | None  # () or (N,)
    anchor: Tensor | None
    potential: Callable[[Tensor], Tensor] | None
    # the state-independent acceleration of an unconstrained system without springs or a
    # learned potential, by state shape, computed at its first RK4 stage of the call
    constant_acceleration: dict = dataclass_field(default_factory=dict)
    # whether a candidate has restitution (cor > 0), read once at the first projection of
    # the velocities (a captured rollout's warm-up step): None until then
    bouncing: bool | None = None

    def has_restitution(self) -> bool:
        """Whether any candidate's ``cor`` is positive (one read of the device, once)."""
        if self.bouncing is None:
            self.bouncing = bool((self.cor.detach() > 0).any())
        return self.bouncing

    @property
    def force_is_constant(self) -> bool:
        """Whether ``-M^-1 grad V`` is the same at every state (gravity alone, no springs,
        no learned potential) and the dynamics have no constraints to project on."""
        unconstrained = self.constraints is None or self.constraints.num_equations == 0
        return self.stiffness is None and self.potential is None and unconstrained

    @staticmethod
    def per_state(t: Tensor, x: Tensor, base: int, extra: int) -> Tensor:
        """Align a parameter with states ``x: (N, ..., P, dim)``.

        An unbatched ``t`` (``base`` dims) is returned as it is; a batched one,
        ``(N, *rest)``, becomes ``(N, 1, ..., 1, *rest, 1 * extra)`` with a
        singleton for each batch dim of ``x`` after the first.
        """
        if t.dim() == base:
            return t
        inner = x.dim() - 3
        return t.reshape(t.shape[0], *([1] * inner), *t.shape[1:], *([1] * extra))

    def select(self, t: Tensor, base: int, rows: Tensor) -> Tensor:
        """``t`` for the states ``rows`` (a batched ``t``), or ``t`` itself (unbatched)."""
        return t if t.dim() == base else t[rows]


def _consistent_velocities(v: Tensor, J_E: Tensor, M_inv: Tensor) -> Tensor:
    """The velocities ``v: (n, P, dim)`` with the part that breaks the equality constraints
    ``J_E: (n, E, D)`` taken out in the mass metric (``M_inv``: ``(P, P)`` or ``(n, P, P)``
    over points): ``v - M^-1 J_E^T (J_E M^-1 J_E^T)^-1 J_E v``, so that ``J_E v = 0``.

    The contact impulse acts on these. RK4 leaves ``J_E v`` of the order of its local
    error, and the part of ``J_C v`` it causes lies where ``A = J_C Mhat^-1 J_C^T`` is
    singular (``Mhat^-1`` takes the constraints' directions out, ``J_C`` does not): along
    such a direction inside the friction cone (a gyroscope's rim at ``mu = 2``,
    ``test_a_gyroscope_with_much_friction_simulates``) the contact problem was then
    unbounded, and the simulation stopped with ``ConeQPError``.
    """
    n, P, dim = v.shape
    flat = v.reshape(n, P * dim, 1)
    B = kron_identity(M_inv, dim) @ J_E.transpose(-1, -2)  # (n, D, E): M^-1 J_E^T
    return v - (B @ spd_solve(J_E @ B, J_E @ flat)).reshape(n, P, dim)


class System:
    """A simulated system of extended bodies with contacts (see the module docstring).

    Build it with :func:`load_system`, or ``System(spec)`` with anything
    :func:`load_config` takes (a task name such as ``"BP5"``, a ``.yaml``/``.json``
    path, a mapping or a validated config). Attributes:

    - structure: ``config``, ``name``, ``type``, ``dim``, ``n_points``,
      ``n_bodies``, ``body_points`` (first point of each body), ``n_contacts``
      (candidates K), ``d`` (contact-space dimension), ``contact_names``,
      ``geometry``, ``constraints``, ``dt``, ``horizon``, ``default_steps``,
      ``penetration_fraction``, ``penetration_metric`` (``"mass"`` or ``"euclidean"``),
      ``position_projection``, ``velocity_projection``, ``foresee_crossings``,
      ``dynamics``, ``integrator``
      (``"rk4"`` or ``"rk4_38"``, the config's Runge-Kutta rule), ``contact_model``
      (what ``simulate``, ``step`` and ``resolve_contacts`` use when given none: ``"CM"``,
      or a learned model's own in its ``as_system()``);
    - parameters (float64 tensors; any may require grad): ``mass (B,)``,
      ``second_moments (B, k)`` or ``None`` for point masses, ``mu (K,)`` and
      ``cor (K,)`` (a 0-d tensor broadcasts to all contacts), ``gravity ()``
      (magnitude, along -y in 2D and -z in 3D), and for the rope
      ``stiffness ()`` and ``rest_length ()``.
    """

    def __init__(self, config: Any) -> None:
        # a task name or a path as load_system takes it (parse_config alone said
        # "expected a mapping of keys, got str" to System("BP5"))
        named = isinstance(config, (str, os.PathLike))
        cfg = load_config(config) if named else parse_config(config)
        self.config = cfg
        self.type: str = cfg.type
        self.name: str = cfg.name or cfg.type
        self.dt: float = float(cfg.dt)
        self.horizon: float = float(cfg.horizon)
        self.penetration_fraction: float = float(cfg.penetration_fraction)
        self.penetration_metric: str = cfg.penetration_metric
        self.position_projection: int = int(cfg.position_projection)
        self.velocity_projection: bool = bool(cfg.velocity_projection)
        self.foresee_crossings: bool = bool(cfg.foresee_crossings)
        self.dynamics: str = cfg.dynamics
        # the contact model of simulate/step/resolve_contacts when they are given none (a
        # learned model's as_system() sets its own, so that its rollouts are the model's)
        self.contact_model: Any = "CM"
        self.integrator: str = cfg.integrator
        self.second_moments: Tensor | None = None
        self.stiffness: Tensor | None = None
        self.rest_length: Tensor | None = None
        self._anchor: Tensor | None = None
        builder = {
            "bouncing_masses": self._build_circles,
            "bouncing_disks": self._build_circles,
            "chain_pendulum": self._build_chain,
            "gyroscope": self._build_gyroscope,
            "rope": self._build_rope,
        }[cfg.type]
        builder(cfg)
        self.n_contacts: int = self.geometry.n_candidates
        assert self.n_contacts == cfg.n_contacts == len(self.contact_names)
        self.d: int = self.geometry.d
        self.mu: Tensor = torch.tensor(cfg.per_contact("mu"), dtype=_F)
        self.cor: Tensor = torch.tensor(cfg.per_contact("cor"), dtype=_F)
        if cfg.type == "rope" and self.position_projection > 0 and bool((self.cor > 0).any()):
            warnings.warn(ROPE_RESTITUTION_WARNING, UserWarning, stacklevel=3)
        self.gravity: Tensor = torch.tensor(float(cfg.gravity), dtype=_F)
        self.eps: float | Tensor = 0.01  # CMr's regulariser (contact models that use one)
        # an extra potential V(x): (..., P, dim) -> (...), e.g. a learned network, added
        # to the built-in terms; the dynamics take its gradient by autograd
        self.potential_model: Callable[[Tensor], Tensor] | None = None
        self._device_cache: dict[str, tuple[Any, EqualityConstraints | None]] = {}
        # what a read-free position projection needs to know without reading the device
        widths = self.geometry.gap_widths() if hasattr(self.geometry, "gap_widths") else None
        self._two_sided = widths is not None and bool(torch.isfinite(widths).any())
        self._point_masses = all(body.kind == "point" for body in self._bodies)
        self._projection_rows = PROJECTION_ROWS
        # the contacts per state a padded step sends to the solve, once a rollout needed
        # more than GRAPH_CONTACTS (None: GRAPH_CONTACTS; Rollout.contact_padding)
        self._contact_padding: int | None = None
        # whether the last simulate call replayed a CUDA graph (for benchmarks and tests)
        self._last_rollout_graphed = False

    # ------------------------------------------------------------------ builders
    def _build_circles(self, cfg: BouncingMassesConfig | BouncingDisksConfig) -> None:
        disks = cfg.type == "bouncing_disks"
        B = cfg.n_bodies
        k = 3 if disks else 1
        self.dim, self.n_bodies, self.n_points = 2, B, k * B
        self.body_points = [k * b for b in range(B)]
        self.mass = torch.tensor(cfg.masses, dtype=_F)
        self.geometry = circles_2d(["disk" if disks else "point"] * B, cfg.radii, cfg.walls)
        if disks:
            self.second_moments = torch.tensor(cfg.body_second_moments(), dtype=_F)
            self.constraints = concat_constraints(
                *(rigid_body_constraints(k * b, 2, self.n_points) for b in range(B))
            )
        else:
            self.constraints = None
        W = len(cfg.walls)
        names = [f"body {i} and body {j} overlap" for i in range(B) for j in range(i + 1, B)]
        names += [f"body {i} penetrates wall {j}" for i in range(B) for j in range(W)]
        self.contact_names = names
        self._bodies = [
            Body(b, "disk" if disks else "point", tuple(range(k * b, k * b + k)), cfg.radii[b])
            for b in range(B)
        ]
        pairs = [(i, j) for i in range(B) for j in range(i + 1, B)]
        pairs += [(i, ENVIRONMENT) for i in range(B) for _ in range(W)]
        self._edges = [
            Edge("contact", pair, self._bodies[pair[0]].points + self._points_of(pair[1]), c)
            for c, pair in enumerate(pairs)
        ]

    def _build_chain(self, cfg: ChainPendulumConfig) -> None:
        L = len(cfg.masses)
        self.dim, self.n_bodies, self.n_points = 2, L, L
        self.body_points = list(range(L))
        self.mass = torch.tensor(cfg.masses, dtype=_F)
        self.geometry = circles_2d(["point"] * L, cfg.radii, cfg.walls, pairs=False)
        self.constraints = chain_constraints(cfg.link_lengths, 2, pivot=cfg.pivot)
        W = len(cfg.walls)
        self.contact_names = [f"joint {i} penetrates wall {j}" for i in range(L) for j in range(W)]
        self._bodies = [Body(i, "point", (i,), cfg.radii[i]) for i in range(L)]
        self._edges = [Edge("pin", (0, ENVIRONMENT), (0,), name="pivot")]
        self._edges += [Edge("link", (i - 1, i), (i - 1, i), name=f"link {i}") for i in range(1, L)]
        self._edges += [
            Edge("contact", (i, ENVIRONMENT), (i,), i * W + j) for i in range(L) for j in range(W)
        ]

    def _build_gyroscope(self, cfg: GyroscopeConfig) -> None:
        self.dim, self.n_bodies, self.n_points = 3, 1, 4
        self.body_points = [0]
        self.mass = torch.tensor([cfg.mass], dtype=_F)
        self.second_moments = torch.tensor([cfg.second_moments], dtype=_F)
        self.geometry = RimPlane.build([0], [cfg.rim_radius], [cfg.wall])
        # pivot at body coordinates (0, 0, -com_distance), pinned to the origin
        self.constraints = concat_constraints(
            rigid_body_constraints(0, 3),
            ball_joint(0, [0.0, 0.0, -cfg.com_distance], [0.0, 0.0, 0.0]),
        )
        self.contact_names = ["the rim penetrates the wall"]
        self._bodies = [Body(0, "rigid3d", (0, 1, 2, 3), cfg.rim_radius)]
        self._edges = [
            Edge("pin", (0, ENVIRONMENT), (0, 1, 2, 3), name="pivot"),
            Edge("contact", (0, ENVIRONMENT), (0, 1, 2, 3), 0),
        ]

    def _build_rope(self, cfg: RopeConfig) -> None:
        P = cfg.n_points
        self.dim, self.n_bodies, self.n_points = 2, P, P
        self.body_points = list(range(P))
        self.mass = torch.tensor(cfg.point_masses(), dtype=_F)
        self.geometry = rope_limits(
            P,
            max_angle=cfg.max_angle,
            rest_length=cfg.rest_length,
            min_ratio=cfg.min_ratio,
            max_ratio=cfg.max_ratio,
            anchor=cfg.anchor,
        )
        self.constraints = None
        self.stiffness = torch.tensor(float(cfg.stiffness), dtype=_F)
        self.rest_length = torch.tensor(float(cfg.rest_length), dtype=_F)
        self._anchor = torch.tensor(cfg.anchor, dtype=_F)
        self.contact_names = [f"bending limit at joint {k} exceeded" for k in range(P - 1)] + [
            f"stretch limit of segment {k} exceeded" for k in range(P)
        ]
        self._bodies = [Body(i, "point", (i,)) for i in range(P)]

        def segment(k: int) -> tuple[int, int]:  # segment k: point k - 1 (or the anchor) to k
            return (k, k - 1) if k > 0 else (0, ENVIRONMENT)

        self._edges = [
            Edge(
                "spring",
                segment(k),
                tuple(sorted(p for p in segment(k) if p >= 0)),
                name=f"segment {k}",
            )
            for k in range(P)
        ]
        self._edges += [  # bending at joint k: segment k + 1 against segment k
            Edge("contact", (k, k + 1), tuple(range(max(k - 1, 0), k + 2)), k) for k in range(P - 1)
        ]
        self._edges += [
            Edge("contact", segment(k), tuple(sorted(p for p in segment(k) if p >= 0)), P - 1 + k)
            for k in range(P)
        ]

    # ------------------------------------------------------------------ basics
    @property
    def default_steps(self) -> int:
        """Steps of a full trajectory: ``horizon / dt - 1`` (it holds ``horizon / dt`` states)."""
        return round(self.horizon / self.dt) - 1

    @property
    def state_shape(self) -> tuple[int, int, int]:
        """``(2, P, dim)``."""
        return (2, self.n_points, self.dim)

    def parameters(self) -> PhysicalParams:
        """The system's own physical parameters as an immutable :class:`PhysicalParams`.

        Built from the attributes ``mass``, ``second_moments``, ``mu``, ``cor``,
        ``gravity``, ``stiffness``, ``rest_length``, ``eps`` and
        ``potential_model``; what :meth:`simulate` uses when no ``params`` are
        passed. Change a copy with :meth:`PhysicalParams.replace`.
        """
        return PhysicalParams(
            mass=self.mass,
            second_moments=self.second_moments,
            mu=self.mu,
            cor=self.cor,
            gravity=self.gravity,
            stiffness=self.stiffness,
            rest_length=self.rest_length,
            eps=self.eps,
            potential=self.potential_model,
        )

    def _points_of(self, body: int) -> tuple[int, ...]:
        return () if body == ENVIRONMENT else self._bodies[body].points

    def bodies(self) -> tuple[Body, ...]:
        """The bodies, in body order (see :mod:`diffcontact.systems.graph`)."""
        return tuple(self._bodies)

    def body_graph(self) -> BodyGraph:
        """Bodies as nodes; links, springs, pins and candidate contacts as edges.

        For graph models (interaction networks); see :class:`~diffcontact.systems.graph.BodyGraph`.
        Contact edges come in the system's contact order, so edge ``c`` of
        ``body_graph().edges_of("contact")`` is candidate ``c``.
        """
        edges = tuple(
            replace(e, name=self.contact_names[e.contact]) if e.kind == "contact" else e
            for e in self._edges
        )
        return BodyGraph(tuple(self._bodies), edges, self.n_points)

    def __repr__(self) -> str:
        return (
            f"System(name={self.name!r}, type={self.type!r}, points={self.n_points}, "
            f"dim={self.dim}, contacts={self.n_contacts}, dt={self.dt}, horizon={self.horizon})"
        )

    def _params(self, params: PhysicalParams | None, n_states: int | None) -> PhysicalParams:
        """``params`` (default: :meth:`parameters`), validated for ``n_states`` states."""
        if params is None:
            params = self.parameters()
        elif not isinstance(params, PhysicalParams):
            raise ValueError(
                f"params must be a PhysicalParams (system.parameters().replace(...)), "
                f"got {type(params).__name__}"
            )
        params.validate(
            n_bodies=self.n_bodies,
            n_contacts=self.n_contacts,
            axes=None if self.second_moments is None else self.dim,
            rope=self.type == "rope",
            n_states=n_states,
        )
        return params

    # ------------------------------------------------------------- parameters
    def _static_on(
        self, device: torch.device
    ) -> tuple[Any, EqualityConstraints | None, EqualityConstraints | None]:
        """The geometry, the constraints and the constraints of one body (if they act on
        each body alone, :meth:`EqualityConstraints.split`, and :func:`_per_body` says so
        for ``device``) on ``device``."""
        key = str(device)
        if key not in self._device_cache:
            geometry = self.geometry.to(device)
            constraints = None if self.constraints is None else self.constraints.to(device)
            groups = None
            if constraints is not None and self.second_moments is not None and _per_body(device):
                groups = constraints.split(self.dim + 1)
            self._device_cache[key] = (geometry, constraints, groups)
        return self._device_cache[key]

    def _body_blocks(
        self, params: PhysicalParams, inverse: bool, dtype: torch.dtype, device: torch.device
    ) -> Tensor:
        """``M`` or ``M^-1`` over points, ``(P, P)`` or ``(N, P, P)`` for batched masses."""
        mass = params.mass.to(dtype=dtype, device=device)
        if params.second_moments is None:
            return torch.diag_embed(1.0 / mass if inverse else mass)
        s = params.second_moments.to(dtype=dtype, device=device)
        fn = body_inverse_mass_matrix if inverse else body_mass_matrix
        return assemble_mass_matrix(fn(mass, s).unbind(-3))

    def _inverse_mass_groups(
        self, params: PhysicalParams, dtype: torch.dtype, device: torch.device
    ) -> Tensor:
        """The bodies' inverse mass blocks, ``(B, q, q)`` or ``(N, B, q, q)`` (rigid bodies)."""
        mass = params.mass.to(dtype=dtype, device=device)
        s = params.second_moments.to(dtype=dtype, device=device)
        return body_inverse_mass_matrix(mass, s)

    def _matrix_args(
        self, dtype: Any, device: Any, params: PhysicalParams | None
    ) -> tuple[PhysicalParams, torch.dtype, torch.device]:
        """The checked arguments of :meth:`mass_matrix` and :meth:`inverse_mass_matrix`:
        ``dtype`` float32 or float64 (an integer dtype had truncated the masses to 0),
        ``device`` a CPU or available CUDA device, ``params`` batched or not."""
        if not isinstance(dtype, torch.dtype) or dtype not in (torch.float32, torch.float64):
            raise ValueError(
                f"dtype must be torch.float32 or torch.float64 (the dtypes diffcontact "
                f"computes in), got {dtype!r}"
            )
        device = parse_device(device)
        n = params.batch_size() if isinstance(params, PhysicalParams) else None
        return self._params(params, n), dtype, device

    def mass_matrix(
        self,
        dtype: torch.dtype = _F,
        device: torch.device | str = "cpu",
        *,
        params: PhysicalParams | None = None,
    ) -> Tensor:
        """Mass matrix over points ``M: (P, P)``, or ``(N, P, P)`` where ``params``' masses
        or second moments carry a batch dimension (one set per trajectory).

        Raises:
            ValueError: ``dtype`` not ``torch.float32``/``torch.float64``, ``device`` not
                a CPU or available CUDA device, bad ``params``.
        """
        params, dtype, device = self._matrix_args(dtype, device, params)
        return self._body_blocks(params, False, dtype, device)

    def inverse_mass_matrix(
        self,
        dtype: torch.dtype = _F,
        device: torch.device | str = "cpu",
        *,
        params: PhysicalParams | None = None,
    ) -> Tensor:
        """Inverse mass matrix over points ``M^-1: (P, P)`` (closed form per body), or
        ``(N, P, P)`` for batched masses or second moments (as :meth:`mass_matrix`)."""
        params, dtype, device = self._matrix_args(dtype, device, params)
        return self._body_blocks(params, True, dtype, device)

    def _context(
        self, like: Tensor, params: PhysicalParams | None = None, n_states: int | None = None
    ) -> _Context:
        """Parameters cast to ``like``'s dtype and device, validated for ``n_states``."""
        params = self._params(params, n_states)
        batched = params.batch_size() is not None
        dtype, device = like.dtype, like.device
        geometry, constraints, groups = self._static_on(device)
        if params.second_moments is None:  # point masses: no bodies to run one at a time
            groups = None
        M_inv_groups = None if groups is None else self._inverse_mass_groups(params, dtype, device)
        K = self.n_contacts

        def cast(t: Tensor | None) -> Tensor | None:
            return None if t is None else t.to(dtype=dtype, device=device)

        mass = cast(params.mass)
        com = torch.tensor(self.body_points, dtype=torch.long, device=device)
        if mass.dim() == 2:  # (N, B): one set of masses per trajectory
            weights = mass.new_zeros(mass.shape[0], self.n_points).index_copy(1, com, mass)
        else:
            weights = torch.zeros(self.n_points, dtype=dtype, device=device).index_put((com,), mass)
        g = cast(params.gravity)
        zero = torch.zeros_like(g)
        g_vec = torch.stack([zero, -g] if self.dim == 2 else [zero, zero, -g], dim=-1)
        eps = params.eps
        eps = (
            cast(eps) if isinstance(eps, Tensor) else torch.tensor(eps, dtype=dtype, device=device)
        )

        def per_contact(t: Tensor) -> Tensor:
            t = cast(t)
            return t.expand(t.shape[0], K) if t.dim() == 2 else t.expand(K)

        return _Context(
            dtype=dtype,
            device=device,
            batched=batched,
            geometry=geometry,
            constraints=constraints,
            M=self._body_blocks(params, False, dtype, device),
            M_inv=self._body_blocks(params, True, dtype, device)
            if groups is None
            else block_diagonal(M_inv_groups),  # the same matrix from the same blocks
            groups=groups,
            M_inv_groups=M_inv_groups,
            weights=weights,
            g_vec=g_vec,
            mu=per_contact(params.mu),
            cor=per_contact(params.cor),
            eps=eps,
            stiffness=cast(params.stiffness),
            rest_length=cast(params.rest_length),
            anchor=cast(self._anchor),
            potential=params.potential,
        )

    # ------------------------------------------------------------------ energy
    def _potential(self, x: Tensor, ctx: _Context, check: bool = False) -> Tensor:
        """``V(x)``; with ``check`` (the public entries), ``params.potential``'s output
        shape is checked (:meth:`_check_potential_output`)."""
        weights, g_vec = ctx.per_state(ctx.weights, x, 1, 0), ctx.per_state(ctx.g_vec, x, 1, 0)
        if g_vec.dim() == 1:
            V = -(weights * (x @ g_vec)).sum(-1)
        else:
            V = -(weights * (x @ g_vec.unsqueeze(-1)).squeeze(-1)).sum(-1)
        if ctx.stiffness is not None:
            seg = self._segments(x, ctx)
            length = (seg * seg).sum(-1).sqrt()
            k = ctx.per_state(ctx.stiffness, x, 0, 1)
            rest = ctx.per_state(ctx.rest_length, x, 0, 1)
            V = V + (k * (length - rest) ** 2).sum(-1)
        if ctx.potential is not None:
            extra = ctx.potential(x)
            if check:
                self._check_potential_output(extra, x)
            V = V + extra
        return V

    @staticmethod
    def _check_potential_output(V: Any, x: Tensor) -> None:
        """``ValueError`` unless ``V``, ``params.potential``'s output at positions ``x:
        (..., P, dim)``, is a tensor of shape ``(...)`` (one energy per state: a potential
        returning ``(..., P)`` had been accepted by :meth:`simulate`, whose forces sum it,
        and broke :meth:`energy` with a broadcast error)."""
        want = tuple(x.shape[:-2])
        if not isinstance(V, Tensor) or tuple(V.shape) != want:
            got = tuple(V.shape) if isinstance(V, Tensor) else type(V).__name__
            raise ValueError(
                f"potential (params.potential) must map positions (..., P, dim) to one energy "
                f"per state (...): expected shape {want} for positions of shape "
                f"{tuple(x.shape)}, got {got}"
            )

    def _check_potential(self, ctx: _Context, x: Tensor) -> None:
        """:meth:`_check_potential_output` on one evaluation of ``params.potential`` at
        positions ``x: (..., P, dim)``: once per call at the boundary of the methods that
        use the potential only through its gradient (:meth:`simulate`, :meth:`step`,
        :meth:`integrate`, :meth:`grad_potential`; not per step or RK4 stage)."""
        if ctx.potential is None:
            return
        x = x.detach()
        with torch.no_grad():
            self._check_potential_output(ctx.potential(x), x)

    def _segments(self, x: Tensor, ctx: _Context) -> Tensor:
        anchor = ctx.anchor.expand(*x.shape[:-2], 1, 2)
        return x - torch.cat([anchor, x[..., :-1, :]], dim=-2)

    def _grad_potential(self, x: Tensor, ctx: _Context) -> Tensor:
        """Analytic ``grad_x V``: gravity plus, for the rope, the segment springs."""
        weights, g_vec = ctx.per_state(ctx.weights, x, 1, 0), ctx.per_state(ctx.g_vec, x, 1, 0)
        grad = -weights[..., :, None] * g_vec[..., None, :]  # (P, dim) or (N, ..., P, dim)
        grad = grad.expand_as(x)
        if ctx.stiffness is not None:
            seg = self._segments(x, ctx)
            length = (seg * seg).sum(-1, keepdim=True).clamp_min(1e-300).sqrt()
            k = ctx.per_state(ctx.stiffness, x, 0, 2)
            rest = ctx.per_state(ctx.rest_length, x, 0, 2)
            g_seg = 2.0 * k * (length - rest) / length * seg
            nxt = torch.cat([g_seg[..., 1:, :], torch.zeros_like(g_seg[..., :1, :])], dim=-2)
            grad = grad + g_seg - nxt
        if ctx.potential is not None:
            grad = grad + potential_gradient(ctx.potential, x, create_graph=torch.is_grad_enabled())
        return grad

    def _batch(self, x: Tensor, params: PhysicalParams | None, state_dims: int) -> int | None:
        """The leading batch size that batched ``params`` must match (``None`` if unbatched)."""
        if params is None or params.batch_size() is None:
            return None
        if x.dim() <= state_dims:
            raise ValueError(
                "params carry a batch dimension (one set per trajectory), so the states "
                f"need a leading batch dimension too; got shape {tuple(x.shape)}"
            )
        return int(x.shape[0])

    def potential(self, x: Tensor, *, params: PhysicalParams | None = None) -> Tensor:
        """Potential energy ``V(x): (...)`` of positions ``x: (..., P, dim)``.

        Gravity ``-g . sum_b m_b c_b`` (centres of mass), for the rope
        ``sum_k k (l_k - l0)^2`` over the segments, the first from the anchor,
        and ``params.potential`` when set. Batched ``params`` need ``x: (N, ..., P, dim)``.
        ``x`` holds positions only: a state ``(N, 2, P, dim)`` has the same trailing shape
        and would be read as ``(N, 2)`` positions (pass ``z[..., 0, :, :]``, or use
        :meth:`energy`).

        Raises:
            ValueError: ``x`` not a float32/float64 ``(..., P, dim)`` tensor, bad
                ``params``, or a ``params.potential`` whose output is not ``(...)``.
        """
        self._check_positions(x, "x")
        return self._potential(x, self._context(x, params, self._batch(x, params, 2)), True)

    def grad_potential(self, x: Tensor, *, params: PhysicalParams | None = None) -> Tensor:
        """Analytic ``grad_x V: (..., P, dim)`` of :meth:`potential` (what the dynamics use)."""
        self._check_positions(x, "x")
        ctx = self._context(x, params, self._batch(x, params, 2))
        self._check_potential(ctx, x)
        return self._grad_potential(x, ctx)

    def kinetic_energy(self, z: Tensor, *, params: PhysicalParams | None = None) -> Tensor:
        """Kinetic energy ``0.5 sum_c v_c^T M v_c: (...)`` of states ``z: (..., 2, P, dim)``."""
        self._check_state_shape(z, "z", batched=False)
        ctx = self._context(z, params, self._batch(z, params, 3))
        v = z[..., 1, :, :]
        return 0.5 * (v * (ctx.per_state(ctx.M, v, 2, 0) @ v)).sum((-2, -1))

    def energy(self, z: Tensor, *, params: PhysicalParams | None = None) -> Tensor:
        """Total energy (kinetic + potential) of states or trajectories.

        Args:
            z: ``(..., 2, P, dim)``, e.g. a trajectory ``(N, T, 2, P, dim)``.
            params: physical parameters (default: the system's); batched ones
                need ``z: (N, ...)``.

        Returns:
            ``(...)``, e.g. ``(N, T)``.
        """
        self._check_state_shape(z, "z", batched=False)
        ctx = self._context(z, params, self._batch(z, params, 3))
        x, v = z[..., 0, :, :], z[..., 1, :, :]
        return 0.5 * (v * (ctx.per_state(ctx.M, v, 2, 0) @ v)).sum((-2, -1)) + self._potential(
            x, ctx, True
        )

    def gaps(self, x: Tensor) -> Tensor:
        """Signed gaps ``(..., K)`` of all candidate contacts at positions ``(..., P, dim)``."""
        self._check_positions(x, "x")
        geometry = self._static_on(x.device)[0]
        return geometry.gaps(x)

    def contact_velocities(self, z: Tensor) -> Tensor:
        """Contact-space velocities ``J_C v``: ``(..., K, d)`` of all candidates at ``z``.

        ``z``: states ``(..., 2, P, dim)``. Component 0 is the normal velocity (the
        rate of the gap; negative: approaching), components ``1..d-1`` the
        tangential ones (none for the rope's one-row limits), in the contact
        frames of ``docs/conventions.md``.
        """
        self._check_state_shape(z, "z", batched=False)
        geometry = self._static_on(z.device)[0]
        x, v = z[..., 0, :, :], z[..., 1, :, :]
        K = self.n_contacts
        idx = torch.arange(K, device=z.device).expand(*x.shape[:-2], K)
        return jacobian_matvec(geometry.jacobian_sparse(x, idx), v)

    # -------------------------------------------------------------- validation
    def _check_state_shape(self, z: Tensor, name: str, batched: bool = True) -> None:
        if not isinstance(z, Tensor):
            raise ValueError(f"{name} must be a torch.Tensor, got {type(z).__name__}")
        shape = self.state_shape
        if z.dim() < 3 or tuple(z.shape[-3:]) != shape or (batched and z.dim() != 4):
            want = f"(N, {', '.join(map(str, shape))})" if batched else f"(..., {shape})"
            raise ValueError(
                f"{name} must have shape {want} for {self.name} (positions then velocities "
                f"of {self.n_points} points in {self.dim}D); got {tuple(z.shape)}"
            )
        self._check_values(z, name)

    def _check_positions(self, x: Tensor, name: str) -> None:
        """``x: (..., P, dim)`` positions, float32 or float64 (a ``ValueError`` naming
        ``name`` else: integer positions had given zero masses, cast to their dtype)."""
        if not isinstance(x, Tensor):
            raise ValueError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
        if x.dim() < 2 or tuple(x.shape[-2:]) != (self.n_points, self.dim):
            raise ValueError(
                f"{name} must have shape (..., {self.n_points}, {self.dim}) for {self.name} "
                f"(positions of {self.n_points} points in {self.dim}D); got {tuple(x.shape)}"
            )
        self._check_values(x, name)

    @staticmethod
    def _check_values(t: Tensor, name: str) -> None:
        if t.dtype not in (torch.float32, torch.float64):
            raise ValueError(
                f"{name} must be a float32 or float64 tensor (the dtypes diffcontact "
                f"computes in), got {t.dtype}"
            )
        if t.device.type == "meta":
            raise ValueError(f"{name} is on the meta device, which holds no values")
        if t.layout != torch.strided:
            raise ValueError(
                f"{name} must be a dense tensor, got layout {t.layout} (call .to_dense())"
            )

    def _check_state(self, z: Tensor, name: str) -> None:
        self._check_state_shape(z, name)
        bad = ~torch.isfinite(z.detach()).flatten(1).all(-1)
        if bool(bad.any()):
            rows = bad.nonzero().flatten().tolist()
            raise ValueError(f"{name} contains NaN or infinite values (states {rows[:10]})")

    def _check_no_overlap(self, z: Tensor, name: str) -> None:
        """Raise if a state of ``z`` starts with a negative gap. Below float64 a gap down to
        ``-sqrt(eps)`` is taken as rounding: a state sampled on a limit (a rope's bending
        or length limit) and cast to float32 lands up to ~1e-5 past it."""
        with torch.no_grad():
            gaps = self.gaps(z[..., 0, :, :].detach())
        tol = 0.0 if z.dtype == torch.float64 else math.sqrt(torch.finfo(z.dtype).eps)
        bad = gaps < -tol
        if bool(bad.any()):
            rows, cols = bad.nonzero(as_tuple=True)
            items = [
                f"{name}[{r}]: {self.contact_names[c]} (gap {float(gaps[r, c]):.3g})"
                for r, c in zip(rows.tolist()[:8], cols.tolist()[:8], strict=True)
            ]
            more = "" if rows.numel() <= 8 else f"\n  ... and {rows.numel() - 8} more"
            raise ValueError(
                f"{name} has overlapping bodies or violated limits "
                f"(gap < {f'-{tol:.1e}' if tol else '0'}) in "
                f"{int(bad.any(-1).sum())} of {z.shape[0]} states:\n  "
                + "\n  ".join(items)
                + more
                + "\n(a state a simulation ended in may touch or be slightly inside a contact: "
                "to go on from one, pass check_overlap=False)"
            )

    # ---------------------------------------------------------------- sampling
    def sample_initial_conditions(
        self, n: int, seed: int = 0, *, device: torch.device | str | None = None
    ) -> Tensor:
        """Draw ``n`` initial states from the task's distribution (paper-facts.md).

        Candidates are drawn in batches from a ``torch.Generator`` seeded with
        ``seed`` and those with any gap <= 0 (overlap, contact or a violated
        limit) are rejected, until ``n`` are kept; the layouts are described in
        :mod:`diffcontact.systems.initial_conditions`.

        Args:
            n: number of states (>= 1).
            seed: the seed; the same seed gives the same bytes.
            device: where to put the result (drawn on the CPU): ``"cpu"``, ``"cuda"``,
                ``"cuda:N"`` or a ``torch.device``.

        Returns:
            ``(n, 2, P, dim)`` float64.

        Raises:
            ValueError: bad ``n`` or ``seed``, a device that is not a CPU or CUDA one, or
                CUDA asked for where it is not available.
        """
        given, n = n, _integer(n)
        if n is None or n < 1:
            raise ValueError(f"n must be a positive integer, got {given!r}")
        given, seed = seed, _integer(seed)
        if seed is None or not 0 <= seed < 2**63:  # (None: TypeError; 1.5 was read as 1)
            raise ValueError(f"seed must be an integer in [0, 2**63), got {given!r}")
        target = None if device is None else parse_device(device)  # before the draws
        gen = torch.Generator().manual_seed(seed)
        drawer = ics.DRAWERS[self.type]
        geometry = self._static_on(torch.device("cpu"))[0]

        def draw(m: int, g: torch.Generator) -> Tensor:
            return drawer(self.config, m, g)

        def valid(z: Tensor) -> Tensor:
            return (geometry.gaps(z[:, 0]) > 0).all(-1)

        try:
            z = ics.rejection_sample(draw, valid, n, gen)
        except ValueError as err:  # name what the draws run into (a pivot below the ground)
            probe = draw(1024, torch.Generator().manual_seed(int(seed)))
            share = (geometry.gaps(probe[:, 0]) <= 0).double().mean(0)  # (K,)
            k = int(share.argmax())
            raise ValueError(
                f"{err}; the candidate contact most often closed in the draws is "
                f"{self.contact_names[k]!r} ({100 * float(share[k]):.0f} % of them): check "
                "its geometry (walls, pivot, anchor) against the initial_conditions"
            ) from None
        return z if target is None else z.to(target)

    # -------------------------------------------------------------- simulation
    def _vector_field(self, ctx: _Context, dynamics: str):
        constraints = ctx.constraints

        if dynamics == "lagrangian" and ctx.force_is_constant:
            # the same acceleration at every stage and step: computed once per call (the
            # same operations on the same values, so bitwise the same trajectories)
            cache = ctx.constant_acceleration

            def field(x: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
                acc = cache.get(x.shape)
                if acc is None:
                    grad_V = self._grad_potential(x, ctx)
                    acc = cache[x.shape] = lagrangian_vector_field(x, v, ctx.M_inv, grad_V)
                return v, acc

        elif ctx.groups is not None:
            # constraints on each body alone: the dynamics of one body at a time, a batch of
            # (..., B) bodies of q points (E / B equations each instead of E)
            groups, M_inv = ctx.groups, ctx.M_inv_groups
            q = groups.num_points

            def field(x: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
                grad_V = self._grad_potential(x, ctx)
                xg, vg, gg = (t.unflatten(-2, (-1, q)) for t in (x, v, grad_V))
                if dynamics == "lagrangian":
                    return v, lagrangian_vector_field(xg, vg, M_inv, gg, groups).flatten(-3, -2)
                x_dot, v_dot = hamiltonian_flow(xg, vg, M_inv, gg, groups)
                return x_dot.flatten(-3, -2), v_dot.flatten(-3, -2)

        elif dynamics == "lagrangian":

            def field(x: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
                grad_V = self._grad_potential(x, ctx)
                return v, lagrangian_vector_field(x, v, ctx.M_inv, grad_V, constraints)

        else:

            def field(x: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
                grad_V = self._grad_potential(x, ctx)
                return hamiltonian_flow(x, v, ctx.M_inv, grad_V, constraints)

        return field

    def _integrate(self, z: Tensor, ctx: _Context, dynamics: str) -> Tensor:
        x, v = z[..., 0, :, :], z[..., 1, :, :]
        step = INTEGRATORS[self.integrator]
        x1, v1 = step(self._vector_field(ctx, dynamics), x, v, self.dt)
        return torch.stack([x1, v1], dim=-3)

    def _resolve(
        self,
        z: Tensor,
        ctx: _Context,
        model: ContactModel,
        fraction: float,
        settings: SolverSettings | None = None,
        static_contacts: int | None = None,
        dense_rows: bool = False,
        target_gradient: bool = True,
        margin: float = 0.0,
    ) -> ContactResult:
        """The contact resolution of a step: the states with an active contact, padded to
        the largest active count (one read of the device). With ``static_contacts``:
        every state, its active candidates first, padded to that many candidates (those
        without an active contact as all-padded problems, which get zero impulses; active
        contacts beyond it are dropped, which the caller must detect), so that the shapes
        do not depend on the data and the device is never read
        (:meth:`~diffcontact.systems.rollout.Rollout.graphed`). The result's ``J_C`` is
        ``None`` where the impulse took the rows' sparse entries (:meth:`_sparse_contact`),
        unless ``dense_rows``. ``target_gradient``: differentiate the penetration
        compensation target (else a constant of the gradient, as appendix G).
        ``margin``: a candidate is active below this gap (:meth:`_contact_margin`; 0:
        where it is violated)."""
        x, v = z[..., 0, :, :], z[..., 1, :, :]
        P, dim, d = self.n_points, self.dim, self.d
        D = P * dim
        with torch.no_grad():
            gaps = ctx.geometry.gaps(x.detach())
            active = gaps < margin
            counts = active.sum(-1)  # (N,) contacts per state
            static = static_contacts is not None and gaps.shape[-1] > 0
            if static:
                n, Ka = gaps.shape[0], min(gaps.shape[-1], max(1, static_contacts))
                b = torch.arange(n, device=z.device)
            else:
                # one read of the device for both sizes (each read is a synchronisation on
                # CUDA); the states with a contact, in order, by a stable sort instead of a
                # second read through nonzero
                n, Ka = 0, 0
                if counts.numel() and gaps.shape[-1]:  # (no candidates: nothing to read)
                    n, Ka = torch.stack([(counts > 0).sum(), counts.max()]).tolist()
                b = torch.argsort((counts == 0).to(torch.uint8), stable=True)[:n]  # (n,)
        if n == 0:
            empty = torch.zeros(0, dtype=torch.long, device=z.device)
            zf = z.new_zeros(0, 0, d)
            return ContactResult(
                z, gaps, empty, empty.reshape(0, 0), active[:0, :0], zf, zf,
                z.new_zeros(0, 0, D), z.new_zeros(0, 0),
            )  # fmt: skip
        act = active[b]  # (n, K)
        order = torch.argsort((~act).to(torch.uint8), dim=-1, stable=True)
        idx = order[:, :Ka]  # active candidates first, in candidate order
        mask = act.gather(-1, idx)  # (n, Ka)
        xs, vs = x[b], v[b]
        M_inv = ctx.select(ctx.M_inv, 2, b)
        J: Tensor | None = None
        if self._sparse_contact(model, ctx, n * Ka * d * D, settings, dense_rows):
            # point masses, large rows: the impulse's products from the rows' entries
            rows = ctx.geometry.jacobian_sparse(xs, idx)  # (n, Ka, m), (n, Ka, d, m, dim)
            values = torch.where(mask[:, :, None, None, None], rows.values, 0.0)
            points = rows.points.expand(*values.shape[:2], rows.points.shape[-1])
            op: Tensor | SparseContact = SparseContact(
                SparseJacobian(points, values), M_inv.diagonal(0, -2, -1)
            )
            J_E = Mh = None
        else:
            J = ctx.geometry.jacobian(xs, idx)  # (n, Ka, d, P, dim)
            J = torch.where(mask[:, :, None, None, None], J, torch.zeros_like(J))
            J = J.reshape(n, Ka * d, D)
            J_E, Mh = self._constrained_inverse_inertia(ctx, xs, M_inv, b)
            op = J
            if J_E is not None:  # (the static step's states without a contact keep theirs)
                consistent = _consistent_velocities(vs, J_E, M_inv)
                touched = mask.any(-1)[:, None, None] if static else None
                vs = consistent if touched is None else torch.where(touched, consistent, vs)
        if fraction > 0:
            with torch.set_grad_enabled(torch.is_grad_enabled() and target_gradient):
                # the depths with their graph where the positions have one (the selection
                # above ran without): the target is differentiable like the rest of the step
                graph = xs.requires_grad and torch.is_grad_enabled()
                depth = -(ctx.geometry.gaps(xs) if graph else gaps[b]).gather(-1, idx)
                metric = Mh if self.penetration_metric == "mass" else None
                v_star = _penetration_target(op, depth, mask, self.dt, d, fraction, J_E, metric)
        else:
            v_star = vs.new_zeros(n, Ka * d)

        def pick(t: Tensor) -> Tensor:  # (n, Ka): each field batched or not on its own
            return t[b].gather(-1, idx) if t.dim() == 2 else t[idx]

        mu, cor = pick(ctx.mu), pick(ctx.cor)
        contact_params = ContactParams(mu=mu, cor=cor, eps=ctx.select(ctx.eps, 0, b))
        extra: dict[str, Any] = {}
        if getattr(model, "needs_contact_state", False):  # learned contact models
            extra["state"] = ContactState(xs, gaps[b].gather(-1, idx), idx, b, ctx.geometry)
        try:
            res = model.resolve(
                op,
                Mh,
                vs.reshape(n, D),
                contact_params,
                mask,
                d,
                v_C_star=v_star if fraction > 0 else None,
                settings=self._inner_settings(settings),
                **extra,
            )
        except ConeQPError as err:  # name the states (rows of this step's contact batch)
            status = err.status
            if status is not None and status.converged.shape == (n,):
                err.states = b[~status.converged].tolist()
            raise
        if static:
            v_new = res.v_plus.reshape(n, P, dim)
        else:
            v_new = v.index_put((b,), res.v_plus.reshape(n, P, dim))
        return ContactResult(
            z=torch.stack([x, v_new], dim=-3),
            gaps=gaps,
            batch_index=b,
            contact_index=idx,
            active=mask,
            f_c=res.f_c.reshape(n, Ka, d),
            f_r=res.f_r.reshape(n, Ka, d),
            J_C=J,
            v_C_star=v_star,
        )

    def _sparse_contact(
        self,
        model: ContactModel,
        ctx: _Context,
        size: int,
        settings: SolverSettings | None,
        dense_rows: bool,
    ) -> bool:
        """Whether a step's contact impulse takes its products from the rows' sparse
        entries (:class:`~diffcontact.geometry.sparse_contact.SparseContact`) instead of the
        dense ``J_C`` of ``size`` numbers: for a model that accepts an operator, point
        masses without equality constraints (a diagonal ``Mhat^-1``), rows of at least
        :data:`SPARSE_CONTACT_COLUMNS` columns, where the projection would take the sparse
        Gram matrix too (Warp, :data:`~diffcontact.geometry.sparse_gram.DEVICES`, rows of
        at least :data:`~diffcontact.geometry.sparse_gram.MIN_DENSE_SIZE` numbers), unless
        the caller wants the dense rows back."""
        return (
            not dense_rows
            and self.n_points * self.dim >= SPARSE_CONTACT_COLUMNS
            and size >= MIN_DENSE_SIZE
            and self._point_masses
            and ctx.groups is None
            and (ctx.constraints is None or ctx.constraints.num_equations == 0)
            and getattr(model, "accepts_contact_operator", False)
            and sparse_gram_available(settings, ctx.dtype, ctx.device)
        )

    @staticmethod
    def _constrained_inverse_inertia(
        ctx: _Context, xs: Tensor, M_inv: Tensor, b: Tensor
    ) -> tuple[Tensor | None, Tensor]:
        """``J_E: (n, E, D)`` (``None`` without constraints) and ``Mhat^-1: (n, D, D)``
        (S.12) at the positions ``xs: (n, P, dim)`` of the states ``b``."""
        n, _, dim = xs.shape
        if ctx.groups is not None:  # constraints on each body alone: Mhat^-1 per body
            J_E = ctx.groups.jacobian(xs.unflatten(-2, (-1, ctx.groups.num_points)))
            Mh = block_diagonal(Mhat_inv(ctx.select(ctx.M_inv_groups, 3, b), J_E))
            return block_diagonal(J_E), Mh  # J_E: the rows in the constraints' order
        if ctx.constraints is not None:
            J_E = ctx.constraints.jacobian(xs)  # (n, E, D)
            return J_E, Mhat_inv(M_inv, J_E)
        D = xs.shape[-2] * dim
        return None, kron_identity(M_inv, dim).expand(n, D, D)

    @staticmethod
    def _inner_settings(settings: SolverSettings | None) -> SolverSettings:
        """Solver settings without the per-call sign/symmetry checks (host syncs).

        Inside a step they hold by construction: ``mu`` and ``cor`` are validated
        once at :meth:`simulate`'s boundary, ``A`` is symmetrised and PSD and the
        restitution bound ``e_P f_c,n`` is clamped at zero. The finiteness check
        stays (a rollout that blew up is reported as NaN input).
        """
        settings = settings_or_default(settings, "solver_settings")
        return settings if not settings.check_inputs else replace(settings, check_inputs=False)

    def _options(
        self,
        contact_model: Any,
        dynamics: str | None,
        fraction: float | None,
        params: PhysicalParams | None = None,
        eps: float | Tensor | None = None,
    ) -> tuple[ContactModel, str, float, PhysicalParams | None]:
        model = create_contact_model(self.contact_model if contact_model is None else contact_model)
        dynamics = self.dynamics if dynamics is None else dynamics
        if dynamics not in DYNAMICS:
            raise ValueError(f"dynamics must be one of {DYNAMICS}, got {dynamics!r}")
        given = fraction
        if fraction is None:
            fraction = self.penetration_fraction
        elif isinstance(fraction, bool):
            fraction = math.nan  # (True had been read as 1)
        else:
            try:
                fraction = float(fraction)
            except (TypeError, ValueError, RuntimeError):
                fraction = math.nan
        if not 0 <= fraction <= 1:
            raise ValueError(f"penetration_fraction must be a number in [0, 1], got {given!r}")
        if eps is not None:
            params = (self.parameters() if params is None else params).replace(eps=eps)
        return model, dynamics, fraction, params

    def _contact_margin(self, iterations: int, dtype: torch.dtype) -> float:
        """The gap below which a step's impulse treats a candidate as active: 0 (violated)
        without the velocity projection; with it, the limits closed
        (:func:`~diffcontact.systems.projection.closed_below`), those the velocity
        projection acts on. A limit resting at gap 0 (a rope locked at a bending limit)
        otherwise entered the impulse or not by rounding, and the two sequences of
        projections differ by far more than rounding (a state alone and inside a batch
        then parted after 40 steps)."""
        return closed_below(dtype) if iterations and self.velocity_projection else 0.0

    def _projection_iterations(
        self, iterations: int | None, name: str = "position_projection"
    ) -> int:
        if iterations is None:
            return self.position_projection
        if (
            isinstance(iterations, bool)
            or not isinstance(iterations, int)
            or not 0 <= iterations <= MAX_PROJECTION_ITERATIONS
        ):
            raise ValueError(
                f"{name} must be an integer in [0, {MAX_PROJECTION_ITERATIONS}] "
                f"(as in a config), got {iterations!r}"
            )
        return iterations

    def _project(
        self,
        res: ContactResult,
        ctx: _Context,
        iterations: int,
        settings: SolverSettings | None = None,
        read_free: ReadFree | None = None,
    ) -> Tensor:
        """``res.z`` with its positions projected (``iterations`` Gauss-Newton steps) and,
        with ``velocity_projection``, its velocities onto the limits closed there
        (:func:`~diffcontact.systems.projection.project_state`; ``read_free``: without
        reading the device, :class:`~diffcontact.systems.projection.ReadFree`)."""
        if iterations == 0 or res.batch_index.shape[0] == 0:
            return res.z
        return self._project_state(
            res.z, ctx, iterations, settings, self.velocity_projection, res.gaps, read_free
        )

    def _project_state(
        self,
        z: Tensor,
        ctx: _Context,
        iterations: int,
        settings: SolverSettings | None,
        velocities: bool,
        gaps: Tensor | None = None,
        read_free: ReadFree | None = None,
    ) -> Tensor:
        """``z: (N, 2, P, dim)`` with its positions projected, and its velocities where
        ``velocities`` (``gaps``: at ``z``'s positions, if known)."""
        x, v = z[..., 0, :, :], z[..., 1, :, :]
        # the projection's own function: the public ones check their arguments, reading
        # the device (the states here are checked at the system's boundary, and a rollout
        # goes on after an overflow)
        args = (ctx.geometry, ctx.M_inv, iterations)
        kwargs = {
            "constraints": ctx.constraints,
            "gaps": gaps,
            "settings": self._inner_settings(settings),
            "tol": None,
            "read_free": read_free,
        }
        if velocities:  # foreseeing the crossings of the inelastic limits within a step,
            # with Poisson's restitution on the closed limits that have it
            kwargs["dt"] = self.dt if self.foresee_crossings else None
            kwargs["foresee"] = ctx.cor == 0
            bounce = ctx.has_restitution()
            kwargs["restitution"] = ctx.cor if bounce else None
            x_p, v = _project(x, v, *args, **kwargs)
            if bounce:  # a lift out of a contact paid by the motion along it
                v = _lift_within_energy(self, ctx, x, x_p, v)
            x = x_p
        else:
            x_p = _project(x, None, *args, **kwargs)[0]
            if ctx.constraints is not None and ctx.constraints.num_equations > 0:
                # the velocities tangent to the constraints at the projected positions
                M_inv = ctx.M_inv
                if self._point_masses:
                    M_inv = M_inv.diagonal(dim1=-2, dim2=-1)
                v = keep_constraint_rates(
                    x, x_p, v, ctx.constraints, M_inv, diagonal=self._point_masses
                )
            if ctx.has_restitution():
                v = _lift_within_energy(self, ctx, x, x_p, v)
            x = x_p
        return torch.stack([x, v], dim=-3)

    def _read_free_projection(self, device: torch.device, iterations: int) -> ReadFree | None:
        """A :class:`~diffcontact.systems.projection.ReadFree` for one rollout (``None``
        without the projection): padded to the rows this system remembers."""
        if not iterations:
            return None
        needed = torch.zeros((), dtype=torch.long, device=device)
        rows = min(self._projection_rows, self._projection_rows_all())
        return ReadFree(rows, needed, self._point_masses, self._two_sided)

    def _projection_rows_all(self) -> int:
        """Rows of a projection problem with every limit in it (each side of a two-sided one)."""
        return self.n_contacts * (2 if self._two_sided else 1)

    def _grow_projection_rows(self, read_free: ReadFree | None, needed: int | None = None) -> bool:
        """After a rollout whose projection needed more rows than ``read_free`` padded to
        (``needed``, or one read of ``read_free.needed``): remember half as many more,
        rounded up to a multiple of 8, for this system's next rollouts. Whether it grew."""
        if read_free is None:
            return False
        needed = int(read_free.needed) if needed is None else needed
        if needed <= read_free.rows:
            return False
        grown = max(_grown(needed), self._projection_rows)
        self._projection_rows = min(self._projection_rows_all(), grown)
        return True

    def _grow_contact_padding(self, most: Tensor | int | None, padded: int | None) -> bool:
        """After a padded rollout in which a state had ``most`` (an int, or ``()`` on the
        device: one read) active contacts, more than the ``padded`` it was sent with:
        remember half as many more, rounded up to a multiple of 8, up to every candidate,
        for this system's next rollouts. Whether it grew."""
        if most is None or padded is None:
            return False
        needed = int(most)
        if needed <= padded:
            return False
        grown = max(_grown(needed), self._contact_padding or 0)
        self._contact_padding = min(len(self.contact_names), grown)
        return True

    def project_positions(
        self,
        z: Tensor,
        *,
        params: PhysicalParams | None = None,
        iterations: int | None = None,
        solver_settings: SolverSettings | None = None,
        velocities: bool | None = None,
    ) -> Tensor:
        """Project the positions of ``z`` onto the admissible set of its violated candidates.

        The states with a candidate gap < 0 get the positions nearest in the mass
        metric with every such gap >= 0 and the equality constraints' values kept
        (:mod:`diffcontact.systems.projection`), and then their velocities the smallest
        change in the mass metric that stops them from approaching the limits closed at
        the new positions, or crossing within the next step the inelastic ones still
        open there (with ``foresee_crossings``; an inelastic impulse on those limits, and
        Poisson's restitution on the closed ones with ``cor`` > 0 that approach; unless
        ``velocities`` is false, default the config's ``velocity_projection``).
        What :meth:`step` and :meth:`simulate` do after the impulse when
        ``position_projection > 0``.
        Differentiable (the active set aside).

        Args:
            z: ``(N, 2, P, dim)``.
            params: physical parameters (default: the system's own; the masses matter).
            iterations: Gauss-Newton iterations (default: the config's
                ``position_projection``, or 3 where that is 0).
            solver_settings: :class:`~diffcontact.contact.SolverSettings` of the cone QP.
            velocities: project the velocities too (default: the config's
                ``velocity_projection``, as a step does).

        Returns:
            ``(N, 2, P, dim)``.

        Warns:
            RuntimeWarning: where a state still violates a candidate after the iterations
                (a state far from the admissible set; more iterations may help).
        """
        self._check_state(z, "z")
        if iterations is None:
            iterations = self.position_projection or 3
        iterations = self._projection_iterations(iterations, "iterations")
        if velocities is None:
            velocities = self.velocity_projection
        if not isinstance(velocities, bool):
            raise ValueError(f"velocities must be True, False or None, got {velocities!r}")
        ctx = self._context(z, params, z.shape[0])
        out = self._project_state(z, ctx, iterations, solver_settings, velocities)
        if iterations > 0:  # a state the iterations did not bring to its limits: said
            warn_unconverged(ctx.geometry, out[..., 0, :, :], iterations)
        return out

    def integrate(
        self, z: Tensor, *, params: PhysicalParams | None = None, dynamics: str | None = None
    ) -> Tensor:
        """One RK4 step of the smooth constrained dynamics, no contacts.

        Args:
            z: ``(N, 2, P, dim)``.
            params: physical parameters (default: the system's own).
            dynamics: ``"lagrangian"`` or ``"hamiltonian"`` (default: the config's).

        Returns:
            ``(N, 2, P, dim)``.
        """
        self._check_state(z, "z")
        _, dynamics, _, params = self._options("CM", dynamics, None, params)
        ctx = self._context(z, params, z.shape[0])
        self._check_potential(ctx, z[:, 0])
        return self._integrate(z, ctx, dynamics)

    def resolve_contacts(
        self,
        z: Tensor,
        *,
        params: PhysicalParams | None = None,
        contact_model: Any = None,
        eps: float | Tensor | None = None,
        penetration_fraction: float | None = None,
        solver_settings: SolverSettings | None = None,
    ) -> ContactResult:
        """Collision detection and the contact model's impulse on the velocities of ``z``.

        Only states with an active candidate (gap < 0) go through the contact model.

        Args:
            z: ``(N, 2, P, dim)``.
            params: physical parameters (default: the system's own).
            contact_model: a registered name (:func:`~diffcontact.contact.contact_models`)
                or a :class:`~diffcontact.contact.ContactModel` object; ``None``: the
                system's :attr:`contact_model` (``"CM"`` unless set).
            eps: shorthand for ``params.replace(eps=eps)`` (CMr's regulariser).
            penetration_fraction: share of the depth removed per step by the
                compensation target (default: the config's; 0 switches it off).
            solver_settings: :class:`~diffcontact.contact.SolverSettings` of the cone QP.

        Returns:
            A :class:`ContactResult` (positions unchanged).
        """
        self._check_state(z, "z")
        model, _, fraction, params = self._options(
            contact_model, None, penetration_fraction, params, eps
        )
        ctx = self._context(z, params, z.shape[0])
        return self._resolve(z, ctx, model, fraction, solver_settings, dense_rows=True)

    def step(
        self,
        z: Tensor,
        *,
        params: PhysicalParams | None = None,
        contact_model: Any = None,
        eps: float | Tensor | None = None,
        dynamics: str | None = None,
        penetration_fraction: float | None = None,
        solver_settings: SolverSettings | None = None,
        position_projection: int | None = None,
    ) -> Tensor:
        """One full step: :meth:`integrate`, :meth:`resolve_contacts`, then (with
        ``position_projection > 0``, default the config's) :meth:`project_positions`.
        ``(N, 2, P, dim)``. With the velocities' projection on (``velocity_projection``),
        the impulse also treats candidates closed within
        :data:`~diffcontact.systems.projection.CLOSED` as active, which
        :meth:`resolve_contacts` does not (:meth:`_contact_margin`)."""
        self._check_state(z, "z")
        model, dynamics, fraction, params = self._options(
            contact_model, dynamics, penetration_fraction, params, eps
        )
        iterations = self._projection_iterations(position_projection)
        if iterations:  # the projection removes violations; the target would pump energy
            fraction = 0.0
        ctx = self._context(z, params, z.shape[0])
        self._check_potential(ctx, z[:, 0])
        z1 = self._integrate(z, ctx, dynamics)
        margin = self._contact_margin(iterations, ctx.dtype)
        res = self._resolve(z1, ctx, model, fraction, solver_settings, margin=margin)
        return self._project(res, ctx, iterations, solver_settings)

    def simulate(
        self,
        z0: Tensor,
        steps: int | None = None,
        *,
        params: PhysicalParams | None = None,
        contact_model: Any = None,
        eps: float | Tensor | None = None,
        progress: bool = False,
        dynamics: str | None = None,
        penetration_fraction: float | None = None,
        check_overlap: bool = True,
        solver_settings: SolverSettings | None = None,
        on_tunnelling: str = "warn",
        position_projection: int | None = None,
        threads: int | str | None = "auto",
        cuda_graph: bool | str = "auto",
        penetration_gradient: bool = True,
    ) -> Tensor:
        """Roll out trajectories from initial states: a pure function of ``z0`` and ``params``.

        Args:
            z0: ``(N, 2, P, dim)`` initial states (float64 for ground truth;
                the computation follows its dtype and device).
            steps: number of steps (default :attr:`default_steps`, so that the
                trajectory holds ``horizon / dt`` states).
            params: :class:`~diffcontact.systems.PhysicalParams` (default:
                :meth:`parameters`, the system's own); fields may carry a
                leading dimension ``N`` (one set per trajectory). Differentiable
                with respect to every tensor in it. Where the trajectory depends on
                none of the tensors that require a gradient (``mu`` of a rollout
                without a contact, ``z0`` not requiring one), it still carries a graph
                and they get a zero gradient; a tensor it does not depend on beside
                others it does gets none (``grad`` stays ``None``, torch's rule).
            contact_model: a registered name (``"CM"``, ``"CMr"``, see
                :func:`~diffcontact.contact.contact_models`) or a
                :class:`~diffcontact.contact.ContactModel` object; ``None``: the
                system's :attr:`contact_model` (``"CM"`` unless set, e.g. by a learned
                model's ``as_system()``).
            eps: shorthand for ``params.replace(eps=eps)`` (CMr's regulariser).
            progress: show a progress bar over the steps.
            dynamics: ``"lagrangian"`` (S.2) or ``"hamiltonian"`` (S.4-S.7);
                default the config's.
            penetration_fraction: override of the config's compensation fraction.
            check_overlap: reject initial states with a gap < 0.
            solver_settings: :class:`~diffcontact.contact.SolverSettings` of the cone QP.
            on_tunnelling: what to do when a body ends up deeper inside another body
                or a wall than :data:`TUNNELLING_FRACTION` (1.0) of the smaller radius
                at any state of the trajectory (a step too large for the speeds, so a
                collision was missed or half-resolved): ``"warn"`` (one
                :class:`TunnellingWarning`, a ``RuntimeWarning``, per call naming the
                states), ``"raise"``
                (``ValueError``) or ``"ignore"``. Checked once, after the last step.
                Contacts between bodies without a radius (the rope's limits) are not
                checked.
            position_projection: override of the config's ``position_projection``:
                Gauss-Newton iterations of the position-level projection onto the
                admissible set after each step (:meth:`project_positions`); 0: off.
            threads: torch's CPU threads during the rollout (put back afterwards):
                ``"auto"`` (default) times the steps and runs them on one thread or
                on all available cores, whichever is faster now (several threads
                are far slower than one on a CPU another process is using; a
                rollout of fewer than 24 steps, or one inside a training step or a
                planning iteration, leaves the threads alone;
                :func:`diffcontact.threads.thread_scope`); an integer fixes the
                count; ``None`` leaves torch's setting alone. Results do not depend
                on it beyond the last bits of torch's parallel reductions.
            cuda_graph: on a CUDA device, capture one step in a CUDA graph and replay
                it (the step's hundreds of small kernels launched at once; the step
                then runs every state through the contact solve, padded, so that its
                shapes do not depend on the data; the device is read a few times per
                call, never inside a step; the position projection, if on, runs all
                its iterations on every state with padded rows,
                :class:`~diffcontact.systems.projection.ReadFree`). ``"auto"``
                (default): where the states are on CUDA, the cone-QP backend is Warp,
                the rollout has at least
                :data:`~diffcontact.systems.rollout.GRAPH_MIN_STEPS` steps, the position
                projection (if on) needs at most
                :data:`~diffcontact.systems.rollout.GRAPH_MAX_ROWS` rows per state, of
                a problem of at most
                :data:`~diffcontact.systems.rollout.GRAPH_MAX_LIMIT_ROWS` (long ropes go
                step by step, where the projection selects what it needs) and
                nothing in it requires a gradient, else step by step (a capture that
                fails warns and goes step by step); ``True``: insist (``ValueError`` where it
                cannot); ``False``: never. Results equal the step-by-step ones to
                rounding (with the projection, to its tolerance). A failed solve or a
                non-finite state reruns the rollout step by step, which raises the
                usual error naming the states.
            penetration_gradient: differentiate the penetration compensation target
                (``fraction * depth / dt`` mapped through ``J_C``), so that gradients are
                the rollout's exact derivatives (default). ``False``: the target is a
                constant of the gradient, as in the paper (appendix G: "the gradients of
                v_C^* are not required for learning"); learned models train that way
                (:class:`~diffcontact.learning.LearnedModel`'s ``penetration_gradient``).

        Returns:
            ``(N, steps + 1, 2, P, dim)`` with ``traj[:, 0] == z0``; differentiable with
            respect to ``z0`` and every tensor in ``params``.

        Raises:
            ValueError: bad shape, NaN, overlapping bodies in ``z0`` (a gap below 0;
                below float64, below ``-sqrt(eps)``: rounding), bad parameters or
                options, an unknown contact model; NaN or infinite states during the
                rollout (named, with the likely cause); tunnelling with
                ``on_tunnelling="raise"``.
            ConeQPError: a contact problem could not be solved; the message names
                the step, the states (their speeds and penetration) and the likely
                cause (a blow-up: dt too large; or an ill-conditioned problem).
        """
        if on_tunnelling not in ON_TUNNELLING:
            raise ValueError(f"on_tunnelling must be one of {ON_TUNNELLING}, got {on_tunnelling!r}")
        self._inner_settings(solver_settings)  # a SolverSettings (a dict: one clear error)
        self._check_state(z0, "z0")
        if steps is None:
            steps = self.default_steps
        given, steps = steps, _integer(steps)  # numpy integers too
        if steps is None or steps < 0:
            raise ValueError(f"steps must be a non-negative integer, got {given!r}")
        if too_large := rollout_size_error(z0.shape[0], steps, self.state_shape, z0.itemsize):
            raise ValueError(f"simulate {self.name}: {too_large}")
        model, dynamics, fraction, params = self._options(
            contact_model, dynamics, penetration_fraction, params, eps
        )
        iterations = self._projection_iterations(position_projection)
        if iterations:  # the projection removes violations; the target would pump energy
            fraction = 0.0
        ctx = self._context(z0, params, z0.shape[0])
        self._check_potential(ctx, z0[:, 0])
        for name, flag in (("check_overlap", check_overlap), ("progress", progress)):
            if not isinstance(flag, bool):
                raise ValueError(f"{name} must be True or False, got {flag!r}")
        if check_overlap:
            self._check_no_overlap(z0, "z0")
        # the gaps of each state, for the tunnelling check: the contact resolution's own
        # (a step's positions are final there unless the position projection moves them)
        keep_gaps = not iterations and on_tunnelling != "ignore"
        if not isinstance(penetration_gradient, bool):
            raise ValueError(
                f"penetration_gradient must be True or False, got {penetration_gradient!r}"
            )
        options = RolloutOptions(
            model, dynamics, fraction, iterations, solver_settings, penetration_gradient
        )
        run = Rollout(self, ctx, z0, steps, options, keep_gaps, progress, threads)
        result = run.graphed(strict=cuda_graph is True) if run.graph_wanted(cuda_graph) else None
        self._last_rollout_graphed = result is not None
        if result is None:
            result = run.eager(defer=True)
        traj, gaps, pending = result
        # one read of the device per call for every check (not per step): the deferred
        # ones of the rollout, finiteness, tunnelling
        check_tunnelling = on_tunnelling != "ignore"
        with torch.no_grad():
            no = torch.zeros((), dtype=torch.bool, device=z0.device)
            if check_tunnelling:
                gaps, bad = self._tunnelling(traj, gaps)
            drift = self._constraint_drift(traj)
            checks = [
                no if pending is None else pending,
                ~torch.isfinite(traj.detach()).all() | _blown_up(traj, z0).any(),
                bad.any() if check_tunnelling else no,
                no if drift is None else (drift > CONSTRAINT_DRIFT_TOL).any(),
            ]
            failed, nonfinite, tunnelled, drifted = torch.stack(checks).tolist()
        if failed:  # a deferred solver error or padding overflow: step by step, as it was
            run.grow_padding()  # (the next rollout's)
            traj, gaps, _ = run.eager(defer=False)
            with torch.no_grad():
                finite = torch.isfinite(traj.detach()).all() & ~_blown_up(traj, z0).any()
                nonfinite = not bool(finite)
                if check_tunnelling:
                    gaps, bad = self._tunnelling(traj, gaps)
                    tunnelled = bool(bad.any())
                drift = self._constraint_drift(traj)
                drifted = drift is not None and bool((drift > CONSTRAINT_DRIFT_TOL).any())
        if nonfinite:
            mass = self.mass if params is None else params.mass
            raise self._nonfinite_error(list(traj.unbind(1)), steps, z0, mass)
        if tunnelled:
            learned = getattr(model, "needs_contact_state", False)  # a learned contact model
            self._report_tunnelling(gaps, bad, traj.shape[0], on_tunnelling == "raise", learned)
        if drifted:
            self._report_drift(traj, drift)
        if torch.is_grad_enabled() and not traj.requires_grad:
            given = () if params is None else params.tensors().values()
            wanted = [t for t in (z0, *given) if t.requires_grad]
            if wanted:  # a gradient was asked for: zero, not autograd's "does not require grad"
                traj = _ZeroGradient.apply(traj, *wanted)
        return traj

    def _constraint_drift(self, traj: Tensor) -> Tensor | None:
        """``(N,)`` the largest relative residual of the equality constraints at the last
        state of ``traj`` (no read of the device), or ``None`` without constraints.

        Only the last state: nothing pulls positions back onto the constraints, so the
        drift accumulates, and one state costs a hundredth of a 100-step trajectory's
        states (``_report_drift`` reads them all where one has drifted)."""
        constraints = self.constraints
        if constraints is None or constraints.num_equations == 0:
            return None
        with torch.no_grad():
            x = traj[:, -1, 0].detach()
            return constraints.to(device=x.device, dtype=x.dtype).relative_residual(x).amax(-1)

    def _report_drift(self, traj: Tensor, drift: Tensor) -> None:
        """Warn once, naming the states whose constraints drifted (``drift`` of
        :meth:`_constraint_drift`; some did)."""
        rows = (drift > CONSTRAINT_DRIFT_TOL).nonzero().flatten().tolist()
        with torch.no_grad():
            x = traj[rows[:5], :, 0].detach()  # (n, T, P, dim)
            every = self.constraints.to(device=x.device, dtype=x.dtype).relative_residual(x)
            first = (every.amax(-1) > CONSTRAINT_DRIFT_TOL).to(torch.int8).argmax(-1)
        items = [
            f"state {r}: {float(drift[r]):.3g} at the last step (above {CONSTRAINT_DRIFT_TOL:g} "
            f"from step {int(first[i])})"
            for i, r in enumerate(rows[:5])
        ]
        more = "" if len(rows) <= 5 else f"; and {len(rows) - 5} more"
        warnings.warn(
            f"simulate {self.name}: the equality constraints (link lengths, pivots, rigid "
            f"bodies) drifted by more than {CONSTRAINT_DRIFT_TOL:g} relative in {len(rows)} of "
            f"{drift.shape[0]} trajectories: {'; '.join(items)}{more}. The step dt = "
            f"{self.dt} is too large for these motions (RK4's error goes into the "
            "constraints and the energy): use a smaller dt (a learned model: its potential "
            "may make the motion too fast)",
            ConstraintDriftWarning,
            stacklevel=3,
        )

    def _contact_sizes(self, like: Tensor) -> Tensor:
        """``(K,)`` the smaller radius of the bodies of each candidate (inf: none)."""
        sizes = []
        for edge in self._edges:
            if edge.kind != "contact":
                continue
            radii = [
                self._bodies[b].radius
                for b in edge.bodies
                if b != ENVIRONMENT and self._bodies[b].radius is not None
            ]
            sizes.append(min(radii) if radii else float("inf"))
        return torch.tensor(sizes, dtype=like.dtype, device=like.device)

    def _tunnelling(self, traj: Tensor, gaps: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """``(N, T, K)`` every candidate's gap along ``traj`` and whether it is deeper than
        :data:`TUNNELLING_FRACTION` of the smaller radius of its bodies (no read of the
        device). ``gaps``: ``(N, T, K)`` the gaps of ``traj``'s positions where the
        caller has them."""
        with torch.no_grad():
            if gaps is None:
                gaps = self.gaps(traj[..., 0, :, :].detach())  # (N, T, K)
            gaps = gaps.detach()
            return gaps, gaps < -TUNNELLING_FRACTION * self._contact_sizes(gaps)

    def _report_tunnelling(
        self, gaps: Tensor, bad: Tensor, n: int, raise_error: bool, learned: bool = False
    ) -> None:
        """Warn (or raise) once, naming the states that tunnelled (``gaps`` and ``bad`` of
        :meth:`_tunnelling`; some are). ``learned``: the contact model is a learned one
        (a contact network), which is then the likely cause rather than the step."""
        with torch.no_grad():
            depth = -gaps / self._contact_sizes(gaps)
            rows = bad.flatten(1).any(-1).nonzero().flatten().tolist()
            worst = depth.flatten(1).amax(-1)
            items = []
            for r in rows[:5]:
                t, k = divmod(int(depth[r].argmax()), depth.shape[-1])
                items.append(
                    f"state {r}: {self.contact_names[k]} by {float(worst[r]):.3g} radii at step {t}"
                )
        more = "" if len(rows) <= 5 else f"; and {len(rows) - 5} more"
        message = (
            f"simulate {self.name}: bodies tunnelled (penetration deeper than "
            f"{TUNNELLING_FRACTION} of the smaller radius) in {len(rows)} of {n} "
            f"trajectories: {'; '.join(items)}{more}. "
            + (
                "The learned contact model lets bodies pass through each other (it has not "
                "learned to stop them there)"
                if learned
                else f"The step dt = {self.dt} is too large for these speeds: use a smaller dt"
            )
            + TUNNELLING_HINT
        )
        if raise_error:
            raise ValueError(message)
        warnings.warn(message, TunnellingWarning, stacklevel=3)

    def _solver_failure_message(self, err: ConeQPError, z0: Tensor, z1: Tensor, at: int) -> str:
        """Which states' contact problems failed at step ``at``, and the likely cause."""
        rows = err.states
        if not rows:
            return f"simulate {self.name}: the contact solve failed at step {at}: {err}"
        with torch.no_grad():
            speed0 = z0.detach()[rows, 1].flatten(1).abs().amax(-1)
            speed = z1.detach()[rows, 1].flatten(1).abs().amax(-1)
            gaps = self.gaps(z1.detach()[rows, 0])
            depth = (-gaps / self._contact_sizes(gaps)).amax(-1)
        items = [
            f"state {r} (speed {float(s0):.3g} at step 0, {float(s):.3g} now; deepest "
            f"penetration {float(p):.3g} radii)"
            for r, s0, s, p in zip(rows[:5], speed0, speed, depth, strict=False)
        ]
        more = "" if len(rows) <= 5 else f" and {len(rows) - 5} more"
        from diffcontact.contact.lcp import LCPError

        status = getattr(err, "status", None)
        ray = isinstance(err, LCPError) and status is not None and bool(status.unbounded.any())
        if bool((speed > 1e3 * speed0.clamp_min(1e-12)).any()) or bool((depth > 1).any()):
            cause = (
                f"the motion blew up or bodies tunnelled: dt = {self.dt} is too large for these "
                "speeds or forces; use a smaller dt"
            )
        elif ray:
            cause = (
                "the contacts' Newton LCP has no solution (Lemke's method ended on a ray): "
                "Newton's restitution with a singular contact matrix, e.g. a body wedged "
                "between walls and another body, can ask for more than any impulse gives; "
                "more pivots do not help; the CM and Coulomb models resolve such states"
            )
        elif "fixed-point iterations" in str(err):  # the exact Coulomb model's
            cause = (
                "the exact Coulomb iteration did not converge: more iterations may "
                "(create_contact_model('Coulomb', max_iter=...)); with a singular contact "
                "matrix Coulomb's problem can also have no solution"
            )
        else:
            cause = (
                "the contact problem is too ill-conditioned for the solver (e.g. touching "
                "bodies whose masses differ by many orders of magnitude); solve it with "
                "solve_cone_qp(..., return_status=True) to inspect it"
            )
        return (
            f"simulate {self.name}: the contact solve failed at step {at} for {len(rows)} "
            f"of {z0.shape[0]} trajectories: {'; '.join(items)}{more}. Likely cause: {cause}. "
            f"Solver: {err}"
        )

    def _nonfinite_error(
        self, states: list[Tensor], at: int, z0: Tensor | None = None, mass: Tensor | None = None
    ) -> NonFiniteRolloutError:
        """Which trajectories became NaN or infinite (or, given ``z0``, blew up past
        :data:`BLOW_UP`), when, and the likely cause (``mass``: the masses simulated with,
        named when their spread or size leaves float64 no room)."""
        with torch.no_grad():
            traj = torch.stack([s.detach() for s in states], dim=1)
            bad = ~torch.isfinite(traj).flatten(2).all(-1)  # (N, T)
            if z0 is not None:
                bad = bad | _blown_up(traj, z0, per_state=True)
            rows = bad.any(-1).nonzero().flatten().tolist()
            first = bad.to(torch.int8).argmax(-1).tolist()
        if not rows:  # finite states whose contact problem overflowed (it said "0 of N")
            largest = float(traj.abs().amax()) if traj.numel() else 0.0
            return NonFiniteRolloutError(
                f"simulate {self.name}: the contact problem at step {at} holds NaN or "
                f"infinite values although the states are finite (largest |value| "
                f"{largest:.3g}): positions or velocities too large for float arithmetic; "
                "check the units and scale of z0",
                [],
            )
        where = ", ".join(f"state {r} at step {first[r]}" for r in rows[:8])
        more = "" if len(rows) <= 8 else f" and {len(rows) - 8} more"
        if self.constraints is not None:
            cause = (
                "the constraint system J_E M^-1 J_E^T became singular inside an RK4 step "
                "(the state left its constraint manifold)"
            )
        else:
            cause = "the motion blew up"
        advice = f"dt = {self.dt} may be too large for this system: try a smaller dt"
        extreme = _extreme_masses(mass)
        if extreme is not None:  # (masses of 1e300 had been told to try a smaller dt)
            advice = f"{extreme}; if they are right, dt = {self.dt} may be too large"
        message = (
            f"simulate {self.name}: NaN, infinite or blown-up values (beyond {BLOW_UP:g} "
            f"times the initial state's) in {len(rows)} of "
            f"{traj.shape[0]} trajectories ({where}{more}; step {at} was reached). Likely "
            f"cause: {cause}; {advice}"
        )
        return NonFiniteRolloutError(message, rows)


MASS_SPREAD = 1e12
"""Masses spread wider than this (largest over smallest), or beyond ``MASS_SPREAD**4`` /
below its inverse in size, are named by :class:`NonFiniteRolloutError` as the likely
cause rather than the step: float64 keeps 16 digits, and a rollout with masses 1e300 and
1 failed at dt = 0.01 and at 0.001 alike."""


def _extreme_masses(mass: Tensor | None) -> str | None:
    """Why ``mass`` may be what broke the arithmetic, or ``None`` (plausible masses)."""
    if mass is None or mass.numel() == 0:
        return None
    m = mass.detach().double().abs().flatten()
    low, high = float(m.min()), float(m.max())
    if low > 0 and high / low <= MASS_SPREAD and MASS_SPREAD**-4 <= low and high <= MASS_SPREAD**4:
        return None
    return (
        f"or the masses, from {low:.3g} to {high:.3g}: a spread or size float64 cannot "
        f"resolve (beyond {MASS_SPREAD:g} apart, or beyond {MASS_SPREAD**4:g} or below "
        f"{MASS_SPREAD**-4:g}); check their units"
    )


def _blown_up(traj: Tensor, z0: Tensor, per_state: bool = False) -> Tensor:
    """``(N,)`` (or with ``per_state`` ``(N, T)``) bool: where ``traj: (N, T, 2, P, dim)``
    holds a finite value beyond :data:`BLOW_UP` times the largest of ``z0: (N, 2, P, dim)``
    (at least 1): a blow-up that has not overflowed yet."""
    t = traj.detach().abs()
    scale = z0.detach().abs().flatten(1).amax(-1).clamp_min(1.0)  # (N,)
    largest = t.flatten(2).amax(-1) if per_state else t.flatten(1).amax(-1)
    limit = BLOW_UP * (scale[:, None] if per_state else scale)
    return torch.isfinite(largest) & (largest > limit)


def _lift_within_energy(system: System, ctx: Any, x: Tensor, x_p: Tensor, v_p: Tensor) -> Tensor:
    """The projected velocities ``v_p: (N, P, dim)`` with their motion along the
    projection's displacement ``u = x_p - x`` (with equality constraints, its part tangent
    to them at ``x_p`` in the mass metric, which keeps their rates) slowed so that the
    kinetic energy pays for the potential energy the displacement added, ``dU = U(x_p) -
    U(x) > 0``: the
    component ``(u^T M v / u^T M u) u`` scaled by ``sqrt(max(0, 1 - dU / T_u))``, ``T_u``
    its kinetic energy (a ball lifted by ``delta`` out of the ground keeps ``v^2 - 2 g
    delta``, the speed it would have reached the surface with). Where the potential did
    not rise, or the motion along ``u`` cannot pay (``T_u <= dU``: it stops), ``v_p`` as
    given for the rest. Used where contacts bounce (``cor`` > 0): an elastic ball dropped
    on the ground with the projection on gained energy at every bounce, and keeps it now
    (``tests/systems/test_velocity_projection.py``)."""
    M = ctx.per_state(ctx.M, v_p, 2, 0)
    u = x_p - x
    if ctx.constraints is not None and ctx.constraints.num_equations > 0:
        # the lift's direction tangent to the constraints at x_p (in the mass metric), so
        # that slowing the motion along it keeps the constraints' rates J_E v
        N, P, dim = u.shape
        J = ctx.constraints.jacobian(x_p)  # (N, E, D)
        B = _minv_rows(J, ctx.M_inv, P, dim, False).transpose(-1, -2)  # (N, D, E)
        flat = u.reshape(N, P * dim, 1)
        u = (flat - B @ spd_solve(J @ B, J @ flat)).reshape(N, P, dim)
    Mu = M @ u
    uMu, uMv = (u * Mu).sum((-2, -1)), (v_p * Mu).sum((-2, -1))
    dU = system._potential(x_p, ctx) - system._potential(x, ctx)
    uMu_safe = torch.where(uMu > 0, uMu, torch.ones_like(uMu))
    T_u = 0.5 * uMv * uMv / uMu_safe
    lifted = (dU > 0) & (uMu > 0) & (T_u > 0)
    T_safe = torch.where(lifted, T_u, torch.ones_like(T_u))
    keep = torch.where(lifted, (1 - dU / T_safe).clamp(0, 1).sqrt(), torch.ones_like(T_u))
    return v_p - ((1 - keep) * uMv / uMu_safe)[:, None, None] * u
