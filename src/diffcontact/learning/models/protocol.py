"""What training, evaluation and control ask of a learned model: :class:`DynamicsModel`.

A learned model is a simulator with learnable parts (DESIGN.md). Training
(:mod:`diffcontact.learning.training`) only calls the methods below, so a new
model (a baseline, a different contact model inside the physical model) is a
class with them plus one :func:`~diffcontact.learning.register_model` call.
Models are ``torch.nn.Module`` s: their ``state_dict`` is what is saved.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

from torch import Tensor

__all__ = ["DynamicsModel", "OptimizerSettings"]


@dataclass(frozen=True)
class OptimizerSettings:
    """Learning rates and weight decay a model turns into optimiser groups.

    Attributes:
        lr: learning rate of network weights.
        weight_decay: AdamW weight decay of network weights.
        physics_lr: learning rate of interpretable physical parameters
            (masses, inertia, mu, e_P, eps).
    """

    lr: float
    weight_decay: float
    physics_lr: float


@runtime_checkable
class DynamicsModel(Protocol):
    """The learned-model protocol (all CM/CMr models and the baselines implement it).

    Attributes:
        model_name: the registered name (``--model``).
        config: the validated system config of the known structure.
        dt: time step of a simulated step.
        state_shape: ``(2, P, dim)``.
        default_steps: steps of a full trajectory of the task.
    """

    model_name: str
    config: Any

    @property
    def dt(self) -> float: ...

    @property
    def state_shape(self) -> tuple[int, int, int]: ...

    @property
    def default_steps(self) -> int: ...

    def simulate(
        self,
        z0: Tensor,
        steps: int | None = None,
        *,
        check_overlap: bool = True,
        solver_settings: Any = None,
        progress: bool = False,
    ) -> Tensor:
        """``(N, 2, P, dim)`` initial states -> ``(N, steps + 1, 2, P, dim)`` rollouts,
        differentiable with respect to the model's parameters and ``z0``."""
        ...

    def options(self) -> dict[str, Any]:
        """Constructor options as plain JSON data; ``factory(config, **options)``
        rebuilds the model (weights come from the ``state_dict``)."""
        ...

    def param_groups(self, settings: OptimizerSettings) -> list[dict[str, Any]]:
        """Optimiser parameter groups (``torch.optim`` dicts), each with a ``"name"``;
        every trainable parameter in exactly one group. Gradient-spike checks
        and logs are per group."""
        ...

    def metrics(self) -> dict[str, float]:
        """Scalars to log every epoch, by name ``"param/<label>"`` (e.g.
        ``param/mu``). Evaluation plots them and, where the model can say, compares
        them with the truth (:meth:`learned_parameters`). May be empty."""
        ...
