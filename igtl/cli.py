"""The ``igtl`` command: listen, connect, send, dump and bench OpenIGTLink messages.

This module is an entry point: it alone (in ``igtl/``) prints, parses arguments and configures
logging. Everything it does goes through the public API (codec, messages, transports).
Run ``igtl --help`` or ``igtl COMMAND --help`` for the options; exit codes are listed in
:data:`EXIT_CODES_HELP`.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as _dt
import functools
import json
import logging
import math
import os
import queue
import sys
import textwrap
import threading
import time
import types
import typing
import xml.etree.ElementTree as ET
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NoReturn, TextIO

import numpy as np

from . import __version__, wire
from .codec import StreamDecoder
from .errors import DecodeError, IGTLError, TruncatedMessageError
from .messages import REGISTRY, Message, RawMessage

EXIT_OK = 0
EXIT_ERROR = 1  # runtime failure: connection refused or lost, cannot bind, unreadable file
EXIT_USAGE = 2  # bad command line (argparse's own convention)
EXIT_TIMEOUT = 3  # --timeout expired before --count messages arrived
EXIT_DECODE = 4  # dump: at least one decode error
EXIT_REFUSED = 5  # send: the peer answered a request FAIL (its error is printed on stderr)
EXIT_INTERRUPTED = 130  # Ctrl-C while a --count was still outstanding

EXIT_CODES_HELP = """\
exit codes:
  0    success (for listen/connect: --count messages received, or --timeout
       expired / Ctrl-C / peer closed when no --count was given)
  1    runtime error (connection refused or lost, cannot bind, unreadable file)
  2    usage error (bad or inconsistent options)
  3    timeout: --timeout expired with fewer than --count messages
  4    dump: at least one decode error (errors are reported with their offsets)
  5    send: the peer answered a request FAIL (RTS_COMMAND or ACK_ STRING with
       Status=FAIL, or an error STATUS); the reply's error is printed on stderr
  130  interrupted (Ctrl-C) before --count messages arrived
"""

DEFAULT_PORT = 18944
DEFAULT_CONNECT_TIMEOUT = 5.0
#: Human output shortens content to this many characters.
HUMAN_CONTENT_WIDTH = 160

log = logging.getLogger("igtl.cli")


class CLIError(Exception):
    """A runtime failure reported as one line on stderr and exit code 1."""


# ------------------------------------------------------------------------------------------
# Output
def _peer_text(peer: Any) -> str:
    """``host:port`` of a transport peer (a Peer object or an address tuple)."""
    peer = getattr(peer, "address", peer)
    if isinstance(peer, tuple) and len(peer) >= 2:
        host, port = peer[0], peer[1]
        return f"[{host}]:{port}" if ":" in str(host) else f"{host}:{port}"
    return "" if peer is None else str(peer)


def _finite(value: Any) -> Any:
    """Replace NaN/inf (not valid JSON) by None, recursively."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, list):
        return [_finite(v) for v in value]
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    return value


def _dumps(obj: Any) -> str:
    try:
        return json.dumps(obj, allow_nan=False, ensure_ascii=False, separators=(",", ":"))
    except ValueError:
        return json.dumps(_finite(obj), ensure_ascii=False, separators=(",", ":"))


def message_record(msg: Message, **extra: Any) -> dict[str, Any]:
    """The JSON object printed for one message (``--json``)."""
    record: dict[str, Any] = {
        "type": msg.message_type,
        "device": msg.device_name,
        "timestamp": msg.timestamp,
        "header_version": msg.header_version,
        "metadata": dict(msg.metadata),
        "message_id": msg.message_id,
        "content": msg.content_summary(),
    }
    if msg.message_type == "BIND":
        # the children decoded, each like a message of its own (an undecodable one says why)
        children = []
        for child in getattr(msg, "children", ()):
            try:
                children.append(message_record(child.decode()))
            except IGTLError as err:
                children.append(
                    {"type": child.type_name, "device": child.device_name, "error": str(err)}
                )
        record["children"] = children
    record.update({k: v for k, v in extra.items() if v is not None})
    return record


def _short(value: Any, budget: int = 16) -> str:
    """Compact human rendering: floats to 6 significant digits, long lists elided."""
    if isinstance(value, bool) or value is None:
        return json.dumps(value)
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, list):
        items = [_short(v, budget) for v in value[:budget]]
        if len(value) > budget:
            items.append(f"...(+{len(value) - budget})")
        return "[" + ",".join(items) + "]"
    if isinstance(value, dict):
        return "{" + ",".join(f"{k}={_short(v, budget)}" for k, v in value.items()) + "}"
    return str(value)


def _time_text(timestamp: float) -> str:
    if not timestamp:
        return "-"
    try:
        moment = _dt.datetime.fromtimestamp(timestamp, tz=_dt.UTC)
    except (OverflowError, OSError, ValueError):
        return f"{timestamp:.6f}"
    return moment.strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def message_line(msg: Message, peer: Any = None, offset: int | None = None) -> str:
    """The one-line human rendering of a message."""
    parts = []
    if offset is not None:
        parts.append(f"@{offset}")
    if peer is not None:
        parts.append(_peer_text(peer))
    parts += [
        f"{msg.message_type:<11}",
        f"{msg.device_name!r:<16}",
        _time_text(msg.timestamp),
        f"v{msg.header_version}",
    ]
    if msg.header_version == 2:
        parts.append(f"id={msg.message_id}")
        if msg.metadata:
            parts.append("meta=" + _short(dict(msg.metadata)))
    content = " ".join(f"{k}={_short(v)}" for k, v in msg.content_summary().items())
    if len(content) > HUMAN_CONTENT_WIDTH:
        content = content[: HUMAN_CONTENT_WIDTH - 3] + "..."
    parts.append(content)
    return " ".join(parts)


