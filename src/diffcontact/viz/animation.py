"""GIF animations of trajectories and energy plots (matplotlib, Agg, no screen).

The drawing is driven by a :class:`~diffcontact.viz.scene.Scene`; artists are
created once per panel and only their data changes from frame to frame.
Frames are subsampled to at most ``max_frames``, and written to the GIF one at a time
(memory does not grow with their number). Files are written atomically.
"""

from __future__ import annotations

import math
import os
import struct
import warnings
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle as CirclePatch
from matplotlib.patches import Polygon
from matplotlib.ticker import MaxNLocator

from diffcontact.io import atomic_path

from .scene import Scene

__all__ = ["MAX_PANELS", "MAX_PIXELS", "animate", "frame_indices", "plot_energy", "render_frame"]

# the bodies' colours: matplotlib's tab10 with its red replaced by indigo, since red
# (_CONTACT) marks a body in contact (tab10's red was body 3's, and its contact outline
# did not show)
_PALETTE = (
    "#1f77b4",
    "#ff7f0e",
    "#2ca02c",
    "#393b79",
    "#9467bd",
    "#8c564b",
    "#e377c2",
    "#7f7f7f",
    "#bcbd22",
    "#17becf",
)
_CONTACT = "#e00000"
MAX_PANELS = 16
"""The most trajectories one GIF shows (a grid of panels): a 10 x 10 grid of 192-pixel
panels makes frames of about 2000 x 2000 pixels, slow to render and too small to read."""
MIN_WIDTH = 5.2
"""The figure's least width in inches: room for the title and the legend over one panel."""
MAX_PIXELS = 4096 * 4096
"""The most pixels of a frame (a GIF's, or an image that :func:`render_frame` or
:func:`plot_energy` saves), ``dpi`` x ``dpi`` x its area in square inches: a 4 x 4 grid
of 3.2-inch panels fits at 300 dpi. A ``dpi`` or ``panel_size`` typo that asks for more
is refused before drawing (Agg ran out of memory with ``std::bad_alloc``)."""
_OVERLAY = "#222222"


_COLOR_NAMES = ("blue", "orange", "green", "indigo", "purple", "brown", "pink", "grey",
                "olive", "cyan")  # fmt: skip
"""The names of :data:`_PALETTE`'s colours, in order (for titles that point at a body)."""


def _body_color(i: int) -> str:
    """Body ``i``'s colour: its true state filled, its prediction a dashed outline."""
    return _PALETTE[i % len(_PALETTE)]


def body_color_name(i: int) -> str:
    """The name of body ``i``'s colour in the animations (``"blue"`` for body 0)."""
    return _COLOR_NAMES[i % len(_COLOR_NAMES)]


# ---------------------------------------------------------------------------
# inputs
# ---------------------------------------------------------------------------


