"""Learned models: the ground-truth :class:`~diffcontact.systems.System` with learnable parameters.

A :class:`LearnedModel` *is* a simulator (DESIGN.md): it wraps the same
``System`` class that generates the data and, on every call, fills the
system's parameter tensors from its modules before calling ``System.simulate``.
Collision detection, the mechanics and the contact solver are the ground
truth's; only where ``M^-1``, ``V``, ``mu`` and ``e_P`` come from differs:

- inverse inertia in the extended-body form (``docs/conventions.md``): a
  common log mass scale and one relative log mass per body
  (``mass = exp(log_mass_scale + log_mass_rel)``) and, for rigid bodies, one
  log second moment per body axis
  (``second_moments = exp(log_second_moments)``), initialised at mass 1 and
  second moments equal to each body's known size squared (radius, or the
  gyroscope's rim radius; not the truth). The common scale is its own
  parameter because the data never fix it: scaling every mass and the
  potential by one factor leaves the motion unchanged, so only mass *ratios*
  are learned from data. CM's loss is flat along that direction; CMr's is
  not (its ``eps I`` is in units of inverse mass, so ``eps * mass`` is what
  regularises) and falls as the masses shrink, towards CM. With one parameter
  for the direction, Adam follows that slope at its full step size instead of
  a small fraction of it hidden in per-body gradient noise
  (``docs/training.md``, "CMr and the mass scale");
- potential ``V(x)``: an MLP on the flattened positions ``(..., P*dim)`` with
  Softplus activations (3 hidden layers of 256 by default), plugged in as
  ``System.potential_model``; the system's ``gravity`` (and the rope's spring
  ``stiffness``) are set to 0 so the MLP carries the whole potential;
- friction ``mu = relu(raw_mu)`` and restitution
  ``e_P = hardsigmoid(6 raw_cor - 3)`` (``torch.nn.functional.hardsigmoid``:
  ``clamp(x / 6 + 1/2, 0, 1)``, so ``e_P = clamp(raw_cor, 0, 1)``: the
  argument is scaled so that ``raw_cor`` moves in units of ``e_P``, like
  ``raw_mu`` in units of ``mu``; with the plain hard sigmoid's slope of 1/6,
  ``e_P`` learned six times slower than ``mu``), initialised at 0.5 each; one
  shared value for homogeneous tasks, one per contact for heterogeneous ones
  (BP5, BD5);
- CMr's regulariser ``eps``: a fixed number or ``exp(log_eps)`` (learnable,
  initialised at 0.01).

Model names (:data:`~diffcontact.learning.models.registry.BUILTIN_MODELS`):
``CM-CD-CLNN``, ``CM-CD-CHNN``, ``CMr-CD-CLNN``, ``CMr-CD-CHNN``, ``LCP-CD-CLNN``,
``LCP-CD-CHNN`` (the LCP contact model of :mod:`diffcontact.contact.lcp`: Newton's
restitution, so ``e_P`` is Newton's coefficient there; no ``eps``), and
``Coulomb-CD-CLNN``, ``Coulomb-CD-CHNN`` (exact Coulomb friction,
:mod:`diffcontact.contact.coulomb`; not in the paper).

Example::

    model = LearnedModel("BP5", model="CMr-CD-CLNN", eps="learnable")
    traj = model.simulate(z0, steps=4)          # (N, 5, 2, P, dim), z0's dtype/device
    model.learned_parameters()                  # plain numbers
    model.save("run/model.pt"); model = load_model("run")
"""

from __future__ import annotations

import copy
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from diffcontact.learning.models.protocol import OptimizerSettings
from diffcontact.learning.models.registry import BUILTIN_MODELS as MODELS
from diffcontact.learning.models.registry import parse_model_name
from diffcontact.systems import PhysicalParams, System, load_config

__all__ = [
    "MODELS",
    "PHYSICS_BETAS",
    "LearnedModel",
    "PotentialMLP",
    "hidden_widths",
    "parse_model_name",
]

# paper-facts.md, "Homogeneous tasks": one mu/e_P shared by all contacts, or one per contact
# Adam's betas for the physical parameters: beta2 = 0.99 (not 0.999) so that their step
# size follows the gradient scale within ~100 steps: their gradients shrink by orders of
# magnitude once mu and e_P settle, and a run has only a few hundred steps
PHYSICS_BETAS = (0.9, 0.99)
# 2: e_P = hardsigmoid(6 raw_cor - 3) (format 1 had hardsigmoid(raw_cor))
# 3: mass = exp(log_mass_scale + log_mass_rel) (format 2 had exp(log_mass); read and converted)
FORMAT_VERSION = 3
_INIT_MU = 0.5
_INIT_COR = 0.5
_INIT_EPS = 0.01