class Printer:
    """Serialises output lines from transport threads; flushes each line (pipes, tests)."""

    def __init__(self, json_mode: bool, out: TextIO | None = None, err: TextIO | None = None):
        self.json_mode = json_mode
        self.out = out if out is not None else sys.stdout
        self.err = err if err is not None else sys.stderr
        self._lock = threading.Lock()

    def message(
        self, msg: Message, *, peer: Any = None, offset: int | None = None, file: str | None = None
    ) -> None:
        if self.json_mode:
            extra: dict[str, Any] = {"offset": offset, "file": file}
            if peer is not None:
                extra["peer"] = _peer_text(peer)
            line = _dumps(message_record(msg, **extra))
        else:
            line = message_line(msg, peer, offset)
        with self._lock:
            self.out.write(line + "\n")
            self.out.flush()

    def note(self, text: str) -> None:
        """A diagnostic line on stderr (never mixed into the --json stream)."""
        with self._lock:
            self.err.write(f"igtl: {text}\n")
            self.err.flush()


# ------------------------------------------------------------------------------------------
# Argument types
def host_port(text: str) -> tuple[str, int]:
    """``HOST:PORT``, ``[V6ADDR]:PORT`` or ``:PORT`` (localhost)."""
    host, sep, port_text = text.rpartition(":")
    if not sep:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT, got {text!r}")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    try:
        port = int(port_text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"port must be a number, got {port_text!r}") from None
    if not 0 < port < 65536:
        raise argparse.ArgumentTypeError(f"port must be 1..65535, got {port}")
    return (host or "127.0.0.1", port)


def _port(text: str) -> int:
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"port must be a number, got {text!r}") from None
    if not 0 <= port < 65536:
        raise argparse.ArgumentTypeError(f"port must be 0..65535 (0 = any free port), got {port}")
    return port


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def _key_value(text: str) -> tuple[str, str]:
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    return key, value


def _usage(args: argparse.Namespace, text: str) -> NoReturn:
    parser: argparse.ArgumentParser = args.parser
    parser.error(text)  # prints usage + message on stderr, raises SystemExit(2)


# ------------------------------------------------------------------------------------------
# Receiving (listen / connect)
_CLOSED = object()  # queued by on_disconnect in connect mode


def _on_message_into(inbox: queue.SimpleQueue[Any]) -> Callable[[Any, Message], None]:
    """An ``on_message(peer, msg)`` for a transport's I/O thread: hand over and return."""

    def on_message(peer: Any, msg: Message) -> None:
        inbox.put((peer, msg))

    return on_message


def _drain(
    inbox: queue.SimpleQueue[Any],
    printer: Printer,
    count: int | None,
    timeout: float | None,
    show_peer: bool,
) -> tuple[int, str]:
    """Print queued messages until count/timeout/close; returns (messages, why it stopped)."""
    deadline = None if timeout is None else time.monotonic() + timeout
    received = 0
    while count is None or received < count:
        wait = None if deadline is None else deadline - time.monotonic()
        if wait is not None and wait <= 0:
            return received, "timeout"
        try:
            item = inbox.get(timeout=wait)
        except queue.Empty:
            return received, "timeout"
        if item is _CLOSED:
            return received, "closed"
        peer, msg = item
        printer.message(msg, peer=peer if show_peer else None)
        received += 1
    return received, "count"


def _receive_result(args: argparse.Namespace, printer: Printer, received: int, why: str) -> int:
    if args.count is not None and received < args.count:
        if why == "timeout":
            printer.note(
                f"timeout after {args.timeout:g} s: received {received} of {args.count} messages"
            )
            return EXIT_TIMEOUT
        if why == "closed":
            printer.note(f"connection closed by the peer after {received} of {args.count} messages")
            return EXIT_ERROR
    return EXIT_OK


def _transports() -> Any:
    try:
        from . import transport
    except ImportError as err:
        raise CLIError(f"the transports are not available in this build: {err}") from err
    return transport


def cmd_listen(args: argparse.Namespace) -> int:
    transport = _transports()
    printer = Printer(args.json)
    inbox: queue.SimpleQueue[Any] = queue.SimpleQueue()

    def on_error(peer: Any, exc: BaseException) -> None:
        printer.note(f"error from {_peer_text(peer)}: {type(exc).__name__}: {exc}")

    if args.udp:
        endpoint = transport.UDPEndpoint(
            host=args.host, port=args.port, on_message=_on_message_into(inbox), on_error=on_error
        )
        proto = "udp"
    else:
        endpoint = transport.TCPServer(
            args.host,
            args.port,
            on_message=_on_message_into(inbox),
            on_connect=lambda peer: printer.note(f"{_peer_text(peer)} connected"),
            on_disconnect=lambda peer, reason: printer.note(
                f"{_peer_text(peer)} disconnected ({reason})"
            ),
            on_error=on_error,
        )
        proto = "tcp"
    try:
        endpoint.start()
    except (OSError, IGTLError) as err:
        raise CLIError(f"cannot listen on {args.host}:{args.port} ({proto}): {err}") from err
    try:
        printer.note(f"listening on {proto} {_peer_text(endpoint.address)}")
        received, why = _drain(inbox, printer, args.count, args.timeout, show_peer=True)
        return _receive_result(args, printer, received, why)
    finally:
        endpoint.stop()


