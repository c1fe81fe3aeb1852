"""A name -> factory registry, shared by contact models and learned models.

Torch-free: command-line parsers read the names (``choices``) without loading
the numerical code. Built-in entries may be ``"module:attribute"`` strings
(imported on first use) and third-party packages can add entries through an
entry-point group, read the first time the registry is used.
"""

from __future__ import annotations

import importlib
import inspect
import re
import warnings
from collections.abc import Callable, Iterable
from typing import Any

__all__ = ["Registry"]


NAME_PATTERN = r"[A-Za-z0-9][A-Za-z0-9._-]*"
"""What a registered model or contact-model name looks like (CM-CD-CLNN, MLP-CD-CLNN, CMr):
it is given as a command-line option's value and becomes part of folder names."""


def name_rule(kind: str, option: str) -> str:
    """:data:`NAME_PATTERN` in words, for the messages of the registry of ``kind``."""
    return (
        f"a {kind} name starts with a letter or digit, followed by letters, digits, '-', '_' "
        f"or '.' (it is a {option} argument and part of folder names)"
    )


class Registry:
    """Names to factories, with protected built-ins.

    Args:
        kind: what is registered, for messages (``"contact model"``).
        builtins: built-in name -> factory or ``"module:attribute"``; these
            cannot be replaced or removed.
        entry_point_group: the ``importlib.metadata`` entry-point group read
            on first use.
        name_pattern: a regular expression every name must match in full (registered
            or from an entry point); ``None``: any non-empty name without surrounding
            spaces.
        name_rule: ``name_pattern`` in words, for messages.
    """

    def __init__(
        self,
        kind: str,
        builtins: dict[str, Callable[..., Any] | str],
        entry_point_group: str,
        *,
        name_pattern: str | None = None,
        name_rule: str | None = None,
    ) -> None:
        self.kind = kind
        self._factories: dict[str, Callable[..., Any] | str] = dict(builtins)
        self._builtin = tuple(builtins)
        self._group = entry_point_group
        self._entry_points_loaded = False
        self._pattern = re.compile(name_pattern) if name_pattern is not None else None
        self._rule = name_rule or (f"names match {name_pattern}" if name_pattern else "")
        for name in self._builtin:
            if self._name_problem(name) is not None:
                raise ValueError(f"built-in {kind} name {name!r} breaks its own rule: {self._rule}")

    def _name_problem(self, name: object) -> str | None:
        """Why ``name`` cannot be registered (one line), or ``None`` if it can."""
        if not isinstance(name, str) or not name.strip() or name != name.strip():
            return f"{self.kind} name must be a non-empty string, got {name!r}"
        if self._pattern is not None and self._pattern.fullmatch(name) is None:
            return f"{self.kind} name {name!r} is not allowed: {self._rule}"
        return None

    def _load_entry_points(self) -> None:
        if self._entry_points_loaded:
            return
        self._entry_points_loaded = True
        from importlib.metadata import entry_points

        for ep in entry_points(group=self._group):
            problem = self._name_problem(ep.name)
            if problem is not None:  # one package's bad name must not break every command
                warnings.warn(
                    f"ignored entry point {ep.value!r} of group {self._group}: {problem}",
                    RuntimeWarning,
                    stacklevel=3,
                )
                continue
            self._factories.setdefault(ep.name, ep.value)

    def register(self, name: str, factory: Callable[..., Any], *, overwrite: bool = False) -> None:
        """Add ``factory`` under ``name``.

        Raises:
            ValueError: an empty name or one that breaks the registry's name rule, a
                name already taken (unless ``overwrite``; built-ins never), or a factory
                that is not callable.
        """
        problem = self._name_problem(name)
        if problem is not None:
            raise ValueError(problem)
        if not callable(factory):
            raise ValueError(f"factory for {self.kind} {name!r} must be callable")
        self._load_entry_points()
        if name in self._builtin:
            raise ValueError(f"{name!r} is a built-in {self.kind} and cannot be replaced")
        if name in self._factories and not overwrite:
            raise ValueError(
                f"{self.kind} {name!r} is already registered (pass overwrite=True to replace it)"
            )
        self._factories[name] = factory

    def unregister(self, name: str) -> None:
        """Remove a registered (not built-in) name; unknown names are ignored."""
        if name in self._builtin:
            raise ValueError(f"{name!r} is a built-in {self.kind} and cannot be removed")
        self._factories.pop(name, None)

    def names(self) -> list[str]:
        """Registered names, built-ins first, then the others sorted."""
        self._load_entry_points()
        return [*self._builtin, *sorted(n for n in self._factories if n not in self._builtin)]

    def factory(self, name: str) -> Callable[..., Any]:
        """The factory of ``name``; ``ValueError`` listing the registered names if unknown."""
        self._load_entry_points()
        if name not in self._factories:
            known = ", ".join(self.names())
            raise ValueError(f"unknown {self.kind} {name!r}; registered {self.kind}s: {known}")
        factory = self._factories[name]
        if isinstance(factory, str):
            module, _, attr = factory.partition(":")
            factory = getattr(importlib.import_module(module), attr)
            self._factories[name] = factory
        return factory

    def create(self, name: str, *args: Any, required: Iterable[str] = (), **options: Any) -> Any:
        """``factory(*args, **options)``, checked for the ``required`` methods.

        Raises:
            ValueError: unknown name, options the factory does not take, or a
                product lacking one of ``required``.
        """
        factory = self.factory(name)
        unknown, takes = _unknown_options(factory, options)
        if unknown:
            raise ValueError(
                f"{self.kind} {name!r} has no option {', '.join(map(repr, unknown))}; it takes: "
                f"{', '.join(takes) or 'none'}"
            )
        try:
            product = factory(*args, **options)
        except TypeError as err:
            # a factory taking **options passes them on: name the option, not the class
            match = re.search(r"unexpected keyword argument '(\w+)'", str(err))
            if match:
                raise ValueError(f"{self.kind} {name!r} has no option {match[1]!r}") from None
            raise ValueError(f"{self.kind} {name!r}: bad options: {err}") from None
        for attr in required:
            if not callable(getattr(product, attr, None)):
                raise ValueError(
                    f"the factory of {self.kind} {name!r} returned {type(product).__name__}, "
                    f"which has no {attr} method"
                )
        return product


def _unknown_options(factory: Callable[..., Any], options: dict[str, Any]) -> tuple[list, list]:
    """The ``options`` that ``factory`` does not take, and the keyword options it does
    (none unknown where its signature cannot be read or takes ``**kwargs``)."""
    try:
        params = inspect.signature(factory).parameters.values()
    except (TypeError, ValueError):
        return [], []
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params):
        return [], []
    kinds = (inspect.Parameter.KEYWORD_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    takes = [p.name for p in params if p.kind in kinds and p.default is not inspect.Parameter.empty]
    named = {p.name for p in params if p.kind in kinds}
    return [k for k in options if k not in named], takes