def hidden_widths(name: str, value: Any) -> tuple[int, ...]:
    """Hidden-layer widths: a non-empty list of positive integers, or ``"64,64"`` as a
    ``--model-option`` may give them (``"16"`` is ``[16]``; it was read as the digits
    ``[1, 6]``). Anything else (``[]``, ``16.7``, ``True``) is a ``ValueError`` naming
    ``name``."""
    bad = f"{name} must be a non-empty list of positive integers (e.g. [64, 64]), got {value!r}"
    if isinstance(value, str):
        try:
            value = [int(v) for v in value.split(",") if v.strip()]
        except ValueError:
            raise ValueError(bad) from None
    if not isinstance(value, Sequence) or isinstance(value, (bytes, bytearray)) or not value:
        raise ValueError(bad)
    if any(isinstance(h, bool) or not isinstance(h, int) or h < 1 for h in value):
        raise ValueError(bad)
    return tuple(int(h) for h in value)


def _default_heterogeneous(system: System) -> bool:
    """One mu/e_P per contact when the config says ``contact_parameters: per_contact``."""
    return system.config.contact_parameters == "per_contact"


class _MLPWeights:
    """The potential MLP's arithmetic on given weight tensors: ``hidden`` pairs ``(W_l,
    b_l)`` and the output row ``w`` (no bias), computed in ``compute_dtype`` (``None``:
    ``x``'s). :class:`PotentialMLP` computes with its parameters through it, and
    :meth:`PotentialMLP.for_rollout` with its parameters cast once."""

    def __init__(
        self,
        hidden: Sequence[tuple[Tensor, Tensor | None]],
        out: Tensor,
        compute_dtype: torch.dtype | None,
    ) -> None:
        self.hidden_layers = list(hidden)
        self.out = out
        self.compute_dtype = compute_dtype

    def hidden(
        self, x: Tensor, dtype: torch.dtype | None = None
    ) -> tuple[Tensor, list[tuple[Tensor, Tensor]]]:
        """The last hidden activations ``(..., H)`` and, per hidden layer, its weight (in
        the compute dtype) and pre-activation ``a_l``; ``dtype`` as in
        :meth:`PotentialMLP.features`."""
        h = x.flatten(-2)
        dtype = dtype or self.compute_dtype
        if dtype is not None:
            h = h.to(dtype)
        trace = []
        for w, b in self.hidden_layers:
            if w.dtype != h.dtype or w.device != h.device:
                w, b = w.to(h), None if b is None else b.to(h)
            a = F.linear(h, w, b)
            h = F.softplus(a)
            trace.append((w, a))
        return h, trace

    def __call__(self, x: Tensor) -> Tensor:
        """``V(x)``, ``(..., P, dim) -> (...)`` in ``x``'s dtype."""
        h = self.hidden(x)[0]
        return F.linear(h, self.out.to(h)).squeeze(-1).to(x.dtype)

    def gradient(self, x: Tensor) -> Tensor:
        """``grad_x V(x)`` (:meth:`PotentialMLP.gradient`)."""
        h, trace = self.hidden(x)
        weights = [w for w, _ in trace]
        slopes = [torch.sigmoid(a) for _, a in trace]
        g = slopes[-1] * self.out.to(h).squeeze(0)
        for w_l, s_l in zip(weights[:0:-1], slopes[-2::-1], strict=True):
            g = (g @ w_l) * s_l
        g = g @ weights[0]
        return g.to(x.dtype).unflatten(-1, x.shape[-2:])


