"""Operator requests over OpenIGTLink: parsing and replies.

Three forms are accepted (shared/IGTL-PROTOCOL.md §3.18, §6.1, §6.2):

- ``COMMAND`` (protocol 3, what 3D Slicer and PLUS clients send): the command name is the
  COMMAND_NAME field, or the ``Name`` attribute of an XML ``<Command Name="..." .../>`` content;
  other XML attributes become arguments. Answered by ``RTS_COMMAND`` with the same COMMAND_ID,
  metadata ``Status`` = ``SUCCESS``/``FAIL`` (plus ``Message``/``Error``) and an XML
  ``<CommandReply .../>`` content, as PlusServer does.
- PLUS-style ``STRING`` with device name ``CMD_<uid>``: content ``<Command Name="..."/>`` or a bare
  word (``Enable``). Answered by ``STRING`` ``ACK_<uid>`` holding ``<CommandReply .../>``.
- Queries ``GET_STATUS``, ``GET_CAPABIL``, ``GET_TRANS`` ... (and STT_/STP_). Answered with the
  requested type; refused ones with a ``STATUS`` carrying the error code.

An unknown or refused request always gets an error reply and changes nothing. A command whose
work must not run on the loop thread (planning a trajectory, an Enable whose drives power up
off the loop thread) may be answered later: its handler returns a :class:`Deferred` and completes
it from any thread; the reply then goes out at once.
"""

from __future__ import annotations

import threading
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol, cast
from xml.sax.saxutils import quoteattr

import igtl
from igtl.messages.base import REGISTRY, Message
from occ.errors import CommandError


@dataclass
class Request:
    """A parsed operator request."""

    kind: str  # "command" | "string" | "query"
    name: str  # command name, or the query type (e.g. "GET_STATUS")
    args: dict[str, str] = field(default_factory=dict)
    msg: Message | None = None


class Deferred:
    """The answer to a command that comes later, from any thread (the loop only hands the work
    over). The handler returns it; the operator desk binds the reply to it; whoever finishes
    the work calls :meth:`resolve` (success) or :meth:`fail` (refusal) exactly once, and the
    reply is sent then. Later calls are ignored (the first answer stands)."""

    __slots__ = ("_lock", "_result", "_callback")

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._result: tuple[bool, str] | None = None
        self._callback: Callable[[bool, str], None] | None = None

    def bind(self, callback: Callable[[bool, str], None]) -> None:
        """``callback(ok, text)`` is called once with the answer (now, if it is already in)."""
        with self._lock:
            self._callback = callback
            result = self._result
        if result is not None:
            callback(*result)

    def resolve(self, text: str) -> None:
        self._finish(True, text)

    def fail(self, text: str) -> None:
        self._finish(False, text)

    @property
    def done(self) -> bool:
        return self._result is not None

    @property
    def result(self) -> tuple[bool, str] | None:
        """``(ok, text)`` once answered, else None."""
        return self._result

    def _finish(self, ok: bool, text: str) -> None:
        with self._lock:
            if self._result is not None:
                return
            self._result = (ok, text)
            callback = self._callback
        if callback is not None:
            callback(ok, text)


@dataclass(frozen=True, eq=False)
class ArrayReply:
    """A controller command's answer that carries an array (a cell plan's joint path): the
    operator desk's worker sends ``array`` as an ``NDARRAY`` named ``device`` with ``meta``
    (header version 2), then the reply ``text``, both to the sender alone."""

    text: str
    array: Any  # np.ndarray; read, never written, by the worker
    device: str
    meta: dict[str, str] = field(default_factory=dict)


#: the thread column: answered in the tick that takes it
LOOP = "loop"
#: built and sent by the worker thread (the loop only checks the request and hands it over)
WORKER = "worker"
#: answered when its work is done, from whichever thread did it (a :class:`Deferred`)
DEFERRED = "deferred"

#: what a worker row's handler returns: the job the worker runs (it sends the reply itself)
Job = Callable[[], None]


class Asked(Protocol):
    """A request's arrival as a handler sees it (occ/net/interfaces.py ``Inbound``)."""

    @property
    def interface(self) -> str: ...

    @property
    def role(self) -> str: ...


