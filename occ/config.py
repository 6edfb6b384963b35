"""The daemon configuration: one YAML file per daemon, validated at load.

The schema is a tree of frozen pydantic models rooted at :class:`DaemonConfig`. Loading is
strict (unknown keys are errors) and reports *every* problem at once, one line each, as::

    configs/slave.yaml:14 robot.joints[1].limits.max: expected a number, got 'abc'

Line numbers come from the composed YAML node tree: each pydantic error location is walked
down the nodes; a missing field is reported on the line of its parent mapping.

Units inside ``occ`` are SI (metres, radians, seconds). Fields in other units say so in their
name (``budget_us``, ``period_ms``, ``rate_hz``). Relative paths (``robot.frame.urdf``,
``recording.path``) are resolved against the directory of the configuration file.

Public API: :func:`load_config`, :func:`parse_config`, :class:`DaemonConfig` (and its parts),
:func:`config_reference_markdown` (the field table of ``docs/CONFIG.md``).

``python -m occ.config FILE...`` checks configuration files; ``python -m occ.config --markdown``
prints the reference table; ``python -m occ.config --update-docs docs/CONFIG.md`` rewrites it.
"""

from __future__ import annotations

import difflib
import ipaddress
import os
import re
import sys
import types
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, Literal, Union, get_args, get_origin

import yaml
from pydantic import (
    AfterValidator,
    AllowInfNan,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    FilePath,
    IPvAnyNetwork,
    Strict,
    StringConstraints,
    ValidationError,
    ValidationInfo,
    model_validator,
)
from pydantic_core import ErrorDetails, PydanticCustomError

from igtl.auth import load_key
from occ.errors import ConfigError

__all__ = [
    "DaemonConfig",
    "RobotConfig",
    "FrameConfig",
    "JointConfig",
    "JointLimits",
    "PidGains",
    "DriverConfig",
    "RealtimeConfig",
    "InterfaceConfig",
    "InputConfig",
    "OutputConfig",
    "SafetyConfig",
    "WatchdogConfig",
    "LossConfig",
    "RecordingConfig",
    "StatsConfig",
    "TeleopConfig",
    "BUILTIN_MODELS",
    "load_config",
    "parse_config",
    "format_errors",
    "config_reference_markdown",
]

# --------------------------------------------------------------------------------------------
# Scalar types. Strict: a quoted "1000" is not silently a number, ``true`` is not 1.
# --------------------------------------------------------------------------------------------

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


# --------------------------------------------------------------------------------------------
# robot
# --------------------------------------------------------------------------------------------


class FrameConfig(_Model):
    """Kinematic model: exactly one of a built-in model or a URDF file."""

    model: BuiltinModel | None = Field(
        None, description="Built-in kinematic model name. Exclusive with `urdf`."
    )
    urdf: ExistingFile | None = Field(
        None,
        description="URDF file, relative to the config file's directory; must exist. "
        "Exclusive with `model`.",
    )
    tip_link: Str | None = Field(
        None, description="URDF link whose pose is the tool tip. Required with `urdf`."
    )
    base_link: Str | None = Field(
        None, description="URDF link used as the base frame; null = the URDF root link."
    )

    @model_validator(mode="after")
    def _exactly_one_source(self) -> FrameConfig:
        problems: list[tuple[Loc, str]] = []
        if (self.model is None) == (self.urdf is None):
            which = "both are set" if self.model is not None else "neither is set"
            problems.append(((), f"exactly one of 'model' or 'urdf' is required ({which})"))
        if self.urdf is not None and self.tip_link is None:
            problems.append((("tip_link",), "required when 'urdf' is set"))
        _raise_problems(problems)
        return self


class JointLimits(_Model):
    """Position, velocity and effort limits of one joint (SI units)."""

    min: Float = Field(description="Lower position limit (rad or m).")
    max: Float = Field(description="Upper position limit (rad or m); must be > `min`.")
    velocity: PosFloat = Field(description="Velocity limit (rad/s or m/s), > 0.")
    effort: PosFloat | None = Field(
        None, description="Effort limit (N·m or N); null = not limited here."
    )

    @model_validator(mode="after")
    def _ordered(self) -> JointLimits:
        if not self.min < self.max:
            _raise_problems(
                [(("max",), f"must be greater than min ({_num(self.min)}), got {_num(self.max)}")]
            )
        return self


class PidGains(_Model):
    """Per-joint servo law, used when the driver takes effort commands."""

    kp: NonNegFloat = Field(description="Proportional gain, >= 0.")
    ki: NonNegFloat = Field(0.0, description="Integral gain, >= 0.")
    kd: NonNegFloat = Field(0.0, description="Derivative gain, >= 0.")
    i_limit: NonNegFloat | None = Field(
        None, description="Clamp of the integral term (anti-windup); null = unclamped."
    )
    out_limit: PosFloat | None = Field(
        None, description="Clamp of the output effort; null = the joint's effort limit."
    )