class PotentialMLP(nn.Module):
    """``V(x)``: an MLP on flattened positions, ``(..., P, dim) -> (...)``.

    Softplus hidden activations (smooth, so ``grad V`` and its derivative exist
    for the RK4 dynamics and the training gradient); the output layer has no
    bias (a constant in ``V`` exerts no force). The weights are cast to
    ``x``'s dtype and device when they differ, so one model can roll out in
    float32 and float64 (a no-op when they match).

    With ``compute_dtype`` (e.g. ``torch.float32``) the network runs in that
    dtype whatever ``x``'s (input cast in, ``V`` cast back, gradients flow
    through both casts): its matrix products are most of a training step's
    arithmetic, and float32 halves them while the mechanics and the contact
    solve stay in float64 (docs/training.md, "float32 or float64").

    Args:
        n_inputs: ``P * dim``.
        hidden: widths of the hidden layers.
        compute_dtype: the dtype the layers run in (``None``: ``x``'s).
    """

    def __init__(
        self,
        n_inputs: int,
        hidden: Sequence[int] = (256, 256, 256),
        compute_dtype: torch.dtype | None = None,
    ) -> None:
        super().__init__()
        self.compute_dtype = compute_dtype
        widths = [int(n_inputs), *(int(h) for h in hidden), 1]
        n = len(widths) - 1
        # no output bias: a constant in V changes no force and would get no gradient
        self.layers = nn.ModuleList(
            nn.Linear(widths[i], widths[i + 1], bias=i < n - 1) for i in range(n)
        )

    def _weights(self) -> _MLPWeights:
        hidden = [(layer.weight, layer.bias) for layer in self.layers[:-1]]
        return _MLPWeights(hidden, self.layers[-1].weight, self.compute_dtype)

    def for_rollout(self) -> PotentialMLP | _MLPWeights:
        """This potential for one rollout: with ``compute_dtype`` set and parameters in
        another dtype, a callable (``V(x)``, :meth:`gradient`) holding the parameters cast
        to ``compute_dtype`` once, with their gradients, instead of at every evaluation
        (a training step evaluates ``grad V`` at every RK4 stage; the same values and
        gradients); else this module."""
        dtype = self.compute_dtype
        if dtype is None or all(p.dtype == dtype for p in self.parameters()):
            return self

        def cast(t: Tensor | None) -> Tensor | None:
            return None if t is None else t.to(dtype)

        hidden = [(cast(layer.weight), cast(layer.bias)) for layer in self.layers[:-1]]
        return _MLPWeights(hidden, cast(self.layers[-1].weight), dtype)

    def features(self, x: Tensor, dtype: torch.dtype | None = None) -> Tensor:
        """``phi(x)``: the last hidden layer's activations, ``(..., P, dim) -> (..., H)``.

        ``V(x) = phi(x) @ w`` with ``w`` the output layer's weights (no bias), so ``V``
        is linear in ``w`` (what :mod:`~diffcontact.learning.training.refit` uses).
        ``dtype``: the dtype to compute in (``None``: ``compute_dtype``, else ``x``'s).
        """
        return self._weights().hidden(x, dtype)[0]

    def forward(self, x: Tensor) -> Tensor:
        return self._weights()(x)

    def gradient(self, x: Tensor) -> Tensor:
        """``grad_x V(x)``, ``(..., P, dim) -> (..., P, dim)``, by the chain rule written out.

        ``a_l = W_l h_(l-1) + b_l``, ``h_l = softplus(a_l)``, ``V = w . h_L``, so
        ``grad_x V = W_1^T (s_1 * W_2^T (s_2 * ... W_L^T (s_L * w)))`` with ``s_l =
        sigmoid(a_l)`` (softplus' derivative). The same value as autograd's gradient of
        :meth:`forward` (up to torch's softplus switching to the identity above 20, where
        the sigmoid differs from 1 by less than 2e-9), built from plain tensor operations
        that a training step differentiates once: autograd's ``create_graph`` gradient
        would be differentiated through softplus' backward (double backward), with more
        operations (``python benchmarks/run.py launches`` counts a step's).
        :func:`~diffcontact.mechanics.potential_gradient` uses this method when a
        potential has it.
        """
        return self._weights().gradient(x)


def _initial_second_moments(cfg: Any, shape: tuple[int, int]) -> Tensor:
    """``(B, k)`` initial second moments: each body's known size squared.

    Second moments are lengths squared, and the bodies' sizes are part of the
    known geometry (the collision detection needs them): a disk's radius
    (BD5), the gyroscope's rim radius. Starting from ``size**2`` (a thin
    ring's moment about a diameter is ``size**2 / 2``, a uniform disk's
    ``size**2 / 4``: the truth is *not* assumed) puts every body within a
    factor of a few of any plausible mass distribution; starting from 1 m^2,
    BD5's smallest disk (0.05 m radius, second moment 6e-4 m^2) was a factor
    of 1600 away, which the optimiser did not cover in hundreds of steps.
    """
    radii = getattr(cfg, "radii", None)
    if radii is None:
        radii = [getattr(cfg, "rim_radius", 1.0)] * shape[0]
    size = torch.tensor(radii, dtype=torch.float32)
    return (size**2)[:, None].expand(shape).clone()


def _cor_from_raw(raw: Tensor) -> Tensor:
    """``e_P = hardsigmoid(6 raw - 3) = clamp(raw, 0, 1)``."""
    return F.hardsigmoid(6.0 * raw - 3.0)


def _cor_raw(cor: Tensor) -> Tensor:
    """Inverse of :func:`_cor_from_raw` on [0, 1]: the identity."""
    return cor.clone()