def cmd_connect(args: argparse.Namespace) -> int:
    transport = _transports()
    printer = Printer(args.json)
    inbox: queue.SimpleQueue[Any] = queue.SimpleQueue()
    host, port = args.address
    errors: list[BaseException] = []

    connected = threading.Event()

    def on_error(peer: Any, exc: BaseException) -> None:
        errors.append(exc)
        # A failed first connect is reported once, as the command's error, by _start_client.
        if connected.is_set() or args.reconnect:
            printer.note(f"error from {host}:{port}: {type(exc).__name__}: {exc}")

    def on_disconnect(peer: Any, reason: str) -> None:
        if not args.reconnect:
            inbox.put(_CLOSED)

    client = transport.TCPClient(
        host,
        port,
        on_message=_on_message_into(inbox),
        on_disconnect=on_disconnect,
        on_error=on_error,
        reconnect=args.reconnect,
        connect_timeout=args.connect_timeout,
    )
    try:
        _start_client(client, host, port, args.connect_timeout, errors)
        connected.set()
        printer.note(f"connected to {host}:{port}")
        received, why = _drain(inbox, printer, args.count, args.timeout, show_peer=False)
        return _receive_result(args, printer, received, why)
    finally:
        client.stop()


def _start_client(
    client: Any, host: str, port: int, timeout: float, errors: Sequence[BaseException]
) -> None:
    """Start a TCPClient and wait until it is connected; CLIError when it cannot connect.

    A client that does not reconnect gives up after its first failed attempt; that shows in its
    ``connect_failures`` counter, which we watch so that a refused connection fails at once
    instead of after the whole timeout.
    """
    try:
        client.start()
    except (OSError, IGTLError) as err:
        raise CLIError(f"cannot connect to {host}:{port}: {err}") from err
    deadline = time.monotonic() + timeout
    while not client.wait_connected(min(0.05, max(0.0, deadline - time.monotonic()))):
        if not client.reconnect and client.stats()["connect_failures"]:
            if errors:  # the transport's own words, e.g. "... [Errno 111] ECONNREFUSED"
                reason = str(errors[-1]).removeprefix(f"cannot connect to {host}:{port}: ")
                raise CLIError(f"cannot connect to {host}:{port}: {reason}")
            raise CLIError(f"cannot connect to {host}:{port} (-v shows why)")
        if time.monotonic() >= deadline:
            raise CLIError(f"cannot connect to {host}:{port} within {timeout:g} s")


# ------------------------------------------------------------------------------------------
# Building messages from the command line (send)
#: Content options and the types they apply to.
_CONTENT_OPTIONS: dict[str, tuple[str, ...]] = {
    "matrix": ("TRANSFORM",),
    "position": ("TRANSFORM", "POSITION"),
    "quaternion": ("TRANSFORM", "POSITION"),
    "string": ("STRING",),
    "encoding": ("STRING",),
    "status_code": ("STATUS",),
    "status_subcode": ("STATUS",),
    "status_error_name": ("STATUS",),
    "status_message": ("STATUS",),
    "command_name": ("COMMAND", "RTS_COMMAND"),
    "command_text": ("COMMAND", "RTS_COMMAND"),
    "command_id": ("COMMAND", "RTS_COMMAND"),
}


def _quat_to_rotation(q: Sequence[float]) -> list[list[float]]:
    x, y, z, w = q
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if norm == 0.0:
        raise ValueError("the quaternion must not be all zeros")
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    return [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]


def _status_code(text: str) -> int:
    from .messages import StatusCode

    try:
        return int(text)
    except ValueError:
        pass
    try:
        return int(StatusCode[text.upper()])
    except KeyError:
        names = ", ".join(c.name for c in StatusCode)
        raise ValueError(f"unknown status code {text!r}; use a number or one of {names}") from None


def _content_from_options(type_name: str, args: argparse.Namespace) -> dict[str, Any]:
    """Constructor keywords for the type from the content options given."""
    given = [name for name in _CONTENT_OPTIONS if getattr(args, name) is not None]
    for name in given:
        if type_name not in _CONTENT_OPTIONS[name]:
            flag = "--" + name.replace("_", "-")
            raise ValueError(
                f"{flag} applies to {' / '.join(_CONTENT_OPTIONS[name])} messages, not "
                f"{type_name} (use --json-body FILE for any field of any type)"
            )
    fields: dict[str, Any] = {}
    if type_name == "TRANSFORM":
        if args.matrix is not None and (args.position is not None or args.quaternion is not None):
            raise ValueError("give either --matrix or --position/--quaternion, not both")
        if args.matrix is not None:
            m = args.matrix
            # Row-major 4x4 on the command line; the wire order is column-major 3x4.
            fields["elements"] = tuple(m[r * 4 + c] for c in range(4) for r in range(3))
        elif args.position is not None or args.quaternion is not None:
            rot = _quat_to_rotation(args.quaternion or (0.0, 0.0, 0.0, 1.0))
            pos = args.position or (0.0, 0.0, 0.0)
            fields["elements"] = (*(rot[r][c] for c in range(3) for r in range(3)), *pos)
    elif type_name == "POSITION":
        if args.position is not None:
            fields["position"] = tuple(args.position)
        if args.quaternion is not None:
            fields["quaternion"] = tuple(args.quaternion)
    elif type_name == "STRING":
        if args.string is not None:
            fields["string"] = args.string
        if args.encoding is not None:
            fields["encoding"] = args.encoding
    elif type_name == "STATUS":
        if args.status_code is not None:
            fields["code"] = _status_code(args.status_code)
        if args.status_subcode is not None:
            fields["subcode"] = args.status_subcode
        if args.status_error_name is not None:
            fields["error_name"] = args.status_error_name
        if args.status_message is not None:
            fields["status_message"] = args.status_message
    elif type_name in ("COMMAND", "RTS_COMMAND"):
        for option, field_name in (
            ("command_name", "command_name"),
            ("command_text", "command"),
            ("command_id", "command_id"),
        ):
            if getattr(args, option) is not None:
                fields[field_name] = getattr(args, option)
    return fields