class JointConfig(_Model):
    """One joint of the robot."""

    name: Name = Field(description="Joint name, unique within the robot.")
    type: Literal["revolute", "prismatic"] = Field(
        "revolute", description="Revolute (radians) or prismatic (metres)."
    )
    limits: JointLimits = Field(description="Joint limits.")
    home: Float = Field(0.0, description="Home position; must lie within the limits.")
    pid: PidGains | None = Field(None, description="Servo gains; null = no servo law.")

    @model_validator(mode="after")
    def _home_within_limits(self) -> JointConfig:
        lo, hi = self.limits.min, self.limits.max
        if not lo <= self.home <= hi:
            _raise_problems(
                [(("home",), f"{_num(self.home)} is outside the limits [{_num(lo)}, {_num(hi)}]")]
            )
        return self


class DriverConfig(_Model):
    """One hardware driver (plugin) and the joints it drives."""

    name: Name = Field(description="Driver name, unique within the robot.")
    plugin: Str = Field(
        description="Driver plugin name (`sim`, `can`, ...), looked up when the robot is built."
    )
    joints: Annotated[tuple[Name, ...], Field(min_length=1)] = Field(
        description="Joints this driver drives; each must be declared in `robot.joints`."
    )
    on_limit: Literal["clamp", "fault"] = Field(
        "clamp", description="What a command beyond a joint limit does: clamp it, or fault."
    )
    params: dict[str, Any] = Field({}, description="Free-form parameters passed to the plugin.")


class RealtimeConfig(_Model):
    """Operating-system scheduling of the control loop."""

    fifo_priority: Annotated[Int, Field(ge=1, le=99)] | None = Field(
        None, description="SCHED_FIFO priority 1..99; null = normal scheduling."
    )
    cpu: Annotated[Int, Field(ge=0)] | None = Field(
        None, description="CPU core to pin the loop to; null = no pinning."
    )
    spin_us: Annotated[Float, Field(ge=0, le=1000)] = Field(
        0.0,
        description="The loop sleeps until this long before each deadline, then spins: "
        "less jitter for more CPU (200 us = 20 % of a core at 1 kHz). 0 = sleep only: with "
        "SCHED_FIFO the wake-up is early enough and the master-to-slave latency the same "
        "(docs/BENCHMARKS.md).",
    )
    poll_streams: Bool = Field(
        True,
        description="The loop reads its UDP stream sockets itself, at most 4 datagrams a tick "
        "(no thread wake-up per datagram; a flood costs the tick a bounded amount). false = "
        "an interface thread receives them (docs/BENCHMARKS.md compares both).",
    )
    switch_interval_us: Annotated[Float, Field(ge=50, le=100000)] | None = Field(
        None,
        description="Python's thread switch interval during the run (sys.setswitchinterval): "
        "how long an interface thread may keep the interpreter when the loop wants it; "
        "null = Python's default (5000 us).",
    )
    gc: Literal["freeze", "off", "default"] = Field(
        "freeze",
        description="Garbage collector: `freeze` after start-up, `off` entirely, or `default`.",
    )


class RobotConfig(_Model):
    """The robot: kinematics, joints, drivers and loop timing."""

    name: Name = Field(description="Robot name (used in logs and STATUS messages).")
    rate_hz: Annotated[Int, Field(ge=1, le=10000)] = Field(
        1000, description="Control loop rate in Hz."
    )
    frame: FrameConfig = Field(description="Kinematic model.")
    joints: Annotated[tuple[JointConfig, ...], Field(min_length=1)] = Field(
        description="Joints, in kinematic order; names unique."
    )
    drivers: Annotated[tuple[DriverConfig, ...], Field(min_length=1)] = Field(
        description="Drivers; every joint is driven by exactly one driver."
    )
    realtime: RealtimeConfig = Field(RealtimeConfig(), description="Loop scheduling.")

    @property
    def period_s(self) -> float:
        """The control period in seconds."""
        return 1.0 / self.rate_hz

    @property
    def joint_names(self) -> tuple[str, ...]:
        return tuple(j.name for j in self.joints)

    def joint(self, name: str) -> JointConfig:
        for j in self.joints:
            if j.name == name:
                return j
        raise KeyError(name)

    @model_validator(mode="after")
    def _joints_and_drivers(self) -> RobotConfig:
        problems: list[tuple[Loc, str]] = []
        first_joint: dict[str, int] = {}
        for i, j in enumerate(self.joints):
            if j.name in first_joint:
                problems.append(
                    (
                        ("joints", i, "name"),
                        f"duplicate joint name '{j.name}' (first at joints[{first_joint[j.name]}])",
                    )
                )
            else:
                first_joint[j.name] = i
        first_driver: dict[str, int] = {}
        driven_by: dict[str, str] = {}
        for d, drv in enumerate(self.drivers):
            if drv.name in first_driver:
                problems.append(
                    (
                        ("drivers", d, "name"),
                        f"duplicate driver name '{drv.name}' "
                        f"(first at drivers[{first_driver[drv.name]}])",
                    )
                )
            else:
                first_driver[drv.name] = d
            for k, jname in enumerate(drv.joints):
                loc: Loc = ("drivers", d, "joints", k)
                if jname not in first_joint:
                    problems.append(
                        (loc, f"unknown joint '{jname}'" + _did_you_mean(jname, list(first_joint)))
                    )
                elif jname in driven_by:
                    problems.append(
                        (loc, f"joint '{jname}' is already driven by driver '{driven_by[jname]}'")
                    )
                else:
                    driven_by[jname] = drv.name
        for jname, i in first_joint.items():
            if jname not in driven_by:
                problems.append(
                    (("joints", i, "name"), f"joint '{jname}' is not driven by any driver")
                )
        _raise_problems(problems)
        return self


