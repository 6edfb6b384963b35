"""Loading a daemon configuration: YAML with line numbers, every problem at once.

Strict (unknown keys are errors) and complete: a file is checked against the schema
(:mod:`occ.config`), then every plugin's ``params`` against the plugin's own model (controllers:
``Params``; drivers: their constructor, with no hardware touched), and each problem is reported
as::

    configs/slave.yaml:14 robot.joints[1].limits.max: expected a number, got 'abc'

Line numbers come from the composed YAML node tree: each pydantic error location is walked down
the nodes; a missing field is reported on the line of its parent mapping.

Public API: :func:`load_config`, :func:`parse_config`, :func:`format_errors`.
``python -m occ.core.loader FILE...`` checks configuration files (what ``occd --check`` does).
"""

from __future__ import annotations

import os
import re
import sys
import types
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, Literal, Union, get_args, get_origin

import yaml
from pydantic import BaseModel, ValidationError
from pydantic_core import ErrorDetails

from occ.config import DaemonConfig
from occ.config.base import _CROSS, _PATTERN_TEXT, Loc, _did_you_mean, _format_loc, _num
from occ.errors import ConfigError, OCCError

__all__ = ["load_config", "parse_config", "format_errors"]

_NUMBER_TAGS = ("tag:yaml.org,2002:int", "tag:yaml.org,2002:float")


