"""MuJoCo ``qpos``/``qvel`` to diffcontact trajectories (``docs/own-data.md``).

:func:`trajectories_from_mujoco` maps MuJoCo bodies (or sites) to the bodies of a
diffcontact config and computes their points' positions and velocities from
recorded ``qpos (N, T, nq)`` and ``qvel (N, T, nv)``, batched in torch: its own
forward kinematics from the model's arrays (``body_pos``, ``body_quat``,
``jnt_axis``, ...), the same recursion as MuJoCo's ``mj_kinematics``, so no
per-sample MuJoCo call is made, and MuJoCo itself is needed only to read an
XML file (``pip install diffcontact[mujoco]``). Importing diffcontact never
imports MuJoCo.

Joints: ``slide``, ``hinge``, ``free`` (a body of the world), and ``ball``.
``qvel`` follows MuJoCo: a slide or hinge rate along / about the joint axis, a
free joint's linear velocity of the body frame's origin in world coordinates
then its angular velocity in the body frame, a ball joint's angular velocity
in the body frame.

Body correspondence (``bodies``): one MuJoCo body (name or id) or site per
diffcontact body, in diffcontact's body order, each at most once (default: every
MuJoCo body but the world, in the model's order). Each gives the points of its
diffcontact kind:

- ``"point"``: the body's centre of mass (``xipos``), or a site's position
  (``"site:NAME"``, e.g. the tip of a pendulum link);
- ``"disk"`` (2D rigid body): centre of mass, centre + e_x, centre + e_y, with
  e_x the first axis of the body's frame (``axes``) that lies in the plane and
  e_y = n x e_x (n the plane's normal); the body must rotate about n only;
- ``"rigid3d"``: centre of mass and centre + each axis of the frame.

``axes="inertial"`` (default) takes the principal axes of inertia (``ximat``:
the frame in which diffcontact's diagonal second moments hold),
``axes="body"`` the body frame of the XML (``xmat``). 2D systems take two world
axes (``plane="xz"``: world x and z become diffcontact's x and y; gravity along
-z becomes diffcontact's -y).
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from diffcontact.learning.data.convert import (
    VELOCITY_MISMATCH_WARN,
    _check_finite,
    _check_samples,
    _check_shape,
    _system,
    velocity_mismatch,
)
from diffcontact.mechanics.bodies import quaternion_to_matrix

__all__ = ["MUJOCO_JOINTS", "load_mujoco_model", "trajectories_from_mujoco"]

MUJOCO_JOINTS = {0: "free", 1: "ball", 2: "slide", 3: "hinge"}
"""MuJoCo's joint type numbers (``mjtJoint``) and their names."""
_F = torch.float64
_AXES = ("inertial", "body")
_INSTALL = "pip install diffcontact[mujoco] (or pip install 'mujoco>=3')"


def load_mujoco_model(model: Any) -> Any:
    """An ``mujoco.MjModel``: ``model`` itself, or read from an MJCF ``.xml`` path.

    Raises:
        ImportError: a path was given and MuJoCo is not installed (names the extra).
        ValueError: the file does not exist or MuJoCo cannot compile it.
    """
    if isinstance(model, (str, Path)):
        path = Path(model)
        if not path.is_file():
            raise ValueError(f"MuJoCo model file {str(path)!r} does not exist")
        try:
            import mujoco
        except ImportError:
            raise ImportError(f"reading a MuJoCo model needs MuJoCo: {_INSTALL}") from None
        try:
            return mujoco.MjModel.from_xml_path(str(path))
        except ValueError as err:
            raise ValueError(f"MuJoCo cannot load {path}: {err}") from None
    needed = ("nbody", "nq", "nv", "jnt_type", "body_parentid", "body_pos", "body_quat")
    if not all(hasattr(model, a) for a in needed):
        raise ValueError(
            f"model must be a mujoco.MjModel or the path of an MJCF .xml file; got "
            f"{type(model).__name__}"
        )
    return model


def _names(model: Any, kind: str, count: int) -> list[str]:
    get = model.body if kind == "body" else model.site
    return [get(i).name for i in range(count)]


