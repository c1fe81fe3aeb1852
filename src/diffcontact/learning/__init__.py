"""Learning layer: datasets, learned models, training and evaluation.

Public names are imported lazily (on first attribute access), so ``import
diffcontact.learning`` stays cheap and a subcommand only loads what it uses.
To export a new name, add it to ``_EXPORTS`` (name -> defining module).

Subpackages (each ``cli.py`` builds its subcommand without importing torch,
Lightning or matplotlib; the handler imports them when it runs):

- :mod:`~diffcontact.learning.data` (format in ``docs/data.md``):
  :func:`generate_dataset` simulates train/val/test trajectories of a task and
  chunks them for training; :func:`dataset_from_arrays` writes the same format
  from trajectories recorded elsewhere, after :func:`trajectories_from_positions`,
  :func:`trajectories_from_coordinates` or :func:`trajectories_from_mujoco` where
  they come in another form (``docs/own-data.md``); :func:`load_dataset` reads a dataset
  folder (checksums verified) into a :class:`Dataset`.
- :mod:`~diffcontact.learning.models`: :class:`LearnedModel`
  (CM/CMr-CD-CLNN/CHNN, a ``System`` whose inertia, potential, mu and e_P are
  learned) and :func:`load_model`.
- :mod:`~diffcontact.learning.training`: ``train()`` (Lightning;
  ``docs/training.md``), the rollout loss and its Lightning module.
- :mod:`~diffcontact.learning.evaluation`: metrics, the training log, plots and
  ``evaluate()`` (``docs/evaluation.md``).
"""

from __future__ import annotations

from diffcontact.learning._lazy import lazy_exports

_EXPORTS: dict[str, str] = {
    "DataSplit": "diffcontact.learning.data.format",
    "Dataset": "diffcontact.learning.data.format",
    "DatasetError": "diffcontact.learning.data.format",
    "dataset_from_arrays": "diffcontact.learning.data.arrays",
    "trajectories_from_coordinates": "diffcontact.learning.data.convert",
    "trajectories_from_mujoco": "diffcontact.learning.data.mujoco",
    "trajectories_from_positions": "diffcontact.learning.data.convert",
    "generate_dataset": "diffcontact.learning.data.generate",
    "load_dataset": "diffcontact.learning.data.format",
    "select_chunks": "diffcontact.learning.data.chunks",
    "LearnedModel": "diffcontact.learning.models.physical",
    "DynamicsModel": "diffcontact.learning.models.protocol",
    "OptimizerSettings": "diffcontact.learning.models.protocol",
    "create_model": "diffcontact.learning.models.registry",
    "model_names": "diffcontact.learning.models.registry",
    "register_model": "diffcontact.learning.models.registry",
    "unregister_model": "diffcontact.learning.models.registry",
    "load_model": "diffcontact.learning.models.storage",
    "save_model": "diffcontact.learning.models.storage",
}

__all__ = sorted(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
