"""The learned-model registry: ``--model NAME`` to a factory.

Importing this module loads no torch, so the CLI builds its ``--model``
choices from :func:`model_names` cheaply. A factory is any callable
``factory(config, **options) -> DynamicsModel`` (:mod:`.protocol`); the
built-in physical models (paper-facts.md, "Models compared": contact model
CM, CMr, LCP or Coulomb, true collision detection, constrained Lagrangian or
Hamiltonian network) and the baselines (MLP-CD-CLNN, IN-CP-CLNN, IN-SP-CP) are loaded
on first use. Third-party packages can also register
through the entry-point group ``diffcontact.models``.

Example::

    import diffcontact as dc
    dc.learning.register_model("MyNet", MyNet)     # MyNet(config, **options)
    # then: diffcontact train DATA --model MyNet
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from diffcontact.registry import NAME_PATTERN, Registry, name_rule

__all__ = [
    "BASELINE_MODELS",
    "BUILTIN_MODELS",
    "NAME_PATTERN",
    "PHYSICAL_CONTACT_MODELS",
    "create_model",
    "is_physical_model",
    "model_names",
    "parse_model_name",
    "register_model",
    "unregister_model",
]

# contact models (names in diffcontact.contact.registry) that the physical models
# "<contact>-CD-CLNN" and "<contact>-CD-CHNN" are built with
PHYSICAL_CONTACT_MODELS = ("CM", "CMr", "LCP", "Coulomb")
BUILTIN_MODELS = tuple(
    f"{contact}-CD-{net}" for contact in PHYSICAL_CONTACT_MODELS for net in ("CLNN", "CHNN")
)
# the paper's baselines (diffcontact.learning.models.baselines): an MLP or an interaction
# network replaces the impulse (MLP-CD-CLNN, IN-CP-CLNN) or the whole step (IN-SP-CP)
BASELINE_MODELS = ("MLP-CD-CLNN", "IN-CP-CLNN", "IN-SP-CP")
# a model name is a `diffcontact train --model NAME` argument and part of run-folder names
# (CM-CD-CLNN, MLP-CD-CLNN, IN-SP-CP): no leading '-', no spaces, no '/'
NAME_RULE = name_rule("model", "--model")
_PHYSICAL = "diffcontact.learning.models.physical"
_BASELINES = "diffcontact.learning.models.baselines"
REGISTRY = Registry(
    "model",
    {
        **{name: f"{_PHYSICAL}:{name.replace('-', '_')}" for name in BUILTIN_MODELS},
        **{name: f"{_BASELINES}:{name.replace('-', '_')}" for name in BASELINE_MODELS},
    },
    entry_point_group="diffcontact.models",
    name_pattern=NAME_PATTERN,
    name_rule=NAME_RULE,
)
REQUIRED = ("simulate", "param_groups", "metrics", "options")
# the protocol's attributes (training reads them; a plugin without one failed deep inside)
REQUIRED_ATTRIBUTES = ("model_name", "config", "dt", "state_shape", "default_steps")


def parse_model_name(name: str) -> tuple[str, str]:
    """``"CMr-CD-CHNN"`` -> ``("CMr", "hamiltonian")`` for the built-in physical models.

    Raises:
        ValueError: not a built-in physical model name.
    """
    if name not in BUILTIN_MODELS:
        raise ValueError(
            f"{name!r} is not a physical model; physical models: {', '.join(BUILTIN_MODELS)}"
        )
    contact, _, net = name.split("-")
    return contact, "lagrangian" if net == "CLNN" else "hamiltonian"


def is_physical_model(name: str) -> bool:
    """Whether ``name`` is one of the built-in CM/CMr/LCP physical models."""
    return name in BUILTIN_MODELS


def register_model(name: str, factory: Callable[..., Any], *, overwrite: bool = False) -> None:
    """Register ``factory(config, **options) -> DynamicsModel`` under ``name``.

    ``config`` is the dataset's validated system config (the known structure:
    geometry, constraints, contact candidates, ``dt``); ``options`` are plain
    data (what the model's ``options()`` returns, stored with a trained model
    and passed back when it is loaded).

    ``name`` starts with a letter or digit, followed by letters, digits, ``-``, ``_``
    or ``.`` (:data:`NAME_PATTERN`): it is given as ``diffcontact train DATA --model
    NAME`` and becomes part of folder names. Entry points of the group
    ``diffcontact.models`` with another name are ignored, with a ``RuntimeWarning``.

    Raises:
        ValueError: an empty name or one that breaks that rule, a name already taken
            (unless ``overwrite``; built-in names can never be replaced) or a factory
            that is not callable.
    """
    REGISTRY.register(name, factory, overwrite=overwrite)


def unregister_model(name: str) -> None:
    """Remove a model registered with :func:`register_model` (built-ins stay)."""
    REGISTRY.unregister(name)


def model_names() -> list[str]:
    """Registered model names, built-ins first."""
    return REGISTRY.names()


def create_model(name: str, config: Any, **options: Any) -> Any:
    """Build the model registered as ``name`` for ``config`` with ``options``.

    Raises:
        ValueError: an unknown name (the message lists the registered ones),
            options the factory does not take, a factory that raises, or a product
            that lacks a method or attribute of the
            :class:`~diffcontact.learning.models.protocol.DynamicsModel` protocol.
    """
    try:
        model = REGISTRY.create(name, config, required=REQUIRED, **options)
    except ValueError:
        raise
    except Exception as err:  # a plugin's factory failing: one line, its cause chained
        raise ValueError(
            f"the factory of model {name!r} raised {type(err).__name__}: {err}"
        ) from err
    missing = [attr for attr in REQUIRED_ATTRIBUTES if not hasattr(model, attr)]
    if missing:
        raise ValueError(
            f"the factory of model {name!r} returned {type(model).__name__}, which has no "
            f"{', '.join(missing)} (the DynamicsModel protocol, docs/architecture.md)"
        )
    return model