def _to_numpy(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):  # torch tensor (torch is not imported here)
        x = x.detach().cpu().numpy()
    arr = np.asarray(x, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        # infinities become NaN: left out of the axis limits, drawn as gaps
        arr = np.where(np.isfinite(arr), arr, np.nan)
    return arr


def _as_batch(traj: Any, name: str) -> np.ndarray:
    """``(T, 2, P, dim)`` or ``(N, T, 2, P, dim)`` -> ``(N, T, 2, P, dim)``."""
    arr = _to_numpy(traj)
    if arr.ndim == 4:
        arr = arr[None]
    if arr.ndim != 5 or arr.shape[2] != 2:
        raise ValueError(
            f"{name} must have shape (T, 2, P, dim) or (N, T, 2, P, dim), got {arr.shape}"
        )
    if arr.shape[1] == 0:
        raise ValueError(f"{name} has no time steps")
    return arr


_FORMATS = {".png": "png", ".pdf": "pdf", ".svg": "svg", ".gif": "gif"}


def _image_format(path: str | os.PathLike[str], allowed: tuple[str, ...]) -> str:
    """The file format of ``path`` from its suffix, one of ``allowed`` (e.g. ``".png"``);
    a ``ValueError`` naming the path otherwise (a ``.pdf`` had been given PNG bytes)."""
    name = Path(path).name
    suffix = Path(path).suffix.lower()
    if suffix not in allowed:
        if name.lower() in allowed:  # ".gif": a hidden file's name, without a suffix
            raise ValueError(f"{path}: {name!r} has no file name before its suffix")
        raise ValueError(f"{path}: the file name must end in {' or '.join(allowed)}")
    if Path(path).is_dir():
        raise ValueError(f"{path} is a directory; give a file name")
    return _FORMATS[suffix]


def _positive(name: str, value: Any, integer: bool = False) -> None:
    """``value`` a finite number > 0 (an integer if ``integer``), else a ``ValueError``."""
    kinds = (int,) if integer else (int, float)
    if (
        isinstance(value, bool)
        or not isinstance(value, kinds)
        or not math.isfinite(value)
        or value <= 0
    ):
        what = "a positive integer" if integer else "a finite number > 0"
        raise ValueError(f"{name} must be {what}, got {value!r}")


def _check_pixels(width: float, height: float, dpi: float, sizes: str) -> None:
    """A ``ValueError`` if a ``width`` x ``height`` inch figure at ``dpi`` has more than
    :data:`MAX_PIXELS` pixels; ``sizes`` names the arguments that set them, with the
    verb (``"dpi 600 makes"``)."""
    w, h = width * dpi, height * dpi
    if w * h > MAX_PIXELS:
        side = math.isqrt(MAX_PIXELS)
        raise ValueError(
            f"{sizes} frames of {w:.0f} x {h:.0f} pixels, more than the {MAX_PIXELS} "
            f"pixels ({side} x {side}) that a frame may have"
        )


def frame_indices(n_steps: int, max_frames: int) -> np.ndarray:
    """Indices of the states shown: all of them, or ``max_frames`` evenly spaced
    ones including the first and the last."""
    if n_steps < 1:  # (it returned no index: nothing to draw)
        raise ValueError(f"n_steps must be >= 1, got {n_steps}")
    if max_frames < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    if n_steps <= max_frames:
        return np.arange(n_steps)
    return np.unique(np.linspace(0, n_steps - 1, max_frames).round().astype(np.int64))


# ---------------------------------------------------------------------------
# small geometry helpers
# ---------------------------------------------------------------------------


def _clip_halfplane(poly: np.ndarray, a: float, b: float, c: float) -> np.ndarray:
    """Part of a convex polygon ``(V, 2)`` where ``a x + b y + c <= 0`` (Sutherland-Hodgman)."""
    out = []
    n = len(poly)
    for k in range(n):
        p, q = poly[k], poly[(k + 1) % n]
        fp, fq = a * p[0] + b * p[1] + c, a * q[0] + b * q[1] + c
        if fp <= 0:
            out.append(p)
        if (fp < 0 < fq) or (fq < 0 < fp):
            out.append(p + (q - p) * (fp / (fp - fq)))
    return np.asarray(out, dtype=np.float64).reshape(-1, 2)


def _rect(xlim: Sequence[float], ylim: Sequence[float]) -> np.ndarray:
    return np.array(
        [[xlim[0], ylim[0]], [xlim[1], ylim[0]], [xlim[1], ylim[1]], [xlim[0], ylim[1]]]
    )


def _line_in_rect(w: Sequence[float], xlim, ylim) -> np.ndarray | None:
    """Segment of the line ``a x + b y + c = 0`` inside the rectangle (or None)."""
    a, b, c = w
    d = np.array([-b, a]) / math.hypot(a, b)
    p0 = -c * np.array([a, b]) / (a * a + b * b)
    # parameters t along d where the line meets the rectangle's edges
    ts = []
    for k, (lo, hi) in enumerate((xlim, ylim)):
        if abs(d[k]) > 1e-15:
            for bound in (lo, hi):
                t = (bound - p0[k]) / d[k]
                q = p0 + t * d
                eps = 1e-9 * (1.0 + abs(q).max())
                if (
                    xlim[0] - eps <= q[0] <= xlim[1] + eps
                    and ylim[0] - eps <= q[1] <= ylim[1] + eps
                ):
                    ts.append(t)
    if len(ts) < 2:
        return None
    return np.stack([p0 + min(ts) * d, p0 + max(ts) * d])


def _normalized_walls(walls) -> np.ndarray:
    """Unit-normal walls, scaled first by the larger ``|a|, |b|`` (as
    ``geometry.base.unit_normal_planes``: no overflow for ``[1e160, 0, 0]``)."""
    w = np.asarray(walls, dtype=np.float64).reshape(-1, 3)
    w = w / np.abs(w[:, :2]).max(axis=1, keepdims=True)
    return w / np.hypot(w[:, 0], w[:, 1])[:, None]


def _circle_contacts(x: np.ndarray, scene: Scene) -> np.ndarray:
    """``(F, n_circles)`` bool: the circle penetrates a wall or another circle."""
    if not scene.circles:
        return np.zeros((x.shape[0], 0), dtype=bool)
    idx = np.array([c.point for c in scene.circles])
    r = np.array([c.radius for c in scene.circles])
    centres = x[:, idx, :]  # (F, C, 2)
    touch = np.zeros(centres.shape[:2], dtype=bool)
    if scene.walls:
        w = _normalized_walls(scene.walls)
        dist = centres @ w[:, :2].T + w[:, 2]  # (F, C, W)
        touch |= (dist < r[None, :, None]).any(-1)
    if len(idx) > 1 and not scene.chains:  # pendulum joints do not collide with each other
        diff = centres[:, :, None, :] - centres[:, None, :, :]
        gap = np.linalg.norm(diff, axis=-1) - (r[:, None] + r[None, :])
        np.einsum("fii->fi", gap)[...] = np.inf
        touch |= (gap < 0).any(-1)
    return touch


def _located_points(scene: Scene) -> list[int]:
    """Points that are drawn where they are (not body-axis tips), for the axis limits."""
    keep = {c.point for c in scene.circles} | set(scene.dots)
    keep |= {d.first_point for d in scene.disks3d}
    for ch in scene.chains:
        keep.update(ch.points)
    return sorted(keep)


def _limits_2d(xs: list[np.ndarray], scene: Scene, margin: float = 0.06):
    """Axis limits from the data (all frames), body sizes, walls and pivots."""
    if scene.limits is not None:
        return tuple(scene.limits[0]), tuple(scene.limits[1])
    keep = _located_points(scene)
    radius = np.zeros(max(keep, default=0) + 1)
    for c in scene.circles:
        radius[c.point] = max(radius[c.point], c.radius)
    r = radius[keep][:, None]
    pts = []
    for x in xs:
        centres = x[:, keep]  # (F, k, 2)
        pts += [(centres - r).reshape(-1, 2), (centres + r).reshape(-1, 2)]
    for q in (*scene.pivots, *scene.targets):
        pts.append(np.asarray(q, dtype=np.float64).reshape(1, 2))
    for ch in scene.chains:
        if ch.anchor is not None:
            pts.append(np.asarray(ch.anchor, dtype=np.float64).reshape(1, 2))
    allp = np.concatenate(pts, axis=0)
    allp = allp[np.isfinite(allp).all(-1)]
    if len(allp) == 0:
        allp = np.zeros((1, 2))
    lo, hi = allp.min(0), allp.max(0)
    if scene.target_x:  # a throw's target line, in view even where the plan falls short
        lo[0], hi[0] = min(lo[0], *scene.target_x), max(hi[0], *scene.target_x)
    if scene.walls:
        w = _normalized_walls(scene.walls)
        centre = 0.5 * (lo + hi)
        # closest point of each wall to the data, so every wall is in view
        foot = centre[None, :] - (w[:, :2] @ centre + w[:, 2])[:, None] * w[:, :2]
        # corners of the allowed region (e.g. the box), if bounded
        corners = []
        for i in range(len(w)):
            for j in range(i + 1, len(w)):
                m = np.array([w[i, :2], w[j, :2]])
                if abs(np.linalg.det(m)) > 1e-12:
                    p = np.linalg.solve(m, -np.array([w[i, 2], w[j, 2]]))
                    if np.all(w[:, :2] @ p + w[:, 2] >= -1e-9):
                        corners.append(p)
        extra = np.concatenate([foot, np.asarray(corners).reshape(-1, 2)], axis=0)
        lo, hi = np.minimum(lo, extra.min(0)), np.maximum(hi, extra.max(0))
    span = max(float((hi - lo).max()), 1e-6)
    pad = margin * span
    centre = 0.5 * (lo + hi)
    half = 0.5 * (hi - lo) + pad
    half = np.maximum(half, 0.5 * span * 0.3)  # avoid very thin views
    return (
        (float(centre[0] - half[0]), float(centre[0] + half[0])),
        (float(centre[1] - half[1]), float(centre[1] + half[1])),
    )


def _unit(v: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    ok = n > 1e-12
    return np.where(ok, v / np.where(ok, n, 1.0), fallback)


# ---------------------------------------------------------------------------
# panels
# ---------------------------------------------------------------------------


class _Panel2D:
    """Artists of one 2D subplot; ``update(k)`` moves them to frame ``k``."""

    def __init__(self, ax, scene: Scene, x: np.ndarray, xo: np.ndarray | None, trail: int, lims):
        self.ax, self.scene, self.x, self.xo, self.trail = ax, scene, x, xo, trail
        xlim, ylim = lims
        ax.set_xlim(*xlim)
        ax.set_ylim(*ylim)
        ax.set_aspect("equal")
        # 8 pt at the GIFs' 60 dpi is 7 pixels: fewer, larger tick labels
        ax.tick_params(labelsize=8, length=2)
        ax.xaxis.set_major_locator(MaxNLocator(4))
        ax.yaxis.set_major_locator(MaxNLocator(4))
        # walls: forbidden side shaded, boundary line
        rect = _rect(xlim, ylim)
        for a, b, c in scene.walls:
            poly = _clip_halfplane(rect, a, b, c)
            if len(poly) >= 3:
                ax.add_patch(Polygon(poly, closed=True, fc="#e3e3e3", ec="none", zorder=0))
            seg = _line_in_rect((a, b, c), xlim, ylim)
            if seg is not None:
                ax.plot(seg[:, 0], seg[:, 1], color="k", lw=1.5, zorder=1)
        self.contacts = _circle_contacts(x, scene)
        self.bodies = []  # (patch, orientation line, trail line, circle)
        for i, c in enumerate(scene.circles):
            color = _body_color(i)
            # not antialiased: a moving edge then changes fewer pixels per frame (a smaller GIF)
            patch = CirclePatch(
                (0.0, 0.0), c.radius, fc=color, ec="none", alpha=0.75, lw=0.0, antialiased=False
            )
            patch.set_zorder(3)
            ax.add_patch(patch)
            orient = None
            if c.oriented:
                (orient,) = ax.plot([], [], color="k", lw=1.2, zorder=4)
            tr = None
            if trail > 1:
                (tr,) = ax.plot([], [], color=color, lw=0.8, alpha=0.5, zorder=2)
            self.bodies.append((patch, orient, tr, c))
        self.chains = []
        for ch in scene.chains:
            if ch.style == "rope":
                (line,) = ax.plot([], [], color="#8c564b", lw=1.5, marker="o", ms=3, zorder=2)
            else:
                (line,) = ax.plot([], [], color="#444444", lw=2.0, zorder=2)
            self.chains.append((line, ch))
        self.dots = None
        if scene.dots:
            (self.dots,) = ax.plot([], [], "o", color=_PALETTE[0], ms=4, zorder=3)
        pivots = [
            ax.plot([q[0]], [q[1]], marker="s", color="k", ms=4, zorder=5)[0] for q in scene.pivots
        ]
        for q in scene.targets:  # a plan's target: a cross over everything
            pivots.append(
                ax.plot([q[0]], [q[1]], marker="x", color="k", ms=9, mew=2.0, zorder=6)[0]
            )
        for xv in scene.target_x:
            pivots.append(ax.axvline(xv, color="k", ls=":", lw=1.2, zorder=6))
        # overlay (e.g. a prediction), dashed outlines
        self.over_bodies, self.over_chains = [], []
        if xo is not None:  # each body's prediction: a dashed outline in the body's colour
            for i, c in enumerate(scene.circles):
                color = _body_color(i)
                patch = CirclePatch(
                    (0.0, 0.0), c.radius, fill=False, ec=color, lw=1.6, ls="--", antialiased=False
                )
                patch.set_zorder(6)
                ax.add_patch(patch)
                orient = None
                if c.oriented:
                    (orient,) = ax.plot([], [], color=color, lw=1.2, ls="--", zorder=6)
                self.over_bodies.append((patch, orient, c))
            for ch in scene.chains:
                (line,) = ax.plot([], [], color=_OVERLAY, lw=1.2, ls="--", zorder=6)
                self.over_chains.append((line, ch))
        moving = [a for body in self.bodies for a in body[:3] if a is not None]
        moving += [line for line, _ in self.chains]
        moving += [] if self.dots is None else [self.dots]
        moving += [a for body in self.over_bodies for a in body[:2] if a is not None]
        moving += [line for line, _ in self.over_chains]
        #: artists that change between frames, in drawing order
        # (pivots do not move but are redrawn so that they stay on top)
        self.artists = sorted(moving + pivots, key=lambda a: a.get_zorder())

    @staticmethod
    def _chain_xy(x: np.ndarray, ch) -> np.ndarray:
        pts = x[list(ch.points)]
        if ch.anchor is not None:
            pts = np.concatenate([np.asarray(ch.anchor, dtype=np.float64)[None], pts], axis=0)
        return pts

    @staticmethod
    def _orient_xy(x: np.ndarray, c) -> np.ndarray:
        centre = x[c.point]
        u = _unit(x[c.point + 1] - centre, np.array([1.0, 0.0]))
        return np.stack([centre, centre + c.radius * u])

    def update(self, k: int) -> None:
        x = self.x[k]
        for i, (patch, orient, tr, c) in enumerate(self.bodies):
            patch.set_center(tuple(x[c.point]))
            hit = bool(self.contacts[k, i])
            patch.set_edgecolor(_CONTACT if hit else "none")
            patch.set_linewidth(2.0 if hit else 0.0)
            if orient is not None:
                seg = self._orient_xy(x, c)
                orient.set_data(seg[:, 0], seg[:, 1])
            if tr is not None:
                hist = self.x[max(0, k - self.trail + 1) : k + 1, c.point]
                tr.set_data(hist[:, 0], hist[:, 1])
        for line, ch in self.chains:
            xy = self._chain_xy(x, ch)
            line.set_data(xy[:, 0], xy[:, 1])
        if self.dots is not None:
            pts = x[list(self.scene.dots)]
            self.dots.set_data(pts[:, 0], pts[:, 1])
        if self.xo is not None:
            xo = self.xo[k]
            for patch, orient, c in self.over_bodies:
                patch.set_center(tuple(xo[c.point]))
                if orient is not None:
                    seg = self._orient_xy(xo, c)
                    orient.set_data(seg[:, 0], seg[:, 1])
            for line, ch in self.over_chains:
                xy = self._chain_xy(xo, ch)
                line.set_data(xy[:, 0], xy[:, 1])


def _rim(x: np.ndarray, d, n: int = 48) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rim polygon ``(n, 3)``, com, unit axis of a 3D disk at one state ``x: (P, 3)``."""
    com = x[d.first_point]
    e1, e2, e3 = (x[d.first_point + k] - com for k in (1, 2, 3))
    a = _unit(e3, np.array([0.0, 0.0, 1.0]))
    u = _unit(e1 - (e1 @ a) * a, np.array([1.0, 0.0, 0.0]))
    w = np.cross(a, u)
    if e2 @ w < 0:  # keep the body's own handedness
        w = -w
    th = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    rim = com + d.radius * (np.cos(th)[:, None] * u + np.sin(th)[:, None] * w)
    return rim, com, a


def _rim_gap(x: np.ndarray, d, planes: np.ndarray) -> float:
    """Least signed distance of the rim to the planes (exact closest rim point)."""
    if len(planes) == 0:
        return np.inf
    com = x[d.first_point]
    a = _unit(x[d.first_point + 3] - com, np.array([0.0, 0.0, 1.0]))
    n = planes[:, :3]
    e = n - (n @ a)[:, None] * a
    return float((n @ com + planes[:, 3] - d.radius * np.linalg.norm(e, axis=-1)).min())


def _limits_3d(xs: list[np.ndarray], scene: Scene, margin: float = 0.05):
    if scene.limits is not None:
        return tuple(tuple(lim) for lim in scene.limits)
    keep = _located_points(scene)
    pts = [x[:, keep].reshape(-1, 3) for x in xs]
    pts += [np.asarray(q, dtype=np.float64).reshape(1, 3) for q in scene.pivots]
    allp = np.concatenate(pts, axis=0)
    allp = allp[np.isfinite(allp).all(-1)]
    if len(allp) == 0:
        allp = np.zeros((1, 3))
    r = max([d.radius for d in scene.disks3d], default=0.0)
    lo, hi = allp.min(0) - r, allp.max(0) + r
    planes = np.asarray(scene.planes, dtype=np.float64).reshape(-1, 4)
    if len(planes):
        centre = 0.5 * (lo + hi)
        n = planes[:, :3] / np.linalg.norm(planes[:, :3], axis=-1, keepdims=True)
        e = planes[:, 3] / np.linalg.norm(planes[:, :3], axis=-1)
        foot = centre[None] - (n @ centre + e)[:, None] * n
        lo, hi = np.minimum(lo, foot.min(0)), np.maximum(hi, foot.max(0))
    centre = 0.5 * (lo + hi)
    half = 0.5 * float((hi - lo).max()) * (1.0 + margin) + 1e-6
    return tuple((float(c - half), float(c + half)) for c in centre)


def _camera(scene: Scene) -> tuple[float, float]:
    """``(elev, azim)``: the scene's, or looking along the first plane (it then shows
    edge-on at the left, with true distances to it across the screen)."""
    if scene.view is not None:
        return scene.view
    if scene.planes:
        nx, ny = scene.planes[0][0], scene.planes[0][1]
        if math.hypot(nx, ny) > 1e-9:
            return (20.0, math.degrees(math.atan2(-nx, ny)))
    return (15.0, 30.0)


def _plane_quad(plane: Sequence[float], lims) -> np.ndarray:
    """The plane's patch inside the box ``lims``: 4 corners, solving for its main axis."""
    n = np.asarray(plane[:3], dtype=np.float64)
    e = float(plane[3])
    k = int(np.argmax(np.abs(n)))
    i, j = [m for m in range(3) if m != k]
    quad = []
    for si, sj in ((0, 0), (1, 0), (1, 1), (0, 1)):
        p = np.zeros(3)
        p[i], p[j] = lims[i][si], lims[j][sj]
        p[k] = -(e + n[i] * p[i] + n[j] * p[j]) / n[k]
        quad.append(p)
    return np.asarray(quad)


class _Panel3D:
    """Artists of one 3D subplot (gyroscope-like scenes)."""

    def __init__(self, ax, scene: Scene, x: np.ndarray, xo: np.ndarray | None, trail: int, lims):
        from mpl_toolkits.mplot3d.art3d import Poly3DCollection

        self.ax, self.scene, self.x, self.xo, self.trail = ax, scene, x, xo, trail
        ax.set_xlim(*lims[0])
        ax.set_ylim(*lims[1])
        ax.set_zlim(*lims[2])
        ax.set_box_aspect((1.0, 1.0, 1.0), zoom=1.2)
        ax.set_proj_type("ortho")
        elev, azim = _camera(scene)
        ax.view_init(elev=elev, azim=azim)
        for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
            axis.pane.set_facecolor((1.0, 1.0, 1.0, 0.0))
            axis.pane.set_edgecolor("#bbbbbb")
            axis._axinfo["grid"]["color"] = "#e4e4e4"  # no public setter for 3D grid colour
        # an axis pointing at the camera only gets unreadable, stacked tick labels
        if abs(math.cos(math.radians(azim))) > 0.97:
            ax.set_xticklabels([])
        elif abs(math.sin(math.radians(azim))) > 0.97:
            ax.set_yticklabels([])
        ax.tick_params(labelsize=5, pad=0)
        for lab, setter in zip("xyz", (ax.set_xlabel, ax.set_ylabel, ax.set_zlabel), strict=True):
            setter(lab, fontsize=7, labelpad=-8)
        self.planes = np.asarray(scene.planes, dtype=np.float64).reshape(-1, 4)
        if len(self.planes):
            self.planes = self.planes / np.linalg.norm(self.planes[:, :3], axis=-1, keepdims=True)
        for plane in scene.planes:
            quad = _plane_quad(plane, lims)
            ax.add_collection3d(
                Poly3DCollection([quad], facecolor="#999999", edgecolor="k", alpha=0.25, lw=0.8)
            )
        for q in scene.pivots:
            ax.plot([q[0]], [q[1]], [q[2]], marker="s", color="k", ms=4)
        self.disks = []
        for i, d in enumerate(scene.disks3d):
            color = _body_color(i)
            face = Poly3DCollection(
                [np.zeros((3, 3))], facecolor=color, edgecolor="none", alpha=0.35
            )
            ax.add_collection3d(face)
            (rim,) = ax.plot([], [], [], color=color, lw=1.8)
            (rod,) = ax.plot([], [], [], color="#333333", lw=2.0)
            (spoke,) = ax.plot([], [], [], color="k", lw=1.2)
            tr = None
            if trail > 1:
                (tr,) = ax.plot([], [], [], color=color, lw=0.8, alpha=0.5)
            over = None
            if xo is not None:  # the prediction: dashed, in the body's colour
                (orim,) = ax.plot([], [], [], color=color, lw=1.2, ls="--")
                (orod,) = ax.plot([], [], [], color=color, lw=1.2, ls="--")
                over = (orim, orod)
            self.disks.append((d, face, rim, rod, spoke, tr, over, color))
        self.dots = None
        if scene.dots:
            (self.dots,) = ax.plot([], [], [], "o", color=_PALETTE[0], ms=4)
        #: artists that change between frames, in drawing order
        self.artists = []
        for _, face, rim, rod, spoke, tr, over, _ in self.disks:
            self.artists += [a for a in (tr, face, rim, rod, spoke) if a is not None]
            self.artists += list(over or ())
        self.artists += [] if self.dots is None else [self.dots]

    @staticmethod
    def _rod(d, com, a) -> np.ndarray:
        start = np.asarray(d.pivot, dtype=np.float64) if d.pivot is not None else com
        return np.stack([start, com + 0.3 * d.radius * a])

    def update(self, k: int) -> None:
        x = self.x[k]
        for d, face, rim, rod, spoke, tr, over, color in self.disks:
            ring, com, a = _rim(x, d)
            closed = np.concatenate([ring, ring[:1]], axis=0)
            rim.set_data_3d(closed[:, 0], closed[:, 1], closed[:, 2])
            hit = _rim_gap(x, d, self.planes) < 0.0
            rim.set_color(_CONTACT if hit else color)
            rim.set_linewidth(2.6 if hit else 1.8)
            face.set_verts([ring])
            r = self._rod(d, com, a)
            rod.set_data_3d(r[:, 0], r[:, 1], r[:, 2])
            s = np.stack([com, ring[0]])
            spoke.set_data_3d(s[:, 0], s[:, 1], s[:, 2])
            if tr is not None:
                hist = self.x[max(0, k - self.trail + 1) : k + 1, d.first_point]
                tr.set_data_3d(hist[:, 0], hist[:, 1], hist[:, 2])
            if over is not None:
                oring, ocom, oa = _rim(self.xo[k], d)
                oc = np.concatenate([oring, oring[:1]], axis=0)
                over[0].set_data_3d(oc[:, 0], oc[:, 1], oc[:, 2])
                orr = self._rod(d, ocom, oa)
                over[1].set_data_3d(orr[:, 0], orr[:, 1], orr[:, 2])
        if self.dots is not None:
            pts = x[list(self.scene.dots)]
            self.dots.set_data_3d(pts[:, 0], pts[:, 1], pts[:, 2])


# ---------------------------------------------------------------------------
# public API
# ---------------------------------------------------------------------------


def _build_figure(
    traj: Any,
    scene: Scene,
    *,
    max_trajectories: int,
    overlay: Any,
    max_frames: int,
    labels: Sequence[str] | None,
    trail: int,
    panel_size: float,
    dpi: float | None = None,
):
    x = _as_batch(traj, "traj")[:, :, 0]  # (N, T, P, dim) positions
    n_total, n_steps, n_points, dim = x.shape
    if n_total == 0:
        raise ValueError("traj holds no trajectory (N = 0)")
    _positive("panel_size", panel_size)
    if labels is not None and (isinstance(labels, str) or len(labels) != 2):
        raise ValueError(f"labels must be two names, for (traj, overlay); got {labels!r}")
    scene.check(n_points, dim)
    xo = None
    if overlay is not None:
        xo = _as_batch(overlay, "overlay")[:, :, 0]
        if xo.shape[1:] != x.shape[1:] or xo.shape[0] not in (1, n_total):
            raise ValueError(
                f"overlay shape {xo.shape} does not match traj positions {x.shape} "
                "(same T, P, dim; N equal or 1)"
            )
        xo = np.broadcast_to(xo, x.shape)
    _positive("max_trajectories", max_trajectories, integer=True)
    if max_trajectories > MAX_PANELS:
        raise ValueError(
            f"max_trajectories must be at most {MAX_PANELS} (one panel each), got "
            f"{max_trajectories}: animate a few trajectories per GIF"
        )
    _positive("max_frames", max_frames, integer=True)
    n = min(n_total, max_trajectories)
    if not np.isfinite(x[:n]).any():  # (a blank GIF was written)
        raise ValueError("traj holds no finite position in the trajectories shown: nothing to draw")
    if not np.isfinite(x[:n]).all():
        warnings.warn(
            "traj holds NaN or infinite positions; those bodies are not drawn in those frames",
            RuntimeWarning,
            stacklevel=3,
        )
    if xo is not None and not np.isfinite(xo[:n]).all():  # (the legend names it all the same)
        warnings.warn(
            "overlay holds no finite position in the trajectories shown: it is not drawn"
            if not np.isfinite(xo[:n]).any()
            else "overlay holds NaN or infinite positions; those bodies' dashed outlines are "
            "not drawn in those frames",
            RuntimeWarning,
            stacklevel=3,
        )
    idx = frame_indices(n_steps, max_frames)
    ncols = math.ceil(math.sqrt(n))
    nrows = math.ceil(n / ncols)
    # at least MIN_WIDTH wide: one panel is narrower than the title and the legend
    width = max(panel_size * ncols, MIN_WIDTH)
    height = panel_size * nrows + 0.35
    if dpi is not None:
        _check_pixels(width, height, dpi, f"dpi {dpi} and panel_size {panel_size} make")
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    # shared by all panels; from traj and the scene only: an overlay (a prediction) that
    # leaves them is drawn clipped, rather than shrinking the truth of every panel to a dot
    shown = [x[:n, idx].reshape(-1, n_points, dim)]
    lims = (_limits_3d if dim == 3 else _limits_2d)(shown, scene)
    panels = []
    for i in range(n):
        kw = {"projection": "3d"} if dim == 3 else {}
        if dim == 3:
            import mpl_toolkits.mplot3d  # noqa: F401  (registers the projection)
        ax = fig.add_subplot(nrows, ncols, i + 1, **kw)
        if n > 1:
            ax.set_title(f"#{i}", fontsize=9, pad=2)
        if dim == 2 and i + ncols >= n:  # no panel below
            ax.set_xlabel("x (m)", fontsize=8, labelpad=1)
        if dim == 2 and i % ncols == 0:
            ax.set_ylabel("y (m)", fontsize=8, labelpad=1)
        xi = x[i, idx]
        xoi = None if xo is None else xo[i, idx]
        cls = _Panel3D if dim == 3 else _Panel2D
        panels.append(cls(ax, scene, xi, xoi, trail, lims))
    if xo is not None:
        names = tuple(labels) if labels is not None else ("traj", "overlay")
        if scene.circles:  # bodies: filled, their prediction a dashed outline of their colour
            names = (f"{names[0]} (filled)", f"{names[1]} (dashed; colour per body)")
            handles = [
                Line2D([], [], color="#888888", lw=0, marker="o", ms=7, alpha=0.75),
                Line2D([], [], color="#888888", lw=1.4, ls="--"),
            ]
        else:  # chains and ropes only: lines, the prediction a dark dashed line
            rope = any(ch.style == "rope" for ch in scene.chains)
            names = (f"{names[0]} (solid)", f"{names[1]} (dashed)")
            handles = [
                Line2D([], [], color="#8c564b" if rope else "#444444", lw=1.5,
                       marker="o" if rope else None, ms=3),
                Line2D([], [], color=_OVERLAY, lw=1.2, ls="--"),
            ]  # fmt: skip
        fig.legend(handles, names, loc="outside lower center", ncol=2, fontsize=8, frameon=False)
    return fig, panels, idx


def render_frame(
    traj: Any,
    scene: Scene,
    path: str | os.PathLike[str],
    *,
    frame: int = 0,
    max_trajectories: int = 4,
    overlay: Any = None,
    dt: float | None = None,
    labels: Sequence[str] | None = None,
    trail: int = 10,
    dpi: int = 100,
    panel_size: float = 3.2,
) -> Path:
    """Save one state (index ``frame`` of the time axis, negative from the end) as a
    ``.png``, ``.pdf`` or ``.svg`` (by the suffix), drawn as in :func:`animate` (at most
    :data:`MAX_PIXELS` pixels at ``dpi``)."""
    fmt = _image_format(path, (".png", ".pdf", ".svg"))
    _positive("dpi", dpi)
    fig, panels, _ = _build_figure(
        traj,
        scene,
        max_trajectories=max_trajectories,
        overlay=overlay,
        max_frames=10**9,
        labels=labels,
        trail=trail,
        panel_size=panel_size,
        dpi=dpi,
    )
    n_steps = panels[0].x.shape[0]
    if isinstance(frame, bool) or not isinstance(frame, int) or not -n_steps <= frame < n_steps:
        raise ValueError(f"frame must be an integer in [-{n_steps}, {n_steps}), got {frame!r}")
    k = frame % n_steps
    for p in panels:
        p.update(k)
    fig.suptitle(_title(scene, k, dt), fontsize=9)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format=fmt, dpi=dpi)
    return Path(path)


