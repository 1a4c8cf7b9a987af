"""Checking JSON data against its typed contract (a TypedDict), with messages that name the file
and the key. Reading the JSON is ``seathru.io.jsonfile.read_json``.

A contract is a ``TypedDict``; nested objects are TypedDicts too, lists of objects are
``list[SomeTypedDict]``, maps of objects ``dict[str, SomeTypedDict]``. The check is structural:
every required key is there and every nested object has the shape its TypedDict says (keys the
contract does not know are allowed, so a newer writer's additions do not break older readers).
Leaf values are not type-checked.
"""

from __future__ import annotations

import types
import typing
from pathlib import Path
from typing import Any

from seathru.errors import PipelineError


def _is_typed_dict(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, dict) and hasattr(tp, "__required_keys__")


def _object_problem(data: Any, contract: type, where: str) -> str | None:
    """The first way ``data`` breaks ``contract`` (``where`` = dotted path so far), or None."""
    if not isinstance(data, dict):
        return f"{where or 'the file'}: expected an object, found {type(data).__name__}"
    prefix = f"{where}." if where else ""
    missing = sorted(contract.__required_keys__ - set(data))
    if missing:
        return f"{prefix}{missing[0]}: missing"
    for key, tp in typing.get_type_hints(contract).items():
        if key not in data or data[key] is None:
            continue
        problem = _value_problem(data[key], tp, f"{prefix}{key}")
        if problem:
            return problem
    return None


def _value_problem(value: Any, tp: Any, where: str) -> str | None:
    args = [a for a in typing.get_args(tp) if a is not type(None)]
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType) and len(args) == 1:
        return _value_problem(value, args[0], where)
    if _is_typed_dict(tp):
        return _object_problem(value, tp, where)
    if origin is list and args and _is_typed_dict(args[0]):
        if not isinstance(value, list):
            return f"{where}: expected a list, found {type(value).__name__}"
        for i, item in enumerate(value):
            problem = _object_problem(item, args[0], f"{where}[{i}]")
            if problem:
                return problem
    if origin is dict and len(args) == 2 and _is_typed_dict(args[1]):
        if not isinstance(value, dict):
            return f"{where}: expected an object, found {type(value).__name__}"
        for key, item in value.items():
            problem = _object_problem(item, args[1], f"{where}.{key}")
            if problem:
                return problem
    return None


def check_contract(data: Any, contract: type, path: str | Path, fmt: str,
                   hint: str = "") -> None:
    """Raise :class:`PipelineError` naming ``path`` and the key if ``data`` breaks ``contract``
    or its ``format`` is not ``fmt``; ``hint`` says how to get a good file ("rerun ...").

    Example::

        check_contract(json.loads(text), IngestManifest, path, "seathru-ingest/1")
    """
    tail = f"; {hint}" if hint else ""
    found = data.get("format") if isinstance(data, dict) else None
    if found != fmt:
        raise PipelineError(f"{path}: expected format {fmt!r}, found {found!r}{tail}")
    problem = _object_problem(data, contract, "")
    if problem:
        raise PipelineError(f"{path}: malformed ({problem}){tail}")