# --------------------------------------------------------------------------------------------
# interfaces
# --------------------------------------------------------------------------------------------


class InputConfig(_Model):
    """A message type accepted from an interface into the control loop."""

    type: MessageType = Field(description="OpenIGTLink message type, e.g. `POSITION`.")
    device: DeviceName | None = Field(
        None, description="Accept only this device name (max 20 chars); null = any device."
    )
    queue: Literal["stream", "command"] = Field(
        "stream",
        description="`stream`: bounded, oldest dropped when full, drained every tick; "
        "`command`: bounded FIFO, a full queue answers the sender with an error.",
    )
    depth: Annotated[Int, Field(ge=1)] = Field(10, description="Queue capacity (messages).")


class OutputConfig(_Model):
    """A robot signal sent out through an interface at a fixed rate."""

    type: MessageType = Field(description="OpenIGTLink message type, e.g. `TRANSFORM`.")
    device: DeviceName = Field(description="Device name put in the message header.")
    source: Name = Field(
        description="Named robot signal to send (`tip`, `base`, `joints`, `status`, ...)."
    )
    rate_hz: PosFloat = Field(description="Send rate in Hz; > 0 and <= `robot.rate_hz`.")


class InterfaceConfig(_Model):
    """One OpenIGTLink endpoint (its own thread)."""

    name: Name = Field(description="Interface name, unique in the file.")
    transport: Literal["tcp-server", "tcp-client", "udp", "inproc"] = Field(
        description="Transport; `inproc`: an in-process channel (tests, simulations; no sockets)."
    )
    channel: Name | None = Field(
        None,
        description="inproc: the channel name peers in the same process connect to "
        "(required for inproc).",
    )
    host: Str = Field(
        "127.0.0.1", description="Local address to bind (tcp-server, udp); `0.0.0.0` = all."
    )
    port: Annotated[Int, Field(ge=0, le=65535)] = Field(
        18944, description="Local port to bind (tcp-server, udp); 0 = ephemeral (tests)."
    )
    remote: Remote | None = Field(
        None,
        description="`host:port` to connect to (required for tcp-client) or, for udp, "
        "the send target.",
    )
    allowed_peers: tuple[IPvAnyNetwork, ...] = Field(
        (ipaddress.ip_network("127.0.0.1"),),
        description="IP addresses or CIDR networks allowed to connect or send; others are refused "
        "and counted. Must not be empty (0.0.0.0/0 = any IPv4 peer).",
    )
    role: Literal["none", "viewer", "operator"] = Field(
        "none",
        description="What clients may ask: `none` (a data link: requests refused), `viewer` "
        "(GET_ queries and the read-only commands GetState and GetStats, sequence numbers "
        "withheld; state STATUS pushed; for 3D Slicer), `operator` (every command). Motion "
        "comes only from the configured stream inputs, whatever the role.",
    )
    operators: tuple[IPvAnyNetwork, ...] | None = Field(
        None,
        description="role `operator` only: the addresses or networks that get the operator "
        "role; other allowed peers are viewers. null = every allowed peer is an operator.",
    )
    operator_slots: Annotated[Int, Field(ge=0)] = Field(
        1,
        description="tcp-server with `operators` set: this many of `max_clients` slots are kept "
        "for operator addresses, so viewers cannot lock operators out.",
    )
    header_version: Literal[1, 2] = Field(
        2, description="Header version of what we send (a tcp-server answers each client in kind)."
    )
    max_clients: Annotated[Int, Field(ge=1)] = Field(
        8, description="Maximum simultaneous clients (tcp-server)."
    )
    send_queue: Annotated[Int, Field(ge=1)] = Field(
        256,
        description="Bounded per-client send queue (messages); a slow client loses its "
        "own oldest messages.",
    )
    idle_timeout_s: PosFloat | None = Field(
        None, description="Drop a client silent for this long; null = never."
    )
    max_body_kib: Annotated[Int, Field(ge=1, le=4 * 1024 * 1024)] = Field(
        1024,
        description="Largest message body accepted (KiB); bigger ones are refused and counted "
        "before any of their body is buffered (raise it for an interface that receives images).",
    )
    unread_limit_kib: Annotated[Int, Field(ge=0)] = Field(
        16,
        description="tcp-server: a client whose receive window shows this much of our data "
        "unread for `send_stall_timeout_s` is closed and counted (it does not read; kernel "
        "buffers would hide that for minutes of a 10 Hz stream). 0 = off.",
    )
    message_timeout_s: PosFloat | None = Field(
        10.0,
        description="tcp-server: a message begun must be complete within this time; a client "
        "trickling bytes (slowloris) is closed and counted. null = no limit.",
    )
    send_stall_timeout_s: PosFloat | None = Field(
        5.0,
        description="tcp-server: a client that takes none of our data for this long (it does "
        "not read) is closed and counted, freeing its slot. null = never.",
    )
    inputs: tuple[InputConfig, ...] = Field(
        (), description="Message types accepted into the loop, with queue semantics."
    )
    outputs: tuple[OutputConfig, ...] = Field((), description="Signals sent out periodically.")
    auth_key_file: ExistingFile | None = Field(
        None,
        description="A file holding a shared key (first line; `hex:` prefix for hex bytes; at "
        "least 16 bytes): every message sent here carries an HMAC-SHA256 tag in its v2 "
        "metadata, and every message received without a valid tag is refused and counted "
        "(`unauthenticated`). For a master link on a network that is not trusted; both ends "
        "use the same file. Relative paths are read from the config file's folder.",
    )
    kernel_filter: Bool = Field(
        True,
        description="udp with stream inputs: once the stream has its owner (`stream_source`, "
        "or the first sender), the socket is connected to it and the kernel drops every other "
        "sender's datagrams (a flood from elsewhere can then neither cost the loop a read nor "
        "crowd the master's datagrams out of the buffer; those are not counted as `foreign`).",
    )
    stream_source: Remote | None = Field(
        None,
        description="`host:port` the stream inputs must come from (the master's sending "
        "socket); null = pinned to the first sender until an operator's Reset. Samples "
        "from any other sender are refused and counted.",
    )

    @model_validator(mode="before")
    @classmethod
    def _renamed(cls, data: Any) -> Any:
        if isinstance(data, dict) and "commands" in data:
            raise PydanticCustomError(
                "renamed",
                "`commands` was replaced by `role`: `role: operator` for `commands: true`, "
                "`role: viewer` for a 3D Slicer connection, nothing for a data link",
            )
        return data

    @property
    def remote_address(self) -> tuple[str, int] | None:
        """``remote`` split into ``(host, port)`` (IPv6 brackets removed), or None."""
        if self.remote is None:
            return None
        host, port = self.remote.rsplit(":", 1)
        return host.strip("[]"), int(port)

    def peer_allowed(self, address: str) -> bool:
        """True if ``address`` (an IP string) is within ``allowed_peers``."""
        try:
            ip = ipaddress.ip_address(address)
        except ValueError:
            return False
        return any(ip in net for net in self.allowed_peers)

    @model_validator(mode="after")
    def _transport_rules(self) -> InterfaceConfig:
        problems: list[tuple[Loc, str]] = []
        if self.transport == "tcp-client" and self.remote is None:
            problems.append((("remote",), "required for transport 'tcp-client'"))
        if self.transport == "inproc" and self.channel is None:
            problems.append((("channel",), "required for transport 'inproc'"))
        if self.auth_key_file is not None:
            try:
                load_key(self.auth_key_file.read_text(encoding="utf-8"))
            except (OSError, UnicodeDecodeError, ValueError) as err:
                problems.append((("auth_key_file",), f"unusable key: {err}"))
            if self.header_version != 2:
                problems.append((("auth_key_file",), "needs header_version 2 (metadata)"))
        if self.operators is not None and self.role != "operator":
            problems.append((("operators",), f"needs role 'operator' (role is {self.role!r})"))
        if (
            self.operators is not None
            and self.transport == "tcp-server"
            and self.operator_slots >= self.max_clients
        ):
            problems.append(
                (
                    ("operator_slots",),
                    f"must be below max_clients ({self.max_clients}), got {self.operator_slots}",
                )
            )
        if not self.allowed_peers:
            # read literally, an empty list refuses everyone; the transports once took it as
            # "no filter". Neither is what anyone means: ask.
            problems.append(
                (
                    ("allowed_peers",),
                    "an empty list would refuse every peer; list the addresses or networks "
                    "allowed (0.0.0.0/0 for any IPv4 peer)",
                )
            )
        seen: dict[tuple[str, str | None], int] = {}
        for i, inp in enumerate(self.inputs):
            key = (inp.type, inp.device)
            if key in seen:
                problems.append(
                    (
                        ("inputs", i),
                        f"duplicate input {inp.type}/{inp.device or '*'} "
                        f"(first at inputs[{seen[key]}])",
                    )
                )
            else:
                seen[key] = i
        _raise_problems(problems)
        return self


