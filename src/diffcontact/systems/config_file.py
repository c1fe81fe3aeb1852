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

Two more refusals keep a hostile or mistyped YAML file from costing more than reading it:
a key that is a list or a mapping (``? [1, 2]``, ``{a: 1}: 2``) is an error naming its
line, and so is a file whose aliases stand for more than
:data:`~diffcontact.systems.config.MAX_NODES` values once expanded (nested anchors make a
600-byte file stand for 10^8 values, which took minutes to check).
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
            if not isinstance(key_node, yaml.ScalarNode):
                what = "list" if isinstance(key_node, yaml.SequenceNode) else "mapping"
                raise ValueError(
                    f"line {key_node.start_mark.line + 1}: a key is a {what}; keys must be "
                    "strings (names such as masses)"
                )
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


def _expanded_size(root: Any, limit: int) -> int | None:
    """How many nodes (scalars, lists, mappings; keys included) a composed YAML document
    stands for with every alias expanded, or ``None`` where an alias lies inside the
    node it names (a recursive structure). Each node is sized once (an alias shares its
    anchor's node), so this takes time linear in the file however far aliases expand;
    sizes past ``limit`` are kept as ``limit + 1``."""
    import yaml

    def children(node: Any) -> list[Any]:
        if isinstance(node, yaml.SequenceNode):
            return list(node.value)
        if isinstance(node, yaml.MappingNode):
            return [part for pair in node.value for part in pair]
        return []

    sizes: dict[int, int] = {}
    entered: set[int] = set()  # the nodes on the path from the root, not yet sized
    todo: list[tuple[Any, bool]] = [(root, False)]
    while todo:
        node, finish = todo.pop()
        key = id(node)
        if finish:
            entered.discard(key)
            size = 1 + sum(sizes[id(child)] for child in children(node))
            sizes[key] = min(size, limit + 1)
        elif key not in sizes:
            if key in entered:
                return None
            entered.add(key)
            todo.append((node, True))
            todo.extend((child, False) for child in children(node))
    return sizes[id(root)]


def _load_yaml(text: str) -> Any:
    """The data of a YAML document, refusing one whose aliases expand past
    :data:`~diffcontact.systems.config.MAX_NODES` values before constructing it."""
    from diffcontact.systems.config import MAX_NODES

    loader = _loader()(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        size = _expanded_size(node, MAX_NODES)
        if size is None:
            raise ValueError(
                "an alias lies inside the value it names (a recursive structure); a config "
                "is a mapping of numbers, lists and small mappings"
            )
        if size > MAX_NODES:
            raise ValueError(
                f"with its aliases (*name) expanded it holds more than {MAX_NODES:,} values, "
                "the most a config may hold (an alias repeats the whole value it names)"
            )
        return loader.construct_document(node)
    finally:
        loader.dispose()


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
        ValueError: unreadable, unparsable, a duplicate key, a YAML key that is a list
            or a mapping, YAML aliases expanding past
            :data:`~diffcontact.systems.config.MAX_NODES` values, or nested too deeply;
            the message names the file.
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
            return _load_yaml(text)  # a SafeLoader
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
