"""The contact-model registry: names (``"CM"``, ``"CMr"``, ``"Coulomb"``, yours) to factories.

Importing this module loads no torch: the CLI builds its ``--contact-model``
choices from :func:`contact_models` without loading the solver. A factory is
any callable ``factory(**options) -> ContactModel``; third-party packages can
also register through the entry-point group ``diffcontact.contact_models``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from diffcontact.registry import NAME_PATTERN, Registry, name_rule

__all__ = [
    "contact_models",
    "create_contact_model",
    "register_contact_model",
    "unregister_contact_model",
]

REGISTRY = Registry(
    "contact model",
    {
        "CM": "diffcontact.contact.models:CM",
        "CMr": "diffcontact.contact.models:CMr",
        "LCP": "diffcontact.contact.lcp:LCP",
        "Coulomb": "diffcontact.contact.coulomb:Coulomb",
    },
    entry_point_group="diffcontact.contact_models",
    name_pattern=NAME_PATTERN,
    name_rule=name_rule("contact model", "--contact-model"),
)


def register_contact_model(
    name: str, factory: Callable[..., Any], *, overwrite: bool = False
) -> None:
    """Register ``factory(**options) -> ContactModel`` under ``name``.

    Then ``System.simulate(..., contact_model=name)``, ``diffcontact simulate
    --contact-model name`` and ``diffcontact generate --contact-model name``
    use it.

    ``name`` starts with a letter or digit, followed by letters, digits, ``-``, ``_``
    or ``.`` (:data:`diffcontact.registry.NAME_PATTERN`).

    Raises:
        ValueError: an empty name or one that breaks that rule, a name already taken
            (unless ``overwrite``; the built-in names can never be replaced) or a
            factory that is not callable.
    """
    REGISTRY.register(name, factory, overwrite=overwrite)


def unregister_contact_model(name: str) -> None:
    """Remove a model registered with :func:`register_contact_model` (built-ins stay)."""
    REGISTRY.unregister(name)


def contact_models() -> list[str]:
    """The registered contact-model names, built-ins first."""
    return REGISTRY.names()


def create_contact_model(spec: Any, **options: Any) -> Any:
    """A contact model from a registered name (built with ``options``) or the object itself.

    Args:
        spec: a name from :func:`contact_models`, or an object with a
            ``resolve`` method (returned unchanged; ``options`` must be empty).
        options: keyword arguments of the factory (e.g. ``eps=0.05`` for CMr).

    Raises:
        ValueError: an unknown name (the message lists the registered ones), a
            bad option, or an object that is not a contact model.
    """
    if isinstance(spec, str):
        return REGISTRY.create(spec, required=("resolve",), **options)
    if callable(getattr(spec, "resolve", None)):
        if options:
            raise ValueError("options are for contact-model names; got a contact model object")
        return spec
    raise ValueError(
        "contact_model must be a registered name "
        f"({', '.join(contact_models())}) or an object with a resolve method; "
        f"got {type(spec).__name__}"
    )
