"""``occ-record why DIR``: the chain that led to a black box dump, told from the dump alone.

The investigator of a stopped surgical robot asks why before anything else. A dump
(occ/recording/dump.py) holds the answer in pieces: the manifest names the causes and the
trigger's tick, ``events.jsonl`` the state transitions, the collision verdicts and the notes
the alarms took when they acted (the loss monitor's event with the sequence numbers it judged
lost, the drive failures, who sent each command), ``recording.igtl`` every message the loop
took and sent with its tick, ``ticks.npy`` every drive reading. This module puts them in order:

- a **loss stop** (a gap in the sequence numbers): the stream, the numbers judged lost, the
  last good number before the gap and when it arrived, the number after the gap that proved
  it, when the loss was judged and in which tick, the rule (``safety.loss.max_consecutive``);
- a **late stream** (a hold, then the latch at the grace): the last sample accepted, when the
  robot started holding, every sample that came after it and how late (against when it was
  due at the stream's period), the latch; each hold of the last seconds that resumed is told
  the same way;
- a **drive fault**: the drive, the operation, the joint, the rule of the feedback checks
  (occ/drivers/checks.py) with its setting, and the joint's reading at the trigger's tick and
  the tick before, from ``ticks.npy`` (the raw ``raw.*`` columns when the dump has them, else
  what the loop kept: a reading a check refused is not kept);
- a **collision stop**: the link, what it came near (a region, a link of its own, another
  arm's), the clearance and the margin of the verdict that stopped it, and the verdicts before;
- an **EStop** or an operator's **DumpBlackBox**: the request on the recording, its interface,
  its sender (address, role, signed or not) and the reply;
- always: the robot, the trigger's tick and time, the causes of the manifest, the state
  transitions of the window's last seconds, and what the dump did not hold that the
  explanation needed.

The dump is read by name, never by position: ticks through the manifest's ``tick_columns``,
events by their ``kind``, messages by their ``rec.*`` metadata; files, columns and events it
does not know are passed over. A dump without the alarms' notes (written before they existed)
is explained from the transition's reason and the recording, and says so.
"""

from __future__ import annotations

import json
import math
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from occ.errors import CommandError
from occ.net.commands import parse_request
from occ.net.interfaces import is_operator_request
from occ.recording.dump import read_manifest
from occ.recording.record import (
    DUMP_RECORDING,
    STATE_DEVICE,
    STATE_NAMES,
    ReadReport,
    iter_recording,
)

#: sequence numbers are uint32 (IGTL v2 message ID) and wrap around
MASK32 = 0xFFFFFFFF
#: lost numbers listed one by one (beyond, the first ones and the count)
LIST_AT_MOST = 64
#: verdicts shown before the one that stopped the robot
VERDICTS_SHOWN = 5
#: rec.t is written with 6 decimals: times closer than this are the same tick's
SAME_T = 2e-6

#: the feedback checks' rules (occ/drivers/checks.py): words of the cause, the rule, what it
#: says, the driver setting that tunes it
RULES = (
    ("feedback lost", "lost", "a measured joint's position is not finite", ""),
    (
        "outside its limits",
        "out of range",
        "measured outside the joint's limits by more than the margin",
        "limit_margin",
    ),
    ("feedback jump", "jump", "a step faster than the joint can move", "feedback_jump"),
    (
        "following error",
        "following error",
        "measured too far from the command for too long",
        "following_error",
    ),
    (
        "feedback frozen",
        "frozen",
        "no move beyond the encoder's noise while commanded away",
        "frozen_feedback_ms",
    ),
    ("heartbeat", "heartbeat", "the drive's heartbeat was not heard in time", ""),
)


class NotADump(ValueError):
    """The directory is not a black box dump (no manifest of the format, not a directory)."""


@dataclass(frozen=True)
class Msg:
    """A message of the dump's recording with where the loop took or sent it."""

    tick: int
    t: float
    direction: str  #: ``in`` or ``out``
    interface: str
    msg: Any

    @property
    def seq(self) -> int | None:
        """The sender's sequence number (IGTL v2 message ID), None for a v1 message."""
        if self.msg.metadata.get("rec.hv", "2") != "2":
            return None
        return int(self.msg.message_id)


