"""Learned models: the protocol, the registry, the physical models, saving and loading.

- :mod:`.protocol`: :class:`DynamicsModel`, what training and evaluation ask of a model;
- :mod:`.registry` (torch-free): :func:`register_model`, :func:`model_names`,
  :func:`create_model`;
- :mod:`.physical`: :class:`LearnedModel`, the CM/CMr-CD-CLNN/CHNN models;
- :mod:`.baselines`: the baselines MLP-CD-CLNN, IN-CP-CLNN and IN-SP-CP;
- :mod:`.storage`: :func:`save_model`, :func:`load_model` for any registered model.

Names are imported lazily, so the command line lists the models without torch.
"""

from __future__ import annotations

from diffcontact.learning._lazy import lazy_exports

_EXPORTS: dict[str, str] = {
    "FORMAT_VERSION": "diffcontact.learning.models.physical",
    "LearnedModel": "diffcontact.learning.models.physical",
    "PotentialMLP": "diffcontact.learning.models.physical",
    "DynamicsModel": "diffcontact.learning.models.protocol",
    "OptimizerSettings": "diffcontact.learning.models.protocol",
    "BUILTIN_MODELS": "diffcontact.learning.models.registry",
    "BASELINE_MODELS": "diffcontact.learning.models.registry",
    "INCPCLNN": "diffcontact.learning.models.baselines",
    "INSPCP": "diffcontact.learning.models.baselines",
    "MLPCDCLNN": "diffcontact.learning.models.baselines",
    "create_model": "diffcontact.learning.models.registry",
    "model_names": "diffcontact.learning.models.registry",
    "parse_model_name": "diffcontact.learning.models.registry",
    "register_model": "diffcontact.learning.models.registry",
    "unregister_model": "diffcontact.learning.models.registry",
    "load_model": "diffcontact.learning.models.storage",
    "save_model": "diffcontact.learning.models.storage",
}

__all__ = sorted(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
