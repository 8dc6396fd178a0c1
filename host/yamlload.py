"""YAML as users write numbers: PyYAML follows YAML 1.1, where ``5e-1`` or ``1e300`` (no dot)
are strings, so ``t: 5e-1`` in a trajectory file was refused as "expected a number, got
string". This loader reads YAML 1.2 floats as floats, refuses a mapping that repeats a key (as
YAML 1.2 requires), and is otherwise ``yaml.safe_load``."""

from __future__ import annotations

import re
from typing import Any

import yaml


class _Loader(yaml.SafeLoader):
    """SafeLoader plus YAML 1.2 floats written with an exponent and no dot, and a mapping that
    repeats a key refused (PyYAML keeps the last one: ``{phi: 1, phi: 2}`` silently meant 2)."""

    def construct_mapping(self, node: yaml.Node, deep: bool = False) -> dict:
        if isinstance(node, yaml.MappingNode):
            seen: set = set()
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue  # `<<: *base` then a key of its own overrides it: YAML's meaning
                key = self.construct_object(key_node, deep=False)
                try:
                    dup = key in seen
                    seen.add(key)
                except TypeError:  # unhashable: SafeConstructor says so itself
                    continue
                if dup:
                    raise yaml.constructor.ConstructorError(
                        "while constructing a mapping",
                        node.start_mark,
                        f"found duplicate key {key!r} (which one was meant?)",
                        key_node.start_mark,
                    )
        return super().construct_mapping(node, deep=deep)


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."),
)


def safe_load(text: str) -> Any:
    """``yaml.safe_load`` with YAML 1.2 exponent floats (``5e-1``, ``-2E+3``, ``.5e1``)."""
    return yaml.load(text, Loader=_Loader)  # noqa: S506 - a SafeLoader subclass
