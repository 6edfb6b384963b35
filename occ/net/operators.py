"""Operator requests: commands, queries and their replies, on the loop thread.

Requests arrive parsed (XML included) from the interface threads through the command queue;
the loop hands at most 16 a tick to :meth:`OperatorDesk.handle`. The robot's own commands
(Enable, Run, Stop, EStop, Reset, GetStats, ...) are the rows of one table (occ/net/commands.py
``ROBOT_COMMANDS``): each row's handler answers it, and its thread column says whether the
reply goes now, from the worker thread (``GetStats`` costs milliseconds) or when its work is
done. GET_* queries are answered at once, anything else goes to the controllers. Every request
gets a reply in its sender's form, an error reply when it is refused; a failing handler is a
FAULT with an alert, never a crash. Viewers are shown statistics without what it would take to
forge the master stream. The desk sees the robot through its port (occ/core/ports.py)."""

from __future__ import annotations

import json
import logging
import time
from typing import TYPE_CHECKING, Any

import igtl
from igtl.auth import HMAC_KEY
from igtl.messages.base import Message
from igtl.transport.common import RateLimit
from occ.core.safety import RobotState
from occ.errors import CommandError, StateError, caused
from occ.kinematics.collision import Region, RegionError, region_event, regions_from_event
from occ.net.commands import (
    ROBOT_COMMANDS,
    WORKER,
    ArrayReply,
    Asked,
    Deferred,
    Job,
    Request,
    error_reply,
    parse_request,
    safe_name,
    success_reply,
)
from occ.net.decoders import decode
from occ.net.interfaces import Inbound, is_operator_request
from occ.net.outputs import STATE_STATUS_CODE, pose_to_message
from occ.samples import PoseSample

if TYPE_CHECKING:
    from occ.core.ports import DeskPort
    from occ.recording.control import RecordingControl

#: states a robot stays in until an operator clears them: greeted with why
LATCHED_STATES = (RobotState.FAULT, RobotState.ESTOP, RobotState.STOPPED)

log = logging.getLogger("occ.core.robot")

#: statistics a viewer is not shown: what it would take to forge the master stream (the next
#: sequence number, the stream's source port)
VIEWER_HIDDEN = frozenset({"seq", "last_seq", "stream_owner"})


def redact_for_viewer(value: Any) -> Any:
    """``value`` (a statistics snapshot) without the keys in :data:`VIEWER_HIDDEN`."""
    if isinstance(value, dict):
        return {k: redact_for_viewer(v) for k, v in value.items() if k not in VIEWER_HIDDEN}
    if isinstance(value, list):
        return [redact_for_viewer(v) for v in value]
    return value


