"""Validated system configurations (pydantic v2).

A config is a plain mapping (from YAML, JSON or Python) whose ``type`` key picks
one of five schemas: ``bouncing_masses``, ``bouncing_disks``,
``chain_pendulum``, ``gyroscope`` and ``rope``. Every schema forbids unknown
keys, and :func:`parse_config` turns any validation failure into a
``ValueError`` whose message names the offending key. ``docs/config.md`` lists
every key.

Per-contact coefficients (``mu``, ``cor``) are given as one number for all
contacts, a list in the contact numbering of ``docs/conventions.md`` (body
pairs ``i < j`` first, then body-wall pairs body-major; rope: bending limits,
then stretch limits), or a mapping from contact *groups* to a number or a
list, e.g. ``{pairs: [...], walls: 0.1}``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    TypeAdapter,
    ValidationError,
    model_validator,
)

__all__ = [
    "ALLOW_LARGE_ENV",
    "MAX_LENGTH",
    "MAX_NODES",
    "MAX_STATES",
    "MAX_STATE_BYTES",
    "SYSTEM_TYPES",
    "BouncingDisksConfig",
    "BouncingMassesConfig",
    "ChainPendulumConfig",
    "ContactGroups",
    "GyroscopeConfig",
    "RopeConfig",
    "SystemConfig",
    "large_allowed",
    "parse_config",
    "rollout_size_error",
    "state_bytes",
    "stored_config",
]

# strict: a number must be a number (YAML's "5" or true is an error, not 5.0 or 1.0);
# integers are accepted where a float is expected
Real = Annotated[float, Field(strict=True)]
PositiveFloat = Annotated[float, Field(gt=0, allow_inf_nan=False, strict=True)]
NonNegFloat = Annotated[float, Field(ge=0, allow_inf_nan=False, strict=True)]
Finite = Annotated[float, Field(allow_inf_nan=False, strict=True)]
Fraction = Annotated[float, Field(ge=0, le=1, allow_inf_nan=False, strict=True)]

MAX_LENGTH = 1e150
"""Largest length a config may give (``link_lengths``, ``rest_length``, ``radii``,
``rim_radius``, ``com_distance``): the systems square lengths (a link's constraint is
its squared length, a disk's default second moment ``r^2 / 4``), and the square of
1e300 is not a float64 (``load_system`` failed inside with "target must be finite")."""
Length = Annotated[float, Field(gt=0, le=MAX_LENGTH, allow_inf_nan=False, strict=True)]


def _ordered(value: Any) -> Any:
    """Refuse a set where a list belongs: pydantic reads one as a list in its iteration
    order (``{2.0, 1.0}`` gave masses ``[1.0, 2.0]``)."""
    if isinstance(value, (set, frozenset)):
        raise ValueError(f"a set has no order; give a list (got {value!r})")
    return value


_ORDERED = BeforeValidator(_ordered)
Line = Annotated[tuple[Finite, Finite, Finite], _ORDERED]
Plane = Annotated[tuple[Finite, Finite, Finite, Finite], _ORDERED]
Pair = Annotated[tuple[Finite, Finite], _ORDERED]


# A key that takes one number or a list (or, per contact, a mapping of groups) is
# validated as the one branch its input's type picks: a list or tuple as the list, a
# mapping as the groups, anything else as the number. A plain union would try every
# branch and report all their failures ("mass: Input should be greater than 0; mass:
# Input should be a valid list"); picked, an error names only what is wrong with the
# value given. The tags show in pydantic's error locations; _format_error drops them.
_NUMBER, _LIST, _GROUPS = "<number>", "<list>", "<groups>"


def _number_or_list(value: Any) -> str:
    """The branch of a number-or-list key that ``value`` is validated as (a set as the
    list, which refuses it as unordered)."""
    return _LIST if isinstance(value, (list, tuple, set, frozenset)) else _NUMBER


RealOrList = Annotated[
    Annotated[Real, Tag(_NUMBER)] | Annotated[list[Real], _ORDERED, Tag(_LIST)],
    Discriminator(_number_or_list),
]
"""One number or a list of numbers."""
PositiveOrList = Annotated[
    Annotated[PositiveFloat, Tag(_NUMBER)] | Annotated[list[PositiveFloat], _ORDERED, Tag(_LIST)],
    Discriminator(_number_or_list),
]
"""One positive finite number or a list of them."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ContactGroups(_Strict):
    """Per-contact values by group; each group is one number or one list.

    Groups: ``pairs`` (body-body, ``i < j`` lexicographic) and ``walls``
    (body-wall, body-major) for circle systems and the gyroscope;
    ``bending`` and ``stretch`` for the rope.
    """

    pairs: RealOrList | None = None
    walls: RealOrList | None = None
    bending: RealOrList | None = None
    stretch: RealOrList | None = None


def _per_contact(value: Any) -> str:
    """The branch of a per-contact key (``mu``, ``cor``) that ``value`` is validated as."""
    return _GROUPS if isinstance(value, (Mapping, ContactGroups)) else _number_or_list(value)


PerContact = Annotated[
    Annotated[Real, Tag(_NUMBER)]
    | Annotated[list[Real], _ORDERED, Tag(_LIST)]
    | Annotated[ContactGroups, Tag(_GROUPS)],
    Discriminator(_per_contact),
]
"""One number for all contacts, one per contact, or a mapping of groups to either."""


# --------------------------------------------------------------- initial conditions
class BallInitialConditions(_Strict):
    """Point masses: centres uniform in a box, velocities N(0, velocity_std^2)."""

    position_low: Pair = (0.0, 0.0)
    position_high: Pair = (1.0, 1.0)
    velocity_std: NonNegFloat = 1.0

    @model_validator(mode="after")
    def _box(self) -> BallInitialConditions:
        if not all(lo < hi for lo, hi in zip(self.position_low, self.position_high, strict=True)):
            raise ValueError(
                "position_low must be below position_high in every "
                f"coordinate; got {list(self.position_low)} and {list(self.position_high)}"
            )
        return self


class DiskInitialConditions(BallInitialConditions):
    """Disks: as point masses, plus angle U[0, 2 pi) and N(0, std^2) angular velocity."""

    velocity_std: NonNegFloat = 0.5
    angular_velocity_std: NonNegFloat = 0.5


class ChainInitialConditions(_Strict):
    """Absolute link angles from straight down, uniform; rates N(0, std^2)."""

    angle_low: Finite = 0.0
    angle_high: Finite = math.pi
    angular_velocity_std: NonNegFloat = 1.0

    @model_validator(mode="after")
    def _range(self) -> ChainInitialConditions:
        if not self.angle_low < self.angle_high:
            raise ValueError("angle_low must be below angle_high")
        return self


class GyroscopeInitialConditions(_Strict):
    """Z-X-Z Euler angles and their rates (see ``docs/config.md``)."""

    euler_low: Finite = -1.5
    euler_high: Finite = 1.5
    precession_rate_range: Pair = (-4.5, 4.5)
    nutation_rate_range: Pair = (-0.3, 0.3)
    spin_scale: NonNegFloat = 1.5
    spin_mean: Finite = 7.0
    spin_std: NonNegFloat = 1.0

    @model_validator(mode="after")
    def _ranges(self) -> GyroscopeInitialConditions:
        if not self.euler_low < self.euler_high:
            raise ValueError("euler_low must be below euler_high")
        for key in ("precession_rate_range", "nutation_rate_range"):
            lo, hi = getattr(self, key)
            if not lo < hi:
                raise ValueError(f"{key} must be [low, high] with low < high")
        return self


class RopeInitialConditions(_Strict):
    """First segment angle uniform, relative angles within the bending limit."""

    first_angle_low: Finite = 0.0
    first_angle_high: Finite = math.pi
    angular_velocity_std: NonNegFloat = 1.0

    @model_validator(mode="after")
    def _range(self) -> RopeInitialConditions:
        if not self.first_angle_low < self.first_angle_high:
            raise ValueError("first_angle_low must be below first_angle_high")
        return self


# ----------------------------------------------------------------------- sizes
MAX_STATES = 1_000_000
"""Most states per trajectory (``horizon / dt``) a config may ask for (built-in tasks: 100)."""
MAX_STATE_BYTES = 2**30
"""Most bytes of the dense matrices that resolving one state's contacts may need (1 GiB;
built-in tasks: at most 8.5 MiB, Rope-D400)."""
ALLOW_LARGE_ENV = "DIFFCONTACT_ALLOW_LARGE"
"""Set this environment variable to 1 to lift :data:`MAX_STATES` and :data:`MAX_STATE_BYTES`."""


def _bytes(n: float) -> str:
    for unit, size in (("PiB", 2**50), ("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{n:,.0f} bytes"


def large_allowed() -> bool:
    """Whether :data:`ALLOW_LARGE_ENV` lifts the size limits (:data:`MAX_STATES`, ...)."""
    return os.environ.get(ALLOW_LARGE_ENV, "").strip().lower() in ("1", "true", "yes")


def rollout_size_error(
    n: int,
    steps: int,
    state_shape: tuple[int, ...],
    itemsize: int = 8,
    names: tuple[str, str] = ("steps=", "n="),
) -> str | None:
    """Why a rollout of ``n`` trajectories of ``steps`` steps is refused, or ``None``:
    more than :data:`MAX_STATES` steps, or trajectories ``(n, steps + 1, *state_shape)``
    of ``itemsize`` bytes per value taking more than half the machine's memory (a typo
    such as ``steps=10**12`` would fill it before any error), unless :func:`large_allowed`.
    ``names``: how the message names ``steps`` and ``n`` (e.g. ``("--steps ", "--n ")``)."""
    if large_allowed():
        return None
    lift = f"set {ALLOW_LARGE_ENV}=1 to lift the limit"
    steps_name, n_name = names
    if steps > MAX_STATES:
        return f"{steps_name}{steps}: at most {MAX_STATES} ({lift})"
    size = n * (steps + 1) * math.prod(state_shape) * itemsize
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        return None
    if size > memory / 2:
        return (
            f"{n_name}{n} x {steps_name}{steps}: the trajectories would take {_bytes(size)}, "
            f"more than half of this machine's {_bytes(memory)} ({lift})"
        )
    return None


def state_bytes(n_points: int, dim: int, n_contacts: int) -> int:
    """Bytes of the dense matrices resolving one state's contacts needs, all contacts active.

    ``8 ((K d)^2 + K d D + D^2)`` with ``D = P d`` coordinates and ``K`` candidate
    contacts: the contact-space Delassus matrix ``J_C Mhat_inv J_C^T``, the contact
    Jacobian ``J_C`` and the constrained inverse inertia ``Mhat_inv``, in float64.
    """
    D, C = n_points * dim, n_contacts * dim
    return 8 * (C * C + C * D + D * D)


# ----------------------------------------------------------------------- systems
MAX_PROJECTION_ITERATIONS = 100
"""The most Gauss-Newton iterations of the position projection (``position_projection``)."""


class _SystemBase(_Strict):
    name: str | None = None
    description: str | None = None
    dt: PositiveFloat
    horizon: PositiveFloat
    gravity: NonNegFloat = 0.0
    mu: PerContact = 0.0
    cor: PerContact = 1.0
    penetration_fraction: Fraction = 0.125
    # the metric of the pseudo-inverse that lifts the penetration target to Cartesian
    # space where equality constraints exist: the constrained inverse inertia ("mass",
    # tangential targets stay zero), or appendix G's Euclidean one as written (S.24)
    penetration_metric: Literal["mass", "euclidean"] = "mass"
    # Gauss-Newton iterations of the position-level projection onto the admissible set of
    # the violated contacts after each step (systems/projection.py); 0 switches it off
    position_projection: Annotated[int, Field(ge=0, le=MAX_PROJECTION_ITERATIONS, strict=True)] = 0
    # with the position projection on: the velocities too, inelastically onto the limits
    # closed at the projected positions (which a step's impulse then treats as active);
    # false: the positions only, as before this key (the energy can then rise)
    velocity_projection: Annotated[bool, Field(strict=True)] = True
    # with the velocities projected: also onto the inelastic limits (cor 0) still open at
    # the projected positions that they would cross within the next step; false: the
    # closed limits only, as before this key (a rope at coarse steps can then gain energy)
    foresee_crossings: Annotated[bool, Field(strict=True)] = True
    dynamics: Literal["lagrangian", "hamiltonian"] = "lagrangian"
    # the fourth-order Runge-Kutta rule of the smooth dynamics: classic, or the 3/8 rule
    # (torchdiffeq's "rk4", used by the paper's released code)
    integrator: Literal["rk4", "rk4_38"] = "rk4"
    # how a learned model parameterises mu and e_P: one value shared by all contacts,
    # or one per candidate contact (paper-facts.md, "Homogeneous tasks")
    contact_parameters: Literal["shared", "per_contact"] = "shared"

    # subclasses describe their contacts ------------------------------------
    def contact_groups(self) -> list[tuple[str, int]]:
        """``(group, count)`` in numbering order."""
        raise NotImplementedError

    @property
    def n_contacts(self) -> int:
        """Number of candidate contacts K."""
        return sum(n for _, n in self.contact_groups())

    @property
    def n_states(self) -> int:
        """States per trajectory, ``horizon / dt``."""
        return round(self.horizon / self.dt)

    def points_and_dim(self) -> tuple[int, int]:
        """``(P, d)``: the points of the system's state and their dimension."""
        raise NotImplementedError

    def per_contact(self, key: str) -> list[float]:
        """``mu`` or ``cor`` expanded to one value per candidate contact."""
        return _expand(key, getattr(self, key), self.contact_groups())

    @model_validator(mode="after")
    def _common(self) -> _SystemBase:
        ratio = self.horizon / self.dt
        if not math.isfinite(ratio):  # dt = 1e-320, horizon = 1e300
            raise ValueError(
                f"horizon / dt must be a whole number of states >= 2; got horizon="
                f"{self.horizon}, dt={self.dt} (ratio {ratio:g})"
            )
        if abs(ratio - round(ratio)) > 1e-6 * max(1.0, ratio) or round(ratio) < 2:
            raise ValueError(
                f"horizon / dt must be a whole number of states >= 2; got horizon={self.horizon}, "
                f"dt={self.dt} (ratio {ratio:g})"
            )
        self._check_sizes()
        if not large_allowed():
            self._check_cost(round(ratio))
        if self.n_contacts < 1:
            raise ValueError("the system has no candidate contacts (add walls or bodies)")
        for key, low, high in (("mu", 0.0, math.inf), ("cor", 0.0, 1.0)):
            values = self.per_contact(key)
            for k, value in enumerate(values):
                if not (low <= value <= high) or not math.isfinite(value):
                    rng = "must be finite and >= 0" if key == "mu" else "must lie in [0, 1]"
                    raise ValueError(f"{key}: value {value} of contact {k} {rng}")
        return self

    def _check_sizes(self) -> None:
        pass

    def _check_cost(self, n_states: int) -> None:
        """Refuse sizes that would run for days or exhaust memory (with the estimate)."""
        P, d = self.points_and_dim()
        lift = f"set the environment variable {ALLOW_LARGE_ENV}=1 to allow it"
        if n_states > MAX_STATES:
            raise ValueError(
                f"horizon / dt = {n_states:,} states per trajectory (horizon={self.horizon:g}, "
                f"dt={self.dt:g}): simulating one trajectory takes {n_states - 1:,} steps and "
                f"storing it {_bytes(16.0 * n_states * P * d)}; the limit is {MAX_STATES:,} "
                f"states (is dt in seconds?); {lift}"
            )
        K = self.n_contacts
        need = state_bytes(P, d, K)
        if need > MAX_STATE_BYTES:
            raise ValueError(
                f"{P:,} points in {d}D ({P * d:,} coordinates) with {K:,} candidate contacts: "
                f"resolving one state's contacts needs dense matrices of about {_bytes(need)} "
                f"(float64 (K d)^2 + K d D + D^2), above the limit of "
                f"{_bytes(MAX_STATE_BYTES)} per state; {lift}"
            )


def _count(n: int, word: str) -> str:
    """``n`` and ``word``, plural unless ``n`` is 1 ("1 value", "2 values")."""
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


def _group(n: int, group: str) -> str:
    """``n`` contacts of ``group`` ("1 pair", "10 pairs", "9 bending")."""
    return f"{n} {group[:-1] if n == 1 and group in ('pairs', 'walls') else group}"


def _expand(key: str, value: PerContact, groups: list[tuple[str, int]]) -> list[float]:
    total = sum(n for _, n in groups)
    layout = ", ".join(_group(n, g) for g, n in groups)
    if isinstance(value, (int, float)):
        return [float(value)] * total
    if isinstance(value, list):
        if len(value) != total:
            raise ValueError(
                f"{key}: expected one number or {_count(total, 'value')} (one per contact: "
                f"{layout}), got a list of {len(value)}"
            )
        return [float(v) for v in value]
    names = [g for g, _ in groups]
    given = {g for g in ContactGroups.model_fields if getattr(value, g) is not None}
    unknown = given - set(names)
    if unknown:
        raise ValueError(
            f"{key}: this system has no contact group(s) {sorted(unknown)}; its groups are {names}"
        )
    out: list[float] = []
    for g, n in groups:
        v = getattr(value, g)
        if v is None:
            raise ValueError(f"{key}: missing group '{g}' ({n} contacts)")
        if isinstance(v, list):
            if len(v) != n:
                raise ValueError(
                    f"{key}.{g}: expected one number or {_count(n, 'value')}, "
                    f"got a list of {len(v)}"
                )
            out.extend(float(x) for x in v)
        else:
            out.extend([float(v)] * n)
    return out


def _check_lines(key: str, lines: list[tuple[float, ...]], n_normal: int) -> None:
    """A line or plane needs a non-zero normal, and an offset that stays finite once the
    normal is made a unit vector (the geometry divides by the normal's largest component
    first, so any finite non-zero normal can be normalised)."""
    for j, line in enumerate(lines):
        where = key if key == "wall" else f"{key}[{j}]"
        largest = max(abs(c) for c in line[:n_normal])
        if largest == 0:
            raise ValueError(f"{where}: the normal part of {list(line)} must be non-zero")
        scaled = [c / largest for c in line]
        offset = scaled[-1] / math.hypot(*scaled[:n_normal])
        if not math.isfinite(offset):
            raise ValueError(
                f"{where}: {list(line)} lies too far from the origin: its offset divided by "
                "the length of its normal part is not a finite number"
            )


class _CircleBodies(_SystemBase):
    masses: Annotated[list[PositiveFloat], _ORDERED] = Field(min_length=1)
    radii: Annotated[list[Length], _ORDERED] = Field(min_length=1)
    walls: Annotated[list[Line], _ORDERED] = Field(default_factory=list)

    @property
    def n_bodies(self) -> int:
        return len(self.masses)

    def contact_groups(self) -> list[tuple[str, int]]:
        B = len(self.masses)
        groups = []
        if B > 1:
            groups.append(("pairs", B * (B - 1) // 2))
        if self.walls:
            groups.append(("walls", B * len(self.walls)))
        return groups

    def _check_sizes(self) -> None:
        if len(self.radii) != len(self.masses):
            raise ValueError(
                f"radii: expected {_count(len(self.masses), 'value')} (one per mass), "
                f"got {len(self.radii)}"
            )
        _check_lines("walls", self.walls, 2)


class BouncingMassesConfig(_CircleBodies):
    """Point masses (circles that do not rotate) in 2D."""

    type: Literal["bouncing_masses"]
    initial_conditions: BallInitialConditions = Field(default_factory=BallInitialConditions)

    def points_and_dim(self) -> tuple[int, int]:
        return len(self.masses), 2


class BouncingDisksConfig(_CircleBodies):
    """Uniform rigid disks (3-point extended bodies) in 2D."""

    type: Literal["bouncing_disks"]
    second_moments: (
        Annotated[list[Annotated[tuple[PositiveFloat, PositiveFloat], _ORDERED]], _ORDERED] | None
    ) = None
    initial_conditions: DiskInitialConditions = Field(default_factory=DiskInitialConditions)

    def _check_sizes(self) -> None:
        super()._check_sizes()
        if self.second_moments is not None and len(self.second_moments) != len(self.masses):
            raise ValueError(
                f"second_moments: expected {_count(len(self.masses), 'pair')} (one per body), "
                f"got {len(self.second_moments)}"
            )

    def points_and_dim(self) -> tuple[int, int]:
        return 3 * len(self.masses), 2

    def body_second_moments(self) -> list[tuple[float, float]]:
        """Second moments per unit mass along the body axes (default r^2/4 each)."""
        if self.second_moments is not None:
            return [tuple(s) for s in self.second_moments]
        return [(r * r / 4, r * r / 4) for r in self.radii]


class ChainPendulumConfig(_SystemBase):
    """Planar chain pendulum with point masses at the joints and circular joints."""

    type: Literal["chain_pendulum"]
    masses: Annotated[list[PositiveFloat], _ORDERED] = Field(min_length=1)
    link_lengths: Annotated[list[Length], _ORDERED] = Field(min_length=1)
    radii: Annotated[list[Length], _ORDERED] = Field(min_length=1)
    walls: Annotated[list[Line], _ORDERED] = Field(
        default_factory=lambda: [(0.0, 1.0, 1.0)], min_length=1
    )
    pivot: Pair = (0.0, 0.0)
    initial_conditions: ChainInitialConditions = Field(default_factory=ChainInitialConditions)

    @property
    def n_bodies(self) -> int:
        return len(self.masses)

    def contact_groups(self) -> list[tuple[str, int]]:
        return [("walls", len(self.masses) * len(self.walls))]

    def points_and_dim(self) -> tuple[int, int]:
        return len(self.masses), 2

    def _check_sizes(self) -> None:
        n = len(self.masses)
        for key in ("link_lengths", "radii"):
            got = len(getattr(self, key))
            if got != n:
                raise ValueError(f"{key}: expected {_count(n, 'value')} (one per mass), got {got}")
        _check_lines("walls", self.walls, 2)


class GyroscopeConfig(_SystemBase):
    """A 3D rigid body on a ball joint at the origin with a disk rim and a wall plane."""

    type: Literal["gyroscope"]
    mass: PositiveFloat
    second_moments: Annotated[tuple[PositiveFloat, PositiveFloat, PositiveFloat], _ORDERED]
    com_distance: Length = 0.5
    rim_radius: Length = 0.3
    wall: Plane
    initial_conditions: GyroscopeInitialConditions = Field(
        default_factory=GyroscopeInitialConditions
    )

    def contact_groups(self) -> list[tuple[str, int]]:
        return [("walls", 1)]

    def points_and_dim(self) -> tuple[int, int]:
        return 4, 3

    def _check_sizes(self) -> None:
        _check_lines("wall", [self.wall], 3)


class RopeConfig(_SystemBase):
    """Point masses joined by springs to a fixed anchor, with bending and stretch limits."""

    type: Literal["rope"]
    n_points: int = Field(ge=2, strict=True)
    mass: PositiveOrList
    rest_length: Length
    stiffness: NonNegFloat
    max_angle: Annotated[float, Field(gt=0, le=math.pi, allow_inf_nan=False, strict=True)] = 0.2
    # > 0: at 0 a segment may collapse to a point, where its direction (and bending) is undefined
    min_ratio: PositiveFloat = 0.8
    max_ratio: PositiveFloat = 1.2
    anchor: Pair = (0.0, 0.0)
    cor: PerContact = 0.0
    # the limits hold only approximately at velocity level (docs/config.md, rope)
    position_projection: Annotated[int, Field(ge=0, le=MAX_PROJECTION_ITERATIONS, strict=True)] = 10
    initial_conditions: RopeInitialConditions = Field(default_factory=RopeInitialConditions)

    def contact_groups(self) -> list[tuple[str, int]]:
        return [("bending", self.n_points - 1), ("stretch", self.n_points)]

    def points_and_dim(self) -> tuple[int, int]:
        return self.n_points, 2

    def point_masses(self) -> list[float]:
        if isinstance(self.mass, list):
            return list(self.mass)
        return [float(self.mass)] * self.n_points

    def _check_sizes(self) -> None:
        if isinstance(self.mass, list) and len(self.mass) != self.n_points:
            raise ValueError(
                f"mass: expected one number or {_count(self.n_points, 'value')} (one per point), "
                f"got {len(self.mass)}"
            )
        if not self.min_ratio < 1.0 < self.max_ratio:
            raise ValueError(
                f"need min_ratio < 1 < max_ratio; got min_ratio={self.min_ratio}, "
                f"max_ratio={self.max_ratio}"
            )
        if self.position_projection and self.velocity_projection:
            self._check_bands()

    def _check_bands(self) -> None:
        """The velocities' projection treats a limit within an absolute gap
        (``projection.CLOSED``) as closed: a band narrower than 100 times that would be
        held closed over much of its width (a rope of rest length 1e-6 froze its
        segments), so such a rope is refused with the remedy."""
        from diffcontact.systems.projection import CLOSED

        least = 100 * CLOSED
        bands = (
            (
                "stretch band (max_ratio - min_ratio) * rest_length",
                (self.max_ratio - self.min_ratio) * self.rest_length,
                "express lengths in smaller units (millimetres instead of metres, say)",
            ),
            ("bending band 2 * max_angle", 2 * self.max_angle, "widen max_angle"),
        )
        for name, width, remedy in bands:
            if width < least:
                raise ValueError(
                    f"the rope's {name} = {width:.3g} is narrower than {least:.3g}: the "
                    f"velocities' projection treats a limit within {CLOSED:g} of its gap as "
                    "closed and would hold most of the band closed (the segments frozen); "
                    f"{remedy}, or set velocity_projection: false"
                )


SystemConfig = Annotated[
    BouncingMassesConfig | BouncingDisksConfig | ChainPendulumConfig | GyroscopeConfig | RopeConfig,
    Field(discriminator="type"),
]
"""Any system config, discriminated by its ``type`` key."""

SYSTEM_TYPES = ("bouncing_masses", "bouncing_disks", "chain_pendulum", "gyroscope", "rope")

_ADAPTER: TypeAdapter = TypeAdapter(SystemConfig)


# the union branches' tags in error locations (RealOrList, PositiveOrList, PerContact),
# pydantic's wrong-type errors, and its range errors of a number (shown with the number)
_BRANCHES = {_NUMBER, _LIST, _GROUPS}
_TYPE_ERRORS = {
    "float_type",
    "int_type",
    "list_type",
    "tuple_type",
    "string_type",
    "model_type",
    "dict_type",
}
_RANGE_ERRORS = {
    "greater_than",
    "greater_than_equal",
    "less_than",
    "less_than_equal",
    "finite_number",
}


# pydantic's errors where a number belongs (a string or a boolean given there gets the hint)
_NUMBER_ERRORS = {"float_type", "int_type"}
_NOT_FROM_STRINGS = "numbers are not read from strings or booleans"
MAX_ERROR_LINES = 10
"""The most problems one error message lists; the rest are counted ("and 19,990 more errors")."""


def _format_error(err: ValidationError, source: str) -> str:
    lines: list[str] = []
    seen: set[str] = set()  # (a set: a config with 200,000 bad entries took minutes)
    typed: set[str] = set()
    more = 0
    for e in err.errors(include_url=False):
        loc = [str(p) for p in e["loc"]]
        # drop the system type (the config's discriminator) and the union branches' tags
        if loc and loc[0] in SYSTEM_TYPES:
            loc = loc[1:]
        loc = [p for p in loc if p not in _BRANCHES]
        msg = e["msg"]
        if msg.startswith("Value error, "):
            msg = msg[len("Value error, ") :]
        if e["type"] == "missing" and len(loc) > 1 and loc[-1].isdigit():
            # an item of a fixed-length list (a wall [a, b, c]): say how many were given
            msg = f"too few numbers: got {loc[-1]}"
            loc = loc[:-1]
            if ".".join(loc) in typed:  # one message per list, not one per missing item
                continue
            typed.add(".".join(loc))
        elif e["type"] == "missing":
            msg = "missing key (required)"
        ctx = e.get("ctx", {})
        if e["type"] == "too_long" and {"max_length", "actual_length"} <= set(ctx):
            msg = f"too many values: at most {ctx['max_length']}, got {ctx['actual_length']}"
        if e["type"] == "extra_forbidden":
            msg = "unknown key (not part of the schema; see docs/config.md)"
        if e["type"] == "union_tag_invalid":
            tag = e.get("ctx", {}).get("tag", "?")
            msg = f"unknown system type {tag!r}; expected one of {list(SYSTEM_TYPES)}"
        if e["type"] == "union_tag_not_found":
            msg = f"missing key 'type' (one of {list(SYSTEM_TYPES)})"
        key = ".".join(loc)
        if e["type"] in _TYPE_ERRORS:
            if key in typed:  # one wrong-type message per key
                continue
            typed.add(key)
            got = e["input"]
            if e["type"] in _NUMBER_ERRORS and isinstance(got, (str, bool)):
                msg = f"{msg} (got {got!r}; {_NOT_FROM_STRINGS})"
            else:
                msg = f"{msg} (got {got!r})"
        elif e["type"] in _RANGE_ERRORS:
            bound = next((v for k, v in ctx.items() if k in ("gt", "ge", "lt", "le")), None)
            if isinstance(bound, float) and abs(bound) >= 1e16:  # 1e150, not 1000...0
                msg = f"{msg.rsplit(' ', 1)[0]} {bound:g}"
            msg = f"{msg} (got {e['input']!r})"
        line = f"{key}: {msg}" if key else msg
        if line in seen:
            continue
        seen.add(line)
        if len(lines) < MAX_ERROR_LINES:
            lines.append(line)
        else:
            more += 1
    if more:
        lines.append(f"and {more:,} more error{'s' if more > 1 else ''}")
    return f"invalid system config{source}:\n  " + "\n  ".join(lines)


MAX_DEPTH = 16
"""Deepest nesting of mappings and lists a config may have (the schema needs 4)."""
MAX_NODES = 1_000_000
"""Most values (numbers, strings, lists, mappings and their keys, each alias of a YAML
file counted as what it stands for) a config may hold. The largest within the size
limits hold tens of thousands; YAML aliases of aliases made a 600-byte file stand for
10^8 values, which took minutes to check before this limit."""


def _shape(data: Any, max_depth: int, max_nodes: int) -> tuple[int, int]:
    """``(depth, nodes)``: the nesting depth of dicts and lists in ``data`` and the number
    of values (shared ones counted each time they appear); iterative, it stops counting
    once either passes its limit."""
    deepest, nodes, todo = 0, 0, [(data, 0)]
    while todo:
        item, level = todo.pop()
        nodes += 1
        if nodes > max_nodes:
            break
        if isinstance(item, dict):
            nodes += len(item)  # the keys
            todo.extend((v, level + 1) for v in item.values())
        elif isinstance(item, (list, tuple, set, frozenset)):
            todo.extend((v, level + 1) for v in item)
        else:
            continue
        deepest = max(deepest, level + 1)
        if deepest > max_depth:
            break
    return deepest, nodes


STORED_BEFORE: dict[str, Any] = {
    "penetration_metric": "euclidean",
    "position_projection": 0,
    "velocity_projection": False,
    "foresee_crossings": False,
}
"""Keys added to the configs with a default unlike the behaviour before them: the value
that a stored config without the key stands for."""


def stored_config(data: Any) -> Any:
    """A config as this library stored it (a dataset's metadata, a model file), ready for
    :func:`parse_config`. Stored configs are complete dumps; one without a key of
    :data:`STORED_BEFORE` was written before that key existed and keeps the behaviour it
    was made with: ``penetration_metric`` appendix G's Euclidean target (the default
    became ``mass``), ``position_projection`` 0 (the rope's default became 10),
    ``velocity_projection`` off (the default became on), ``foresee_crossings`` off (the
    default became on)."""
    if isinstance(data, Mapping) and "type" in data:
        missing = {k: v for k, v in STORED_BEFORE.items() if k not in data}
        if missing:
            return {**data, **missing}
    return data


def parse_config(
    data: Any, source: str = ""
) -> (
    BouncingMassesConfig
    | BouncingDisksConfig
    | (ChainPendulumConfig | GyroscopeConfig | RopeConfig)
):
    """Validate a config mapping.

    Args:
        data: a mapping (already parsed YAML/JSON) or a config model instance.
        source: where it came from, for error messages (e.g. ``" in BP5.yaml"``).

    Returns:
        The validated, immutable config model.

    Raises:
        ValueError: naming every bad or unknown key.
    """
    if isinstance(data, _SystemBase):
        return data
    if not isinstance(data, dict):
        raise ValueError(
            f"invalid system config{source}: expected a mapping of keys, got {type(data).__name__}"
        )
    depth, nodes = _shape(data, MAX_DEPTH, MAX_NODES)
    if depth > MAX_DEPTH:
        raise ValueError(
            f"invalid system config{source}: nested more than {MAX_DEPTH} levels deep "
            "(a config is a mapping of numbers, lists and small mappings)"
        )
    if nodes > MAX_NODES:
        raise ValueError(
            f"invalid system config{source}: more than {MAX_NODES:,} values (numbers, "
            "strings, lists and keys, a shared or aliased value counted where it appears; "
            "the largest configs within the size limits hold tens of thousands)"
        )
    try:
        return _ADAPTER.validate_python(data)
    except ValidationError as err:
        raise ValueError(_format_error(err, source)) from None