# --------------------------------------------------------------------------------------------
# safety, recording, stats
# --------------------------------------------------------------------------------------------


class WatchdogConfig(_Model):
    """Loop-period watchdog: overruns are alerts; a run of them, or one big gap, is a stop."""

    budget_us: PosFloat = Field(1000.0, description="Cycle budget in µs; over it = an alert.")
    alert_run: Annotated[Int, Field(ge=1)] = Field(
        1, description="Consecutive over-budget cycles that raise an alert."
    )
    stop_run: Annotated[Int, Field(ge=1)] = Field(
        5, description="Consecutive over-budget cycles that stop the robot; >= `alert_run`."
    )
    hard_gap_ms: PosFloat = Field(
        10.0, description="A single gap between cycles longer than this stops the robot."
    )
    policy: Policy = Field(
        "hold", description="On stop: `hold` the last safe position, or latch `fault`."
    )

    @model_validator(mode="after")
    def _runs_ordered(self) -> WatchdogConfig:
        if self.stop_run < self.alert_run:
            _raise_problems(
                [(("stop_run",), f"must be >= alert_run ({self.alert_run}), got {self.stop_run}")]
            )
        return self


class LossConfig(_Model):
    """Packet-loss monitor on one input interface."""

    enabled: Bool = Field(True, description="Run the loss monitor.")
    input: Name | None = Field(
        None, description="Name of the interface whose stream is watched; null = none."
    )
    period_ms: PosFloat = Field(2.0, description="Expected period of the watched stream in ms.")
    max_consecutive: Annotated[Int, Field(ge=0)] = Field(
        2,
        description="Consecutive losses tolerated; `max_consecutive + 1` in a row stop the robot.",
    )
    deadline_ms: PosFloat | None = Field(
        None,
        description="Hold (stop moving, not latched) when no good packet for this long; null "
        "= `period_ms * (max_consecutive + 1) + period_ms / 4` (6.5 ms: the OCC 7 ms rule).",
    )
    grace_ms: PosFloat = Field(
        100.0,
        description="Latched stop with an alert when the stream stays silent this long (a "
        "dead master); a stream back within it, with no gap of `max_consecutive + 1`, "
        "resumes by itself.",
    )
    strict: Bool = Field(
        False,
        description="The paper's rule word for word: the deadline itself latches the stop "
        "(no hold-and-resume).",
    )
    timestamp_tolerance_ms: PosFloat | None = Field(
        50.0,
        description="Refuse samples whose header timestamp is off by more than this from the "
        "peer's learned clock offset (stale or future); a run of refused samples counts like "
        "loss. null = no timestamp check.",
    )
    policy: Policy = Field(
        "hold", description="On a latched loss: `hold` (STOPPED until Run) or latch `fault`."
    )

    @model_validator(mode="after")
    def _grace_after_deadline(self) -> LossConfig:
        deadline = (
            self.deadline_ms
            if self.deadline_ms is not None
            else self.period_ms * (self.max_consecutive + 1.25)
        )
        if self.grace_ms < deadline:
            _raise_problems(
                [
                    (
                        ("grace_ms",),
                        f"must be >= the deadline ({deadline:g} ms), got {self.grace_ms:g}",
                    )
                ]
            )
        return self