def _resolve(model: Any, spec: Any, position: int) -> tuple[str, int, str]:
    """``("body" | "site", id, label)`` of one entry of ``bodies``.

    An integer is a body id; so is a string of ASCII digits that is not the name of a
    body of the model (as the command line's ``--bodies`` gives ids): a body named
    ``"2"`` wins over the id 2.
    """
    if isinstance(spec, str) and spec.isascii() and spec.isdigit():
        if spec not in _names(model, "body", model.nbody):
            spec = int(spec)
    if isinstance(spec, (int, np.integer)) and not isinstance(spec, bool):
        i = int(spec)
        if not 1 <= i < model.nbody:
            raise ValueError(
                f"bodies[{position}] = {i}: MuJoCo body ids run from 1 to {model.nbody - 1} "
                "(0 is the world)"
            )
        name = _names(model, "body", model.nbody)[i]
        return "body", i, f"body {name!r} (id {i})" if name else f"body {i}"
    if not isinstance(spec, str):
        raise ValueError(f"bodies[{position}] must be a body name, 'site:NAME' or an id")
    kind, name = ("site", spec[5:]) if spec.startswith("site:") else ("body", spec)
    count = model.nbody if kind == "body" else model.nsite
    names = _names(model, kind, count)
    if name not in names:
        known = ", ".join(repr(n) for n in names if n) or "none with a name"
        plural = "bodies" if kind == "body" else "sites"
        raise ValueError(
            f"bodies[{position}]: the model has no {kind} {name!r} (its {plural}: {known})"
        )
    i = names.index(name)
    if kind == "body" and i == 0:
        raise ValueError(f"bodies[{position}]: the world body has no motion to convert")
    return kind, i, f"{kind} {name!r}"


def _rodrigues(axis: Tensor, angle: Tensor) -> Tensor:
    """``(..., 3, 3)`` rotation by ``angle (...)`` about the unit ``axis (3,)``."""
    K = torch.zeros((3, 3), dtype=axis.dtype, device=axis.device)
    K[0, 1], K[0, 2], K[1, 2] = -axis[2], axis[1], -axis[0]
    K = K - K.T
    s, c = torch.sin(angle)[..., None, None], torch.cos(angle)[..., None, None]
    return torch.eye(3, dtype=axis.dtype, device=axis.device) + s * K + (1 - c) * (K @ K)


def _mv(R: Tensor, v: Tensor) -> Tensor:
    return (R @ v[..., None])[..., 0]