class RecordingCommands(Protocol):
    """StartRecording, StopRecording, GetRecordingStatus (occ/recording/control.py)."""

    def start(self, req: Request) -> Deferred: ...

    def stop(self, req: Request) -> Deferred: ...

    def describe(self) -> str: ...


class BlackBoxCommands(Protocol):
    """``DumpBlackBox`` (occ/recording/blackbox.py)."""

    @property
    def enabled(self) -> bool: ...

    def request(self, cause: str, why: str) -> str: ...


class CommandDesk(Protocol):
    """What the rows' handlers use of the operator desk (occ/net/operators.py)."""

    @property
    def recording(self) -> RecordingCommands: ...

    @property
    def black_box(self) -> BlackBoxCommands | None: ...

    def transition(self, req: Request) -> str | Deferred: ...

    def describe_state(self) -> str: ...

    def stats_job(self, req: Request, item: Asked) -> Job: ...

    def state_table_job(self, req: Request, item: Asked) -> Job: ...

    def handover(self, req: Request, item: Asked, now: float) -> str: ...
    def cell(self, req: Request) -> str: ...


#: ``handler(desk, request, arrival, now)``, on the loop thread: the reply's text (loop), a
#: Deferred (deferred) or the job (worker)
Handler = Callable[[CommandDesk, Request, Asked, float], "str | Deferred | Job"]


@dataclass(frozen=True)
class CommandSpec:
    """One of the robot's own commands (not a controller's): who may send it, which thread
    answers it, and its handler. The operator desk calls the handler on the loop thread and
    dispatches by ``thread``: a ``loop`` row's text is the reply in that tick; a ``worker``
    row's handler checks the request (a bad one is refused at once) and returns the job,
    which the desk hands to the worker thread (it builds and sends the reply; a full queue is
    refused with ``busy``); a ``deferred`` row's Deferred is answered when its work is done."""

    name: str
    #: ``viewer``: read-only, any client of a viewer or operator interface may ask;
    #: ``operator``: changes something, operator interfaces only
    role: str
    #: :data:`LOOP`, :data:`WORKER` or :data:`DEFERRED`
    thread: str
    summary: str
    handler: Handler
    #: a worker row refused because the worker's queue is full: ``busy: <this>; try again``
    busy: str = ""


def _transition(desk: CommandDesk, req: Request, item: Asked, now: float) -> str | Deferred:
    return desk.transition(req)


def _dump_black_box(desk: CommandDesk, req: Request, item: Asked, now: float) -> str:
    """``DumpBlackBox`` (``Reason``: why, optional): the black box written off the loop, its
    window closing at the end of this tick; the reply names the directory, the ``BLACKBOX``
    alert says when it is written."""
    box = desk.black_box
    if box is None or not box.enabled:
        raise CommandError("DumpBlackBox: no black box (black_box.enabled is false)")
    reason = req.args.get("Reason", "") or req.args.get("reason", "")
    path = box.request("operator", f"operator DumpBlackBox{': ' + reason if reason else ''}")
    return f"black box: writing {path}"