def _render_frames(fig, panels, idx, title, title_of, colors: int = 255):
    """Draw the frames by blitting: static parts once, then only the moving artists.

    Returns ``(palette, frames)``: the palette (``[r, g, b, ...]``, at most ``colors``
    entries) and an iterator over the frames as palette ("P" mode) Pillow images of that
    palette, so that unchanged pixels stay identical and the GIF stores only changes.
    Each frame is drawn when it is taken: memory does not grow with the frames (all RGB
    frames had been kept until the last was drawn).
    """
    from PIL import Image

    canvas = fig.canvas
    moving = [(p.ax, a) for p in panels for a in p.artists]
    for _, a in moving:
        a.set_animated(True)
    title.set_animated(True)
    title.set_text(title_of(int(idx[-1])))  # reserve its room in the layout
    canvas.draw()
    background = canvas.copy_from_bbox(fig.bbox)

    def draw(k: int) -> np.ndarray:  # frame k in RGB (it depends on k alone)
        canvas.restore_region(background)
        for p in panels:
            p.update(k)
        for ax, a in moving:
            if hasattr(a, "do_3d_projection"):
                a.do_3d_projection()
            ax.draw_artist(a)
        title.set_text(title_of(int(idx[k])))
        fig.draw_artist(title)
        return np.array(canvas.buffer_rgba())[..., :3]

    # one palette: the drawing colours exactly (each body's colour, its filled shade over
    # white and over a wall's grey), the rest median-cut from a few frames
    body = np.array([_hex_rgb(c) for c in _PALETTE], dtype=np.float64)
    fixed = [_hex_rgb(c) for c in (_CONTACT, _OVERLAY, "#000000", "#ffffff", "#e3e3e3")]
    fixed += [tuple(c) for c in body.round().astype(int).tolist()]
    for under in (255.0, 227.0):  # fills have alpha 0.75 (_Panel2D)
        fixed += [tuple(c) for c in (0.75 * body + 0.25 * under).round().astype(int).tolist()]
    fixed = list(dict.fromkeys(fixed))[: max(colors - 2, 1)]
    picks = sorted({0, len(idx) // 2, len(idx) - 1})
    sample = np.concatenate([draw(k) for k in picks], axis=0)
    rest = max(colors - len(fixed), 2)
    cut = Image.fromarray(sample).quantize(colors=rest, method=Image.Quantize.MEDIANCUT)
    del sample
    entries = [c for row in fixed for c in row] + list(cut.getpalette()[: 3 * rest])
    palette = Image.new("P", (1, 1))
    palette.putpalette(entries)

    def frames():
        for k in range(len(idx)):
            image = Image.fromarray(draw(k))
            yield image.quantize(palette=palette, dither=Image.Dither.NONE)

    return entries, frames()


def _hex_rgb(color: str) -> tuple[int, int, int]:
    return tuple(int(color[i : i + 2], 16) for i in (1, 3, 5))  # type: ignore[return-value]


def _save_gif(
    palette: Sequence[int], frames: Iterable[Any], path: str | os.PathLike[str], fps: float
) -> None:
    """Write palette ("P" mode) Pillow frames of ``palette`` (``[r, g, b, ...]``, 1 to
    255 colours) as a looping GIF, atomically, each frame as it comes (Pillow's writer
    keeps them all until the last).

    As Pillow's: after the first frame only the rectangle that changed is stored, its
    unchanged pixels transparent (an index after the palette's colours), and a frame
    equal to the one before lengthens that one.
    """
    from PIL import GifImagePlugin, Image

    if not hasattr(GifImagePlugin, "getdata"):  # (a Pillow without its frame encoder)
        _save_gif_all_at_once(list(frames), path, fps)
        return
    n_colors = len(palette) // 3
    if not 1 <= n_colors <= 255:
        raise ValueError(f"a GIF palette has 1 to 255 colours here, got {n_colors}")
    clear = n_colors  # the transparent index, no colour of the frames
    bits = n_colors.bit_length()  # a colour table of 2**bits entries, clear included
    table = bytes(palette[: 3 * n_colors]) + bytes(3 * ((1 << bits) - n_colors))
    duration = max(20, round(1000.0 / fps))  # milliseconds; GIF counts 1/100 s

    def write(fh, pixels: np.ndarray, offset: tuple[int, int], ms: int, first: bool) -> None:
        params: dict[str, int] = {"duration": min(ms, 655_350), "disposal": 1}  # 1: kept
        if not first:
            params["transparency"] = clear
        height, width = pixels.shape
        image = Image.frombytes("P", (width, height), np.ascontiguousarray(pixels).tobytes())
        for chunk in GifImagePlugin.getdata(image, offset, **params):
            fh.write(chunk)

    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        previous = None  # the last frame's indices
        pending: list[Any] = []  # [pixels, offset, ms, first]: written once the next differs
        for image in frames:
            now = np.asarray(image, dtype=np.uint8)
            if now.max() >= clear:  # (would be drawn transparent)
                raise ValueError(f"a frame has colour indices past the palette's {n_colors}")
            if previous is None:
                height, width = now.shape
                fh.write(b"GIF89a" + struct.pack("<HHBBB", width, height, 0x80 | (bits - 1), 0, 0))
                fh.write(table)
                fh.write(b"!\xff\x0bNETSCAPE2.0\x03\x01\x00\x00\x00")  # loop forever
                pending = [now, (0, 0), duration, True]
            else:
                changed = now != previous
                if not changed.any():
                    pending[2] += duration
                    continue
                write(fh, *pending)
                rows = np.flatnonzero(changed.any(axis=1))
                cols = np.flatnonzero(changed.any(axis=0))
                box = np.s_[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
                part = np.where(changed[box], now[box], np.uint8(clear))
                pending = [part, (int(cols[0]), int(rows[0])), duration, False]
            previous = now
        if not pending:
            raise ValueError("no frame to write")
        write(fh, *pending)
        fh.write(b";")


def _save_gif_all_at_once(frames: list[Any], path: str | os.PathLike[str], fps: float) -> None:
    """Pillow's own GIF writer, which keeps every frame until the last: where
    ``GifImagePlugin.getdata``, which :func:`_save_gif` encodes each frame with, is gone."""
    if not frames:
        raise ValueError("no frame to write")
    with atomic_path(path) as tmp:
        frames[0].save(
            tmp,
            format="GIF",
            save_all=True,
            append_images=frames[1:],
            duration=max(20, round(1000.0 / fps)),
            loop=0,
        )


def _title(scene: Scene, step: int, dt: float | None) -> str:
    t = f"t = {step * dt:.3f} s" if dt is not None else f"step {step}"
    return f"{scene.title}   {t}" if scene.title else t


def animate(
    traj: Any,
    scene: Scene,
    path: str | os.PathLike[str],
    *,
    fps: int = 20,
    max_trajectories: int = 4,
    overlay: Any = None,
    dt: float | None = None,
    max_frames: int = 40,
    labels: Sequence[str] | None = None,
    trail: int = 10,
    dpi: int = 60,
    panel_size: float = 3.2,
    colors: int = 32,
) -> Path:
    """Write a GIF of one or several trajectories.

    Args:
        traj: ``(T, 2, P, dim)`` or ``(N, T, 2, P, dim)`` states (numpy or torch).
        scene: what to draw (see :mod:`diffcontact.viz.scene`); one of a system with
            states of another shape (:attr:`Scene.n_points <diffcontact.viz.scene.Scene>`,
            ``dim``) is refused with a ``ValueError`` naming both shapes.
        path: output ``.gif`` (written atomically).
        fps: playback frames per second.
        max_trajectories: at most this many trajectories, as a grid of subplots (at
            most :data:`MAX_PANELS`).
        overlay: optional second trajectory of the same shape (N may be 1),
            e.g. a prediction, drawn dashed over ``traj``.
        dt: time step, to show the time in the title (else the step index).
        max_frames: at most this many frames, evenly subsampled (first and
            last state included).
        labels: legend names for ``(traj, overlay)``.
        trail: length (in shown frames) of the faded path behind each body; 0
            for none.
        dpi: resolution (a 3.2 inch panel at 60 dpi is 192 pixels).
        panel_size: inches per trajectory panel. A frame has at most
            :data:`MAX_PIXELS` pixels (more is a ``ValueError``, before drawing).
        colors: palette size (2 to 256; fewer colours, smaller files).

    Returns:
        The path written. Each body has its own colour: filled for ``traj``, a
        dashed outline in the same colour for ``overlay``. Bodies in contact
        (penetrating a wall, another body or, in 3D, the plane) have a red
        outline. At the defaults, four BP5 trajectories of 100 states with an
        overlay take about 0.3 MB (``tests/viz/test_gif_colours.py``).
    """
    if not isinstance(colors, int) or not 2 <= colors <= 256:
        raise ValueError(f"colors must be an integer in [2, 256], got {colors!r}")
    _image_format(path, (".gif",))
    _positive("fps", fps)
    _positive("dpi", dpi)
    if dt is not None:  # (NaN or a negative step were shown in the titles)
        _positive("dt", dt)
    if isinstance(trail, bool) or not isinstance(trail, int) or trail < 0:
        raise ValueError(f"trail must be a non-negative integer, got {trail!r}")
    fig, panels, idx = _build_figure(
        traj,
        scene,
        max_trajectories=max_trajectories,
        overlay=overlay,
        max_frames=max_frames,
        labels=labels,
        trail=trail,
        panel_size=panel_size,
        dpi=dpi,
    )
    fig.set_dpi(dpi)
    title = fig.suptitle("", fontsize=9)
    palette, frames = _render_frames(
        fig, panels, idx, title, lambda step: _title(scene, step, dt), colors=min(colors, 255)
    )
    _save_gif(palette, frames, path, fps)
    return Path(path)


def plot_energy(
    E: Any,
    dt: float,
    path: str | os.PathLike[str],
    *,
    title: str = "",
    max_lines: int = 32,
    dpi: int = 100,
) -> Path:
    """Save a plot of energy against time: ``E(t)`` and ``E(t) - E(0)``.

    Args:
        E: ``(T,)`` or ``(N, T)`` energies (numpy or torch).
        dt: time step (> 0).
        path: output ``.png``, ``.pdf`` or ``.svg`` (by the suffix; written atomically).
        max_lines: at most this many trajectories are drawn (the title says when
            there were more).
        dpi: resolution; at most :data:`MAX_PIXELS` pixels (an 8 x 3.2 inch figure).
    """
    fmt = _image_format(path, (".png", ".pdf", ".svg"))
    _positive("dt", dt)
    _positive("dpi", dpi)
    _positive("max_lines", max_lines, integer=True)
    figsize = (8.0, 3.2)
    _check_pixels(*figsize, dpi, f"dpi {dpi} makes")
    e = _to_numpy(E)
    if e.ndim == 1:
        e = e[None]
    if e.ndim != 2 or e.shape[1] == 0 or e.shape[0] == 0:
        raise ValueError(f"E must have shape (T,) or (N, T) with N, T >= 1, got {np.shape(E)}")
    if not np.isfinite(e).any():
        raise ValueError("E holds no finite value (every trajectory diverged)")
    n_given = len(e)
    e = e[:max_lines]
    t = np.arange(e.shape[1]) * float(dt)
    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.subplots(1, 2)
    alpha = 1.0 if len(e) <= 4 else 0.6
    # trajectories, not bodies: tab10 (the GIFs' palette has two blues, bodies 0 and 3)
    colors = matplotlib.colormaps["tab10"].colors
    for i, ei in enumerate(e):
        color = colors[i % len(colors)]
        ax1.plot(t, ei, color=color, lw=1.2, alpha=alpha, label=f"#{i}")
        ax2.plot(t, ei - ei[0], color=color, lw=1.2, alpha=alpha)
    ax1.set_ylabel("energy E (J)")
    ax2.set_ylabel("E(t) - E(0) (J)")
    ax2.add_collection(LineCollection([[(t[0], 0.0), (t[-1], 0.0)]], colors="k", lw=0.6))
    if len(e) <= 10:  # named as the GIF's panels
        ax1.legend(title="trajectory", fontsize=7, title_fontsize=7, ncol=2 if len(e) > 5 else 1)
    for ax in (ax1, ax2):
        ax.set_xlabel("time (s)")
        ax.grid(True, lw=0.3)
    if n_given > max_lines:
        title = f"{title}   ({max_lines} of {n_given} trajectories)".strip()
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format=fmt, dpi=dpi)
    return Path(path)