def _kinematics(model: Any, qpos: Tensor, qvel: Tensor, needed: set[int]) -> dict[int, tuple]:
    """World frame and twist ``(xpos, R, omega, v_o)`` of the bodies in ``needed`` and
    their ancestors: ``xpos (N, T, 3)`` the body frame's origin, ``R (N, T, 3, 3)`` its
    axes, ``omega`` the angular velocity and ``v_o`` the velocity of the body-fixed point
    at the world origin (a point p moves with ``v_o + omega x p``)."""
    arr = {k: torch.as_tensor(np.asarray(getattr(model, k)), dtype=_F) for k in (
        "body_pos", "body_quat", "jnt_axis", "jnt_pos", "qpos0",
    )}  # fmt: skip
    parent = np.asarray(model.body_parentid)
    jnt_num, jnt_adr = np.asarray(model.body_jntnum), np.asarray(model.body_jntadr)
    jnt_type = np.asarray(model.jnt_type)
    qadr, dadr = np.asarray(model.jnt_qposadr), np.asarray(model.jnt_dofadr)
    mocap = np.asarray(model.body_mocapid)
    names = _names(model, "body", model.nbody)
    chain: set[int] = set()
    for b in needed:
        while b > 0:
            chain.add(b)
            b = int(parent[b])
    batch = qpos.shape[:-1]
    zero3 = qpos.new_zeros((*batch, 3))
    frames: dict[int, tuple] = {
        0: (zero3, torch.eye(3, dtype=_F).expand(*batch, 3, 3), zero3, zero3)
    }
    for b in sorted(chain):  # MuJoCo orders every parent before its children
        label = f"body {names[b] or b}"
        if mocap[b] >= 0:
            raise ValueError(f"{label} is a mocap body: its motion is not in qpos")
        p_pos, p_R, p_w, p_v = frames[int(parent[b])]
        joints = range(int(jnt_adr[b]), int(jnt_adr[b] + jnt_num[b]))
        types = [MUJOCO_JOINTS.get(int(jnt_type[j]), str(jnt_type[j])) for j in joints]
        if "free" in types:
            if len(types) != 1 or parent[b] != 0:
                raise ValueError(
                    f"{label}: a free joint is supported only as the single joint of a "
                    "child of the world"
                )
            j = joints[0]
            a, d = int(qadr[j]), int(dadr[j])
            xpos = qpos[..., a : a + 3]
            R = quaternion_to_matrix(qpos[..., a + 3 : a + 7])
            w = _mv(R, qvel[..., d + 3 : d + 6])
            v_o = qvel[..., d : d + 3] + torch.linalg.cross(xpos, w, dim=-1)
            frames[b] = (xpos, R, w, v_o)
            continue
        xpos = p_pos + _mv(p_R, arr["body_pos"][b])
        R = p_R @ quaternion_to_matrix(arr["body_quat"][b])
        w, v_o = p_w, p_v
        balls: list[tuple[Tensor, Tensor]] = []  # (anchor, body-frame rate): need the final R
        for j, kind in zip(joints, types, strict=True):
            a, d = int(qadr[j]), int(dadr[j])
            axis = _mv(R, arr["jnt_axis"][j])
            anchor = xpos + _mv(R, arr["jnt_pos"][j])
            if kind == "slide":
                xpos = xpos + axis * (qpos[..., a : a + 1] - arr["qpos0"][a])
                v_o = v_o + axis * qvel[..., d : d + 1]
            elif kind in ("hinge", "ball"):
                if kind == "hinge":
                    local = _rodrigues(arr["jnt_axis"][j], qpos[..., a] - arr["qpos0"][a])
                    w_j = axis * qvel[..., d : d + 1]
                    w, v_o = w + w_j, v_o + torch.linalg.cross(anchor, w_j, dim=-1)
                else:
                    local = quaternion_to_matrix(qpos[..., a : a + 4])
                    balls.append((anchor, qvel[..., d : d + 3]))
                R = R @ local
                xpos = anchor - _mv(R, arr["jnt_pos"][j])
            else:
                raise ValueError(
                    f"{label}: joint {j} has type {kind!r}; supported: slide, hinge, ball, free"
                )
        for anchor, rate in balls:
            w_j = _mv(R, rate)
            w, v_o = w + w_j, v_o + torch.linalg.cross(anchor, w_j, dim=-1)
        frames[b] = (xpos, R, w, v_o)
    return frames


def _plane(plane: Any, dim: int) -> tuple[int, int] | None:
    if dim == 3:
        if plane is not None:
            raise ValueError(f"plane applies to 2D systems only; this system is 3D (got {plane!r})")
        return None
    if not (isinstance(plane, str) and len(plane) == 2 and set(plane) <= set("xyz")):
        raise ValueError(
            "a 2D system needs plane: the two world axes that become its x and y, e.g. "
            f"plane='xy' or plane='xz' (gravity along -z becomes diffcontact's -y); got {plane!r}"
        )
    i, j = "xyz".index(plane[0]), "xyz".index(plane[1])
    if i == j:
        raise ValueError(f"plane must name two different axes; got {plane!r}")
    return i, j