class SupervisorConfig(_Model):
    """The supervisor: a thread outside the loop that notices a loop that stopped ticking."""

    enabled: Bool = Field(True, description="Run the supervisor thread.")
    timeout_ms: PosFloat = Field(
        20.0,
        description="A loop that has not ticked for this long is hung: drivers to their safe "
        "state at once, operators alerted, FAULT when the loop comes back.",
    )
    fifo_priority: Annotated[Int, Field(ge=1, le=99)] | None = Field(
        None,
        description="SCHED_FIFO priority of the supervisor thread; null = one above the loop's "
        "`robot.realtime.fifo_priority` (when that is set and permitted).",
    )


class SafetyConfig(_Model):
    """Safety monitors."""

    watchdog: WatchdogConfig = Field(WatchdogConfig(), description="Watchdog.")
    loss: LossConfig = Field(LossConfig(), description="Packet-loss monitor.")
    supervisor: SupervisorConfig = Field(SupervisorConfig(), description="Loop supervisor.")


class RecordingConfig(_Model):
    """Recording of robot state (and optionally messages) to a file."""

    path: OutputPath | None = Field(
        None, description="Output file, relative to the config file's directory; null = off."
    )
    rate_hz: PosFloat = Field(
        100.0, description="Sampling rate of robot state in Hz; <= `robot.rate_hz`."
    )
    include_messages: Bool = Field(True, description="Also record IGTL messages in and out.")


class StatsConfig(_Model):
    """Timing statistics (always collected)."""

    log_every_s: PosFloat = Field(10.0, description="Log a statistics summary this often (s).")


Vec3 = tuple[Float, Float, Float]