class OperatorDesk:
    """Answers the operators of one robot (see the module docstring)."""

    def __init__(self, port: DeskPort, recording: RecordingControl) -> None:
        self.port = port
        self.handled = 0
        self.refused = 0
        self.reply_errors = 0
        self._refusal_log = RateLimit(5)
        #: StartRecording, StopRecording, GetRecordingStatus (occ/recording/control.py)
        self.recording = recording
        self.black_box = port.black_box  # DumpBlackBox (occ/net/commands.py)

    def greet(self, iface: Any, peer: Any) -> None:
        """A new client of a viewer or operator interface is told the state (runs on the
        interface thread: only queues a STATUS)."""
        r = self.port
        if iface.answers:
            st = r.states.state
            iface.send_to_peer(
                igtl.StatusMessage(
                    code=int(STATE_STATUS_CODE[st]),
                    error_name=st.value,
                    status_message=f"{r.name} is {st.value}"
                    + (
                        f": {r.alarms.last_alert}"
                        if st in LATCHED_STATES and r.alarms.last_alert
                        else ""
                    ),
                    device_name=r.name[:20],
                    timestamp=r.clock.wall_time(),
                ),
                peer,
            )

    def counters(self) -> dict[str, int]:
        return {
            "handled": self.handled,
            "refused": self.refused,
            "reply_errors": self.reply_errors,
            "worker_refused": self.port.worker.refused,
        }

    def refuse_input(self, item: Inbound, err: CommandError) -> None:
        """A controller refused an input (an invalid fixture, from the command queue or a
        stream): nothing changed; counted, logged (at most five lines a second) and the sender
        told with an error reply."""
        r = self.port
        msg = item.msg
        self.refused += 1
        if self._refusal_log.allow():
            log.warning(
                "%s: refused %s from %s:%s: %s",
                item.interface,
                msg.message_type,
                *item.peer.address[:2],
                err,
            )
        r.reply(
            item,
            error_reply(
                msg,
                str(err),
                code=igtl.StatusCode.ILLEGAL_INSTRUCTION,
                timestamp=r.clock.wall_time(),
            ),
        )

    def _collision_region(self, item: Inbound, event: Any) -> bool:
        """A forbidden region from 3D Slicer for the whole-arm collision check (metadata
        ``kind=forbidden-region``: occ/kinematics/collision.py): defined (replacing the node's
        previous one), a checked plan not yet acknowledged invalidated; True when it was one.
        A model (POLYDATA: up to 200k triangles, hundreds of milliseconds) is built on the
        worker and takes effect when built (refused from there when it cannot be used).
        CommandError when it cannot be used or the robot checks no collisions."""
        name = region_event(event)
        if name is None:
            return False
        r = self.port
        if r.collision is None:
            raise CommandError(
                f"region {name!r}: this robot checks no collisions (config safety.collision)"
            )
        if event.kind == "POLYDATA":
            if not r.worker.start().submit(lambda: self._build_region(item, event)):
                raise CommandError(f"region {name!r}: busy building regions; try again")
            return True
        try:
            found = regions_from_event(event)
        except RegionError as err:
            raise caused(CommandError(str(err)), err) from err
        assert found is not None
        self._define_region(*found)
        return True

    def _build_region(self, item: Inbound, event: Any) -> None:
        """On the worker: a Slicer model made a mesh region (giving up the interpreter lock
        between its parts: occ/kinematics/regions.py), then defined; refused with the reason
        when it cannot be used."""
        try:
            found = regions_from_event(event, pause=_let_others_run)
        except RegionError as err:
            self.refuse_input(item, caused(CommandError(str(err)), err))
            return
        assert found is not None
        self._define_region(*found)

    def _define_region(self, name: str, regions: list[Region]) -> None:
        """Any thread: the node's regions replaced; a checked plan not acknowledged voided."""
        guard = self.port.collision
        assert guard is not None
        guard.cm.define(name, regions)
        for c in self.port.controller.controllers:
            invalidate = getattr(c, "invalidate_plan", None)
            if invalidate is not None:
                invalidate(f"the forbidden region {name!r} changed")
        log.info("forbidden region %r: %d shape(s) from 3D Slicer", name, len(regions))

    def handle(self, item: Inbound, now: float) -> None:
        r = self.port
        msg = item.msg
        recorder = r.recorder()
        if recorder is not None:
            recorder.record_message(msg, "in", item.interface, now)
        if r.black_box is not None:
            r.black_box.took_request(item, item.interface)
        req: Request | None = item.request
        if req is None and not is_operator_request(msg):
            # a discrete input routed to the command queue (e.g. VFIXTURE), decoded by its
            # interface (here when it was not: a test, a replay); a pose (a Base TRANSFORM, a
            # fixture's) as a typed sample, as on a stream
            event = item.event
            if event is None:
                event = decode(item.interface, item.peer, msg, item.t_rx)
            try:
                if self._collision_region(item, event):
                    return
                if isinstance(event, PoseSample):
                    r.controller.on_sample(event, now)
                else:
                    r.controller.on_input(event, now)
            except CommandError as err:
                self.refuse_input(item, err)
            except Exception as err:  # noqa: BLE001
                r.alarms.plugin_error(f"controller {r.controller.name}: on_input", err)
            return
        wall = r.clock.wall_time()
        try:
            if req is None:  # not parsed by an interface thread (a test, a replay)
                req = parse_request(msg)
            if req.kind == "query":
                reply = self._answer_query(req, wall)
            else:
                if r.black_box is not None:  # who asked (occ-record why): commands, not queries
                    r.black_box.note("request", _requester(item, req.name))
                text = self._execute(req, item, now)
                if text is None:  # the worker replies (statistics, the state table)
                    self.handled += 1
                    return
                if isinstance(text, ArrayReply):
                    self._reply_array(item, req, text)
                    self.handled += 1
                    return
                if isinstance(text, Deferred):
                    # answered when the work is done (a controller's planner thread)
                    self.handled += 1
                    done = req
                    text.bind(lambda ok, answer: self._reply_later(item, done, ok, answer))
                    return
                reply = success_reply(req, text, timestamp=wall)
            self.handled += 1
        except (CommandError, StateError) as err:
            self.refused += 1
            if self._refusal_log.allow():  # a flood of bad commands must not flood the log
                log.warning(
                    "%s: refused %s from %s:%s: %s",
                    item.interface,
                    msg.message_type,
                    *item.peer.address[:2],
                    err,
                )
            reply = error_reply(
                msg, str(err), code=igtl.StatusCode.ILLEGAL_INSTRUCTION, timestamp=wall
            )
        except Exception as err:  # noqa: BLE001 - a failing handler is a FAULT, not a crash
            self.refused += 1
            name = req.name if req is not None else msg.message_type
            r.alarms.plugin_error(f"command {name!r}", err)
            reply = error_reply(
                msg, f"{name} failed: {err}", code=igtl.StatusCode.UNKNOWN_ERROR, timestamp=wall
            )
        self._send_reply(item, reply, now)

    def _send_reply(self, item: Inbound, reply: Message, now: float) -> None:
        r = self.port
        try:
            r.reply(item, reply)
        except Exception as err:  # noqa: BLE001 - a reply that cannot be sent is counted
            self.reply_errors += 1
            log.warning("%s: reply to %s could not be sent: %s", item.interface, item.peer, err)
            return
        recorder = r.recorder()
        if recorder is not None:
            recorder.record_message(reply, "out", item.interface, now)
        if r.black_box is not None:
            r.black_box.sent(reply, item.interface)

    def _reply_later(self, item: Inbound, req: Request, ok: bool, text: str) -> None:
        """The answer to a :class:`Deferred` command, on whichever thread finished it (the
        transports' ``send`` is thread-safe; the recording takes it through its any-thread
        entry)."""
        r = self.port
        wall = r.clock.wall_time()
        assert req.msg is not None
        if ok:
            reply = success_reply(req, text, timestamp=wall)
        else:
            self.refused += 1
            reply = error_reply(
                req.msg, text, code=igtl.StatusCode.ILLEGAL_INSTRUCTION, timestamp=wall
            )
        try:
            r.reply(item, reply)
        except Exception as err:  # noqa: BLE001 - a reply that cannot be sent is counted
            self.reply_errors += 1
            log.warning("%s: reply to %s could not be sent: %s", item.interface, item.peer, err)
            return
        recorder = r.recorder()  # read once: StopRecording detaches it on the loop thread
        if recorder is not None:
            recorder.record_message_late(reply, "out", item.interface, r.clock.now())
        if r.black_box is not None:  # any thread: stamped with the tick under way
            r.black_box.sent(reply, item.interface)

    def _reply_array(self, item: Inbound, req: Request, answer: ArrayReply) -> None:
        """A controller's answer with an array (:class:`ArrayReply`): packed and sent by the
        worker (a plan's path is megabytes: its CRC is not the loop's to compute), the NDARRAY
        first, then the reply."""

        def job() -> None:
            msg = req.msg
            assert msg is not None
            wall = self.port.clock.wall_time()
            array = igtl.NDArrayMessage(
                array=answer.array,
                device_name=safe_name(answer.device),
                header_version=2,
                message_id=msg.message_id,
                metadata=dict(answer.meta),
                timestamp=wall,
            )
            self.port.reply(item, array)
            self.port.reply(item, success_reply(req, answer.text, timestamp=wall))

        if not self.port.worker.start().submit(job):
            raise CommandError("busy: the worker is still sending an earlier reply; try again")

    def _execute(
        self, req: Request, item: Inbound, now: float
    ) -> str | Deferred | ArrayReply | None:
        """A robot command through its row's handler, dispatched by the row's thread
        (occ/net/commands.py ROBOT_COMMANDS), any other to the controllers. None: the worker
        thread sends the reply."""
        spec = ROBOT_COMMANDS.get(req.name.strip().lower())
        if spec is None:
            return self.port.controller.on_command(req, now) or "OK"
        answer = spec.handler(self, req, item, now)
        if spec.thread != WORKER:
            assert isinstance(answer, str | Deferred), spec.name
            return answer
        assert callable(answer), spec.name
        # built off the loop thread: the worker replies
        if not self.port.worker.start().submit(answer):
            raise CommandError(f"busy: {spec.busy}; try again")
        return None

    # -- what the rows of ROBOT_COMMANDS call (occ/net/commands.py ``CommandDesk``)
    def transition(self, req: Request) -> str | Deferred:
        """A state-machine event of the command's name; Reset clears the monitors first, and
        in STOPPED only the alert (Run resumes). An Enable whose drives power up off the loop
        thread is answered when they are up (a Deferred: occ/core/powerup.py)."""
        port = self.port
        event = req.name.strip().lower()
        if event == "reset":
            port.reset_monitors()
            if port.states.state is RobotState.STOPPED:
                port.alarms.last_alert = ""
                return "STOPPED: alerts cleared; send Run to resume"
        return port.transition(event, f"operator {req.name}")

    def stats_job(self, req: Request, item: Asked) -> Job:
        assert isinstance(item, Inbound)
        return lambda: self._reply_stats(item, req)

    def state_table_job(self, req: Request, item: Asked) -> Job:
        """``GetStateTable`` (``Seconds``: the last seconds, default all; ``Since``: rows after
        this daemon time; ``Every``: every n-th row): the worker sends an ``NDARRAY``
        ``StateTable`` (rows x columns, names in metadata ``columns``), then the reply."""
        assert isinstance(item, Inbound)
        if self.port.state_table is None:
            raise CommandError("GetStateTable: no state table (configure state_table.seconds)")
        args = {k.lower(): v for k, v in req.args.items()}
        try:
            seconds = float(args["seconds"]) if "seconds" in args else None
            since = float(args["since"]) if "since" in args else None
            every = int(args.get("every", "1"))
        except ValueError as err:
            raise CommandError(f"GetStateTable: bad argument: {err}") from err
        if seconds is not None and not seconds > 0.0:
            raise CommandError(f"GetStateTable: Seconds must be > 0, got {seconds}")
        if since is not None and since != since:
            raise CommandError("GetStateTable: Since must be a number")
        if every < 1:
            raise CommandError(f"GetStateTable: Every must be >= 1, got {every}")
        return lambda: self._reply_state_table(item, req, seconds, since, every)

    def cell(self, req: Request) -> str:
        """``CellLeave``, ``CellJoin``, ``CellForget Member=<name>`` (occ/core/cell.py)."""
        if self.port.cell is None:
            raise CommandError("this daemon is in no cell (no `cell:` section)")
        try:
            return self.port.cell(req.name, req.args)
        except ValueError as err:
            raise CommandError(str(err)) from err

    def handover(self, req: Request, item: Asked, now: float) -> str:
        to = req.args.get("To", req.args.get("to", "")).strip()
        return self.port.handover(to, item.interface, now)

    # -- the worker's jobs
    def _reply_stats(self, item: Inbound, req: Request) -> None:
        """On the worker thread: the snapshot (histogram percentiles, controller statistics)
        costs milliseconds; the loop only handed the request over."""
        port = self.port
        snap = self.report()
        if req.args.get("Histogram", "").lower() == "lateness":
            # the raw buckets: a client subtracts two of them into a window's percentiles
            snap["lateness_buckets"] = port.lateness_buckets()
        if item.role != "operator":
            snap = redact_for_viewer(snap)
        text = json.dumps(snap, separators=(",", ":"), default=str)
        wall = port.clock.wall_time()
        if req.args.get("Format", "").lower() == "json":
            # plain JSON a script can parse as it is: a STRING (ACK_<id> for a PLUS-style
            # request, STATS for a COMMAND) holding nothing but the statistics
            msg = req.msg
            assert msg is not None
            device = "ACK_" + msg.device_name[4:] if req.kind == "string" else "STATS"
            reply: Message = igtl.StringMessage(
                text,
                device_name=safe_name(device),
                header_version=msg.header_version,
                message_id=msg.message_id,
                timestamp=wall,
            )
        else:
            reply = success_reply(req, text, timestamp=wall)
        port.reply(item, reply)

    def _reply_state_table(
        self,
        item: Inbound,
        req: Request,
        seconds: float | None,
        since: float | None,
        every: int,
    ) -> None:
        """On the worker thread: the rows asked for as an ``NDARRAY``, then the reply."""
        port = self.port
        table = port.state_table
        assert table is not None
        rows = table.window(seconds, since=since, every=every)
        msg = req.msg
        assert msg is not None
        wall = port.clock.wall_time()
        meta = {"columns": ",".join(table.columns), "robot": port.name}
        if port.collab is not None:
            meta["owners"] = ",".join(port.collab.masters)
        array = igtl.NDArrayMessage(
            array=rows,
            device_name="StateTable",
            header_version=2,
            message_id=msg.message_id,
            metadata=meta,
            timestamp=wall,
        )
        port.reply(item, array)
        span = f" from t={rows[0, 0]:.6f} to t={rows[-1, 0]:.6f}" if len(rows) else ""
        # the columns in the reply too: a header-version-1 client gets the array without metadata
        text = f"StateTable: {len(rows)} rows{span}; columns {meta['columns']}"
        port.reply(item, success_reply(req, text, timestamp=wall))

    def _answer_query(self, req: Request, wall: float) -> Message:
        r = self.port
        msg = req.msg
        assert msg is not None
        name = req.name
        if name == "GET_STATUS":
            st = r.states.state
            return igtl.StatusMessage(
                code=int(STATE_STATUS_CODE[st]),
                error_name=st.value,
                status_message=self.describe_state(),
                device_name=safe_name(msg.device_name or r.name),
                header_version=msg.header_version,
                message_id=msg.message_id,
                timestamp=wall,
            )
        if name == "GET_CAPABIL":
            types = [
                "TRANSFORM",
                "POSITION",
                "STATUS",
                "STRING",
                "COMMAND",
                "CAPABILITY",
                "GET_STATUS",
                "GET_CAPABIL",
                "GET_TRANS",
            ]
            return igtl.CapabilityMessage(
                types=tuple(types),
                device_name=safe_name(msg.device_name),
                header_version=msg.header_version,
                message_id=msg.message_id,
                timestamp=wall,
            )
        if name in ("GET_TRANS", "GET_TRANSFOR"):
            want = safe_name(msg.device_name or "Tip")
            pose = r.data.base if want.lower() == "base" else r.data.world_tip()
            return pose_to_message(
                pose, "TRANSFORM", want, msg.header_version, wall, msg.message_id
            )
        raise CommandError(f"{name} is not supported by {r.name}")

    def describe_state(self) -> str:
        r = self.port
        st = r.states.state
        parts = [f"state={st.value}"]
        if r.alarms.last_alert:
            parts.append(f"alert={r.alarms.last_alert}")
        if r.states.last_reason:
            parts.append(f"reason={r.states.last_reason}")
        return "; ".join(parts)

    def report(self) -> dict[str, Any]:
        """Every statistic of the robot (GetStats, ``occd --stats``): each part's, from the
        registry the robot was assembled with (occ/core/assembly.py); off the loop thread."""
        return self.port.stats.report()


def _let_others_run() -> None:
    """Give up the interpreter lock for a moment (the loop thread takes it if it waits)."""
    time.sleep(0)


def _requester(item: Inbound, name: str) -> dict[str, str]:
    """Who sent a command, as the black box notes it: the interface, the command's name, the
    sender's address and role, and whether it was signed (a shared key's HMAC)."""
    host, port = item.peer.address[:2]
    signed = HMAC_KEY in item.msg.metadata
    return {
        "interface": item.interface,
        "name": name,
        "peer": f"{host}:{port}",
        "role": item.role,
        "signed": "yes" if signed else "no",
    }
