"""Pydantic validation errors as one-line messages that name the dotted key.

:func:`describe` turns one error into ``<key> <what is allowed>, got <value>``; validators
raise :func:`fail` (a message that already names its key) or :func:`field_error` (a phrase
about the value at the error's location).
"""

import difflib
import types
from collections.abc import Sequence
from typing import Annotated, Any, Union, get_args, get_origin

import yaml
from pydantic import BaseModel
from pydantic_core import PydanticCustomError


def fail(message: str) -> PydanticCustomError:
    """An error whose message already names its full dotted key."""
    return PydanticCustomError("silva", message)


def field_error(phrase: str) -> PydanticCustomError:
    """An error about the value at the error's location: '<key> <phrase>, got <value>'."""
    return PydanticCustomError("silva_field", phrase)


def show(value: Any) -> str:
    """A value as a user wrote it in YAML."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if value is None:
        return "null"
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, (int, float)):
        return repr(value)
    try:
        return yaml.safe_dump(value, default_flow_style=True, width=10_000).strip()
    except yaml.YAMLError:
        return repr(value)


def unwrap(annotation: Any) -> Any:
    """The type inside Optional[...] / Annotated[...]."""
    while True:
        origin = get_origin(annotation)
        if origin is Annotated:
            annotation = get_args(annotation)[0]
        elif origin is Union or origin is types.UnionType:
            args = [a for a in get_args(annotation) if a is not type(None)]
            if len(args) != 1:
                return annotation
            annotation = args[0]
        else:
            return annotation


def submodel(annotation: Any) -> type[BaseModel] | None:
    inner = unwrap(annotation)
    return inner if isinstance(inner, type) and issubclass(inner, BaseModel) else None


def _model_at(root: type[BaseModel], loc: Sequence) -> type[BaseModel] | None:
    model = root
    for part in loc:
        if model is None or part not in model.model_fields:
            return None
        model = submodel(model.model_fields[part].annotation)
    return model


def dotted(loc: Sequence) -> str:
    text = ""
    for part in loc:
        if isinstance(part, int):
            text += f"[{part}]"
        elif part == "[key]":
            text += " key"
        else:
            text += f".{part}" if text else str(part)
    return text


_PHRASES = {
    "int_type": "must be an integer",
    "int_parsing": "must be an integer",
    "int_from_float": "must be an integer",
    "float_type": "must be a number",
    "float_parsing": "must be a number",
    "finite_number": "must be a finite number",
    "bool_type": "must be true or false",
    "bool_parsing": "must be true or false",
    "string_type": "must be text",
    "list_type": "must be a list",
    "dict_type": "must be a mapping of keys to values",
    "model_type": "must be a mapping of keys to values",
    "model_attributes_type": "must be a mapping of keys to values",
}


def describe(error: dict, root: type[BaseModel]) -> str:
    """One pydantic error of a ``root`` model as '<dotted key> <what is allowed>, got <value>'."""
    kind, loc, ctx = error["type"], tuple(error["loc"]), error.get("ctx") or {}
    # Union members add their type name to the location; drop them.
    loc = tuple(p for p in loc if p not in ("str", "int", "float"))
    key, got = dotted(loc), show(error.get("input"))
    if kind == "silva":
        return error["msg"]
    if kind == "extra_forbidden":
        model = _model_at(root, loc[:-1])
        valid = list(model.model_fields) if model is not None else []
        close = difflib.get_close_matches(str(loc[-1]), valid, n=1, cutoff=0.6)
        hint = (f"did you mean '{close[0]}'?" if close
                else f"valid keys here: {', '.join(valid)}" if valid else "remove it")
        return f"unknown key '{key}' ({hint})"
    if kind == "missing":
        return f"{key} is required"
    if kind == "silva_field":
        phrase = error["msg"]
    elif kind in _PHRASES:
        phrase = _PHRASES[kind]
    elif kind in ("greater_than", "greater_than_equal", "less_than", "less_than_equal"):
        op = {"greater_than": ">", "greater_than_equal": ">=",
              "less_than": "<", "less_than_equal": "<="}[kind]
        bound = next(iter(ctx.values()), "")
        if isinstance(bound, float) and bound.is_integer():
            bound = int(bound)  # "> 0", as the user would write it
        phrase = f"must be {op} {bound}"
    elif kind == "literal_error":
        phrase = f"must be {ctx.get('expected', '')}"
    elif kind == "string_too_short":
        phrase = "must not be empty"
    else:
        phrase = error["msg"][:1].lower() + error["msg"][1:]
    return f"{key} {phrase}, got {got}"