class TeleopConfig(_Model):
    """Master-slave teleoperation (occ/controllers/teleop.py). Lengths in mm, as on the wire."""

    role: Literal["master", "slave"] = Field(description="Which side of the pair this daemon is.")
    # --- master
    input: Literal["sim", "igtl", "driver"] = Field(
        "sim",
        description="Master: where the operator's motion comes from: `sim` (the OCC paper's "
        "test motion), `igtl` (a TRANSFORM/POSITION stream), `driver` (a hand-moved device "
        "read by the master's drivers, e.g. CAN).",
    )
    amplitude_mm: Vec3 = Field(
        (50.0, 50.0, 0.0), description="Master `sim`: amplitudes of X = A sin, Y = A cos, Z (mm)."
    )
    offset_mm: Vec3 = Field(
        (0.0, 0.0, 20.0),
        description="Master `sim`: constant offset (mm) from the handle at zero joint values.",
    )
    frequency_hz: PosFloat = Field(0.1, description="Master `sim`: frequency of the motion (Hz).")
    clutch: Bool = Field(False, description="Master: clutch pressed at start.")
    fixture_radius_mm: PosFloat = Field(
        5.0,
        description="Master: radius of the forbidden sphere around each Markups point received "
        "as POINT (used when the point carries no radius, as 3D Slicer sends them).",
    )
    fixture_hardness: Annotated[Float, Field(ge=0)] = Field(
        1.0, description="Master: hardness (N/mm) of the spheres made from POINT messages."
    )
    first_seq: Annotated[Int, Field(ge=0, le=0xFFFFFFFF)] = Field(
        0, description="Master: sequence number before the first POSITION (the first is +1)."
    )
    # --- both
    input_interface: Name | None = Field(
        None,
        description="Master `igtl`: interface of the input stream. Slave: interface of the "
        "master's POSITION stream (null = any).",
    )
    input_device: DeviceName | None = Field(
        None, description="Only samples with this device name are used (null = any)."
    )
    # --- slave
    scale: Annotated[Float, Field(gt=0, le=10)] = Field(
        0.1, description="Slave: motion scaling, slave motion / master motion (0.1 = 10:1)."
    )
    rotation: tuple[Vec3, Vec3, Vec3] | None = Field(
        None, description="Slave: 3x3 rotation from master to slave axes (rows); null = identity."
    )
    base_mm: Vec3 | None = Field(
        None, description="Slave: base position in the world (mm), sent as TRANSFORM `Base`."
    )
    base_interface: Name | None = Field(
        None, description="Slave: interface on which a tracker sends the base TRANSFORM."
    )
    base_device: DeviceName = Field("Base", description="Slave: device name of that TRANSFORM.")
    phase_lock_us: Annotated[Float, Field(ge=0)] | None = Field(
        400.0,
        description="Slave: shift the loop's deadlines so the master samples this long before "
        "a tick (by its POSITION timestamps): a sample then waits about this long, not up to a "
        "whole period, for the tick that uses it. Must cover the transport time; null = off.",
    )


class DaemonConfig(_Model):
    """The whole configuration of one daemon."""

    robot: RobotConfig = Field(description="The robot.")
    interfaces: tuple[InterfaceConfig, ...] = Field(
        (), description="OpenIGTLink interfaces; names and binds unique."
    )
    safety: SafetyConfig = Field(SafetyConfig(), description="Safety monitors.")
    recording: RecordingConfig = Field(RecordingConfig(), description="Recorder.")
    stats: StatsConfig = Field(StatsConfig(), description="Timing statistics.")
    teleop: TeleopConfig | None = Field(
        None, description="Teleoperation (master or slave); null = no teleoperation."
    )

    def interface(self, name: str) -> InterfaceConfig:
        for itf in self.interfaces:
            if itf.name == name:
                return itf
        raise KeyError(name)

    @model_validator(mode="after")
    def _cross_sections(self) -> DaemonConfig:
        problems: list[tuple[Loc, str]] = []
        names: dict[str, int] = {}
        binds: list[tuple[int, InterfaceConfig]] = []
        loop_hz = self.robot.rate_hz
        switch_us = self.robot.realtime.switch_interval_us
        sup = self.safety.supervisor
        if sup.enabled and switch_us is not None and switch_us * 1e-3 >= sup.timeout_ms / 2:
            # a thread waits up to the switch interval for the interpreter lock: the supervisor
            # must get it well within its timeout, or a hung loop looks like a paused machine
            problems.append(
                (
                    ("robot", "realtime", "switch_interval_us"),
                    f"must be below half of safety.supervisor.timeout_ms "
                    f"({sup.timeout_ms * 500:g} us), got {switch_us:g}",
                )
            )
        for i, itf in enumerate(self.interfaces):
            if itf.name in names:
                problems.append(
                    (
                        ("interfaces", i, "name"),
                        f"duplicate interface name '{itf.name}' "
                        f"(first at interfaces[{names[itf.name]}])",
                    )
                )
            else:
                names[itf.name] = i
            if itf.transport not in ("tcp-client", "inproc") and itf.port != 0:
                for j, other in binds:
                    if (
                        other.transport == itf.transport
                        and other.port == itf.port
                        and (
                            other.host == itf.host
                            or other.host in _WILDCARD_HOSTS
                            or itf.host in _WILDCARD_HOSTS
                        )
                    ):
                        problems.append(
                            (
                                ("interfaces", i, "port"),
                                f"{itf.transport} bind {itf.host}:{itf.port} conflicts with "
                                f"{other.host}:{other.port} of interface '{other.name}' "
                                f"(interfaces[{j}])",
                            )
                        )
                        break
                binds.append((i, itf))
            for k, out in enumerate(itf.outputs):
                if out.rate_hz > loop_hz:
                    problems.append(
                        (
                            ("interfaces", i, "outputs", k, "rate_hz"),
                            f"{_num(out.rate_hz)} Hz exceeds the loop rate "
                            f"(robot.rate_hz = {loop_hz})",
                        )
                    )
        if self.recording.rate_hz > loop_hz:
            problems.append(
                (
                    ("recording", "rate_hz"),
                    f"{_num(self.recording.rate_hz)} Hz exceeds the loop rate "
                    f"(robot.rate_hz = {loop_hz})",
                )
            )
        if self.teleop is not None:
            for key in ("input_interface", "base_interface"):
                ref = getattr(self.teleop, key)
                if ref is not None and ref not in names:
                    problems.append(
                        (
                            ("teleop", key),
                            f"unknown interface '{ref}'" + _did_you_mean(ref, list(names)),
                        )
                    )
            if (
                self.teleop.input == "igtl"
                and self.teleop.role == "master"
                and (self.teleop.input_interface is None)
            ):
                problems.append((("teleop", "input_interface"), "required with input: igtl"))
        loss_input = self.safety.loss.input
        if loss_input is not None and loss_input not in names:
            problems.append(
                (
                    ("safety", "loss", "input"),
                    f"unknown interface '{loss_input}'" + _did_you_mean(loss_input, list(names)),
                )
            )
        _raise_problems(problems)
        return self


