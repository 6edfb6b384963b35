"""The configuration's common ground: strict scalar types, the base model, cross-field problems.

Strict: a quoted "1000" is not silently a number, ``true`` is not 1. The scalar types are
public (plugin parameter models use them, so their errors read like the rest of the file's).
A cross-field validator collects (relative location, message) pairs and raises them together
(:func:`_raise_problems`); :mod:`occ.core.loader` expands them into one line each.
"""

from __future__ import annotations

import difflib
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    AllowInfNan,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    FilePath,
    Strict,
    StringConstraints,
    ValidationInfo,
)
from pydantic_core import PydanticCustomError

NAME_PATTERN = r"^[A-Za-z0-9_-]+$"
MESSAGE_TYPE_PATTERN = r"^[A-Za-z0-9_]{1,12}$"
REMOTE_PATTERN = r"^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):[0-9]{1,5}$"

#: Friendly descriptions of the string patterns, used in error messages and in the docs.
_PATTERN_TEXT = {
    NAME_PATTERN: "a name of letters, digits, '_' and '-'",
    MESSAGE_TYPE_PATTERN: "an OpenIGTLink type name (1-12 letters, digits or '_')",
    REMOTE_PATTERN: "'host:port'",
}

Int = Annotated[int, Strict()]
Float = Annotated[float, Strict(), AllowInfNan(False)]  # ints are accepted, bools and NaN not
Bool = Annotated[bool, Strict()]
Str = Annotated[str, Strict(), StringConstraints(min_length=1)]
Name = Annotated[str, Strict(), StringConstraints(pattern=NAME_PATTERN)]
MessageType = Annotated[str, Strict(), StringConstraints(pattern=MESSAGE_TYPE_PATTERN)]
DeviceName = Annotated[str, Strict(), StringConstraints(min_length=1, max_length=20)]
PosFloat = Annotated[Float, Field(gt=0)]
NonNegFloat = Annotated[Float, Field(ge=0)]

Policy = Literal["hold", "fault"]
BUILTIN_MODELS = ("occ_slave", "master3")
BuiltinModel = Literal["occ_slave", "master3"]

_WILDCARD_HOSTS = frozenset({"", "0.0.0.0", "::"})


def _check_remote_port(value: str) -> str:
    port = int(value.rsplit(":", 1)[1])
    if not 1 <= port <= 65535:
        raise ValueError(f"remote port must be 1..65535, got {port}")
    return value


Remote = Annotated[
    str, Strict(), StringConstraints(pattern=REMOTE_PATTERN), AfterValidator(_check_remote_port)
]


def _resolve_path(value: Any, info: ValidationInfo) -> Any:
    """Make a relative path absolute against the config file's directory (``base_dir``)."""
    if not isinstance(value, str | os.PathLike) or str(value) == "":
        return value  # let the schema produce the type error
    path = Path(value).expanduser()
    if not path.is_absolute():
        ctx = info.context if isinstance(info.context, dict) else {}
        base = Path(ctx.get("base_dir") or os.getcwd())
        path = base / path
    return os.path.normpath(path.absolute())  # a str: valid input in python and JSON modes


ExistingFile = Annotated[FilePath, BeforeValidator(_resolve_path)]
OutputPath = Annotated[Path, BeforeValidator(_resolve_path)]


# --------------------------------------------------------------------------------------------
# Cross-field problems: a validator collects (relative location, message) pairs and raises
# them together; the error formatter expands them into one line each.
# --------------------------------------------------------------------------------------------

_CROSS = "occ_cross_field"
Loc = tuple[str | int, ...]


def _format_loc(loc: Loc) -> str:
    text = ""
    for part in loc:
        if isinstance(part, int):
            text += f"[{part}]"
        else:
            text += f".{part}" if text else str(part)
    return text or "(top level)"


def _raise_problems(problems: list[tuple[Loc, str]]) -> None:
    if problems:
        summary = "; ".join(f"{_format_loc(loc)}: {msg}" for loc, msg in problems)
        raise PydanticCustomError(
            _CROSS, "{summary}", {"summary": summary, "problems": tuple(problems)}
        )


def _did_you_mean(word: str, candidates: Sequence[str]) -> str:
    close = difflib.get_close_matches(word, list(candidates), n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


def _num(value: float) -> str:
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    return str(value)


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


#: three coordinates (a point or a direction)
Vec3 = tuple[Float, Float, Float]