#: The robot's commands, by lower-case name (a name not here goes to the controllers).
#: docs/ARCHITECTURE.md, "Add an operator command".
ROBOT_COMMANDS: dict[str, CommandSpec] = {
    c.name.lower(): c
    for c in (
        CommandSpec(
            "Enable",
            "operator",
            DEFERRED,  # in the tick, or when drives that power up off the loop thread are up
            "servos on, holding: READY -> ENABLED",
            _transition,
        ),
        CommandSpec("Run", "operator", LOOP, "follow the controllers: -> RUNNING", _transition),
        CommandSpec("Stop", "operator", LOOP, "hold the last setpoint: -> STOPPED", _transition),
        CommandSpec("Hold", "operator", LOOP, "RUNNING -> ENABLED", _transition),
        CommandSpec("Disable", "operator", LOOP, "servos off: -> READY", _transition),
        CommandSpec("EStop", "operator", LOOP, "emergency stop, latched: -> ESTOP", _transition),
        CommandSpec("Reset", "operator", LOOP, "clear a latch: FAULT/ESTOP -> READY", _transition),
        CommandSpec(
            "GetState", "viewer", LOOP, "the state and why", lambda d, r, i, n: d.describe_state()
        ),
        CommandSpec(
            "GetStats",
            "viewer",
            WORKER,
            "every statistic (JSON)",
            lambda d, r, i, n: d.stats_job(r, i),
            busy="too many statistics requests",
        ),
        CommandSpec(
            "GetStateTable",
            "viewer",
            WORKER,
            "the State Data Table (NDARRAY)",
            lambda d, r, i, n: d.state_table_job(r, i),
            busy="too many requests for the worker",
        ),
        CommandSpec(
            "Handover",
            "operator",
            LOOP,
            "give the motion to another master",
            lambda d, r, i, n: d.handover(r, i, n),
        ),
        CommandSpec(
            "CellLeave",
            "operator",
            LOOP,
            "leave the cell: this arm's stops stop no other, theirs not this one",
            lambda d, r, i, n: d.cell(r),
        ),
        CommandSpec(
            "CellJoin", "operator", LOOP, "join the cell again", lambda d, r, i, n: d.cell(r)
        ),
        CommandSpec(
            "CellForget",
            "operator",
            LOOP,
            "Member=<name>: a member that is gone stops this one no more (until heard again)",
            lambda d, r, i, n: d.cell(r),
        ),
        CommandSpec(
            "StartRecording",
            "operator",
            DEFERRED,
            "record to OutputFilename",
            lambda d, r, i, n: d.recording.start(r),
        ),
        CommandSpec(
            "StopRecording",
            "operator",
            DEFERRED,
            "close the recording",
            lambda d, r, i, n: d.recording.stop(r),
        ),
        CommandSpec(
            "DumpBlackBox",
            "operator",
            LOOP,
            "write the black box (the last black_box.seconds) off the loop; Reason= optional",
            _dump_black_box,
        ),
        CommandSpec(
            "GetRecordingStatus",
            "viewer",
            LOOP,
            "whether and where it records",
            lambda d, r, i, n: d.recording.describe(),
        ),
    )
}

#: what a viewer may ask (the rest of its requests are refused by its interface)
READ_ONLY_COMMANDS = frozenset(k for k, c in ROBOT_COMMANDS.items() if c.role == "viewer")


def _parse_xml_command(text: str) -> tuple[str, dict[str, str]] | None:
    text = text.strip()
    if not text.startswith("<"):
        return None
    if len(text) > MAX_XML_BYTES:
        raise CommandError(f"XML command too long ({len(text)} characters, limit {MAX_XML_BYTES})")
    if "<!" in text:
        # a DTD is the door to entity expansion ("billion laughs", 477 bytes stalled a loop for
        # 98 ms) and external entities; no command of this protocol needs one
        raise CommandError("XML command refused: DOCTYPE, ENTITY and CDATA are not accepted")
    try:
        root = ET.fromstring(text)
    except (ET.ParseError, ValueError) as err:  # ValueError: bytes no charset could decode
        raise CommandError(f"malformed XML command: {err}") from err
    attrs = dict(root.attrib)
    name = attrs.pop("Name", "") or attrs.pop("name", "")
    return name, attrs


def parse_request(msg: Message) -> Request:
    """Turn an operator message into a :class:`Request`; CommandError if it is malformed."""
    mtype = msg.message_type
    if mtype == "COMMAND":
        name = str(getattr(msg, "command_name", "")).strip()
        text = str(getattr(msg, "command", "") or "")
        parsed = _parse_xml_command(text) if text else None
        args: dict[str, str] = {}
        if parsed is not None:
            xml_name, args = parsed
            if xml_name:
                name = xml_name
        if not name:
            raise CommandError("COMMAND without a command name")
        return Request("command", name, args, msg)
    if mtype == "STRING":
        text = str(getattr(msg, "string", "")).strip()
        parsed = _parse_xml_command(text)
        if parsed is not None:
            name, args = parsed
        else:
            name, args = text, {}
        if not name:
            raise CommandError(f"empty command in STRING {msg.device_name!r}")
        return Request("string", name, args, msg)
    if mtype.startswith(("GET_", "STT_", "STP_")):
        return Request("query", mtype, {}, msg)
    raise CommandError(f"{mtype} is not an operator request")


#: Largest XML command accepted (the commands of this protocol are a few hundred bytes).
MAX_XML_BYTES = 8192


