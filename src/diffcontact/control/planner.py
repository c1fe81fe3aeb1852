"""One interface over what can be planned with: a ground-truth System or a learned model.

:func:`as_planner` wraps

- a :class:`~diffcontact.systems.System` (the true dynamics; every physical
  parameter can be optimised),
- a physical learned model (``CM-CD-CLNN`` ...: its learned parameters can be
  optimised too; its weights are frozen while planning),
- any other registered :class:`~diffcontact.learning.DynamicsModel`
  (initial-state variables only),
- or a string: a run directory or ``model.pt`` (the trained model), a built-in
  task name or a config file (the true system).

A :class:`Planner` knows its bodies, its parameters and the true system its
data came from (``truth``: the config's system), so that a plan made with a
learned model can be judged by the ground truth.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torch import Tensor

__all__ = ["Planner", "as_planner"]


@dataclass
class Planner:
    """A differentiable simulator with its structure.

    Attributes:
        name: what it is (``"BP5 (true system)"``, ``"CM-CD-CLNN model of BP5"``).
        system: the System holding the structure (bodies, geometry, ``dt``).
        truth: the ground-truth System of the same config.
        learned: whether the dynamics are a learned model's.
        truth_contact_model: the contact model the truth simulates with (a model
            loaded from a training run: its dataset's, e.g. ``"LCP"``; else ``"CM"``).
        truth_known: whether :attr:`truth` is the data's system (``False`` for a model
            trained on recorded data whose true parameters were not declared: the
            config's masses, mu and e_P are placeholders, and nothing can judge a plan).
    """

    name: str
    system: Any
    truth: Any
    learned: bool
    _simulate: Callable[..., Tensor]
    _parameters: Callable[[], Any]
    _frozen: Callable[[], contextlib.AbstractContextManager[None]]
    truth_contact_model: Any = "CM"
    truth_known: bool = True

    def simulate_truth(self, z0: Tensor, steps: int) -> Tensor:
        """``(N, steps + 1, 2, P, dim)``: ``z0`` under the ground truth (its contact model)."""
        if not self.truth_known:
            raise ValueError(f"the ground truth of {self.name} is unknown (recorded data)")
        return self.truth.simulate(z0, steps, contact_model=self.truth_contact_model)

    @property
    def bodies(self) -> tuple[Any, ...]:
        return self.system.bodies()

    @property
    def dim(self) -> int:
        return self.system.dim

    @property
    def dt(self) -> float:
        return float(self.system.dt)

    @property
    def state_shape(self) -> tuple[int, int, int]:
        return tuple(self.system.state_shape)

    def parameters(self) -> Any:
        """The planner's :class:`PhysicalParams` (``None`` for a model without them)."""
        return self._parameters()

    def simulate(
        self, z0: Tensor, steps: int, params: Any = None, *, check_overlap: bool = True
    ) -> Tensor:
        """``(N, 2, P, dim) -> (N, steps + 1, 2, P, dim)`` with ``params`` (default its own)."""
        return self._simulate(z0, steps, params, check_overlap)

    def frozen(self) -> contextlib.AbstractContextManager[None]:
        """A context in which the model's own weights take no gradient."""
        return self._frozen()


@contextlib.contextmanager
def _no_grad_weights(module: Any) -> Iterator[None]:
    params = list(module.parameters())
    flags = [p.requires_grad for p in params]
    try:
        for p in params:
            p.requires_grad_(False)
        yield
    finally:
        for p, flag in zip(params, flags, strict=True):
            p.requires_grad_(flag)


def _from_string(spec: str) -> tuple[Any, dict[str, Any]]:
    """The object ``spec`` names, and what its training data say about the truth."""
    path = Path(spec)
    if path.is_dir() or path.suffix in (".pt", ".ckpt"):
        from diffcontact.learning.models.storage import load_model

        return load_model(path), _truth_of_run(path if path.is_dir() else path.parent)
    from diffcontact.systems import load_system

    return load_system(spec), {}


def _truth_of_run(run: Path) -> dict[str, Any]:
    """``truth_contact_model`` and ``truth_known`` from the dataset of a training run
    (``run.json``'s ``data_dir``); nothing for a model file without a run, and a warning
    where the run's data cannot be read (the truth is then the config's, with CM)."""
    import json
    import warnings

    from diffcontact.learning.data.format import load_dataset

    try:
        data_dir = json.loads((run / "run.json").read_text())["data_dir"]
    except (OSError, ValueError, KeyError, TypeError):
        return {}
    try:
        dataset = load_dataset(data_dir)
    except ValueError as err:
        warnings.warn(
            f"the data of run {run} cannot be read ({err}): plans are judged by the "
            "config's system with CM, which may not be the data's",
            stacklevel=3,
        )
        return {}
    return {
        "truth_contact_model": dataset.contact_model or "CM",
        "truth_known": dataset.parameters_known,
    }


def as_planner(obj: Any, *, contact_model: Any = None) -> Planner:
    """Wrap ``obj`` (a System, a learned model, or a string; see the module docstring).

    Args:
        obj: what to plan with.
        contact_model: the contact model of a System (``None``: the System's own
            ``contact_model``, ``"CM"`` unless set, e.g. by a learned model's
            ``as_system()``; a learned model has its own).

    Raises:
        ValueError: a string that names no run, model file, task or config; an
            object that is none of the above.
    """
    from diffcontact.contact.registry import create_contact_model
    from diffcontact.systems import System, load_system

    if isinstance(obj, Planner):
        return obj
    about_truth: dict[str, Any] = {}
    if isinstance(obj, (str, Path)):
        obj, about_truth = _from_string(str(obj))
    if isinstance(obj, System):
        system = obj
        if contact_model is None:
            contact_model = system.contact_model
        create_contact_model(contact_model)  # an unknown name: an error now, not mid-rollout

        def simulate(z0: Tensor, steps: int, params: Any, check: bool) -> Tensor:
            return system.simulate(
                z0, steps, params=params, contact_model=contact_model, check_overlap=check
            )

        return Planner(
            name=f"{system.name} (true system)",
            system=system,
            truth=system,
            learned=False,
            _simulate=simulate,
            _parameters=system.parameters,
            _frozen=contextlib.nullcontext,
            truth_contact_model=contact_model,
        )
    config = getattr(obj, "config", None)
    if config is None or not callable(getattr(obj, "simulate", None)):
        raise ValueError(
            f"cannot plan with {type(obj).__name__}: give a System, a trained model, a run "
            "directory, a task name or a config file"
        )
    truth = load_system(config)
    model = obj
    label = f"{getattr(model, 'model_name', type(model).__name__)} model of {truth.name}"
    if hasattr(model, "physical_params") and hasattr(model, "system"):

        def simulate(z0: Tensor, steps: int, params: Any, check: bool) -> Tensor:
            return model.system.simulate(
                z0,
                steps,
                params=model.physical_params() if params is None else params,
                contact_model=model.contact_model,
                dynamics=model.dynamics,
                check_overlap=check,
            )

        parameters: Callable[[], Any] = model.physical_params
        system = model.system
    else:

        def simulate(z0: Tensor, steps: int, params: Any, check: bool) -> Tensor:
            if params is not None:
                raise ValueError(f"{label} has no physical parameters to optimise")
            return model.simulate(z0, steps, check_overlap=check)

        def parameters() -> Any:
            return None

        system = truth
    frozen = (
        (lambda: _no_grad_weights(model))
        if hasattr(model, "parameters")
        else contextlib.nullcontext
    )
    return Planner(
        name=label,
        system=system,
        truth=truth,
        learned=True,
        _simulate=simulate,
        _parameters=parameters,
        _frozen=frozen,
        **about_truth,
    )