@dataclass
class Dump:
    """What ``why`` reads of a dump (each file by name; what could not be read in ``lacks``)."""

    path: Path
    manifest: dict[str, Any]
    rows: np.ndarray | None
    columns: dict[str, int]
    events: list[dict[str, Any]]
    messages: list[Msg]
    config: dict[str, Any]
    lacks: list[str] = field(default_factory=list)

    @property
    def tick(self) -> int:
        return int(self.manifest["trigger"]["tick"])

    @property
    def t(self) -> float:
        return float(self.manifest["trigger"]["t"])

    def value(self, column: str, tick: int) -> float | None:
        """``column`` of ``tick``'s row (None: no such column, or the tick is not kept)."""
        i = self.columns.get(column)
        if self.rows is None or i is None:
            return None
        r = tick - int(self.manifest.get("window", {}).get("first_tick", 0))
        if not 0 <= r < len(self.rows):
            return None
        return float(self.rows[r, i])

    def t_of(self, tick: int) -> float | None:
        return self.value("t", tick)

    def notes(self, what: str, until: int | None = None) -> list[tuple[int, Any]]:
        """(tick, value) of the notes ``what`` up to tick ``until`` (the trigger's)."""
        end = self.tick if until is None else until
        return [
            (int(e["tick"]), e.get("value"))
            for e in self.events
            if e.get("kind") == "note" and e.get("what") == what and int(e["tick"]) <= end
        ]

    def stream(self, interface: str) -> list[Msg]:
        """The samples the loop took from ``interface`` (in order)."""
        return [
            m
            for m in self.messages
            if m.direction == "in" and m.interface == interface and not is_operator_request(m.msg)
        ]

    def loss_config(self) -> dict[str, Any]:
        safety = self.config.get("safety") or {}
        loss = safety.get("loss") if isinstance(safety, dict) else None
        return loss if isinstance(loss, dict) else {}


# ---------------------------------------------------------------------- reading the dump
def load_dump(path: str | Path) -> Dump:
    """The dump at ``path``; :class:`NotADump` when it is none (what is missing said)."""
    p = Path(path)
    if not p.is_dir():
        what = "does not exist" if not p.exists() else "is not a directory"
        raise NotADump(f"{p}: {what}: a black box dump is a directory with a manifest.json")
    try:
        manifest = read_manifest(p)
    except ValueError as err:
        raise NotADump(str(err)) from err
    trigger = manifest.get("trigger")
    if not (
        isinstance(trigger, dict)
        and isinstance(trigger.get("tick"), int)
        and isinstance(trigger.get("t"), int | float)
    ):
        raise NotADump(f"{p}: the manifest has no trigger (tick, t): not a whole dump")
    lacks: list[str] = []
    rows, columns = _ticks(p, manifest, lacks)
    return Dump(
        path=p,
        manifest=manifest,
        rows=rows,
        columns=columns,
        events=_events(p, lacks),
        messages=_messages(p, lacks),
        config=_config(p, lacks),
        lacks=lacks,
    )


def _ticks(p: Path, manifest: dict[str, Any], lacks: list[str]) -> tuple[Any, dict[str, int]]:
    names = manifest.get("tick_columns")
    if not isinstance(names, list):
        lacks.append("the manifest names no tick columns: ticks.npy not read")
        return None, {}
    try:
        rows = np.load(p / "ticks.npy", allow_pickle=False)
    except (OSError, ValueError) as err:
        lacks.append(f"ticks.npy could not be read ({err}): no drive readings")
        return None, {}
    if rows.ndim != 2 or rows.shape[1] != len(names):
        lacks.append(
            f"ticks.npy has shape {rows.shape}, the manifest names {len(names)} columns: not read"
        )
        return None, {}
    return rows, {str(n): i for i, n in enumerate(names)}


def _events(p: Path, lacks: list[str]) -> list[dict[str, Any]]:
    try:
        lines = (p / "events.jsonl").read_text(encoding="utf-8").splitlines()
    except OSError as err:
        lacks.append(f"events.jsonl could not be read ({err}): no transitions, verdicts, notes")
        return []
    out, bad = [], 0
    for line in lines:
        try:
            ev = json.loads(line)
        except ValueError:
            bad += 1
            continue
        if isinstance(ev, dict) and isinstance(ev.get("tick"), int):
            out.append(ev)
        else:
            bad += 1
    if bad:
        lacks.append(f"events.jsonl: {bad} line(s) that are not events, passed over")
    return out