_COMMON_NAMES = frozenset(f.name for f in dataclasses.fields(Message))


def _content_fields(cls: type[Any]) -> dict[str, dataclasses.Field[Any]]:
    return {f.name: f for f in dataclasses.fields(cls) if f.init and f.name not in _COMMON_NAMES}


def _type_hints(cls: type[Any]) -> dict[str, Any]:
    try:
        return typing.get_type_hints(cls)
    except Exception:  # noqa: BLE001 - unresolvable annotations: coerce by value only
        return {}


def _coerce(hint: Any, value: Any) -> Any:
    """JSON value -> what a dataclass field of type ``hint`` expects (tuples, bytes, nested)."""
    if hint is None or value is None:
        return value
    origin = typing.get_origin(hint)
    targs = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        options = [a for a in targs if a is not type(None)]
        for option in options:
            if option is bytes or dataclasses.is_dataclass(option) or typing.get_origin(option):
                return _coerce(option, value)
        return value
    if hint is bytes:
        if isinstance(value, dict) and set(value) == {"hex"}:
            return bytes.fromhex(value["hex"])
        if isinstance(value, str):
            return value.encode("utf-8")
        if isinstance(value, list):
            return bytes(value)
        return value
    if hint is np.ndarray:
        if isinstance(value, dict) and set(value) <= {"data", "dtype"} and "data" in value:
            return np.asarray(value["data"], dtype=value.get("dtype"))
        if isinstance(value, list):
            array = np.asarray(value)
            # JSON integers become int64, which no OpenIGTLink array type holds: use int32.
            if array.dtype == np.int64 and array.size and np.abs(array).max() < 2**31:
                array = array.astype(np.int32)
            return array
        return value
    if dataclasses.is_dataclass(hint) and isinstance(value, dict):
        target = typing.cast(type[Any], hint)
        return target(**dataclass_kwargs(target, value, skip_common=False))
    if origin in (tuple, list) or (origin is not None and origin.__name__ == "Sequence"):
        if not isinstance(value, list):
            return value
        if origin is tuple and targs and targs[-1] is not Ellipsis:
            items = [_coerce(h, v) for h, v in zip(targs, value, strict=False)]
            items += value[len(targs) :]
        else:
            elem = targs[0] if targs else None
            items = [_coerce(elem, v) for v in value]
        return items if origin is list else tuple(items)
    return value


def dataclass_kwargs(
    cls: type[Any], data: Mapping[str, Any], *, skip_common: bool = True
) -> dict[str, Any]:
    """Constructor keywords for ``cls`` from a JSON object of its field names (values coerced to
    the field types; unknown keys are a ValueError naming the valid ones)."""
    if not isinstance(data, Mapping):
        raise ValueError(  # noqa: TRY004 - the user's JSON, reported as a usage error
            f"{cls.__name__} fields must be a JSON object, got {type(data).__name__}"
        )
    fields = (
        _content_fields(cls)
        if skip_common
        else {f.name: f for f in dataclasses.fields(cls) if f.init}
    )
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ValueError(
            f"unknown field(s) {', '.join(unknown)} for {cls.__name__}; "
            f"its fields are: {', '.join(fields) or '(none)'}"
        )
    hints = _type_hints(cls)
    return {k: _coerce(hints.get(k), v) for k, v in data.items()}


def _load_json_body(path: str) -> Any:
    try:
        if path == "-":
            return json.load(sys.stdin)
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    except OSError as err:
        raise CLIError(f"cannot read --json-body {path}: {err.strerror or err}") from err
    except json.JSONDecodeError as err:
        raise ValueError(f"--json-body {path} is not valid JSON: {err}") from err


def build_message(args: argparse.Namespace) -> Message:
    """The message described by the ``send`` options (timestamp and id are set per send)."""
    type_name = args.type
    if type_name not in REGISTRY and type_name.upper() in REGISTRY:
        type_name = type_name.upper()
    if not 0 < len(type_name.encode("latin-1", "replace")) <= wire.TYPE_SIZE:
        raise ValueError(f"--type must be 1..{wire.TYPE_SIZE} characters, got {type_name!r}")
    cls = REGISTRY.get(type_name)

    common: dict[str, Any] = {"device_name": args.device, "header_version": args.header_version}
    if args.meta:
        common["metadata"] = dict(args.meta)
    if args.header_version == 2:
        common["message_id"] = args.message_id

    if args.json_body is not None:
        given = [n for n in _CONTENT_OPTIONS if getattr(args, n) is not None]
        if given:
            flag = "--" + given[0].replace("_", "-")
            raise ValueError(f"give the content either with --json-body or with {flag}, not both")
        body = _load_json_body(args.json_body)
        if cls is None:
            fields = dataclass_kwargs(RawMessage, body)
            fields.pop("type_name", None)
            return RawMessage(type_name=type_name, **fields, **common)
        return typing.cast(Message, cls(**dataclass_kwargs(cls, body), **common))
    if cls is None:
        known = ", ".join(sorted(REGISTRY))
        raise ValueError(
            f"unknown message type {type_name!r}: give its content with --json-body FILE "
            f'({{"content": "text"}} or {{"content": {{"hex": "0a0b"}}}}), or use one of: {known}'
        )
    fields = _content_from_options(type_name, args)
    if getattr(cls, "NEEDS_TYPE_NAME", False):
        # one class for several types (GET_TRANS, GET_STATUS, RTS_TDATA ...): without its
        # name it would be its default type, and `--type GET_TRANS` would send a GET_STATUS
        fields["type_name"] = type_name
    return typing.cast(Message, cls(**fields, **common))


