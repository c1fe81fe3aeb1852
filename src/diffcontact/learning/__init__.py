"""Learning layer: datasets, learnable parameterisations, models, training and evaluation.

Public names are imported lazily (on first attribute access), so ``import
diffcontact.learning`` stays cheap and a subcommand only loads what it uses.
To export a new name, add it to ``_EXPORTS`` (name -> defining module).

Datasets (:mod:`diffcontact.learning.data`, format in ``docs/data.md``):

- :func:`generate_dataset` simulates train/val/test trajectories of a task
  and chunks them for training;
- :func:`dataset_from_arrays` writes the same format from trajectories
  recorded elsewhere;
- :func:`load_dataset` reads a dataset folder (checksums verified) into a
  :class:`Dataset`.

Models, training and evaluation:

- :class:`LearnedModel` (:mod:`~diffcontact.learning.model`): CM/CMr-CD-CLNN/CHNN, a
  ``System`` whose inertia, potential, mu and e_P are learned; :func:`load_model`;
- ``diffcontact.learning.train.train`` (Lightning; ``docs/training.md``);
- ``diffcontact.learning.evaluate.evaluate`` (``docs/evaluation.md``).
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS: dict[str, str] = {
    "DataSplit": "diffcontact.learning.data",
    "Dataset": "diffcontact.learning.data",
    "DatasetError": "diffcontact.learning.data",
    "dataset_from_arrays": "diffcontact.learning.data",
    "generate_dataset": "diffcontact.learning.data",
    "load_dataset": "diffcontact.learning.data",
    "select_chunks": "diffcontact.learning.data",
    "LearnedModel": "diffcontact.learning.model",
    "load_model": "diffcontact.learning.model",
    "MODELS": "diffcontact.learning.model",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'diffcontact.learning' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
