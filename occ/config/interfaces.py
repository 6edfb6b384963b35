"""The ``interfaces`` section: OpenIGTLink endpoints, their inputs and outputs."""

from __future__ import annotations

import ipaddress
from typing import Annotated, Any, Literal

from pydantic import Field, IPvAnyNetwork, model_validator
from pydantic_core import PydanticCustomError

from igtl.auth import load_key
from occ.config.base import (
    Bool,
    DeviceName,
    ExistingFile,
    Float,
    Int,
    Loc,
    MessageType,
    Name,
    PosFloat,
    Remote,
    Str,
    _Model,
    _raise_problems,
)


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
        description="Named robot signal to send (`tip`, `base`, `joints`, `status`, `setpoint`, "
        "`setpoint_tip`, ...)."
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
        "the send target; a udp interface without one sends its outputs to its stream's "
        "owner (a slave's return channel to its master).",
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
    max_buffered_kib: Annotated[Int, Field(ge=1)] | None = Field(
        None,
        description="tcp-server: bytes of incomplete messages over all its clients together "
        "(KiB), at least `max_body_kib`; the client whose data goes over it is closed and "
        "counted (`over_budget`). null = twice `max_body_kib`, at least 8 MiB.",
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
    auth_max_age_s: Annotated[Float, Field(gt=0, le=3600)] = Field(
        30.0,
        description="With `auth_key_file`: a signed request (a command, a query, a command "
        "input) is taken once, and only when its header timestamp is within this many seconds "
        "of the daemon's clock; a repeat or an older one is refused as a replay, answered and "
        "counted (`replayed`). Both ends' clocks must agree within it.",
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
        if self.max_buffered_kib is not None and self.max_buffered_kib < self.max_body_kib:
            problems.append(
                (
                    ("max_buffered_kib",),
                    f"must be at least max_body_kib ({self.max_body_kib}), "
                    f"got {self.max_buffered_kib}",
                )
            )
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