def cmd_send(args: argparse.Namespace) -> int:
    if args.meta and args.header_version == 1:
        _usage(args, "--meta needs --header-version 2 (metadata does not exist in version 1)")
    if args.message_id is not None and args.header_version == 1:
        _usage(args, "--message-id needs --header-version 2")
    if args.header_version is None:
        args.header_version = 2 if (args.meta or args.message_id is not None) else 1
    if args.message_id is None:
        args.message_id = 0
    if args.count > 1 and args.rate is None and args.udp:
        log.info("sending %d UDP datagrams without --rate: the receiver may drop some", args.count)
    try:
        template = build_message(args)
        template.pack()  # validate everything (sizes, encodings) before touching the network
    except ValueError as err:
        _usage(args, str(err))

    transport = _transports()
    host, port = args.address
    printer = Printer(False)
    errors: list[BaseException] = []
    sender: Any
    if args.udp:
        # Bind where the datagrams can leave from: loopback for a local peer, else anywhere.
        if host in ("127.0.0.1", "localhost", "::1"):
            local = host if host != "localhost" else "127.0.0.1"
        else:
            local = "::" if ":" in host else "0.0.0.0"
        sender = transport.UDPEndpoint(host=local, port=0, remote=(host, port))
        try:
            sender.start()
        except (OSError, IGTLError) as err:
            raise CLIError(f"cannot open a UDP socket: {err}") from err
    else:
        sender = transport.TCPClient(
            host,
            port,
            reconnect=False,
            connect_timeout=args.connect_timeout,
            on_error=lambda *a: errors.append(a[-1]),
            on_message=lambda peer, msg: replies.put(msg),
        )
    replies: queue.Queue[Message] = queue.Queue()
    wants_reply = not args.udp and args.wait > 0 and _is_request(template)
    answered = 0
    refusals: list[str] = []
    try:
        if not args.udp:
            _start_client(sender, host, port, args.connect_timeout, errors)
        sent = _send_loop(sender, template, args)
        if wants_reply and sent:
            # a request's answer (RTS_, ACK_ or the queried type, STATUS for a refusal) comes
            # back on this connection: print it, so `igtl send ... GetState` shows the state
            answered = _print_replies(
                replies, template, sent, args.wait, Printer(args.json), refusals
            )
    finally:
        sender.stop()
    if wants_reply and sent and answered < sent:
        printer.note(f"{sent - answered} of {sent} request(s) not answered within {args.wait:g} s")
    if sent < args.count:
        reason = f": {errors[-1]}" if errors else ""
        printer.note(f"sent {sent} of {args.count} messages to {host}:{port}{reason}")
        return EXIT_ERROR
    if args.verbose:
        printer.note(f"sent {sent} message(s) to {host}:{port}")
    for refusal in refusals:
        printer.note(refusal)
    return EXIT_REFUSED if refusals else EXIT_OK


def _reply_attributes(text: str) -> dict[str, str]:
    """The attributes of an XML reply (``<CommandReply Status="FAIL" Error="..."/>``, as
    PlusServer and the OCC daemons answer), or none when the text is not one."""
    text = text.strip()
    if not text.startswith("<"):
        return {}
    try:
        return dict(ET.fromstring(text).attrib)
    except ET.ParseError:
        return {}


def refusal(reply: Message, request: Message) -> str | None:
    """What a reply to ``request`` says went wrong, or None when it is not a refusal: an
    RTS_COMMAND or an ACK_ STRING whose Status is FAIL (metadata, else its XML content), or a
    STATUS with an error code refusing a command or a query (a GET_STATUS is answered with a
    STATUS: that one is the answer, whatever its code)."""
    rtype = reply.message_type
    if rtype == "STATUS":
        code = int(getattr(reply, "code", 1))
        if code == 1 or request.message_type == "GET_STATUS":
            return None
        name = getattr(reply, "error_name", "") or f"code {code}"
        return f"refused ({name}): {getattr(reply, 'status_message', '')}"
    if rtype == "RTS_COMMAND":
        attrs = _reply_attributes(str(getattr(reply, "command", "")))
        meta = reply.metadata
        status = meta.get("Status") or attrs.get("Status", "")
        error = meta.get("Error") or meta.get("Message") or attrs.get("Error")
        error = error or attrs.get("Message", "")
        what = str(getattr(reply, "command_name", "")) or "command"
    elif rtype == "STRING":
        attrs = _reply_attributes(str(getattr(reply, "string", "")))
        status = attrs.get("Status", "")
        error = attrs.get("Error") or attrs.get("Message", "")
        what = attrs.get("Name") or reply.device_name
    else:
        return None
    if status.upper() != "FAIL":
        return None
    return f"{what}: FAIL: {error or '(no reason given)'}"


def _is_request(msg: Message) -> bool:
    """COMMAND, a PLUS-style ``CMD_<id>`` STRING or a GET_/STT_/STP_ query: a peer answers."""
    mtype = msg.message_type
    if mtype == "COMMAND" or mtype.startswith(("GET_", "STT_", "STP_")):
        return True
    return mtype == "STRING" and msg.device_name.startswith("CMD_")


def _is_reply_to(reply: Message, request: Message) -> bool:
    rtype, qtype = reply.message_type, request.message_type
    if qtype == "COMMAND":
        # an RTS_COMMAND, or a STATUS refusing the connection (ACCESS_DENIED)
        return rtype == "RTS_COMMAND" or (rtype == "STATUS" and getattr(reply, "code", 1) != 1)
    if qtype == "STRING":
        return rtype == "STRING" and reply.device_name == "ACK_" + request.device_name[4:]
    if rtype == "STATUS":  # a query's answer, or the refusal of one
        return qtype == "GET_STATUS" or getattr(reply, "code", 1) != 1
    return rtype == qtype.split("_", 1)[1] or rtype.startswith(qtype.split("_", 1)[1][:4])