def trajectories_from_mujoco(
    model: Any,
    qpos: Any,
    qvel: Any,
    config: Any,
    *,
    bodies: list[Any] | None = None,
    plane: str | None = None,
    axes: str = "inertial",
    origin: Any = None,
    on_out_of_plane: str = "warn",
) -> np.ndarray:
    """Trajectories ``(N, T, 2, P, d)`` of a diffcontact config from MuJoCo ``qpos``/``qvel``.

    Args:
        model: a ``mujoco.MjModel`` or the path of an MJCF ``.xml`` file.
        qpos: ``(N, T, nq)`` recorded ``MjData.qpos`` (numpy or torch).
        qvel: ``(N, T, nv)`` recorded ``MjData.qvel``.
        config: the diffcontact system (task name, ``.yaml``/``.json`` path, dict or
            ``System``): its bodies' kinds and dimension define the points.
        bodies: one entry per diffcontact body, in its order: a MuJoCo body name or
            id (an ``int``, or a string of digits that names no body of the model:
            ``"2"`` is the body named ``"2"`` if there is one, else id 2), or
            ``"site:NAME"`` (a site, for point bodies). Each MuJoCo body or site may
            appear once. Default: every MuJoCo body but the world, in the model's order.
        plane: 2D systems: two of ``"xyz"``, the world axes that become diffcontact's
            x and y (``"xz"``: a vertical plane with gravity along -z). ``None`` in 3D.
        axes: ``"inertial"`` (principal axes, default) or ``"body"`` (the XML body
            frame): the axis points of disks and rigid 3D bodies.
        origin: ``(3,)`` world point that becomes diffcontact's origin (e.g. a
            pendulum's pivot; default the world origin).
        on_out_of_plane: 2D systems: ``"warn"`` (default), ``"raise"`` or
            ``"ignore"`` when some point moves out of the plane (the projection drops
            that motion).

    Returns:
        ``z (N, T, 2, P, d)`` float64 numpy array, ready for ``dataset_from_arrays`` /
        ``diffcontact generate --from-arrays``.

    Raises:
        ValueError: wrong shapes, unknown body or site names, a count of bodies
            different from the config's, a MuJoCo body or site given twice, an
            unsupported joint (with its type), a disk that does not rotate about the
            plane's normal, a site for a rigid body.
        ImportError: an XML path was given and MuJoCo is not installed.
    """
    model = load_mujoco_model(model)
    system = _system(config)
    if axes not in _AXES:
        raise ValueError(f"axes must be one of {', '.join(_AXES)}; got {axes!r}")
    if on_out_of_plane not in ("warn", "raise", "ignore"):
        raise ValueError(f"on_out_of_plane must be warn, raise or ignore; got {on_out_of_plane!r}")
    proj = _plane(plane, system.dim)
    qp = torch.as_tensor(np.asarray(qpos, dtype=np.float64) if not isinstance(qpos, Tensor)
                         else qpos.detach().cpu().to(_F))  # fmt: skip
    qv = torch.as_tensor(np.asarray(qvel, dtype=np.float64) if not isinstance(qvel, Tensor)
                         else qvel.detach().cpu().to(_F))  # fmt: skip
    _check_shape(qp, "qpos", (model.nq,), f"nq = {model.nq} of the MuJoCo model")
    _check_shape(qv, "qvel", (model.nv,), f"nv = {model.nv} of the MuJoCo model")
    _check_samples(qp, "qpos", 1)
    if qp.shape[:2] != qv.shape[:2]:
        raise ValueError(
            f"qpos and qvel must hold the same trajectories and samples: (N, T) = "
            f"{tuple(qp.shape[:2])} and {tuple(qv.shape[:2])}"
        )
    _check_finite(qp, "qpos")
    _check_finite(qv, "qvel")

    kinds = [b.kind for b in system.bodies()]
    specs = list(range(1, model.nbody)) if bodies is None else list(bodies)
    if len(specs) != len(kinds):
        listed = ", ".join(repr(n or i) for i, n in enumerate(_names(model, "body", model.nbody)))
        raise ValueError(
            f"{system.name} has {len(kinds)} bodies but {len(specs)} MuJoCo "
            f"{'bodies' if bodies is not None else 'bodies besides the world'} were given; "
            f"pass bodies=[...] (MuJoCo body names, ids or 'site:NAME', one per diffcontact "
            f"body in its order); the model's bodies: {listed}"
        )
    resolved = [_resolve(model, s, i) for i, s in enumerate(specs)]
    first: dict[tuple[str, int], int] = {}
    for j, (kind, i, label) in enumerate(resolved):
        k = first.setdefault((kind, i), j)
        if k != j:
            raise ValueError(
                f"bodies[{k}] and bodies[{j}] are both MuJoCo {label}: each diffcontact "
                "body needs its own MuJoCo body or site"
            )
    owner = [i if k == "body" else int(model.site_bodyid[i]) for k, i, _ in resolved]
    frames = _kinematics(model, qp, qv, set(owner))
    shift = torch.zeros(3, dtype=_F) if origin is None else torch.as_tensor(origin, dtype=_F)
    if shift.shape != (3,):
        raise ValueError(f"origin must be a point (x, y, z); got shape {tuple(shift.shape)}")
    normal = None
    if proj is not None:
        normal = torch.linalg.cross(
            torch.eye(3, dtype=_F)[proj[0]], torch.eye(3, dtype=_F)[proj[1]]
        )

    points: list[Tensor] = []  # world points (N, T, 3) of each diffcontact point
    owners: list[int] = []
    for (kind, i, label), kind_dc, b in zip(resolved, kinds, owner, strict=True):
        xpos, R = frames[b][0], frames[b][1]
        if kind == "site":
            if kind_dc != "point":
                raise ValueError(f"{label}: a site gives one point, but body is a {kind_dc!r}")
            points.append(xpos + _mv(R, torch.as_tensor(np.asarray(model.site_pos[i]), dtype=_F)))
            owners.append(b)
            continue
        ipos = torch.as_tensor(np.asarray(model.body_ipos[i]), dtype=_F)
        centre = xpos + _mv(R, ipos)
        if axes == "inertial":
            R = R @ quaternion_to_matrix(torch.as_tensor(np.asarray(model.body_iquat[i]), dtype=_F))
        if kind_dc == "point":
            new = [centre]
        elif kind_dc == "rigid3d":
            new = [centre, *(centre + R[..., :, k] for k in range(3))]
        elif kind_dc == "disk" and normal is not None:
            along = (R.transpose(-1, -2) @ normal).abs()  # (N, T, 3): |axis_k . n|
            normal_axis = (along > 1 - 1e-6).all(0).all(0)
            if not bool(normal_axis.any()):
                raise ValueError(
                    f"{label}: none of its {axes} axes stays along the normal of plane "
                    f"{plane!r}; a 2D disk must rotate about that normal only (try "
                    f"axes={'body' if axes == 'inertial' else 'inertial'!r})"
                )
            k = int((~normal_axis).nonzero()[0])
            e_x = R[..., :, k]
            new = [centre, centre + e_x, centre + torch.linalg.cross(normal.expand_as(e_x), e_x)]
        else:
            raise ValueError(f"{label}: no conversion to a diffcontact body of kind {kind_dc!r}")
        points += new
        owners += [b] * len(new)

    x = torch.stack(points, dim=2)  # (N, T, P, 3)
    w = torch.stack([frames[b][2] for b in owners], dim=2)
    v_o = torch.stack([frames[b][3] for b in owners], dim=2)
    v = v_o + torch.linalg.cross(w, x, dim=-1)
    x = x - shift
    if proj is not None:
        _check_planar(x, v, normal, on_out_of_plane)
        x, v = x[..., list(proj)], v[..., list(proj)]
    if x.shape[1] >= 3:  # as convert coordinates warns (it showed only in the checks line)
        mismatch = velocity_mismatch(x, v, float(system.dt))
        if mismatch > VELOCITY_MISMATCH_WARN:
            warnings.warn(
                f"the velocities from qvel do not match the motion of qpos: the point "
                f"velocities differ from the positions' finite differences (at the config's "
                f"dt={system.dt:g}) by {mismatch:.2f} of the median speed; check that the "
                "recording is sampled at the config's dt and that qvel is MjData.qvel",
                RuntimeWarning,
                stacklevel=2,
            )
    return torch.stack([x, v], dim=2).numpy()


def _check_planar(x: Tensor, v: Tensor, normal: Tensor, on_out_of_plane: str) -> None:
    if on_out_of_plane == "ignore":
        return
    off = x @ normal
    drift = float((off - off[:, :1]).abs().max())
    speed = float((v @ normal).abs().max())
    scale = 1.0 + float(x.abs().max()) + float(v.abs().max())
    if max(drift, speed) <= 1e-6 * scale:
        return
    message = (
        f"the points move out of the plane by up to {drift:.3g} (out-of-plane speed up to "
        f"{speed:.3g}); the projection onto the plane drops that motion"
    )
    if on_out_of_plane == "raise":
        raise ValueError(message)
    warnings.warn(message, RuntimeWarning, stacklevel=3)
