"""Reading a config file: YAML or JSON into plain data, strictly.

Two departures from ``yaml.safe_load`` / ``json.loads``, both so that a config means
what its author wrote:

- a key given twice in one mapping is an error (both parsers keep the last one
  silently: ``radii`` written twice took the second list);
- YAML scalars are read by YAML 1.2's core schema, as JSON reads them, not by the
  YAML 1.1 rules of PyYAML: ``1e-3``, ``5e2`` and ``1.0e9`` are numbers (YAML 1.1 made
  them strings, which the config's validation then refused as "not a number"), ``010``
  is ten (YAML 1.1: eight, octal), and only ``true`` / ``false`` are booleans (YAML 1.1
  also read ``yes``, ``no``, ``on`` and ``off``, so a typo passed as a setting).
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
# YAML 1.2's core-schema integers and booleans
_INT = re.compile(r"^(?:[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+)$")
_BOOL = re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$")


def _loader():
    import yaml

    class StrictLoader(yaml.SafeLoader):
        """``SafeLoader`` refusing duplicate keys, with YAML 1.2's numbers and booleans."""

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

    def integer(loader: StrictLoader, node: yaml.ScalarNode) -> int:
        text = loader.construct_scalar(node)
        if text.startswith(("0o", "0x")):
            return int(text[2:], 8 if text[1] == "o" else 16)
        return int(text, 10)  # (leading zeros are decimal)

    StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, mapping)
    StrictLoader.add_constructor("tag:yaml.org,2002:int", integer)
    # the float, int and bool resolvers: replace YAML 1.1's (first characters as there)
    ours = {"tag:yaml.org,2002:float", "tag:yaml.org,2002:int", "tag:yaml.org,2002:bool"}
    resolvers = {
        k: [(tag, rx) for tag, rx in v if tag not in ours]
        for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()
    }
    StrictLoader.yaml_implicit_resolvers = resolvers
    StrictLoader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT, list("-+0123456789."))
    StrictLoader.add_implicit_resolver("tag:yaml.org,2002:int", _INT, list("-+0123456789"))
    StrictLoader.add_implicit_resolver("tag:yaml.org,2002:bool", _BOOL, list("tTfF"))
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