def _print_replies(
    replies: queue.Queue[Message],
    request: Message,
    expected: int,
    wait: float,
    out: Printer,
    refusals: list[str],
) -> int:
    """Print the replies to ``expected`` requests like ``request`` arriving within ``wait``
    seconds of the last send (other messages, e.g. a connect greeting or a pose stream, are
    skipped); returns how many came. What each refusal says (:func:`refusal`) is appended to
    ``refusals``."""
    got = 0
    deadline = time.monotonic() + wait
    while got < expected:
        left = deadline - time.monotonic()
        if left <= 0:
            break
        try:
            msg = replies.get(timeout=left)
        except queue.Empty:
            break
        if _is_reply_to(msg, request):
            out.message(msg)
            got += 1
            why = refusal(msg, request)
            if why is not None:
                refusals.append(why)
    return got


#: TCP: most messages handed to the client and not yet written to its socket. The client's send
#: queue (256) drops its oldest message when full, which is right for a control loop and wrong
#: for a command-line sender, so we stay well below it.
TCP_WINDOW = 128
#: UDP: how long to retry a datagram the (full) socket buffer refused before giving up.
UDP_RETRY_SECONDS = 1.0
#: TCP: bound on waiting for queued messages to reach the socket before closing.
DRAIN_SECONDS = 10.0


def _wait(cond: Callable[[], bool], seconds: float) -> bool:
    """Poll ``cond`` (transport counters have no wake-up of their own) for up to ``seconds``."""
    deadline = time.monotonic() + seconds
    pause = 0.0001
    while not cond():
        if time.monotonic() >= deadline:
            return False
        time.sleep(pause)
        pause = min(pause * 2, 0.01)
    return True


def _send_one(sender: Any, msg: Message, udp: bool, handed: int) -> bool:
    if udp:
        deadline = time.monotonic() + UDP_RETRY_SECONDS
        while not sender.send(msg):
            stats = sender.stats()
            if stats["send_errors"] or time.monotonic() >= deadline:
                return False  # a real socket error, or the buffer never drained
            time.sleep(0.0005)
        return True
    # TCP: keep the client's queue from overflowing (it would drop silently).
    if handed - sender.stats()["sent"] >= TCP_WINDOW and not _wait(
        lambda: not sender.connected or handed - sender.stats()["sent"] < TCP_WINDOW,
        DRAIN_SECONDS,
    ):
        return False
    return bool(sender.send(msg))


def _send_loop(sender: Any, template: Message, args: argparse.Namespace) -> int:
    """Send ``args.count`` stamped copies, paced on absolute deadlines when --rate is given.
    Returns how many were handed over (TCP: and written to the socket)."""
    period = 1.0 / args.rate if args.rate else 0.0
    fixed_time = args.timestamp
    start = time.monotonic()
    sent = 0
    for i in range(args.count):
        if period:
            delay = start + i * period - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        changes: dict[str, Any] = {"timestamp": time.time() if fixed_time is None else fixed_time}
        if template.header_version == 2:
            changes["message_id"] = (args.message_id + i) & 0xFFFFFFFF
        if not _send_one(sender, template.replace(**changes), args.udp, sent):
            break
        sent += 1
    if not args.udp:
        # stop() discards whatever is still queued: wait until it has reached the socket.
        _wait(lambda: not sender.connected or sender.stats()["sent"] >= sent, DRAIN_SECONDS)
        written = sender.stats()["sent"]
        if written < sent:
            return int(written)
    return sent


# ------------------------------------------------------------------------------------------
# dump
def _read_input(path: str) -> bytes:
    try:
        if path == "-":
            return sys.stdin.buffer.read()
        with open(path, "rb") as fh:
            return fh.read()
    except OSError as err:
        raise CLIError(f"cannot read {path}: {err.strerror or err}") from err


def cmd_dump(args: argparse.Namespace) -> int:
    printer = Printer(args.json)
    total_errors = 0
    for path in args.files:
        data = _read_input(path)
        decoder = StreamDecoder(crc_check=not args.no_crc, max_body_size=args.max_body_size)
        decoder.feed(data)
        messages = errors = 0
        label = path if len(args.files) > 1 or args.json else None
        while True:
            start = decoder.offset
            try:
                msg = decoder.next_message()
            except DecodeError as err:
                errors += 1
                printer.note(f"{path}: {type(err).__name__} at offset {err.offset}: {err}")
                if decoder.failed:
                    printer.note(
                        f"{path}: cannot find the next message after offset "
                        f"{start}; {decoder.buffered} bytes not decoded"
                    )
                    break
                continue
            if msg is None:
                break
            messages += 1
            printer.message(msg, offset=start, file=label)
        if not decoder.failed:
            try:
                decoder.close()
            except TruncatedMessageError as err:
                errors += 1
                printer.note(f"{path}: {type(err).__name__} at offset {err.offset}: {err}")
        if errors or args.verbose or len(args.files) > 1:
            printer.note(f"{path}: {messages} message(s), {errors} decode error(s)")
        total_errors += errors
    return EXIT_DECODE if total_errors else EXIT_OK


# ------------------------------------------------------------------------------------------
# bench
def cmd_bench(args: argparse.Namespace) -> int:
    from . import bench

    printer = Printer(False)
    types = [t.upper() for t in args.type] if args.type else list(bench.BENCH_TYPES)
    for t in types:
        if t not in bench.BENCH_TYPES:
            _usage(args, f"no benchmark for type {t!r}; choose from {', '.join(bench.BENCH_TYPES)}")
    results = bench.run_codec_bench(
        types, n=args.n, repeat=args.repeat, with_pyigtl=not args.no_pyigtl, warn=printer.note
    )
    if args.json:
        for r in results:
            row = dataclasses.asdict(r)
            row["roundtrip_us"] = r.roundtrip_us
            sys.stdout.write(_dumps(row) + "\n")
    else:
        sys.stdout.write(bench.format_table(results) + "\n")
    sys.stdout.flush()
    return EXIT_OK