def load_config(path: str | os.PathLike[str]) -> DaemonConfig:
    """Read and validate the YAML configuration file at ``path``.

    Raises :class:`~occ.errors.ConfigError` listing every problem as ``FILE:LINE path: message``.
    """
    source = os.fspath(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise ConfigError(f"{source}: cannot read configuration: {reason}") from None
    return parse_config(text, source=source, base_dir=Path(source).absolute().parent)


def parse_config(
    text: str, source: str = "<string>", base_dir: str | os.PathLike[str] | None = None
) -> DaemonConfig:
    """Validate configuration YAML ``text``; ``source`` names it in error messages.

    Relative paths resolve against ``base_dir``; by default the directory of ``source`` when it
    looks like a file name, else the current directory.
    """
    if base_dir is None:
        base_dir = Path(source).absolute().parent if not source.startswith("<") else Path.cwd()
    root, data, problems = _compose(text, source)
    if root is None:
        msg = (
            f"{source}:1 (top level): the file is empty; expected a mapping with a 'robot' section"
        )
        raise ConfigError(msg, [msg])
    try:
        config = DaemonConfig.model_validate(data, context={"base_dir": Path(base_dir)})
    except ValidationError as exc:
        problems.extend(_located_errors(exc, root))
    else:
        problems.extend(_plugin_problems(config, root, Path(base_dir)))
        if not problems:
            return _with_plugin_paths_resolved(config, Path(base_dir))
    lines = format_errors(problems, source)
    raise ConfigError("\n".join(lines), lines)


class _Loader(yaml.SafeLoader):
    """YAML 1.1 as PyYAML reads it, without base-60 numbers: ``scale: 10:1`` meant as a ratio
    would silently be 601 (and ``1:30`` 90). Such a value stays a string, which the schema
    then refuses with the line ("expected a number, got '10:1'")."""


_Loader.yaml_implicit_resolvers = {
    first: [(tag, rx) for tag, rx in resolvers if tag not in _NUMBER_TAGS]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
for _tag, _pattern, _first in (
    (
        "tag:yaml.org,2002:int",
        r"""^(?:[-+]?0b[0-1_]+|[-+]?0[0-7_]+|[-+]?(?:0|[1-9][0-9_]*)|[-+]?0x[0-9a-fA-F_]+)$""",
        "-+0123456789",
    ),
    (
        "tag:yaml.org,2002:float",
        r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+][0-9]+)?|\.[0-9][0-9_]*(?:[eE][-+][0-9]+)?"""
        r"""|[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$""",
        "-+0123456789.",
    ),
):
    _Loader.add_implicit_resolver(_tag, re.compile(_pattern, re.X), list(_first))


def format_errors(problems: list[tuple[int, Loc, str]], source: str) -> list[str]:
    """Sort ``(line, loc, message)`` triples by line and render ``FILE:LINE path: message``."""
    ordered = sorted(problems, key=lambda p: p[0])
    return [f"{source}:{line} {_format_loc(loc)}: {msg}" for line, loc, msg in ordered]


def _compose(text: str, source: str) -> tuple[yaml.Node | None, Any, list[tuple[int, Loc, str]]]:
    """Compose and construct the YAML; syntax errors raise ConfigError with the line."""
    loader = _Loader(text)
    try:
        root = loader.get_single_node()
        problems = _duplicate_keys(root) if root is not None else []
        data = loader.construct_document(root) if root is not None else None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark else 1
        what = exc.problem or exc.context or "syntax error"
        col = f" (column {mark.column + 1})" if mark else ""
        msg = f"{source}:{line} invalid YAML: {what}{col}"
        raise ConfigError(msg, [msg]) from None
    except yaml.YAMLError as exc:
        msg = f"{source}:1 invalid YAML: {exc}"
        raise ConfigError(msg, [msg]) from None
    finally:
        loader.dispose()
    return root, data, problems


def _duplicate_keys(node: yaml.Node, loc: Loc = ()) -> list[tuple[int, Loc, str]]:
    """PyYAML silently keeps the last of duplicate keys; a config file must not have any."""
    found: list[tuple[int, Loc, str]] = []
    if isinstance(node, yaml.MappingNode):
        first: dict[str, int] = {}
        for key, value in node.value:
            if key.tag == "tag:yaml.org,2002:merge" or not isinstance(key, yaml.ScalarNode):
                continue
            line = key.start_mark.line + 1
            if key.value in first:
                found.append(
                    (line, (*loc, key.value), f"duplicate key (first at line {first[key.value]})")
                )
            else:
                first[key.value] = line
            found.extend(_duplicate_keys(value, (*loc, key.value)))
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            found.extend(_duplicate_keys(item, (*loc, i)))
    return found


def _line_of(root: yaml.Node | None, loc: Loc) -> int:
    """The line of the deepest node on ``loc`` that exists (a key's own line for mappings)."""
    if root is None:
        return 1
    node: yaml.Node = root
    line = root.start_mark.line + 1
    for part in loc:
        if isinstance(node, yaml.MappingNode):
            match = None
            for key, value in node.value:  # the last duplicate wins, as in construction
                if isinstance(key, yaml.ScalarNode) and key.value == str(part):
                    match = (key, value)
            if match is None:
                break
            line, node = match[0].start_mark.line + 1, match[1]
        elif isinstance(node, yaml.SequenceNode) and isinstance(part, int):
            if not 0 <= part < len(node.value):
                break
            node = node.value[part]
            line = node.start_mark.line + 1
        else:
            break
    return line


def _located_errors(
    exc: ValidationError,
    root: yaml.Node | None,
    prefix: Loc = (),
    model: type[BaseModel] = DaemonConfig,
) -> list[tuple[int, Loc, str]]:
    """``exc``'s errors with their lines; ``prefix`` is where ``model`` sits in the file (a
    plugin's ``params``)."""
    out: list[tuple[int, Loc, str]] = []
    errors = exc.errors(include_url=False)
    failed_items = {tuple(e["loc"][:-1]) for e in errors if e["loc"]}
    for err in errors:
        rel: Loc = tuple(err["loc"])
        if err["type"] == "too_short" and any(f[: len(rel)] == rel for f in failed_items):
            continue  # pydantic counts only the valid items of a tuple; the item errors suffice
        loc = (*prefix, *rel)
        if err["type"] == _CROSS:
            for sub, msg in err["ctx"]["problems"]:
                full = (*loc, *sub)
                out.append((_line_of(root, full), full, msg))
        else:
            out.append((_line_of(root, loc), loc, _message(err, rel, model)))
    return out


def _describe(value: Any) -> str:
    """A short, YAML-flavoured rendering of an offending input value."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return repr(value if len(value) <= 40 else value[:37] + "...")
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, dict):
        return "a mapping"
    if isinstance(value, list | tuple):
        return "a list"
    return repr(str(value))


_TYPE_MESSAGES = {
    "int_type": "expected an integer",
    "int_parsing": "expected an integer",
    "int_from_float": "expected an integer",
    "float_type": "expected a number",
    "float_parsing": "expected a number",
    "finite_number": "expected a finite number",
    "bool_type": "expected true or false",
    "bool_parsing": "expected true or false",
    "string_type": "expected a string",
    "model_type": "expected a mapping",
    "model_attributes_type": "expected a mapping",
    "dict_type": "expected a mapping",
    "list_type": "expected a list",
    "tuple_type": "expected a list",
    "path_type": "expected a path",
    "ip_any_network": "expected an IP address or CIDR network",
    "ip_any_address": "expected an IP address",
}

_BOUNDS = {
    "greater_than": (">", "gt"),
    "greater_than_equal": (">=", "ge"),
    "less_than": ("<", "lt"),
    "less_than_equal": ("<=", "le"),
}


def _message(err: ErrorDetails, loc: Loc, model: type[BaseModel] = DaemonConfig) -> str:
    kind = err["type"]
    ctx = err.get("ctx") or {}
    got = _describe(err.get("input"))
    if kind == "missing":
        return "missing required field"
    if kind == "extra_forbidden":
        found = _annotation_at(loc[:-1], model)
        fields = list(found.model_fields) if _is_model(found) else []
        return f"unknown field '{loc[-1]}'" + _did_you_mean(str(loc[-1]), fields)
    if kind in _TYPE_MESSAGES:
        return f"{_TYPE_MESSAGES[kind]}, got {got}"
    if kind == "literal_error":
        ann = _annotation_at(loc, model)
        if get_origin(ann) is Literal:
            choices = " | ".join(str(a) for a in get_args(ann))
        else:
            choices = str(ctx.get("expected", "?"))
        return f"must be one of {choices}, got {got}"
    if kind in _BOUNDS:
        op, key = _BOUNDS[kind]
        return f"must be {op} {_num(ctx[key])}, got {got}"
    if kind == "too_short":
        n = ctx.get("min_length", 1)
        return "must not be empty" if n == 1 else f"must have at least {n} items"
    if kind == "too_long":
        return f"must have at most {ctx.get('max_length')} items"
    if kind == "string_too_short":
        return "must not be empty"
    if kind == "string_too_long":
        return f"must be at most {ctx.get('max_length')} characters, got {got}"
    if kind == "string_pattern_mismatch":
        pattern = str(ctx.get("pattern", ""))
        return f"expected {_PATTERN_TEXT.get(pattern, 'a string matching ' + pattern)}, got {got}"
    if kind == "path_not_file":
        return f"file not found: {err.get('input')}"
    if kind == "value_error":
        return str(err["msg"]).removeprefix("Value error, ")
    msg = str(err["msg"])
    return msg[:1].lower() + msg[1:]


def _strip_annotation(tp: Any) -> Any:
    """Peel ``Annotated[...]`` and ``X | None`` off a type."""
    while True:
        origin = get_origin(tp)
        if origin is Annotated:
            tp = get_args(tp)[0]
            continue
        if origin in (Union, types.UnionType):
            args = [a for a in get_args(tp) if a is not type(None)]
            if len(args) == 1:
                tp = args[0]
                continue
        return tp


def _is_model(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, BaseModel)


def _annotation_at(loc: Loc, model: type[BaseModel] = DaemonConfig) -> Any:
    """The (stripped) type annotation at ``loc`` under ``model``, or None."""
    tp: Any = model
    for part in loc:
        tp = _strip_annotation(tp)
        if _is_model(tp):
            field = tp.model_fields.get(part) if isinstance(part, str) else None
            if field is None:
                return None
            tp = field.annotation
        elif get_origin(tp) in (tuple, list) and isinstance(part, int):
            tp = get_args(tp)[0]
        elif get_origin(tp) is dict:
            tp = get_args(tp)[1]
        else:
            return None
    return _strip_annotation(tp)


# --------------------------------------------------------------------------------------------
# Plugins: each one's parameters against its own model
# --------------------------------------------------------------------------------------------


def _with_plugin_paths_resolved(config: DaemonConfig, base_dir: Path) -> DaemonConfig:
    """``config`` whose controller ``params`` hold every path field as the absolute path it
    resolved to against the file's directory: the robot validates them again later without
    knowing that directory (a keyframe file beside the config stays found from any cwd)."""
    from occ.controllers import load_controller_class

    out = []
    for cc in config.controllers:
        raw = dict(cc.params)
        model = load_controller_class(cc.plugin).Params.model_validate(
            raw, context={"base_dir": base_dir}
        )
        resolved = {
            key: os.fspath(value)
            for key in raw
            if isinstance(value := getattr(model, key, None), os.PathLike)
        }
        if any(raw[key] != value for key, value in resolved.items()):
            cc = cc.model_copy(update={"params": {**raw, **resolved}})
        out.append(cc)
    if all(a is b for a, b in zip(out, config.controllers, strict=True)):
        return config
    shape = out[0] if not isinstance(config.controller, tuple) else tuple(out)
    return config.model_copy(update={"controller": shape})


def _plugin_problems(
    config: DaemonConfig, root: yaml.Node | None, base_dir: Path | None = None
) -> list[tuple[int, Loc, str]]:
    """Controller ``params`` against the plugin's ``Params`` (and its ``check`` against the
    rest of the file); driver ``params`` through the driver's constructor, which opens no
    hardware (that happens in ``configure``). Unknown plugin names are problems too."""
    from occ.controllers import load_controller_class
    from occ.core.data import RobotData

    problems: list[tuple[int, Loc, str]] = []
    shape = config.controller
    names = [j.name for j in config.robot.joints]
    owners: dict[str, str] = {}
    for i, cc in enumerate(config.controllers):
        at: Loc = ("controller", i) if isinstance(shape, tuple) else ("controller",)
        try:
            cls = load_controller_class(cc.plugin)
        except ConfigError as err:
            problems.append((_line_of(root, (*at, "plugin")), (*at, "plugin"), str(err)))
            continue
        try:
            params = cls.Params.model_validate(
                dict(cc.params), context={"base_dir": base_dir or Path.cwd()}
            )
        except ValidationError as exc:
            problems.extend(_located_errors(exc, root, (*at, "params"), cls.Params))
            continue
        for sub, msg in cls.check(params, config):
            loc = (*at, "params", *sub)
            problems.append((_line_of(root, loc), loc, msg))
        # each command interface has one owner: two controllers on one joint are refused here
        # (occd --check), not only when the robot is built
        try:
            ctrl = cls(params)
            ctrl.data = RobotData(
                config.robot.name,
                names,
                [j.home for j in config.robot.joints],
                None,  # claims need the joint names only
                None,  # type: ignore[arg-type]
            )
            claims = ctrl.command_interfaces()
        except Exception as err:  # noqa: BLE001 - a plugin's own problem, reported with its line
            problems.append((_line_of(root, at), at, f"controller {cc.plugin!r}: {err}"))
            continue
        for claim in claims:
            if claim in owners:
                problems.append(
                    (
                        _line_of(root, at),
                        at,
                        f"command interface {claim!r} is claimed by {owners[claim]!r} too: "
                        "each command has one owner",
                    )
                )
                break
            owners[claim] = cc.plugin
    return problems + _driver_problems(config, root)


def _driver_problems(config: DaemonConfig, root: yaml.Node | None) -> list[tuple[int, Loc, str]]:
    """Each driver's ``params`` through its constructor, which opens no hardware (that happens
    in ``configure``); an unknown plugin on its ``plugin:`` line."""
    from occ.core.assembly import build_joint
    from occ.drivers import create_driver, load_driver_class

    problems: list[tuple[int, Loc, str]] = []
    joints = {j.name: build_joint(j) for j in config.robot.joints}
    for i, dc in enumerate(config.robot.drivers):
        try:
            load_driver_class(dc.plugin)
        except (OCCError, ValueError, TypeError, KeyError) as err:
            where = ("robot", "drivers", i, "plugin")
            problems.append((_line_of(root, where), where, str(err)))
            continue
        try:
            drv = create_driver(
                dc.plugin,
                dc.name,
                [joints[n] for n in dc.joints if n in joints],
                dict(dc.params),
                on_limit=dc.on_limit,
            )
        except (OCCError, ValueError, TypeError, KeyError) as err:
            at = _param_named(("robot", "drivers", i, "params"), dc.params, str(err))
            problems.append((_line_of(root, at), at, str(err)))
        else:
            del drv  # never configured: nothing was opened
    return problems


def _param_named(at: Loc, params: Mapping[str, Any], message: str) -> Loc:
    """Where a driver's refusal belongs: the deepest key of its ``params`` the message names
    after its subject ("cia402 driver 'arm': nodes.yaw: eds ..." -> ``params.nodes.yaw``; a
    dotted name or a bare key the message begins with), else ``params`` itself. A refusal of
    the whole (a bus load of all the nodes) stays on ``params``."""
    _, sep, rest = message.partition(": ")
    head = rest.split(":", 1)[0].split(" ", 1)[0] if sep else ""
    loc, node = at, params
    for part in head.split(".") if head else ():
        if not isinstance(node, Mapping) or part not in node:
            break
        loc, node = (*loc, part), node[part]
    return loc


def _main(argv: list[str]) -> int:
    if not argv or argv[0].startswith("-"):
        print("usage: python -m occ.core.loader FILE.yaml...", file=sys.stderr)
        return 2
    status = 0
    for name in argv:
        try:
            load_config(name)
        except ConfigError as exc:
            print("\n".join(exc.errors), file=sys.stderr)
            status = 1
        else:
            print(f"{name}: ok")
    return status


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
