"""Training (``docs/training.md``).

- :mod:`.options`: every training default, in one place, and their checks;
- :mod:`.module`: the rollout loss and :class:`RolloutModule` (Lightning),
  which skips non-finite, failed and spiking steps;
- :mod:`.run`: :func:`train` (resume, the Trainer) and the data module;
- :mod:`.rundir`: what may be written where (a run directory is new, empty or
  ours, holds no links), ``run.json`` and the CSV log;
- :mod:`.checkpoints`: checkpoints written atomically and read with
  ``weights_only=True``; which one a resumed run continues from;
- :mod:`.stopping`: SIGINT/SIGTERM stop after the running step with a
  checkpoint; ``max_time``;
- :mod:`.cli`: ``diffcontact train`` (no torch or Lightning at import).

Names are imported lazily, so ``diffcontact.learning.training.cli`` loads
neither torch nor Lightning.
"""

from __future__ import annotations

from diffcontact.learning._lazy import lazy_exports

_MODULE = "diffcontact.learning.training.module"
_RUN = "diffcontact.learning.training.run"
_EXPORTS: dict[str, str] = {
    "TrainingFailed": "diffcontact.learning.training.options",
    "TrainingInputError": "diffcontact.learning.training.options",
    "TrainingInterrupted": "diffcontact.learning.training.options",
    "RolloutModule": _MODULE,
    "rollout_loss": _MODULE,
    "solver_settings_for": _MODULE,
    "ChunkDataModule": _RUN,
    "EpochShuffleSampler": _RUN,
    "contact_weights": _RUN,
    "read_training_data": _RUN,
    "train": _RUN,
    "register_cli": "diffcontact.learning.training.cli",
}

__all__ = sorted(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
