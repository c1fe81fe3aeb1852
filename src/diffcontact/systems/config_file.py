"""Reading a config file: YAML or JSON into plain data, strictly.

Two departures from ``yaml.safe_load`` / ``json.loads``, both so that a config means
what its author wrote:

- a key given twice in one mapping is an error (both parsers keep the last one
  silently: ``radii`` written twice took the second list);
- YAML numbers in the exponent forms ``1e-3``, ``5e2`` or ``1.0e9`` are numbers
  (YAML 1.2, JSON), not the strings YAML 1.1 makes of them, which the config's
  validation then refused as "not a number".
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

__all__ = ["read_config_file"]

# YAML 1.2's core-schema floats (and YAML 1.1's, which need a dot and a signed exponent)
_FLOAT = re.compile(
    r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
    |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
    |[-+]?\.(?:inf|Inf|INF)
    |\.(?:nan|NaN|NAN))$""",
    re.X,
)


def _loader():
    import yaml

    class StrictLoader(yaml.SafeLoader):
        """``SafeLoader`` refusing duplicate keys, with YAML 1.2's floats."""

    def mapping(loader: StrictLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: dict[Any, Any] = {}
        for key_node, _ in node.value:
            key = loader.construct_object(key_node, deep=deep)
            if key in seen:
                mark = key_node.start_mark
                raise ValueError(
                    f"key {key!r} is given twice in one mapping (line {seen[key] + 1} and "
                    f"line {mark.line + 1}); give each key once"
                )
            seen[key] = key_node.start_mark.line
        return yaml.SafeLoader.construct_mapping(loader, node, deep=deep)

    StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, mapping)
    # the float resolver: replace YAML 1.1's (first characters as there)
    resolvers = {
        k: [(tag, rx) for tag, rx in v if tag != "tag:yaml.org,2002:float"]
        for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()
    }
    StrictLoader.yaml_implicit_resolvers = resolvers
    StrictLoader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT, list("-+0123456789."))
    return StrictLoader


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise ValueError(f"key {key!r} is given twice in one object; give each key once")
        out[key] = value
    return out


def read_config_file(path: Path) -> Any:
    """The data of a ``.json`` (JSON) or any other (YAML) config file.

    Raises:
        ValueError: unreadable, unparsable, a duplicate key, or nested too deeply; the
            message names the file.
    """
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"cannot read config file {path}: {err}") from None
    kind = "JSON" if path.suffix.lower() == ".json" else "YAML"
    try:
        if kind == "JSON":
            try:
                return json.loads(text, object_pairs_hook=_no_duplicates)
            except json.JSONDecodeError as err:
                raise ValueError(f"cannot parse {path} as JSON: {err}") from None
        import yaml

        try:
            return yaml.load(text, Loader=_loader())  # a SafeLoader
        except yaml.YAMLError as err:
            raise ValueError(f"cannot parse {path} as YAML: {err}") from None
    except RecursionError:
        raise ValueError(
            f"cannot parse {path} as {kind}: nested too deeply (a config is a mapping of "
            "numbers, lists and small mappings)"
        ) from None
    except ValueError as err:
        if str(err).startswith("cannot parse"):
            raise
        raise ValueError(f"config file {path}: {err}") from None