# --------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------


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
        if not problems:
            return config
    lines = format_errors(problems, source)
    raise ConfigError("\n".join(lines), lines)


def format_errors(problems: list[tuple[int, Loc, str]], source: str) -> list[str]:
    """Sort ``(line, loc, message)`` triples by line and render ``FILE:LINE path: message``."""
    ordered = sorted(problems, key=lambda p: p[0])
    return [f"{source}:{line} {_format_loc(loc)}: {msg}" for line, loc, msg in ordered]


def _compose(text: str, source: str) -> tuple[yaml.Node | None, Any, list[tuple[int, Loc, str]]]:
    """Compose and construct the YAML; syntax errors raise ConfigError with the line."""
    loader = yaml.SafeLoader(text)
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


def _located_errors(exc: ValidationError, root: yaml.Node | None) -> list[tuple[int, Loc, str]]:
    out: list[tuple[int, Loc, str]] = []
    errors = exc.errors(include_url=False)
    failed_items = {tuple(e["loc"][:-1]) for e in errors if e["loc"]}
    for err in errors:
        loc: Loc = tuple(err["loc"])
        if err["type"] == "too_short" and any(f[: len(loc)] == loc for f in failed_items):
            continue  # pydantic counts only the valid items of a tuple; the item errors suffice
        if err["type"] == _CROSS:
            for rel, msg in err["ctx"]["problems"]:
                full = (*loc, *rel)
                out.append((_line_of(root, full), full, msg))
        else:
            out.append((_line_of(root, loc), loc, _message(err, loc)))
    return out


def _format_loc(loc: Loc) -> str:
    text = ""
    for part in loc:
        if isinstance(part, int):
            text += f"[{part}]"
        else:
            text += f".{part}" if text else str(part)
    return text or "(top level)"


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


def _message(err: ErrorDetails, loc: Loc) -> str:
    kind = err["type"]
    ctx = err.get("ctx") or {}
    got = _describe(err.get("input"))
    if kind == "missing":
        return "missing required field"
    if kind == "extra_forbidden":
        model = _annotation_at(loc[:-1])
        fields = list(model.model_fields) if _is_model(model) else []
        return f"unknown field '{loc[-1]}'" + _did_you_mean(str(loc[-1]), fields)
    if kind in _TYPE_MESSAGES:
        return f"{_TYPE_MESSAGES[kind]}, got {got}"
    if kind == "literal_error":
        ann = _annotation_at(loc)
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


def _annotation_at(loc: Loc) -> Any:
    """The (stripped) type annotation at ``loc`` under :class:`DaemonConfig`, or None."""
    tp: Any = DaemonConfig
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
# Reference documentation, generated from the JSON schema of the models
# --------------------------------------------------------------------------------------------

DOC_BEGIN = "<!-- BEGIN config-reference: generated by occ.config, do not edit -->"
DOC_END = "<!-- END config-reference -->"


def config_reference_markdown() -> str:
    """A Markdown table of every field: path, type, default and meaning."""
    schema = DaemonConfig.model_json_schema()
    defs = schema.get("$defs", {})
    rows: list[tuple[str, str, str, str]] = []
    _reference_rows(schema, "", defs, rows)
    lines = ["| Field | Type | Default | Meaning |", "|---|---|---|---|"]
    for path, typ, default, meaning in rows:
        cells = (f"`{path}`", typ, default, meaning)
        lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    return "\n".join(lines) + "\n"


def _deref(prop: dict[str, Any], defs: dict[str, Any]) -> dict[str, Any]:
    if "$ref" in prop:
        return defs[prop["$ref"].rsplit("/", 1)[1]]
    if len(prop.get("allOf", ())) == 1:
        return _deref(prop["allOf"][0], defs)
    return prop


