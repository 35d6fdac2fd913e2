"""Field types and the base section shared by the configuration's sections.

Each type checks its value before pydantic converts it and reports problems as a phrase
about the value (see :mod:`workflows.config.messages`).
"""

import math
import os
import re
from typing import Annotated, Any, Literal, Union

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, model_validator
from pydantic_core import PydanticCustomError

from workflows.config.messages import field_error


# -- field types ---------------------------------------------------------------------------
# Booleans are ints in Python (and pydantic's lax mode accepts them as numbers): refuse them,
# so "stages: true" is an error instead of one stage.
def _not_bool(kind: str):
    def check(value):
        if isinstance(value, bool):
            raise PydanticCustomError("silva_field", f"must be {kind}")
        return value

    return BeforeValidator(check)


Integer = Annotated[int, _not_bool("an integer")]
Number = Annotated[float, _not_bool("a number"), Field(allow_inf_nan=False)]


class Section(BaseModel):
    """Common behaviour: unknown keys are errors, values are frozen, null means default."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    @model_validator(mode="before")
    @classmethod
    def _null_is_default(cls, data: Any) -> Any:
        # "key:" with nothing after it in YAML is None; for keys whose default is not None
        # that means "use the default" (a template with its values commented out).
        if isinstance(data, dict):
            fields = cls.model_fields
            return {
                k: v for k, v in data.items()
                if not (v is None and k in fields and not _defaults_to_none(fields[k]))
            }
        return data


def _defaults_to_none(field) -> bool:
    return field.default_factory is None and field.default is None


def _path_list(value: Any) -> Any:
    # A single path or glob is a list of one; Path objects are written as text.
    if isinstance(value, (str, os.PathLike)):
        value = [value]
    if isinstance(value, (list, tuple)):
        value = [os.fspath(v) if isinstance(v, os.PathLike) else v for v in value]
        for item in value:
            if item == "":
                raise field_error("must not contain an empty path")
    return value


PathList = Annotated[list[str], BeforeValidator(_path_list)]


def _chunk_size(value: Any) -> Any:
    if isinstance(value, str) and value == "auto":
        return value
    if isinstance(value, str):  # YAML 1.1 reads 1e-9 (no dot) as text
        try:
            value = float(value)
        except ValueError:
            pass
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value) or value <= 0:
        raise field_error("must be 'auto' or a number of metres > 0")
    return float(value)


ChunkSize = Annotated[Union[Literal["auto"], float], BeforeValidator(_chunk_size)]
#: a length in metres that may also be derived from the data ('auto')
AutoLength = ChunkSize


def _auto_or_bool(value: Any) -> Any:
    if value == "auto" or isinstance(value, bool):
        return value
    raise field_error("must be 'auto', true or false")


AutoBool = Annotated[Union[Literal["auto"], bool], BeforeValidator(_auto_or_bool)]


def _max_features(value: Any) -> Any:
    ok = (
        value in ("sqrt", "log2")
        or (isinstance(value, int) and not isinstance(value, bool) and value >= 1)
        or (isinstance(value, float) and 0 < value <= 1)
    )
    if not ok:
        raise field_error("must be 'sqrt', 'log2', an integer >= 1 or a number in (0, 1]")
    return value


def _memory(value: Any) -> Any:
    """Dask memory syntax: 'auto', '4GiB', '500MB' or a number of bytes."""
    if isinstance(value, bool):
        raise field_error("must be 'auto', a size such as '4GiB' or a number of bytes")
    if isinstance(value, str) and value != "auto":
        from dask.utils import parse_bytes

        try:
            if parse_bytes(value) <= 0:
                raise ValueError
        except (ValueError, TypeError):
            raise field_error("must be 'auto', a size such as '4GiB' or a number of bytes")
    elif isinstance(value, (int, float)) and value <= 0:
        raise field_error("must be 'auto', a size such as '4GiB' or a number of bytes > 0")
    return value


_WALLTIME = re.compile(r"^(\d+-)?\d+(:\d+){0,2}$")


def _walltime(value: Any) -> Any:
    if not isinstance(value, str) or not _WALLTIME.match(value):
        raise field_error("must be a SLURM time such as '08:00:00', '90' or '1-12:00:00' "
                          "(quote it in YAML)")
    return value


MaxFeatures = Annotated[Union[str, int, float], BeforeValidator(_max_features)]
Memory = Annotated[str, BeforeValidator(_memory)]
MemoryLimit = Annotated[Union[str, int, float], BeforeValidator(_memory)]
Walltime = Annotated[str, BeforeValidator(_walltime)]