def _messages(p: Path, lacks: list[str]) -> list[Msg]:
    if not (p / DUMP_RECORDING).is_file():
        lacks.append(f"no {DUMP_RECORDING}: no messages (samples, requests)")
        return []
    report = ReadReport()
    out = []
    try:
        for m in iter_recording(p, report):
            if m.device_name == STATE_DEVICE and m.message_type == "NDARRAY":
                continue  # the tick rows again: ticks.npy has them bit for bit
            meta = m.metadata
            try:
                tick, t = int(meta["rec.tick"]), float(meta["rec.t"])
            except (KeyError, ValueError):
                continue
            out.append(Msg(tick, t, meta.get("rec.dir", ""), meta.get("rec.if", ""), m))
    except OSError as err:
        lacks.append(f"{DUMP_RECORDING} could not be read after {len(out)} messages ({err})")
        return out
    if not report.complete:
        lacks.append(report.describe())
    return out


def _config(p: Path, lacks: list[str]) -> dict[str, Any]:
    try:
        cfg = yaml.safe_load((p / "config.yaml").read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as err:
        lacks.append(f"config.yaml could not be read ({err}): the rules' settings not named")
        return {}
    return cfg if isinstance(cfg, dict) else {}


# ---------------------------------------------------------------------- the explanation
def explain(d: Dump, last_s: float = 5.0) -> dict[str, Any]:
    """The chain that led to the dump (module docstring), as JSON can hold it."""
    m = d.manifest
    trig = m["trigger"]
    wall = trig.get("wall")
    state_code = d.value("state", d.tick)
    listed = m.get("causes")
    causes = [c for c in listed if isinstance(c, dict)] if isinstance(listed, list) else []
    since = d.t - last_s
    window = m.get("window") or {}
    return _finite(
        {
            "dump": str(d.path),
            "robot": m.get("robot"),
            "trigger": {
                "tick": d.tick,
                "t": d.t,
                "wall": wall,
                "utc": _utc(wall),
                "state": _state_name(state_code),
            },
            "causes": causes,
            "chains": [_explain_cause(d, c) for c in causes],
            "holds": _holds(d, since),
            "stream_events": [
                {
                    "tick": tick,
                    "t": v["event"].get("time"),
                    "stream": v.get("stream"),
                    "kind": v["event"].get("kind"),
                    "cause": v["event"].get("cause"),
                }
                for tick, v in d.notes("loss")
                if isinstance(v, dict) and _kind(v) and _num(v["event"].get("time")) >= since
            ],
            "last_s": last_s,
            "transitions": [
                {k: e.get(k) for k in ("tick", "t", "from", "to", "event", "reason")}
                for e in d.events
                if e.get("kind") == "transition" and _t(d, e) >= since and e["tick"] <= d.tick
            ],
            "window": {
                k: window.get(k)
                for k in ("first_tick", "ticks", "seconds", "events_whole_from_tick", "rows_lost")
            },
            "software": m.get("software"),
            "lacks": d.lacks,
        }
    )


def _explain_cause(d: Dump, cause: dict[str, Any]) -> dict[str, Any]:
    """One cause of the manifest, explained by what the dump holds for its kind."""
    word, reason = str(cause.get("cause", "")), str(cause.get("reason", ""))
    found: dict[str, Any]
    if word == "operator":
        found = _request(d, "DumpBlackBox", _dump_tick(d, word, reason))
    elif word == "estop" and reason.startswith("operator ") and len(reason.split()) > 1:
        found = _request(d, reason.split()[1], d.tick)
    elif reason.startswith("packet loss on "):
        found = _loss(d, reason)
    elif reason.startswith("collision:"):
        found = _collision(d, reason)
    elif failures := _failures(d, reason):
        found = _drive(d, failures)
    else:
        found = {"kind": "other", "lacks": []}
    return {"cause": word, "reason": reason, **found}


def _dump_tick(d: Dump, word: str, reason: str) -> int:
    """The tick a dump request was made in (the trigger's when none is recorded)."""
    ticks = [
        int(e["tick"])
        for e in d.events
        if e.get("kind") == "dump" and e.get("cause") == word and e.get("reason") == reason
    ]
    return ticks[-1] if ticks else d.tick


# ---------------------------------------------------------------------- requests
def _request(d: Dump, name: str, tick: int) -> dict[str, Any]:
    """Who asked: the request ``name`` the loop took in ``tick``, its sender and reply."""
    found: tuple[Msg, dict[str, str]] | None = None
    for m in d.messages:
        if m.tick != tick or m.direction != "in":
            continue
        try:
            req = parse_request(m.msg)
        except (CommandError, ValueError, AttributeError):
            continue
        if req.kind != "query" and req.name.strip().lower() == name.lower():
            found = (m, dict(req.args))
    if found is None:
        return {
            "kind": "request",
            "command": name,
            "tick": tick,
            "lacks": [f"the {name} request of tick {tick} is not on the recording"],
        }
    m, args = found
    sender = [v for k, v in d.notes("request", tick) if k == tick and _is_sender(v, m, name)]
    # its reply: RTS_COMMAND, or STRING ACK_<uid> to a STRING CMD_<uid> (both hold a
    # <CommandReply Name=...>); the one naming the request, when several went out in the tick
    replies = [
        r
        for r in d.messages
        if r.tick == tick
        and r.direction == "out"
        and r.interface == m.interface
        and (r.msg.message_type == "RTS_COMMAND" or r.msg.device_name.startswith("ACK_"))
    ]
    named = f'name="{name.lower()}"'
    reply = next(
        (r for r in replies if named in str(getattr(r.msg, "command", "")).lower()),
        next((r for r in replies if named in str(getattr(r.msg, "string", "")).lower()), None),
    ) or (replies[0] if replies else None)
    out: dict[str, Any] = {
        "kind": "request",
        "command": name,
        "tick": m.tick,
        "t": m.t,
        "interface": m.interface,
        "message": f"{m.msg.message_type} {m.msg.device_name!r}",
        "args": args,
        "sender": sender[-1] if sender else None,
        "reply": None,
        "lacks": [] if sender else ["the sender's address (no request note in this dump)"],
    }
    if reply is not None:
        meta = reply.msg.metadata
        text = getattr(reply.msg, "command", "") or getattr(reply.msg, "string", "")
        out["reply"] = {"status": meta.get("Status"), "message": meta.get("Message") or text}
    return out


def _is_sender(note: Any, m: Msg, name: str) -> bool:
    return (
        isinstance(note, dict)
        and note.get("interface") == m.interface
        and str(note.get("name", "")).lower() == name.lower()
    )


# ---------------------------------------------------------------------- losses
_STREAM = re.compile(r"^packet loss on (\S+?): (.*)$")
_SEQ = re.compile(r"seq (\d+)-(\d+) missing")
_SILENT = re.compile(r"no packet for ([\d.]+) ms")


def _loss(d: Dump, reason: str) -> dict[str, Any]:
    """A latched loss: a gap in the numbers (:func:`_gap`) or a late stream (:func:`_late`)."""
    match = _STREAM.match(reason)
    stream, cause = (match.group(1), match.group(2)) if match else ("", reason)
    event: dict[str, Any] | None = None
    judged = d.tick
    for tick, v in d.notes("loss"):
        ev = v.get("event") if isinstance(v, dict) else None
        if isinstance(ev, dict) and ev.get("kind") == "latch" and v.get("stream") == stream:
            event, judged = ev, tick
    source = event.get("source") if event else None
    if source is None:
        source = "sequence" if _SEQ.search(cause) else "grace"
    base = {
        "stream": stream,
        "policy": d.loss_config().get("policy"),
        "from": "the loss monitor's note" if event else "the transition's reason",
    }
    if source in ("sequence", "timestamp"):
        return {**base, **_gap(d, stream, cause, event, judged)}
    return {**base, **_late(d, stream, cause, event, judged)}


def _gap(
    d: Dump, stream: str, cause: str, event: dict[str, Any] | None, judged: int
) -> dict[str, Any]:
    """The numbers judged lost, the last good one before them and the one after."""
    lost = event.get("lost") if event else None
    if not (isinstance(lost, list) and len(lost) == 2):
        found = _SEQ.search(cause)
        lost = [int(found.group(1)), int(found.group(2))] if found else None
    rule = d.loss_config().get("max_consecutive")
    out: dict[str, Any] = {"kind": "loss", "max_consecutive": rule, "lacks": []}
    t_judged = float(event["time"]) if event else d.t_of(judged)
    out["judged"] = {"tick": judged, "t": t_judged}
    if event:
        out["judged"]["since_last_good_ms"] = float(event["since_last_good_s"]) * 1e3
    if lost is None:  # a gap told by the sender's timestamps (a v1 peer): no numbers
        out["lacks"].append(f"no sequence numbers: {cause}")
        return out
    first, last = int(lost[0]), int(lost[1])
    count = ((last - first) & MASK32) + 1
    out["lost"] = [(first + i) & MASK32 for i in range(min(count, LIST_AT_MOST))]
    out["count"] = count
    samples = [m for m in d.stream(stream) if m.tick <= judged]
    for key, seq in (("last_good", (first - 1) & MASK32), ("proved_by", (last + 1) & MASK32)):
        m = next((s for s in reversed(samples) if s.seq == seq), None)
        out[key] = _sample(d, m) if m is not None else {"seq": seq}
        if m is None:
            out["lacks"].append(f"seq {seq} of {stream} is not on the recording")
    return out


def _late(
    d: Dump, stream: str, cause: str, event: dict[str, Any] | None, judged: int
) -> dict[str, Any]:
    """A stream that came late or not at all: the hold, the samples late, the latch."""
    t_row = d.t_of(judged)
    t_judged = float(event["time"]) if event else (t_row if t_row is not None else d.t)
    if event:
        since = float(event["since_last_good_s"])
    else:
        silent = _SILENT.search(cause)
        since = float(silent.group(1)) * 1e-3 if silent else math.nan
    loss = d.loss_config()
    out: dict[str, Any] = {
        "kind": "late",
        "latched": {"tick": judged, "t": t_judged, "cause": cause},
        "grace_ms": loss.get("grace_ms"),
        "lacks": [] if event else ["the loss monitor's note (the latch told by its reason)"],
    }
    if math.isnan(since):
        out["lacks"].append("when the last sample was accepted")
        return out
    out.update(_episode(d, stream, t_judged - since, t_judged))
    holds = [
        (tick, v["event"])
        for tick, v in d.notes("loss", judged)
        if isinstance(v, dict) and v.get("stream") == stream and _kind(v) == "hold"
    ]
    holds = [(k, ev) for k, ev in holds if float(ev["time"]) >= t_judged - since - SAME_T]
    if holds:
        tick, ev = holds[-1]
        out["hold"] = {"tick": tick, "t": ev["time"], "after_ms": ev["since_last_good_s"] * 1e3}
    return out


def _kind(note: dict[str, Any]) -> str | None:
    ev = note.get("event")
    return ev.get("kind") if isinstance(ev, dict) else None


def _episode(d: Dump, stream: str, t_good: float, t_end: float) -> dict[str, Any]:
    """The last sample accepted at ``t_good`` and every sample after it up to ``t_end``,
    each with how late it came: its arrival against when it was due (the stream's period
    after the last good one) and, for a stamped stream, its age on arrival against the
    freshest sample's before it (the clock offset the loss monitor judges ages by)."""
    period = float(d.loss_config().get("period_ms") or 2.0) * 1e-3
    samples = d.stream(stream)
    good = [_sample(d, m) for m in samples if m.t <= t_good + SAME_T]
    ages = [s["age_ms"] for s in good if "age_ms" in s]
    fresh = min(ages) if ages else None
    seq0 = good[-1]["seq"] if good else None
    late = []
    after = [m for m in samples if t_good + SAME_T < m.t <= t_end + SAME_T]
    for i, m in enumerate(after, start=1):
        n = (m.seq - seq0) & MASK32 if seq0 is not None and m.seq is not None else i
        due = t_good + n * period
        s = {**_sample(d, m), "due": due, "late_ms": _ms(m.t - due)}
        if fresh is not None and "age_ms" in s:
            s["older_ms"] = round(s["age_ms"] - fresh, 6) + 0.0
        late.append(s)
    out: dict[str, Any] = {
        "last_good": good[-1] if good else {"t": t_good},
        "period_ms": period * 1e3,
        "samples": late,
    }
    if fresh is not None:
        out["freshest_age_ms"] = fresh
    return out


def _ms(seconds: float) -> float:
    """Milliseconds, rounded to the nanosecond (no -0.0 from float noise)."""
    return round(seconds * 1e3, 6) + 0.0


def _holds(d: Dump, since: float) -> list[dict[str, Any]]:
    """Every hold of the last seconds that ended otherwise than in the stop's latch (it
    resumed, or still holds at the trigger): the samples late, and by how much."""
    out = []
    notes = [(k, v) for k, v in d.notes("loss") if isinstance(v, dict) and _kind(v)]
    for i, (tick, v) in enumerate(notes):
        ev = v["event"]
        if ev["kind"] != "hold" or float(ev["time"]) < since:
            continue
        end = next((n for n in notes[i + 1 :] if n[1].get("stream") == v.get("stream")), None)
        if end is not None and _kind(end[1]) == "latch":
            continue  # the stop's own chain (:func:`_late`)
        t_end = float(end[1]["event"]["time"]) if end else d.t
        t_good = float(ev["time"]) - float(ev["since_last_good_s"])
        ended = (
            {"kind": _kind(end[1]), "tick": end[0], "t": t_end, "cause": end[1]["event"]["cause"]}
            if end
            else {"kind": "still holding", "tick": d.tick, "t": d.t}
        )
        out.append(
            {
                "stream": v.get("stream"),
                "held": {"tick": tick, "t": ev["time"], "cause": ev["cause"]},
                "ended": ended,
                **_episode(d, str(v.get("stream")), t_good, t_end),
            }
        )
    return out


def _sample(d: Dump, m: Msg) -> dict[str, Any]:
    """A stream sample as the explanation names it: its number, when the loop took it, and
    the sender's stamp with its age on arrival when the sample carries one."""
    out: dict[str, Any] = {"seq": m.seq, "tick": m.tick, "t": m.t}
    stamp = float(m.msg.timestamp)
    trig = d.manifest["trigger"]
    if stamp > 0.0 and isinstance(trig.get("wall"), int | float):
        out["stamp"] = stamp
        out["age_ms"] = _ms(m.t + float(trig["wall"]) - d.t - stamp)
    return out


# ---------------------------------------------------------------------- drives
_FAILED = r"driver (\S+): (\w[\w ]*?) failed: "
_FAILURE = re.compile(_FAILED + r"(.+?)(?=; " + _FAILED + r"|$)")
_JOINT = re.compile(r"joint '?([^\s':]+)'?: ")


def _failures(d: Dump, reason: str) -> list[dict[str, Any]]:
    """The drive failures behind the trigger: the alarms' note of its tick, else the
    transition's reason read back (``driver X: read failed: ...``)."""
    for tick, v in reversed(d.notes("drive failure")):
        if tick == d.tick and isinstance(v, dict) and isinstance(v.get("failures"), list):
            return [f for f in v["failures"] if isinstance(f, dict)]
    return [
        {"driver": f.group(1), "action": f.group(2), "cause": f.group(3), "from": "reason"}
        for f in _FAILURE.finditer(reason)
    ]


def _drive(d: Dump, failures: list[dict[str, Any]]) -> dict[str, Any]:
    """Each failed drive: the joint, the rule, the reading at the trigger and the tick before."""
    drivers = (d.config.get("robot") or {}).get("drivers") or []
    joints_of = {str(x.get("name")): list(x.get("joints") or []) for x in drivers}
    out = []
    lacks: list[str] = []
    for f in failures:
        cause = str(f.get("cause", ""))
        joint = _JOINT.search(cause)
        rule, says, setting = next(
            ((r, s, k) for words, r, s, k in RULES if words in cause),
            ("the driver's own words", "", ""),
        )
        joints = [joint.group(1)] if joint else joints_of.get(str(f.get("driver")), [])
        readings = {j: [_reading(d, j, k) for k in (d.tick - 1, d.tick)] for j in joints}
        out.append(
            {
                "driver": f.get("driver"),
                "action": f.get("action"),
                "cause": cause,
                "joint": joint.group(1) if joint else None,
                "rule": rule,
                "rule_says": says,
                "setting": setting,
                "readings": readings,
            }
        )
        if f.get("from") == "reason":
            lacks.append("the drive failure note (the failure read back from the reason)")
    if d.rows is not None and not any(c.startswith("raw.") for c in d.columns):
        lacks.append(
            "raw drive readings (no raw.* columns): the readings shown are what the loop "
            "kept, and a reading a check refused is not kept"
        )
    return {"kind": "drive", "failures": out, "lacks": lacks}


def _reading(d: Dump, joint: str, tick: int) -> dict[str, Any]:
    """``joint``'s reading in ``tick``'s row: raw (``raw.<what>.<joint>``) when the dump has
    it, what the loop kept (``pos``, ``vel``, ``eff``, ``stamp``) and the setpoint written."""
    raw = {
        c[4 : -len(joint) - 1]: d.value(c, tick)
        for c in d.columns
        if c.startswith("raw.") and c.endswith(f".{joint}")
    }
    kept = {w: d.value(f"{w}.{joint}", tick) for w in ("pos", "vel", "eff", "stamp")}
    return {
        "tick": tick,
        "t": d.t_of(tick),
        "raw": raw or None,
        "kept": kept,
        "setpoint": d.value(f"sp.{joint}", tick),
    }


# ---------------------------------------------------------------------- collisions
def _collision(d: Dump, reason: str) -> dict[str, Any]:
    """The verdict that stopped the robot and the ones before it. The stop's reason quotes
    the verdict's contact (its ``text``): the last verdict by the trigger that it quotes is
    the one; without one, the last inside its margin before the trigger's tick (a verdict
    of the trigger's own tick may be the next check, made after the stop)."""
    verdicts = [
        (int(e["tick"]), e.get("t"), e["value"])
        for e in d.events
        if e.get("kind") == "verdict"
        and int(e["tick"]) <= d.tick
        and isinstance(e.get("value"), dict)
        and isinstance(e["value"].get("worst"), dict)
    ]
    if not verdicts:
        whole = (d.manifest.get("window") or {}).get("events_whole_from_tick")
        return {
            "kind": "collision",
            "lacks": [f"no collision verdict in the window (events whole from tick {whole})"],
        }
    quoted = [v for v in verdicts if v[2]["worst"].get("text") and v[2]["worst"]["text"] in reason]
    inside = [v for v in verdicts if _num(v[2].get("slack")) < 0.0 and v[0] < d.tick]
    stop = (quoted or inside or verdicts)[-1]
    before = [v for v in verdicts if v[0] < stop[0]][-VERDICTS_SHOWN:]
    return {
        "kind": "collision",
        "verdict": _verdict(*stop),
        "before": [_verdict(*v) for v in before],
        "lacks": [],
    }


def _verdict(tick: int, t: Any, v: dict[str, Any]) -> dict[str, Any]:
    w = v["worst"]
    distance, slack = _num(w.get("distance")), _num(v.get("slack"))
    peers = [
        {"arm": p[0], "clearance_mm": _num(p[-1]) * 1e3}
        for p in v.get("peers") or []
        if isinstance(p, list) and p
    ]
    return {
        "tick": tick,
        "t": t,
        "link": w.get("link"),
        "near": w.get("region"),
        "text": w.get("text"),
        "clearance_mm": distance * 1e3,
        "margin_mm": (distance - slack) * 1e3,
        "inside_by_mm": -slack * 1e3,
        "peers": peers,
    }


# ---------------------------------------------------------------------- small helpers
def _num(x: Any) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


def _t(d: Dump, e: dict[str, Any]) -> float:
    """An event's time: its own, else its tick's row's (``-inf``: neither; a row's time of 0.0
    is a time, not none: before 2026-11-29 such a transition was left out)."""
    t = e.get("t")
    if isinstance(t, int | float):
        return float(t)
    row = d.t_of(int(e["tick"]))
    return -math.inf if row is None else row


def _utc(wall: Any) -> str | None:
    if not isinstance(wall, int | float):
        return None
    ms = int(round(wall * 1000.0)) % 1000
    return time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(wall)) + f".{ms:03d} UTC"


def _state_name(code: float | None) -> str | None:
    """The name of a tick row's state code (the recording's codes)."""
    if code is None or math.isnan(code):
        return None
    return STATE_NAMES.get(int(code), f"code {code:g}")


def _finite(obj: Any) -> Any:
    """Non-finite floats as text (``nan``, ``inf``): JSON has no number for them."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else str(obj)
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    return obj


def to_json(explanation: dict[str, Any]) -> str:
    return json.dumps(explanation, indent=1, allow_nan=False)