class LearnedModel(nn.Module):
    """A CM/CMr/LCP-CD-CLNN/CHNN model: a :class:`System` whose parameters are learnable.

    Args:
        config: the known structure: a built-in task name, a config path, a
            dict or a validated config (geometry, constraints, contact
            candidates and ``dt`` are taken from it; its masses, potential,
            ``mu`` and ``cor`` are *not* used).
        model: one of :data:`MODELS`.
        eps: CMr's regulariser: a positive number (0.001, 0.01, 0.1 in the
            paper's ablation) or ``"learnable"`` (``exp(log_eps)``, initialised
            at 0.01). Ignored (``None``) for CM models.
        heterogeneous: one ``mu``/``e_P`` per contact (``True``) or one shared
            value (``False``); ``None`` reads the config key
            ``contact_parameters`` (``per_contact`` in BP5 and BD5, ``shared``
            by default; docs/config.md).
        hidden: hidden widths of the potential MLP.
        potential_dtype: ``"float32"`` runs the potential MLP in float32 inside
            a float64 rollout (:class:`PotentialMLP`'s ``compute_dtype``): about
            1.5x faster training steps; ``None`` (default): the rollout's dtype.
        penetration_gradient: whether :meth:`simulate` (the training rollouts)
            differentiates the penetration compensation target. ``False``
            (default): the paper's training set-up (appendix G), which every
            result in docs/results.md used; ``True``: the exact derivative of the
            rollout (``System.simulate``'s default, and what planning through the
            model uses, :func:`~diffcontact.control.as_planner`).

    Parameters (``nn.Parameter``): ``log_mass_scale ()``, ``log_mass_rel (B,)``,
    ``log_second_moments (B, dim)`` (rigid bodies only), ``raw_mu (1,)`` or
    ``(K,)``, ``raw_cor`` likewise, ``log_eps ()`` (CMr with learnable eps only)
    and the MLP's.

    The dtype and device of a rollout follow ``z0`` (the parameters are cast
    as needed, with gradients); move the model with ``.to(...)`` to keep its
    parameters where the data is.
    """

    def __init__(
        self,
        config: Any,
        *,
        model: str = "CM-CD-CLNN",
        eps: float | str | None = 0.01,
        heterogeneous: bool | None = None,
        hidden: Sequence[int] = (256, 256, 256),
        potential_dtype: str | None = None,
        penetration_gradient: bool = False,
    ) -> None:
        super().__init__()
        self.contact_model, self.dynamics = parse_model_name(model)
        if not isinstance(penetration_gradient, bool):
            raise ValueError(
                f"penetration_gradient must be True or False, got {penetration_gradient!r}"
            )
        self.penetration_gradient = penetration_gradient
        self.model_name = model
        cfg = load_config(config)
        self.system = System(cfg)
        system = self.system
        if heterogeneous is None:
            heterogeneous = _default_heterogeneous(system)
        if not isinstance(heterogeneous, bool):
            raise ValueError(f"heterogeneous must be True, False or None, got {heterogeneous!r}")
        self.heterogeneous = heterogeneous
        self.hidden = hidden = hidden_widths("hidden", hidden)

        self.eps_option: float | str | None
        if self.contact_model != "CMr":
            self.eps_option = None
        elif eps == "learnable":
            self.eps_option = "learnable"
            self.log_eps = nn.Parameter(torch.tensor(math.log(_INIT_EPS)))
        else:
            try:
                value = float(eps)  # type: ignore[arg-type]
            except (TypeError, ValueError):
                raise ValueError(
                    f"eps must be a positive number or 'learnable', got {eps!r}"
                ) from None
            if not (value > 0 and math.isfinite(value)):
                raise ValueError(f"eps must be a positive number or 'learnable', got {eps!r}")
            self.eps_option = value

        B, K = system.n_bodies, system.n_contacts
        self.log_mass_scale = nn.Parameter(torch.zeros(()))
        self.log_mass_rel = nn.Parameter(torch.zeros(B))
        if system.second_moments is not None:
            init = _initial_second_moments(cfg, tuple(system.second_moments.shape))
            self.log_second_moments = nn.Parameter(init.log())
        else:
            self.log_second_moments = None
        n_coef = K if heterogeneous else 1
        self.raw_mu = nn.Parameter(torch.full((n_coef,), _INIT_MU))
        self.raw_cor = nn.Parameter(_cor_raw(torch.full((n_coef,), _INIT_COR)))
        self.potential: nn.Module | None = PotentialMLP(system.n_points * system.dim, hidden)
        self.potential_dtype = potential_dtype

    @property
    def potential_dtype(self) -> str | None:
        """The dtype the potential MLP runs in: ``"float32"``, ``"float64"`` or ``None``
        (the rollout's). Settable on a trained model, e.g. ``"float32"`` to plan or
        simulate with a model trained in float64: planning iterations 1.5-1.8x faster
        on a 2-core CPU (``python benchmarks/run.py control``, its learned rows)."""
        return self._potential_dtype

    @potential_dtype.setter
    def potential_dtype(self, value: str | None) -> None:
        if value not in (None, "float32", "float64"):
            raise ValueError(f"potential_dtype must be 'float32', 'float64' or None, got {value!r}")
        self._potential_dtype = value
        if isinstance(getattr(self, "potential", None), PotentialMLP):
            self.potential.compute_dtype = None if value is None else getattr(torch, value)

    # ------------------------------------------------------------ structure
    @property
    def config(self):
        """The validated config of the known structure."""
        return self.system.config

    @property
    def name(self) -> str:
        return self.system.name

    @property
    def dt(self) -> float:
        return self.system.dt

    @property
    def default_steps(self) -> int:
        return self.system.default_steps

    @property
    def state_shape(self) -> tuple[int, int, int]:
        return self.system.state_shape

    @property
    def n_contacts(self) -> int:
        return self.system.n_contacts

    def options(self) -> dict[str, Any]:
        """The constructor options as plain data (what :meth:`save` stores)."""
        return {
            "model": self.model_name,
            "eps": self.eps_option,
            "heterogeneous": self.heterogeneous,
            "hidden": list(self.hidden),
            **({} if self.potential_dtype is None else {"potential_dtype": self.potential_dtype}),
            **({"penetration_gradient": True} if self.penetration_gradient else {}),
        }

    def extra_repr(self) -> str:
        return (
            f"model={self.model_name!r}, system={self.name!r}, eps={self.eps_option!r}, "
            f"heterogeneous={self.heterogeneous}"
        )

    # ---------------------------------------------------------- parameters
    def mass(self) -> Tensor:
        """``(B,)`` learned masses."""
        return (self.log_mass_scale + self.log_mass_rel).exp()

    def second_moments(self) -> Tensor | None:
        """``(B, dim)`` learned second moments per unit mass, or ``None`` (point masses)."""
        return None if self.log_second_moments is None else self.log_second_moments.exp()

    def mu(self) -> Tensor:
        """``(K,)`` friction coefficients (a shared value is expanded; gradients sum)."""
        return F.relu(self.raw_mu).expand(self.system.n_contacts)

    def cor(self) -> Tensor:
        """``(K,)`` Poisson coefficients of restitution in [0, 1]."""
        return _cor_from_raw(self.raw_cor).expand(self.system.n_contacts)

    def eps(self) -> Tensor | float | None:
        """CMr's regulariser (a tensor when learnable), ``None`` for CM."""
        if self.eps_option == "learnable":
            return self.log_eps.exp()
        return self.eps_option

    @torch.no_grad()
    def set_parameters(
        self,
        *,
        mass: Any = None,
        second_moments: Any = None,
        mu: Any = None,
        cor: Any = None,
        eps: float | None = None,
    ) -> LearnedModel:
        """Set physical parameters (e.g. to known values); ``None`` leaves one as is.

        ``mu``/``cor`` take one number or, for heterogeneous models, one per
        contact. Values are mapped through the inverse parameterisations
        (``log``, the identity for ``relu`` and for the scaled hard sigmoid);
        masses are split into the common scale (the mean log mass) and the
        per-body logs relative to it.

        Raises:
            ValueError: a value of the wrong shape, a non-positive mass or second
                moment, ``mu < 0``, ``cor`` outside [0, 1], a non-positive ``eps``
                or anything non-finite; nothing is changed then.
        """

        def shaped(name: str, value: Any, shape: torch.Size) -> Tensor:
            try:
                t = torch.as_tensor(value, dtype=torch.float64).detach().cpu()
            except (TypeError, ValueError, RuntimeError):
                raise ValueError(f"{name} must be numbers, got {value!r}") from None
            try:
                return t.expand(shape)
            except RuntimeError:
                raise ValueError(
                    f"{name} must be one number or of shape {tuple(shape)}, got shape "
                    f"{tuple(t.shape)}"
                ) from None

        def check(name: str, t: Tensor, ok: Tensor, what: str) -> Tensor:
            if not (torch.isfinite(t).all() and ok.all()):
                raise ValueError(f"{name} must be {what}, got {t.tolist()}")
            return t

        # validate everything first, so that a bad value changes nothing
        writes: list[tuple[Tensor, Tensor]] = []
        if mass is not None:
            t = shaped("mass", mass, self.log_mass_rel.shape)
            log_mass = check("mass", t, t > 0, "positive and finite").log()
            # masses the parameters' dtype cannot hold (1e-50 is 0 in float32)
            held = log_mass.to(self.log_mass_rel.dtype).exp()
            check("mass", t, (held > 0) & torch.isfinite(held),
                  f"positive and finite in {self.log_mass_rel.dtype}")  # fmt: skip
            writes += [
                (self.log_mass_scale, log_mass.mean()),
                (self.log_mass_rel, log_mass - log_mass.mean()),
            ]
        if second_moments is not None:
            if self.log_second_moments is None:
                raise ValueError(f"{self.name} has point masses only: no second moments")
            t = shaped("second_moments", second_moments, self.log_second_moments.shape)
            t = check("second_moments", t, t > 0, "positive and finite")
            writes.append((self.log_second_moments, t.log()))
        if mu is not None:
            t = shaped("mu", mu, self.raw_mu.shape)
            writes.append((self.raw_mu, check("mu", t, t >= 0, ">= 0 and finite")))
        if cor is not None:
            t = shaped("cor", cor, self.raw_cor.shape)
            t = check("cor (e_P)", t, (t >= 0) & (t <= 1), "in [0, 1]")
            writes.append((self.raw_cor, _cor_raw(t)))
        eps_value = None
        if eps is not None:
            if self.eps_option is None:
                raise ValueError(
                    f"eps is the regulariser of the CMr models; {self.model_name} has none"
                )
            try:
                eps_value = float(eps)
            except (TypeError, ValueError):
                eps_value = math.nan
            if not (math.isfinite(eps_value) and eps_value > 0):
                raise ValueError(f"eps must be a positive number, got {eps!r}")
            if self.eps_option == "learnable":  # (1e300 became inf, 1e-300 zero in float32)
                held = torch.tensor(math.log(eps_value), dtype=self.log_eps.dtype).exp()
                if not (bool(torch.isfinite(held)) and float(held) > 0):
                    raise ValueError(
                        f"eps must be positive and finite in {self.log_eps.dtype} (a learnable "
                        f"eps is stored as its log), got {eps!r}"
                    )
        for param, value in writes:
            param.copy_(value.to(param))
        if eps_value is not None:
            if self.eps_option == "learnable":
                self.log_eps.fill_(math.log(eps_value))
            elif self.eps_option is not None:
                self.eps_option = eps_value
        return self

    def learned_parameters(self) -> dict[str, Any]:
        """The physical parameters as plain Python numbers.

        Returns:
            ``mass`` (list, per body), ``mass_ratios`` (to the first body),
            ``second_moments`` (list of per-axis lists, or ``None``), ``mu`` and
            ``cor`` (lists in contact numbering, expanded for shared values),
            ``eps`` (float, or ``None`` for CM models).
        """
        with torch.no_grad():
            mass = self.mass().double().cpu()
            s = self.second_moments()
            eps = self.eps()
            return {
                "mass": mass.tolist(),
                "mass_ratios": (mass / mass[0]).tolist(),
                "second_moments": None if s is None else s.double().cpu().tolist(),
                "mu": self.mu().double().cpu().tolist(),
                "cor": self.cor().double().cpu().tolist(),
                "eps": None if eps is None else float(eps),
            }

    def physical_parameters(self) -> list[nn.Parameter]:
        """The physical parameters: ``log_mass_scale``, ``log_mass_rel``,
        ``log_second_moments``, ``raw_mu``, ``raw_cor`` and ``log_eps`` (those that
        exist), i.e. everything but the potential."""
        names = (
            "log_mass_scale", "log_mass_rel", "log_second_moments", "raw_mu", "raw_cor", "log_eps"
        )  # fmt: skip
        return [p for n in names if isinstance(p := getattr(self, n, None), nn.Parameter)]

    def network_parameters(self) -> list[nn.Parameter]:
        """The potential MLP's parameters (empty when there is no potential network)."""
        return [] if self.potential is None else list(self.potential.parameters())

    # ------------------------------------------------------ training protocol
    def param_groups(self, settings: OptimizerSettings) -> list[dict[str, Any]]:
        """Two AdamW groups: the potential network (``lr``, weight decay) and the
        physical parameters (``physics_lr``, no weight decay, which would pull them
        towards the parameterisation's zero; betas :data:`PHYSICS_BETAS`)."""
        physical = [p for p in self.physical_parameters() if p.requires_grad]
        chosen = {id(p) for p in physical}
        network = [p for p in self.parameters() if p.requires_grad and id(p) not in chosen]
        return [
            {
                "name": "network",
                "params": network,
                "lr": settings.lr,
                "weight_decay": settings.weight_decay,
            },
            {
                "name": "physical",
                "params": physical,
                "lr": settings.physics_lr,
                "weight_decay": 0.0,
                "betas": PHYSICS_BETAS,
            },
        ]

    def metrics(self) -> dict[str, float]:
        """``param/mass_0`` (the free mass scale), ``param/mass_ratio_i`` (i >= 1),
        ``param/mu`` and ``param/cor`` (or ``param/mu_k``, ``param/cor_k`` per
        contact) and ``param/eps`` when learnable."""
        params = self.learned_parameters()
        out: dict[str, float] = {"param/mass_0": params["mass"][0]}
        for i, r in enumerate(params["mass_ratios"][1:], start=1):
            out[f"param/mass_ratio_{i}"] = r
        for key in ("mu", "cor"):
            values = params[key]
            if self.heterogeneous:
                out.update({f"param/{key}_{k}": v for k, v in enumerate(values)})
            else:
                out[f"param/{key}"] = values[0]
        if params["eps"] is not None and self.eps_option == "learnable":
            out["param/eps"] = params["eps"]
        return out

    # ---------------------------------------------------------- simulation
    def physical_params(self) -> PhysicalParams:
        """The learned parameters (with their graphs) as the system's :class:`PhysicalParams`.

        Gravity (and the rope's springs) are zero: the potential network carries
        the whole potential, and is passed as ``potential``.
        """
        ref = self.log_mass_rel
        zero = torch.zeros((), dtype=ref.dtype, device=ref.device)
        base = self.system.parameters()
        eps = self.eps()
        return base.replace(
            mass=self.mass(),
            second_moments=self.second_moments(),
            mu=self.mu(),
            cor=self.cor(),
            gravity=zero,
            stiffness=None if base.stiffness is None else zero,
            eps=base.eps if eps is None else eps,
            potential=self._rollout_potential(),
        )

    def _rollout_potential(self) -> Any:
        """The potential for one rollout: :meth:`PotentialMLP.for_rollout` where the
        potential has it (another module, e.g. the refit's, as it is)."""
        for_rollout = getattr(self.potential, "for_rollout", None)
        return self.potential if for_rollout is None else for_rollout()

    def _check_options(self, contact_model: str | None, eps: Any, dynamics: str | None) -> None:
        if contact_model is not None and contact_model != self.contact_model:
            raise ValueError(
                f"{self.model_name} uses contact_model={self.contact_model!r}, "
                f"got contact_model={contact_model!r}"
            )
        if dynamics is not None and dynamics != self.dynamics:
            raise ValueError(
                f"{self.model_name} uses dynamics={self.dynamics!r}, got dynamics={dynamics!r}"
            )
        if eps is not None and self.contact_model == "CMr":
            raise ValueError("eps is a parameter of the model; use set_parameters(eps=...)")
        if eps is not None:  # (it had been ignored: eps=0.1 and eps="bogus" ran as without)
            raise ValueError(
                f"{self.model_name} has no eps (its contact model {self.contact_model} has no "
                f"regulariser; CMr models have one), got eps={eps!r}"
            )

    def simulate(
        self,
        z0: Tensor,
        steps: int | None = None,
        *,
        contact_model: str | None = None,
        eps: Any = None,
        dynamics: str | None = None,
        progress: bool = False,
        penetration_fraction: float | None = None,
        check_overlap: bool = True,
        solver_settings: Any = None,
        on_tunnelling: str = "warn",
        threads: int | str | None = "auto",
    ) -> Tensor:
        """Roll out trajectories with the learned parameters: ``System.simulate``'s contract.

        Args:
            z0: ``(N, 2, P, dim)`` initial states; the rollout runs in its dtype
                and on its device.
            steps: number of steps (default: the task's ``horizon / dt - 1``).
            contact_model, eps, dynamics: accepted for interchangeability with
                ``System.simulate``; they must match the model (or be ``None``).
            progress, penetration_fraction, check_overlap, solver_settings,
                on_tunnelling, threads: as in :meth:`System.simulate`.

        Returns:
            ``(N, steps + 1, 2, P, dim)``, differentiable with respect to the
            model's parameters and ``z0`` (the penetration compensation target a
            constant of the gradient unless the model's ``penetration_gradient``).
        """
        self._check_options(contact_model, eps, dynamics)
        return self.system.simulate(
            z0,
            steps,
            params=self.physical_params(),
            contact_model=self.contact_model,
            dynamics=self.dynamics,
            progress=progress,
            penetration_fraction=penetration_fraction,
            check_overlap=check_overlap,
            solver_settings=solver_settings,
            on_tunnelling=on_tunnelling,
            threads=threads,
            penetration_gradient=self.penetration_gradient,
        )

    def forward(self, z0: Tensor, steps: int | None = None, **kwargs: Any) -> Tensor:
        """Same as :meth:`simulate`."""
        return self.simulate(z0, steps, **kwargs)

    def energy(self, z: Tensor) -> Tensor:
        """Learned energy ``0.5 v^T M v + V(x)``: ``(..., 2, P, dim) -> (...)``."""
        return self.system.energy(z, params=self.physical_params())

    def as_system(self) -> System:
        """A new :class:`System` holding the learned values (detached), potential included,
        with the model's contact model (``contact_model``, CMr's ``eps`` among the values)
        and dynamics as its defaults: its ``simulate(z0, steps)`` is the model's rollout
        (a CMr, LCP or Coulomb model's had run CM)."""
        system = System(self.system.config)
        system.contact_model, system.dynamics = self.contact_model, self.dynamics
        with torch.no_grad():
            p = self.physical_params()
        for name, value in p.tensors().items():
            setattr(system, name, value.detach() if isinstance(value, Tensor) else value)
        # a copy of the network, frozen: the system keeps the values of now, whatever the
        # model learns next (the live module was shared, parameters and gradients included)
        potential = p.potential
        if isinstance(potential, nn.Module):
            potential = copy.deepcopy(potential).requires_grad_(False)
        elif isinstance(potential, _MLPWeights):  # the weights cast for a rollout
            layers = [(w.detach().clone(), None if b is None else b.detach().clone())
                      for w, b in potential.hidden_layers]  # fmt: skip
            potential = _MLPWeights(layers, potential.out.detach().clone(), potential.compute_dtype)
        system.potential_model = potential
        return system

    # ------------------------------------------------------------ saving
    def checkpoint(self) -> dict[str, Any]:
        """Everything :meth:`from_checkpoint` needs, as plain data and tensors."""
        from diffcontact.learning.models.storage import model_checkpoint

        return model_checkpoint(self, FORMAT_VERSION)

    @classmethod
    def from_checkpoint(cls, data: Mapping[str, Any]) -> LearnedModel:
        """Rebuild a model from :meth:`checkpoint`'s dict (dtype of the stored weights)."""
        version = data.get("format_version") if isinstance(data, Mapping) else None
        if version not in (2, FORMAT_VERSION):
            newer = isinstance(version, int) and not isinstance(version, bool)
            if newer and version > FORMAT_VERSION:
                why = "written by a newer diffcontact: update diffcontact to read it"
            else:
                why = "format 1 parameterised e_P differently: retrain"
            raise ValueError(
                f"model file format {version!r} is not supported (this diffcontact reads "
                f"formats 2 and {FORMAT_VERSION}; {why})"
            )
        try:
            options = dict(data["options"])
            model = cls(data["config"], **options)
            state = dict(data["state_dict"])
            if version == 2:  # one log mass per body: the same masses with a zero common scale
                state["log_mass_rel"] = state.pop("log_mass")
                state["log_mass_scale"] = torch.zeros((), dtype=state["log_mass_rel"].dtype)
        except KeyError as err:
            raise ValueError(f"not a diffcontact model file: missing {err}") from None
        dtype = next(iter(state.values())).dtype if state else torch.float32
        model.to(dtype)
        model.load_state_dict(state)
        return model

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the model (config, options, state dict) to ``path`` atomically."""
        from diffcontact.learning.models.storage import save_model

        return save_model(self, path)


def _physical_factory(name: str):
    def factory(config: Any, **options: Any) -> LearnedModel:
        given = options.pop("model", name)
        if given != name:
            raise ValueError(f"options name model {given!r}, the factory builds {name!r}")
        return LearnedModel(config, model=name, **options)

    factory.__name__ = name.replace("-", "_")
    factory.__doc__ = f"Registry factory of ``{name}``: ``LearnedModel(config, model={name!r})``."
    return factory


# the registry's built-in entries (registry.py names them "physical:CM_CD_CLNN", ...),
# one per name of BUILTIN_MODELS
CM_CD_CLNN = _physical_factory("CM-CD-CLNN")
CM_CD_CHNN = _physical_factory("CM-CD-CHNN")
CMr_CD_CLNN = _physical_factory("CMr-CD-CLNN")
CMr_CD_CHNN = _physical_factory("CMr-CD-CHNN")
Coulomb_CD_CLNN = _physical_factory("Coulomb-CD-CLNN")
Coulomb_CD_CHNN = _physical_factory("Coulomb-CD-CHNN")
LCP_CD_CLNN = _physical_factory("LCP-CD-CLNN")
LCP_CD_CHNN = _physical_factory("LCP-CD-CHNN")