def _reference_rows(
    obj: dict[str, Any], prefix: str, defs: dict[str, Any], rows: list[tuple[str, str, str, str]]
) -> None:
    required = set(obj.get("required", ()))
    for name, prop in obj.get("properties", {}).items():
        path = prefix + name
        typ, child, suffix = _type_text(prop, defs)
        if name in required:
            default = "**required**"
        elif "default" in prop:
            default = _default_text(prop["default"], child is not None)
        else:
            default = ""
        meaning = prop.get("description") or _deref(prop, defs).get("description", "")
        rows.append((path, typ, default, meaning))
        if child is not None:
            _reference_rows(child, path + suffix + ".", defs, rows)


def _type_text(
    prop: dict[str, Any], defs: dict[str, Any]
) -> tuple[str, dict[str, Any] | None, str]:
    """(type description, nested model schema or None, path suffix for the nested fields)."""
    if "anyOf" in prop:
        options = [o for o in prop["anyOf"] if o.get("type") != "null"]
        nullable = len(options) < len(prop["anyOf"])
        if len(options) == 1:
            text, child, suffix = _type_text(options[0], defs)
            return (f"{text} or null" if nullable else text), child, suffix
        return " or ".join(_type_text(o, defs)[0] for o in prop["anyOf"]), None, ""
    target = _deref(prop, defs)
    if target is not prop:
        return "mapping", target, ""
    if "enum" in prop:
        return "one of " + ", ".join(f"`{v}`" for v in prop["enum"]), None, ""
    if "const" in prop:
        return f"`{prop['const']}`", None, ""
    kind = prop.get("type")
    if kind == "array":
        item_text, child, _ = _type_text(prop.get("items", {}), defs)
        text = "list of " + ("mappings" if child is not None else _PLURAL.get(item_text, item_text))
        if prop.get("minItems"):
            text += f" (at least {prop['minItems']})"
        return text, child, "[]"
    if kind in ("integer", "number"):
        text = kind
        bounds = []
        for key, op in (
            ("minimum", ">="),
            ("exclusiveMinimum", ">"),
            ("maximum", "<="),
            ("exclusiveMaximum", "<"),
        ):
            if key in prop:
                bounds.append(f"{op} {_num(prop[key])}")
        return (text + ", " + " and ".join(bounds) if bounds else text), None, ""
    if kind == "string":
        fmt = prop.get("format")
        if fmt == "file-path":
            return "path (existing file)", None, ""
        if fmt == "path":
            return "path", None, ""
        if fmt == "ipvanynetwork":
            return "IP address or CIDR network", None, ""
        if "pattern" in prop:
            return _PATTERN_DOC.get(prop["pattern"], f"string `{prop['pattern']}`"), None, ""
        if "maxLength" in prop:
            return f"string (at most {prop['maxLength']} chars)", None, ""
        return "string", None, ""
    if kind == "boolean":
        return "boolean", None, ""
    if kind == "object":
        return "mapping (free-form)", None, ""
    return str(kind or "any"), None, ""


_PATTERN_DOC = {
    NAME_PATTERN: "name",
    MESSAGE_TYPE_PATTERN: "IGTL type name",
    REMOTE_PATTERN: "`host:port`",
}
_PLURAL = {"name": "names", "IP address or CIDR network": "IP addresses or CIDR networks"}


def _default_text(value: Any, is_section: bool) -> str:
    if is_section and isinstance(value, dict):
        return "(defaults below)"
    if value is None:
        return "`null`"
    if isinstance(value, bool):
        return "`true`" if value else "`false`"
    if isinstance(value, list):
        return "`[" + ", ".join(str(v) for v in value) + "]`"
    if isinstance(value, dict):
        return "`{}`" if not value else f"`{value}`"
    if isinstance(value, float):
        return f"`{_num(value)}`"
    return f"`{value}`"


def update_reference_doc(path: str | os.PathLike[str]) -> bool:
    """Rewrite the generated block of ``path`` (e.g. docs/CONFIG.md); True if it changed."""
    doc = Path(path)
    text = doc.read_text(encoding="utf-8")
    pattern = re.compile(re.escape(DOC_BEGIN) + r".*?" + re.escape(DOC_END), re.DOTALL)
    if not pattern.search(text):
        raise ValueError(f"{path}: generated-block markers not found")
    block = f"{DOC_BEGIN}\n\n{config_reference_markdown()}\n{DOC_END}"
    new = pattern.sub(lambda _m: block, text, count=1)
    if new != text:
        doc.write_text(new, encoding="utf-8")
    return new != text


def _main(argv: list[str]) -> int:
    if argv[:1] == ["--markdown"]:
        sys.stdout.write(config_reference_markdown())
        return 0
    if argv[:1] == ["--update-docs"] and len(argv) == 2:
        changed = update_reference_doc(argv[1])
        print(f"{argv[1]}: {'updated' if changed else 'up to date'}")
        return 0
    if not argv or argv[0].startswith("-"):
        print(
            "usage: python -m occ.config FILE.yaml...\n"
            "       python -m occ.config --markdown\n"
            "       python -m occ.config --update-docs docs/CONFIG.md",
            file=sys.stderr,
        )
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
