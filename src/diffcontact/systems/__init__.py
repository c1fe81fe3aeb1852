"""Systems: validated configs, built-in tasks (YAML data files) and the ``System`` simulator.

``load_system("BP5")`` (a built-in task name, a ``.yaml``/``.json`` path or a
dict) returns a :class:`System` with ``sample_initial_conditions``,
``simulate`` and ``energy``; ``docs/config.md`` documents every config key.
"""

from diffcontact.systems.config import SYSTEM_TYPES, parse_config
from diffcontact.systems.params import PhysicalParams
from diffcontact.systems.system import (
    ConstraintDriftWarning,
    ContactResult,
    NonFiniteRolloutError,
    RolloutWarning,
    System,
    TunnellingWarning,
    list_tasks,
    load_config,
    load_system,
)

__all__ = [
    "SYSTEM_TYPES",
    "ConstraintDriftWarning",
    "ContactResult",
    "NonFiniteRolloutError",
    "PhysicalParams",
    "RolloutWarning",
    "System",
    "TunnellingWarning",
    "list_tasks",
    "load_config",
    "load_system",
    "parse_config",
]
