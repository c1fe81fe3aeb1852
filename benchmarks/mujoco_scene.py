"""A MuJoCo scene matched to a ``bouncing_masses`` task (BP5), for the simulate benchmark.

This is a benchmark module, not part of the library: ``python benchmarks/run.py simulate
--compare mujoco`` times ``System("BP5").simulate`` against ``mujoco.rollout`` on this
scene. Everything is read from the task's config (``dc.load_system(task).config``):

- every body is a sphere of the config's radius and mass in the plane ``z = 0``, on two
  slide joints (x, y) and no hinge: the task's bodies are point masses that do not rotate
  (``BouncingMassesConfig``), so ``qpos`` is the body's (x, y) position and ``qvel`` its
  velocity, the same numbers as the rows of our state ``z: (N, 2, P, 2)``;
- every wall ``[a, b, c]`` (allowed side ``a x + b y + c > 0``) is a plane geom whose
  normal (its z axis) is ``(a, b, 0) / |(a, b)|``, through the point of the line nearest
  the origin; MuJoCo planes are one-sided half-spaces, as our walls are;
- the contacts are explicit ``<pair>`` elements in our numbering (body pairs ``(i, j)``,
  ``i < j``, then body-wall pairs body-major), each with the config's per-contact
  friction ``mu`` (elliptic cone, ``condim`` 3; ``condim`` 1, frictionless, where
  ``mu = 0``) and a restitution-derived ``solref``; the geoms' own collision masks are off,
  so exactly these pairs can collide;
- ``timestep`` is the config's ``dt``, gravity is ``(0, -g, 0)`` (ours acts along -y),
  the integrator is MuJoCo's default semi-implicit ``Euler``.

What is *not* matched, by construction: MuJoCo's contacts are soft. A contact is a
constraint whose reference acceleration is a spring-damper on the penetration,
``a_ref = -b v - k r``, solved by a convex optimisation every step while the bodies
overlap (several steps per bounce), where ours is the paper's hard two-phase impulse
(compression, then Poisson restitution ``e_P``) applied in one step, plus a penetration
compensation. We approximate ``e_P`` the documented MuJoCo way, with the direct
(negative) ``solref = (-stiffness, -damping)`` format: stiffness ``k = 1 / timeconst^2``
(``timeconst = 2 dt`` by default, the smallest time constant MuJoCo's documentation
recommends for a stable contact at step ``dt``) and damping ``b = 2 zeta sqrt(k)`` with the
damping ratio ``zeta`` for which a linear damped oscillator loses the fraction of speed
that ``e_P`` asks for, ``e = exp(-pi zeta / sqrt(1 - zeta^2))``. ``e_P = 1`` gives no
damping, ``e_P = 0`` critical damping. The realised restitution differs (the constraint
force cannot pull, the step is discrete), and so do friction during the several contact
steps and the penetration depths, so trajectories agree to rounding only until the first
contact. The benchmark prints both differences.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

MISSING_MUJOCO = (
    "--compare mujoco needs the `mujoco` package (MuJoCo's Python bindings): "
    'pip install mujoco   (or pip install -e ".[bench]")'
)


def import_mujoco() -> Any:
    """The ``mujoco`` module, or ``ImportError`` with a message saying how to install it."""
    try:
        import mujoco
        import mujoco.rollout  # the submodule is not imported by `mujoco` itself
    except ImportError as err:
        raise ImportError(f"{MISSING_MUJOCO} ({err})") from None
    return mujoco


def damping_ratio(e: float) -> float:
    """Damping ratio ``zeta`` of a linear oscillator whose coefficient of restitution is ``e``.

    A contact modelled as ``r'' = -2 zeta w r' - w^2 r`` (``zeta < 1``) leaves with
    ``e = exp(-pi zeta / sqrt(1 - zeta^2))`` times its approach speed; inverted,
    ``zeta = -ln e / sqrt(pi^2 + ln^2 e)``. ``e = 0`` gives 1 (critical damping).
    """
    if not 0.0 <= e <= 1.0:
        raise ValueError(f"a coefficient of restitution must be in [0, 1], got {e}")
    if e == 0.0:
        return 1.0
    log_e = math.log(e)
    return -log_e / math.sqrt(math.pi**2 + log_e**2)


@dataclass(frozen=True)
class MujocoScene:
    """A compiled MuJoCo model matched to a task, and how to map states to it.

    Attributes:
        model: the ``mujoco.MjModel``.
        xml: the MJCF text it was compiled from.
        n_bodies: P, the number of bodies (points) of the task.
        timeconst: the contact time constant used for every ``solref``.
        qpos_slice, qvel_slice: where ``qpos`` and ``qvel`` sit in a
            ``mjSTATE_FULLPHYSICS`` state vector.
        nstate: the length of that vector.
        pair_ids: ``(K,)`` the ``model.pair_*`` row of each of our contact candidates
            (MuJoCo's compiler sorts pairs by body, so the rows are not in our order).
    """

    model: Any
    xml: str
    n_bodies: int
    timeconst: float
    qpos_slice: slice
    qvel_slice: slice
    nstate: int
    pair_ids: np.ndarray


def _fmt(x: float) -> str:
    return repr(float(x))


def build_scene(config: Any, *, timeconst: float | None = None) -> MujocoScene:
    """MJCF scene of a ``bouncing_masses`` config (e.g. ``dc.load_system("BP5").config``).

    Args:
        config: a ``BouncingMassesConfig`` (point masses in 2D with walls).
        timeconst: contact time constant in seconds (default ``2 * config.dt``).

    Returns:
        A :class:`MujocoScene`; ``model.pair_*[scene.pair_ids]`` are our contact
        candidates in our numbering (``config.per_contact``).
    """
    mujoco = import_mujoco()
    if getattr(config, "type", None) != "bouncing_masses":
        raise ValueError(
            "build_scene matches bouncing_masses tasks (point masses and walls in 2D), "
            f"got type {getattr(config, 'type', None)!r}"
        )
    dt = float(config.dt)
    tc = 2.0 * dt if timeconst is None else float(timeconst)
    if not tc > 0:
        raise ValueError(f"timeconst must be positive, got {tc}")
    masses, radii, walls = list(config.masses), list(config.radii), list(config.walls)
    B, W = len(masses), len(walls)
    mu, cor = config.per_contact("mu"), config.per_contact("cor")
    stiffness = 1.0 / tc**2

    lines = [
        f'<mujoco model="{config.name or "bouncing_masses"}">',
        f'  <option timestep="{_fmt(dt)}" gravity="0 {_fmt(-float(config.gravity))} 0" '
        'integrator="Euler" cone="elliptic"/>',
        "  <worldbody>",
    ]
    for j, (a, b, c) in enumerate(walls):
        norm = math.hypot(a, b)
        nx, ny, off = a / norm, b / norm, c / norm
        # the point of the line a x + b y + c = 0 nearest the origin: -off * n
        lines.append(
            f'    <geom name="wall{j}" type="plane" size="0 0 1" contype="0" conaffinity="0" '
            f'pos="{_fmt(-off * nx)} {_fmt(-off * ny)} 0" zaxis="{_fmt(nx)} {_fmt(ny)} 0"/>'
        )
    for i, (m, r) in enumerate(zip(masses, radii, strict=True)):
        inertia = 0.4 * m * r * r  # a solid sphere's; no rotational joint uses it
        lines += [
            f'    <body name="body{i}">',
            f'      <inertial pos="0 0 0" mass="{_fmt(m)}" diaginertia="{_fmt(inertia)} '
            f'{_fmt(inertia)} {_fmt(inertia)}"/>',
            f'      <joint name="body{i}_x" type="slide" axis="1 0 0"/>',
            f'      <joint name="body{i}_y" type="slide" axis="0 1 0"/>',
            f'      <geom name="ball{i}" type="sphere" size="{_fmt(r)}" contype="0" '
            'conaffinity="0"/>',
            "    </body>",
        ]
    lines += ["  </worldbody>", "  <contact>"]
    geom_pairs = [(f"ball{i}", f"ball{j}") for i in range(B) for j in range(i + 1, B)]
    geom_pairs += [(f"ball{i}", f"wall{j}") for i in range(B) for j in range(W)]
    for k, (g1, g2) in enumerate(geom_pairs):
        damping = 2.0 * damping_ratio(float(cor[k])) * math.sqrt(stiffness)
        condim = 3 if mu[k] > 0 else 1
        lines.append(
            f'    <pair name="contact{k}" geom1="{g1}" geom2="{g2}" condim="{condim}" '
            f'friction="{_fmt(mu[k])} {_fmt(mu[k])} 0 0 0" '
            f'solref="{_fmt(-stiffness)} {_fmt(-damping)}"/>'
        )
    lines += ["  </contact>", "</mujoco>"]
    xml = "\n".join(lines) + "\n"
    model = mujoco.MjModel.from_xml_string(xml)

    full = mujoco.mjtState.mjSTATE_FULLPHYSICS.value
    # the components of a state vector are concatenated in the order of their bits
    t_size = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_TIME.value)
    q_end = mujoco.mj_stateSize(
        model, mujoco.mjtState.mjSTATE_TIME.value | mujoco.mjtState.mjSTATE_QPOS.value
    )
    return MujocoScene(
        model=model,
        xml=xml,
        n_bodies=B,
        timeconst=tc,
        qpos_slice=slice(t_size, q_end),
        qvel_slice=slice(q_end, q_end + model.nv),
        nstate=mujoco.mj_stateSize(model, full),
        pair_ids=np.array(
            [
                mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_PAIR, f"contact{k}")
                for k in range(len(geom_pairs))
            ]
        ),
    )


def initial_states(scene: MujocoScene, z0: Tensor) -> np.ndarray:
    """``mjSTATE_FULLPHYSICS`` states ``(N, nstate)`` of our states ``z0: (N, 2, P, 2)``.

    Time 0, ``qpos`` = the positions, ``qvel`` = the velocities (body-major, x then y),
    every other component (activations, warm start, ...) zero.
    """
    if z0.dim() != 4 or z0.shape[1:] != (2, scene.n_bodies, 2):
        raise ValueError(f"z0 must have shape (N, 2, {scene.n_bodies}, 2), got {tuple(z0.shape)}")
    z = z0.detach().to(device="cpu", dtype=torch.float64).numpy()
    out = np.zeros((z.shape[0], scene.nstate), dtype=np.float64)
    out[:, scene.qpos_slice] = z[:, 0].reshape(z.shape[0], -1)
    out[:, scene.qvel_slice] = z[:, 1].reshape(z.shape[0], -1)
    return out


class Roller:
    """``mujoco.rollout`` on ``nthread`` threads, set up once so that a call times only stepping.

    Holds ``nthread`` MjData instances (one per thread) and a ``mujoco.rollout.Rollout``
    pool: with one thread the rollout runs on the calling thread (no pool), with more in a
    pool of that many threads. Use as a context manager, or call :meth:`close`.
    """

    def __init__(self, scene: MujocoScene, nthread: int = 1) -> None:
        mujoco = import_mujoco()
        if nthread < 1:
            raise ValueError(f"nthread must be >= 1, got {nthread}")
        self.scene = scene
        self.nthread = nthread
        self._data = [mujoco.MjData(scene.model) for _ in range(nthread)]
        self._pool = mujoco.rollout.Rollout(nthread=0 if nthread == 1 else nthread)

    def __call__(self, init: np.ndarray, nstep: int) -> np.ndarray:
        """States after each step, ``(N, nstep, nstate)``, from ``init: (N, nstate)``."""
        data = self._data if self.nthread > 1 else self._data[0]
        state, _ = self._pool.rollout(self.scene.model, data, init, nstep=nstep)
        return state

    def close(self) -> None:
        self._pool.close()

    def __enter__(self) -> Roller:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def rollout(scene: MujocoScene, init: np.ndarray, nstep: int, *, nthread: int = 1) -> np.ndarray:
    """One :class:`Roller` call: ``(N, nstep, nstate)`` states after each step."""
    with Roller(scene, nthread) as roll:
        return roll(init, nstep)


def positions(scene: MujocoScene, init: np.ndarray, states: np.ndarray) -> Tensor:
    """Positions ``(N, nstep + 1, P, 2)`` (float64) of a rollout, the initial state first."""
    q = np.concatenate([init[:, None, scene.qpos_slice], states[:, :, scene.qpos_slice]], 1)
    return torch.from_numpy(q).reshape(q.shape[0], q.shape[1], scene.n_bodies, 2)
