"""What to draw for a system: a small, explicit scene description.

A :class:`Scene` names which state points carry which drawable element, so the
drawing code never needs to know about systems. :func:`scene_from_config`
(and :func:`scene_from_system`) builds one from a task configuration.

Point indices refer to the ``P`` axis of a state ``z: (..., 2, P, dim)``; see
``docs/conventions.md`` for how bodies map to points (a point mass is one
point, a 2D disk three ``[centre, centre + e_x, centre + e_y]``, a 3D rigid
body four ``[com, com + e1, com + e2, com + e3]``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any, Literal

__all__ = [
    "Chain",
    "Circle",
    "Disk3D",
    "Scene",
    "scene_from_config",
    "scene_from_system",
]


@dataclasses.dataclass(frozen=True)
class Circle:
    """A 2D circular body of ``radius`` centred on state point ``point``.

    ``oriented`` bodies (rigid disks) also get a line from the centre towards
    the body x axis, i.e. towards point ``point + 1``.
    """

    point: int
    radius: float
    oriented: bool = False


@dataclasses.dataclass(frozen=True)
class Chain:
    """A polyline through state points, optionally starting at a fixed anchor.

    ``style="links"`` draws rigid pendulum links; ``style="rope"`` a thin rope
    with a marker on every point.
    """

    points: tuple[int, ...]
    anchor: tuple[float, ...] | None = None
    style: Literal["links", "rope"] = "links"


@dataclasses.dataclass(frozen=True)
class Disk3D:
    """A 3D rigid disk: 4 state points from ``first_point`` (com, com+e1, com+e2, com+e3).

    The rim of ``radius`` lies in the plane through the com normal to the
    symmetry axis ``e3``. If ``pivot`` is given, a rod is drawn from it to the
    com along the symmetry axis.
    """

    first_point: int
    radius: float
    pivot: tuple[float, float, float] | None = None


@dataclasses.dataclass(frozen=True)
class Scene:
    """Everything :func:`diffcontact.viz.animate` draws, besides the trajectory.

    Attributes:
        dim: spatial dimension of the states (2 or 3).
        circles: 2D circular bodies.
        chains: 2D polylines (pendulum links, ropes).
        walls: 2D lines ``(a, b, c)``: ``a x + b y + c = 0``, allowed side ``> 0``
            (the forbidden side is shaded).
        disks3d: 3D rigid disks (gyroscope).
        planes: 3D planes ``(a, b, c, e)``: ``a x + b y + c z + e = 0``.
        pivots: fixed points drawn as small black markers.
        targets: 2D points marked with a cross (a plan's target, e.g. ``diffcontact
            billiards``).
        target_x: 2D vertical lines ``x = value``, dotted (``diffcontact throw``'s target).
        dots: state points drawn as plain dots (fallback for unknown systems).
        title: shown above the animation.
        limits: optional fixed axis limits ``((xmin, xmax), (ymin, ymax)[, (zmin, zmax)])``;
            by default they are fitted to the data and the walls.
        view: 3D camera ``(elevation, azimuth)`` in degrees (orthographic). By
            default the camera looks along the first plane, so that the plane
            is seen edge-on at the left and distances to it are true on screen.
        n_points: the number of state points ``P`` of the system the scene draws
            (:func:`scene_from_config` sets it): states of another shape
            ``(2, P, dim)``, another system's, are refused by :meth:`check`
            rather than drawn as this one. ``None``: any ``P`` whose points the
            scene refers to.
    """

    dim: int
    circles: tuple[Circle, ...] = ()
    chains: tuple[Chain, ...] = ()
    walls: tuple[tuple[float, float, float], ...] = ()
    disks3d: tuple[Disk3D, ...] = ()
    planes: tuple[tuple[float, float, float, float], ...] = ()
    pivots: tuple[tuple[float, ...], ...] = ()
    targets: tuple[tuple[float, float], ...] = ()
    target_x: tuple[float, ...] = ()
    dots: tuple[int, ...] = ()
    title: str = ""
    limits: tuple[tuple[float, float], ...] | None = None
    view: tuple[float, float] | None = None
    n_points: int | None = None

    def __post_init__(self) -> None:
        if self.dim not in (2, 3):
            raise ValueError(f"Scene.dim must be 2 or 3, got {self.dim}")
        if self.n_points is not None and (
            isinstance(self.n_points, bool) or not isinstance(self.n_points, int)
            or self.n_points < 1
        ):  # fmt: skip
            raise ValueError(f"Scene.n_points must be a positive integer, got {self.n_points!r}")
        if self.dim == 3 and (self.circles or self.chains or self.walls):
            raise ValueError("Scene: circles, chains and walls are 2D elements (dim=2)")
        if self.dim == 2 and (self.disks3d or self.planes):
            raise ValueError("Scene: disks3d and planes are 3D elements (dim=3)")
        if self.dim == 3 and (self.targets or self.target_x):
            raise ValueError("Scene: targets and target_x are 2D elements (dim=2)")
        for q in self.targets:
            if len(q) != 2 or not all(math.isfinite(v) for v in q):
                raise ValueError(f"Scene: target {q} must be two finite numbers (x, y)")
        if not all(math.isfinite(v) for v in self.target_x):
            raise ValueError(f"Scene: target_x {self.target_x} must be finite numbers")
        for w in self.walls:
            if len(w) != 3 or math.hypot(w[0], w[1]) == 0.0:
                raise ValueError(f"Scene: wall {w} must be (a, b, c) with (a, b) != 0")
        for p in self.planes:
            if len(p) != 4 or math.hypot(p[0], p[1], p[2]) == 0.0:
                raise ValueError(f"Scene: plane {p} must be (a, b, c, e) with (a, b, c) != 0")
        for q in self.pivots:
            if len(q) != self.dim:
                raise ValueError(f"Scene: pivot {q} must have {self.dim} coordinates")
        if self.limits is not None and len(self.limits) != self.dim:
            raise ValueError(f"Scene.limits must have {self.dim} (lo, hi) pairs")

    def used_points(self) -> set[int]:
        """State point indices the scene refers to."""
        used: set[int] = set(self.dots)
        for c in self.circles:
            used.add(c.point)
            if c.oriented:
                used.add(c.point + 1)
        for ch in self.chains:
            used.update(ch.points)
        for d in self.disks3d:
            used.update(range(d.first_point, d.first_point + 4))
        return used

    def check(self, n_points: int, dim: int) -> None:
        """Raise ``ValueError`` if states of ``n_points`` points in ``dim`` don't fit: another
        dimension, points the scene refers to beyond ``n_points``, or (where the scene
        knows its system's :attr:`n_points`) states of another shape than its system's."""
        if self.n_points is not None and (n_points, dim) != (self.n_points, self.dim):
            of = f" ({self.title})" if self.title else ""
            raise ValueError(
                f"trajectory states have shape {(2, n_points, dim)}, but the scene{of} draws a "
                f"system with states {(2, self.n_points, self.dim)}: the scene of another system"
            )
        if dim != self.dim:
            raise ValueError(f"trajectory has dim={dim} but the scene is {self.dim}D")
        bad = sorted(i for i in self.used_points() if not 0 <= i < n_points)
        if bad:
            raise ValueError(
                f"scene refers to point indices {bad} but the trajectory has {n_points} points"
            )

    @classmethod
    def points(cls, n_points: int, dim: int, title: str = "") -> Scene:
        """A fallback scene drawing every point as a dot."""
        return cls(dim=dim, dots=tuple(range(n_points)), title=title, n_points=n_points)


# ---------------------------------------------------------------------------
# from a configuration
# ---------------------------------------------------------------------------


def _get(cfg: Any, *names: str, default: Any = None) -> Any:
    """First present, non-None field among ``names`` of a pydantic model or mapping."""
    for name in names:
        if isinstance(cfg, Mapping):
            value = cfg.get(name)
        else:
            value = getattr(cfg, name, None)
        if value is not None:
            return value
    return default


def _floats(values: Any) -> tuple[float, ...]:
    if hasattr(values, "tolist"):
        values = values.tolist()
    return tuple(float(v) for v in values)


def _per_body(value: Any, n: int, what: str) -> tuple[float, ...]:
    """``value`` as ``n`` floats (a scalar is broadcast)."""
    if value is None:
        raise ValueError(f"scene: config has no {what}")
    if isinstance(value, int | float):
        return (float(value),) * n
    out = _floats(value)
    if len(out) == 1 and n > 1:
        out = out * n
    if len(out) != n:
        raise ValueError(f"scene: expected {n} {what}, got {len(out)}")
    return out


def _lines(values: Any, width: int, what: str) -> tuple[tuple[float, ...], ...]:
    if values is None:
        return ()
    if hasattr(values, "tolist"):
        values = values.tolist()
    if len(values) > 0 and isinstance(values[0], int | float):
        values = [values]  # a single line given flat
    out = tuple(_floats(v) for v in values)
    for v in out:
        if len(v) != width:
            raise ValueError(f"scene: each {what} needs {width} numbers, got {list(v)}")
    return out


def _n_bodies(cfg: Any, default: int | None = None) -> int:
    n = _get(cfg, "n_bodies", "n", "n_points", "num_bodies")
    if n is not None:
        return int(n)
    for name in ("masses", "mass", "radii"):
        value = _get(cfg, name)
        if value is not None and not isinstance(value, int | float):
            return len(_floats(value))
    if default is None:
        raise ValueError("scene: cannot tell the number of bodies from the config")
    return default


def scene_from_config(cfg: Any, *, title: str | None = None) -> Scene:
    """Build a :class:`Scene` from a task configuration (pydantic model or dict).

    Recognised ``type`` values: ``bouncing_masses``, ``bouncing_disks``,
    ``chain_pendulum``, ``gyroscope``, ``rope``.
    """
    kind = _get(cfg, "type", "kind")
    if kind is None:
        raise ValueError("scene: config has no 'type'")
    kind = str(getattr(kind, "value", kind))
    name = title if title is not None else str(_get(cfg, "name", "task", default=kind))

    if kind in ("bouncing_masses", "bouncing_disks"):
        n = _n_bodies(cfg)
        radii = _per_body(_get(cfg, "radii", "radius"), n, "radii")
        walls = _lines(_get(cfg, "walls"), 3, "wall")
        per = 3 if kind == "bouncing_disks" else 1
        circles = tuple(Circle(point=per * i, radius=radii[i], oriented=per == 3) for i in range(n))
        return Scene(dim=2, circles=circles, walls=walls, title=name, n_points=per * n)

    if kind == "chain_pendulum":
        lengths = _get(cfg, "link_lengths", "lengths", "links")
        n = len(_floats(lengths)) if lengths is not None else _n_bodies(cfg)
        radii = _per_body(_get(cfg, "joint_radii", "radii", "radius"), n, "joint radii")
        pivot = _floats(_get(cfg, "pivot", "anchor", "origin", default=(0.0, 0.0)))
        walls = _lines(_get(cfg, "ground", "ground_line", "walls"), 3, "ground line")
        return Scene(
            dim=2,
            circles=tuple(Circle(point=i, radius=radii[i]) for i in range(n)),
            chains=(Chain(points=tuple(range(n)), anchor=pivot, style="links"),),
            walls=walls,
            pivots=(pivot,),
            title=name,
            n_points=n,
        )

    if kind == "rope":
        n = _n_bodies(cfg)
        anchor = _floats(_get(cfg, "anchor", "pivot", "origin", default=(0.0, 0.0)))
        return Scene(
            dim=2,
            chains=(Chain(points=tuple(range(n)), anchor=anchor, style="rope"),),
            pivots=(anchor,),
            title=name,
            n_points=n,
        )

    if kind == "gyroscope":
        radius = float(_get(cfg, "rim_radius", "disk_radius", "radius", default=0.3))
        pivot = _floats(_get(cfg, "pivot", "anchor", "origin", default=(0.0, 0.0, 0.0)))
        planes = _lines(_get(cfg, "wall_plane", "planes", "walls", "wall"), 4, "wall plane")
        return Scene(
            dim=3,
            disks3d=(Disk3D(first_point=0, radius=radius, pivot=pivot),),  # type: ignore[arg-type]
            planes=planes,
            pivots=(pivot,),
            title=name,
            n_points=4,
        )

    raise ValueError(f"scene: unknown system type {kind!r}")


def scene_from_system(system: Any, *, title: str | None = None) -> Scene:
    """Build a :class:`Scene` from a ``diffcontact`` system (reads ``system.config``)."""
    cfg = getattr(system, "config", system)
    return scene_from_config(cfg, title=title)
