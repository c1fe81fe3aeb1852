"""Evaluation of a learned model (``docs/evaluation.md``).

- :mod:`.metrics`: relative error, 95% confidence intervals, energy drift,
  true parameters, rollout length (numpy; torch only for energies);
- :mod:`.log`: the training log (Lightning's ``metrics.csv``) per epoch;
- :mod:`.plots`: the PNG plots (matplotlib);
- :mod:`.uncertainty`: how well the data determine the learned parameters
  (:func:`parameter_uncertainty`, :func:`contact_regimes`);
- :mod:`.evaluate`: ``evaluate()``, the whole protocol on a run
  (``from diffcontact.learning.evaluation.evaluate import evaluate``: the
  function is not re-exported here, where the name is its module's);
- :mod:`.cli`: ``diffcontact evaluate`` (no torch or matplotlib at import).

Names are imported lazily, so ``diffcontact.learning.evaluation.cli`` loads
neither torch nor matplotlib.
"""

from __future__ import annotations

from diffcontact.learning._lazy import lazy_exports

_METRICS = "diffcontact.learning.evaluation.metrics"
_LOG = "diffcontact.learning.evaluation.log"
_UNCERTAINTY = "diffcontact.learning.evaluation.uncertainty"
_EXPORTS: dict[str, str] = {
    "energy_rel_drift": _METRICS,
    "energy_scale": _METRICS,
    "mean_ci95": _METRICS,
    "relative_error": _METRICS,
    "rollout_steps": _METRICS,
    "t_quantile_975": _METRICS,
    "true_energy": _METRICS,
    "true_parameters": _METRICS,
    "find_training_log": _LOG,
    "read_training_log": _LOG,
    "DivergedRolloutsWarning": "diffcontact.learning.evaluation.evaluate",
    "EvaluationInputError": "diffcontact.learning.evaluation.evaluate",
    "register_cli": "diffcontact.learning.evaluation.cli",
    "UncertaintySettings": _UNCERTAINTY,
    "contact_regimes": _UNCERTAINTY,
    "parameter_uncertainty": _UNCERTAINTY,
}

__all__ = sorted(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
