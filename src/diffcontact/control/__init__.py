"""Control through differentiable simulators: planning by gradient descent (``docs/control.md``).

- :func:`optimize`: multi-start, batched gradient-based optimisation of parts
  of the initial state and/or physical parameters through ``simulate``, with
  box bounds, early stopping and a progress bar; returns an :class:`OptimizeResult`.
- Variables: :class:`Velocity`, :class:`Spin`, :class:`Position`, :class:`Parameter`.
- :func:`as_planner`: a System, a trained model, a run directory or a task
  name as one :class:`Planner` (with the ground-truth system to judge a plan).
- :mod:`.tasks`: the billiards and throwing problems of the paper's downstream
  experiments (``diffcontact billiards``, ``diffcontact throw``).

Importing this package is cheap; torch loads with the first use of a name.
"""

from diffcontact.learning._lazy import lazy_exports

_EXPORTS = {
    "ControlError": "diffcontact.control.optimize",
    "OptimizeResult": "diffcontact.control.optimize",
    "optimize": "diffcontact.control.optimize",
    "Planner": "diffcontact.control.planner",
    "as_planner": "diffcontact.control.planner",
    "Parameter": "diffcontact.control.variables",
    "Position": "diffcontact.control.variables",
    "Spin": "diffcontact.control.variables",
    "Velocity": "diffcontact.control.variables",
}

__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