def safe_name(name: str, limit: int = 20) -> str:
    """A device name that can always be packed: at most ``limit`` bytes of UTF-8, cut at a
    character boundary. A peer's name that was not valid UTF-8 (decoded as latin-1) or that
    grows past 20 bytes when re-encoded is answered under this shortened name, never with an
    exception on the loop thread."""
    raw = name.encode("utf-8", "replace")  # a lone surrogate becomes "?"
    if len(raw) <= limit and raw.decode("utf-8") == name:
        return name
    return raw[:limit].decode("utf-8", "ignore")


def _printable(text: str) -> str:
    """``text`` that encodes in UTF-8 (a peer's undecodable bytes become U+FFFD)."""
    return text.encode("utf-8", "replace").decode("utf-8", "replace")


def _reply_xml(name: str, ok: bool, message: str) -> str:
    name, message = _printable(name), _printable(message)
    status = "SUCCESS" if ok else "FAIL"
    name_attr = f" Name={quoteattr(name)}" if name else ""
    err_attr = "" if ok else f" Error={quoteattr(message)}"
    return f'<CommandReply{name_attr} Status="{status}"{err_attr} Message={quoteattr(message)} />'


def _rts_command(msg: Message, name: str, ok: bool, message: str, timestamp: float) -> Message:
    cls = cast("type[igtl.RTSCommandMessage]", REGISTRY["RTS_COMMAND"])
    message = _printable(message)
    meta = {"Status": "SUCCESS" if ok else "FAIL", "Message": message}
    if not ok:
        meta["Error"] = message
    return cls(
        command_id=int(getattr(msg, "command_id", 0)),
        command_name=safe_name(name, 128),
        command=_reply_xml(name, ok, message),
        device_name=safe_name(msg.device_name),
        header_version=2,
        message_id=msg.message_id,  # the reply names the request it answers
        metadata=meta,
        timestamp=timestamp,
    )


def _ack_string(msg: Message, name: str, ok: bool, message: str, timestamp: float) -> Message:
    uid = msg.device_name[4:]
    return igtl.StringMessage(
        _reply_xml(name, ok, message),
        device_name=safe_name("ACK_" + uid),
        header_version=msg.header_version,
        message_id=msg.message_id,
        timestamp=timestamp,
    )


def success_reply(req: Request, message: str = "", *, timestamp: float = 0.0) -> Message:
    """The success answer to a command or string request (queries build their own replies)."""
    assert req.msg is not None
    if req.kind == "command":
        return _rts_command(req.msg, req.name, True, message, timestamp)
    if req.kind == "string":
        return _ack_string(req.msg, req.name, True, message, timestamp)
    raise ValueError("queries are answered with the requested message type")


def error_reply(
    msg: Message,
    text: str,
    *,
    code: int = igtl.StatusCode.UNKNOWN_ERROR,
    timestamp: float = 0.0,
) -> Message:
    """The error answer to any operator message, in the form its sender expects."""
    mtype = msg.message_type
    if mtype == "COMMAND":
        name = str(getattr(msg, "command_name", "") or "")
        return _rts_command(msg, name, False, text, timestamp)
    if mtype == "STRING" and msg.device_name.startswith("CMD_"):
        return _ack_string(msg, "", False, text, timestamp)
    if mtype.startswith("STT_") or mtype.startswith("STP_"):
        rts = "RTS_" + mtype[4:]
        # a query-family class (RTSMessage): it takes the type name and a status
        cls = cast("Callable[..., Message] | None", REGISTRY.get(rts))
        if cls is not None and getattr(cls, "NEEDS_TYPE_NAME", False):
            try:
                return cls(
                    type_name=rts,
                    status=1,
                    device_name=safe_name(msg.device_name),
                    header_version=msg.header_version,
                    message_id=msg.message_id,
                    timestamp=timestamp,
                )
            except (TypeError, ValueError):
                pass
    return igtl.StatusMessage(
        code=int(code),
        subcode=0,
        error_name=igtl.StatusCode(int(code)).name[:20],
        status_message=text,
        device_name=safe_name(msg.device_name),
        header_version=msg.header_version,
        message_id=msg.message_id,
        timestamp=timestamp,
    )