# ------------------------------------------------------------------------------------------
# Parser
class _Formatter(argparse.RawDescriptionHelpFormatter):
    """Keeps the exit-code table as written; shows only defaults that say something."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        default = action.default
        if (
            "%(default)" not in text
            and action.option_strings
            and default not in (None, False, "", argparse.SUPPRESS)
            and not isinstance(default, bool)
        ):
            text += " (default: %(default)s)"
        return text


def _add_receive_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--json",
        action="store_true",
        help="one JSON object per message: type, device, timestamp, header_version, "
        "metadata, message_id, content (+ peer)",
    )
    p.add_argument(
        "--count",
        type=_positive_int,
        metavar="N",
        help="stop after N messages (exit 3 if --timeout expires first)",
    )
    p.add_argument("--timeout", type=_positive_float, metavar="S", help="stop after S seconds")


def build_parser() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "-v",
        "--verbose",
        action="count",
        default=argparse.SUPPRESS,
        help="log more (-v: info, -vv: debug) on stderr",
    )

    parser = argparse.ArgumentParser(
        prog="igtl",
        description="Send, receive, decode and benchmark OpenIGTLink messages.",
        epilog=EXIT_CODES_HELP + "\nrun 'igtl COMMAND --help' for the options of a command.",
        formatter_class=_Formatter,
        parents=[common],
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.set_defaults(verbose=0)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    add = functools.partial(_add_command, sub, common)
    _add_listen(add)
    _add_connect(add)
    _add_send(add)
    _add_dump(add)
    _add_bench(add)
    return parser


#: adds one sub-command: (name, help, description) -> its parser
_Add = Callable[[str, str, str], argparse.ArgumentParser]


def _add_command(
    sub: Any, common: argparse.ArgumentParser, name: str, help_text: str, description: str
) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser(
        name,
        help=help_text,
        description=textwrap.fill(description, 79),
        epilog=EXIT_CODES_HELP,
        formatter_class=_Formatter,
        parents=[common],
    )
    p.set_defaults(parser=p)
    return p


def _add_listen(add: _Add) -> None:
    p = add(
        "listen",
        "run a server and print every message received",
        "Listen for OpenIGTLink peers (TCP server, or a UDP socket with --udp) and print one "
        "line per message. Peer errors go to stderr with the peer's address.",
    )
    p.add_argument(
        "--host", default="127.0.0.1", help="address to bind (0.0.0.0 for every interface)"
    )
    p.add_argument("--port", type=_port, default=DEFAULT_PORT, help="port (0 = any free port)")
    p.add_argument("--udp", action="store_true", help="receive UDP datagrams instead of TCP")
    _add_receive_options(p)
    p.set_defaults(func=cmd_listen)


def _add_connect(add: _Add) -> None:
    p = add(
        "connect",
        "connect to a server and print every message received",
        "Connect to an OpenIGTLink server (e.g. 3D Slicer, PlusServer) and print one line per "
        "message received.",
    )
    p.add_argument("address", type=host_port, metavar="HOST:PORT")
    _add_receive_options(p)
    p.add_argument(
        "--connect-timeout",
        type=_positive_float,
        default=DEFAULT_CONNECT_TIMEOUT,
        metavar="S",
        help="give up (exit 1) if not connected within S seconds",
    )
    p.add_argument(
        "--reconnect",
        action="store_true",
        help="reconnect when the server goes away instead of exiting",
    )
    p.set_defaults(func=cmd_connect)


def _add_send(add: _Add) -> None:
    p = add(
        "send",
        "send messages to a server (TCP) or a UDP endpoint",
        "Send one message (or --count N, paced by --rate) of --type T. Content comes from "
        "the options of that type or, for any type, from --json-body FILE: a JSON object "
        "whose keys are the content field names (bytes fields: a UTF-8 string or "
        '{"hex": "..."}). A type the library does not know is sent raw: '
        '--json-body with {"content": ...}.',
    )
    p.add_argument("address", type=host_port, metavar="HOST:PORT")
    p.add_argument("--udp", action="store_true", help="send UDP datagrams instead of TCP")
    p.add_argument(
        "--type",
        required=True,
        metavar="T",
        help=f"message type ({', '.join(sorted(REGISTRY))}, or any other name)",
    )
    p.add_argument("--device", default="", metavar="D", help="device name (<= 20 bytes)")
    _add_send_header(p.add_argument_group("header"))
    _add_send_content(p.add_argument_group("content"))
    _add_send_repetition(p.add_argument_group("repetition"))
    p.add_argument(
        "--connect-timeout",
        type=_positive_float,
        default=DEFAULT_CONNECT_TIMEOUT,
        metavar="S",
        help="TCP: give up (exit 1) if not connected within S seconds",
    )
    p.add_argument(
        "--wait",
        type=float,
        default=2.0,
        metavar="S",
        help="TCP requests (COMMAND, STRING CMD_*, GET_*): print the answers arriving within S "
        "seconds (default 2; 0 = do not wait)",
    )
    p.add_argument("--no-wait", dest="wait", action="store_const", const=0.0, help="--wait 0")
    p.add_argument("--json", action="store_true", help="print the answers as JSON")
    p.set_defaults(func=cmd_send)


def _add_send_header(g: argparse._ArgumentGroup) -> None:
    """send: the header options."""
    g.add_argument(
        "--header-version",
        type=int,
        choices=(1, 2),
        default=None,
        help="1 or 2; default 1, or 2 when --meta/--message-id is given",
    )
    g.add_argument(
        "--meta",
        type=_key_value,
        action="append",
        metavar="K=V",
        help="metadata entry (header version 2), repeatable",
    )
    g.add_argument(
        "--message-id",
        type=int,
        metavar="N",
        help="message ID of the first message (header version 2; +1 per message)",
    )
    g.add_argument(
        "--timestamp",
        type=float,
        metavar="SECONDS",
        help="fixed header timestamp in Unix seconds (0 = unused; default: now)",
    )


def _add_send_content(g: argparse._ArgumentGroup) -> None:
    """send: the content options, by message type."""
    g.add_argument("--json-body", metavar="FILE", help="content fields as JSON ('-' = stdin)")
    g.add_argument(
        "--matrix",
        type=float,
        nargs=16,
        metavar="M",
        help="TRANSFORM: 4x4 matrix, 16 numbers row by row (translation in mm)",
    )
    g.add_argument(
        "--position",
        type=float,
        nargs=3,
        metavar=("X", "Y", "Z"),
        help="POSITION / TRANSFORM: position in mm",
    )
    g.add_argument(
        "--quaternion",
        type=float,
        nargs=4,
        metavar=("OX", "OY", "OZ", "W"),
        help="POSITION / TRANSFORM: orientation",
    )
    g.add_argument("--string", metavar="TEXT", help="STRING: the text")
    g.add_argument(
        "--encoding",
        type=int,
        metavar="MIBENUM",
        help="STRING: IANA encoding (3 = US-ASCII, 106 = UTF-8; default: the smallest)",
    )
    g.add_argument(
        "--status-code", metavar="CODE", help="STATUS: number or name (OK, NOT_READY, ...)"
    )
    g.add_argument("--status-subcode", type=int, metavar="N", help="STATUS: sub-code")
    g.add_argument("--status-error-name", metavar="NAME", help="STATUS: error name (<= 20 bytes)")
    g.add_argument("--status-message", metavar="TEXT", help="STATUS: message text")
    g.add_argument("--command-name", metavar="NAME", help="COMMAND: command name")
    g.add_argument("--command-text", metavar="TEXT", help="COMMAND: command body (usually XML)")
    g.add_argument("--command-id", type=int, metavar="N", help="COMMAND: command ID")


def _add_send_repetition(g: argparse._ArgumentGroup) -> None:
    """send: how many messages, how fast."""
    g.add_argument(
        "--count",
        type=_positive_int,
        default=1,
        metavar="N",
        help="number of messages (each re-stamped)",
    )
    g.add_argument(
        "--rate",
        type=_positive_float,
        metavar="HZ",
        help="messages per second (default: as fast as possible)",
    )


def _add_dump(add: _Add) -> None:
    p = add(
        "dump",
        "decode files of concatenated messages",
        "Decode recordings (concatenated messages, e.g. shared/igtl-vectors/*.bin) and print "
        "one line per message, prefixed by its byte offset. Decode errors are reported with "
        "their offsets; decoding continues after a bad message when the stream is still in "
        "sync. Exit 4 if there was any error.",
    )
    p.add_argument("files", nargs="+", metavar="FILE", help="file to decode ('-' = stdin)")
    p.add_argument(
        "--json", action="store_true", help="one JSON object per message (with offset and file)"
    )
    p.add_argument("--no-crc", action="store_true", help="do not verify CRC-64")
    p.add_argument(
        "--max-body-size",
        type=_positive_int,
        default=wire.DEFAULT_MAX_BODY_SIZE,
        metavar="BYTES",
        help="reject messages announcing a larger body",
    )
    p.set_defaults(func=cmd_dump)


def _add_bench(add: _Add) -> None:
    p = add(
        "bench",
        "codec throughput per message type, against pyigtl if installed",
        "Time pack and unpack (CRC verified) per message type, best of --repeat rounds of "
        "--n calls, next to pyigtl (whose unpack never checks the CRC) when it is importable.",
    )
    p.add_argument(
        "--type",
        action="append",
        metavar="T",
        help="TRANSFORM, POSITION, STRING or IMAGE (repeatable; default: all)",
    )
    p.add_argument(
        "--n", type=_positive_int, default=20_000, help="calls per round (IMAGE uses n/200)"
    )
    p.add_argument("--repeat", type=_positive_int, default=5, help="rounds; the best is kept")
    p.add_argument("--no-pyigtl", action="store_true", help="time igtl only")
    p.add_argument("--json", action="store_true", help="one JSON object per result row")
    p.set_defaults(func=cmd_bench)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``igtl`` command; returns the exit code (also when called in-process)."""
    parser = build_parser()
    args: argparse.Namespace | None = None
    try:
        args = parser.parse_args(argv)
        if args.command is None:
            parser.print_help(sys.stderr)
            return EXIT_USAGE
        if args.verbose:
            logging.basicConfig(
                level=logging.DEBUG if args.verbose > 1 else logging.INFO,
                format="%(asctime)s %(name)s %(levelname)s: %(message)s",
            )
        return int(args.func(args))
    except SystemExit as exc:  # argparse: --help (0), usage errors (2)
        return exc.code if isinstance(exc.code, int) else EXIT_USAGE
    except CLIError as err:
        sys.stderr.write(f"igtl: error: {err}\n")
        return EXIT_ERROR
    except KeyboardInterrupt:
        # Ctrl-C is the normal way to end an open-ended listen/connect.
        return EXIT_INTERRUPTED if getattr(args, "count", None) is not None else EXIT_OK
    except BrokenPipeError:
        # The reader of our stdout went away (igtl listen | head): not an error of ours.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_OK


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
