"""What the console knows of one daemon, built from what the daemon sends its operators.

Pure bookkeeping, no sockets and no threads of its own: :class:`DaemonView` is fed the
messages of one operator connection (``on_status``, ``on_state_reply``, ``on_stats``) and the
link's events (``on_connect``, ``on_disconnect``), and :meth:`DaemonView.snapshot` turns it into
the JSON the page and ``/api/daemons`` show. Callers hold :attr:`DaemonView.lock` around each
call: the link's I/O thread writes, the web server's thread reads.

Derived here, from successive ``GetStats`` answers (the daemon reports counters since its
start):

- stream rates: each interface's received and sent messages per second between two answers;
- loss and hold events: the loss monitor's counters, and a log line when holds, resumes, trips
  or lost packets grew between two answers (the daemon broadcasts a resume and a latched stop,
  not a hold);
- the live loop-timing histogram: the daemon's raw lateness buckets (``Histogram="lateness"``)
  of now minus those of ``window_s`` ago, re-binned into a few 1-2-5 bins, with that window's
  percentiles (:class:`occ.core.stats.Histogram`);
- fixtures, tool and owner: whichever of :data:`HIGHLIGHT_KEYS` the statistics carry, at the
  top level or in the controller's, shown as they are.
- forces (bilateral teleoperation, issue 27): :func:`forces_of` picks what a slave reports of
  its contact force (the controller's ``force``: the force on the instrument, its magnitude and
  source) and what a master reports of the force on the hand (displayed, the slave's feedback,
  the fixtures', the clamp, the passivity controller's state: on, engaged this poll, energy).
- drives (CANopen CiA 402, issue 38): :func:`drives_of` lists each node a driver reports
  (``drivers.NAME.nodes``: the cia402 driver's) with its CiA 402 state, NMT state, statusword
  and last EMCY (code, meaning); an EMCY count that grew between two answers is a log line.

A daemon that restarted (its tick counter went down) starts the rates and the histogram again.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

from occ.core.stats import Histogram, bucket_bounds

#: the daemon's states (occ.core.safety.RobotState values): a STATUS with one of these names is a
#: state report (the greeting or a transition); any other name is an alert
STATES = ("INIT", "READY", "ENABLED", "RUNNING", "STOPPED", "FAULT", "ESTOP", "SHUTDOWN")

#: edges (µs) of the live histogram's bins: 1-2-5 steps from 10 µs to 100 ms, then overflow
HIST_EDGES_US: tuple[float, ...] = (
    0.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0, 1e3, 2e3, 5e3, 1e4, 2e4, 5e4, 1e5, math.inf,
)  # fmt: skip

#: statistics shown in the "fixtures, tool and owner" panel when a daemon reports them (the
#: master's virtual fixtures today; the owner of the robot and the tool's force and position as
#: other work adds them), looked for at the top level and in the controller's statistics
HIGHLIGHT_KEYS = (
    "owner",
    "fixtures",
    "fixture_contacts",
    "fixture_force_n",
    "force_n",
    "tool_mm",
    "clutch",
    "master_run",
    "master_clutch",
)


def _vec(value: Any) -> list[float] | None:
    """A 3-vector of numbers from the statistics, else None."""
    if (
        isinstance(value, list)
        and len(value) == 3
        and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    ):
        return [float(v) for v in value]
    return None


def _mag(v: list[float] | None) -> float | None:
    return None if v is None else round(math.sqrt(sum(c * c for c in v)), 4)


def forces_of(stats: dict[str, Any], previous: dict[str, Any] | None = None) -> dict[str, Any]:
    """The forces panel from one ``GetStats`` answer (the module docstring): ``contact`` for a
    slave with a force source, ``hand`` for a master that displays one; empty when neither.
    ``previous`` is the last answer's panel: the passivity controller counts as engaged when
    its active ticks grew since then."""
    ctrl = stats.get("controller")
    if not isinstance(ctrl, dict):
        return {}
    out: dict[str, Any] = {}
    force = ctrl.get("force")
    if isinstance(force, dict):  # teleop-slave: the force on its instrument
        f = _vec(force.get("force_n"))
        out["contact"] = {
            "force_n": f,
            "magnitude_n": _mag(f),
            "source": force.get("used") or "none",
            "sources": force.get("sources"),
            "tared": force.get("tared"),
        }
    displayed = _vec(ctrl.get("force_n"))
    if displayed is not None and "feedback_n" in ctrl:  # teleop-master: the force on the hand
        feedback = _vec(ctrl.get("feedback_n"))
        raw = ctrl.get("passivity")
        pas: dict[str, Any] = raw if isinstance(raw, dict) else {}
        active = pas.get("active_ticks")
        before = ((previous or {}).get("hand") or {}).get("passivity") or {}
        engaged = (
            isinstance(active, int)
            and isinstance(before.get("active_ticks"), int)
            and active > before["active_ticks"]
        )
        out["hand"] = {
            "displayed_n": displayed,
            "displayed_magnitude_n": _mag(displayed),
            "feedback_n": feedback,
            "feedback_magnitude_n": _mag(feedback),
            "fixture_n": _vec(ctrl.get("fixture_force_n")),
            "force_feedback": ctrl.get("force_feedback"),
            "force_scale": ctrl.get("force_scale"),
            "clamped_ticks": ctrl.get("force_clamped_ticks"),
            "passivity": {
                "on": pas.get("on"),
                "engaged": engaged,
                "active_ticks": active,
                "energy_mj": pas.get("energy_mj"),
                "dissipated_mj": pas.get("dissipated_mj"),
                "damping": pas.get("damping"),
            },
        }
    return out


def _text(value: Any) -> str | None:
    return value if isinstance(value, str) else None


def drives_of(stats: dict[str, Any]) -> list[dict[str, Any]] | None:
    """The drives panel from one ``GetStats`` answer (the module docstring): per driver that
    reports nodes (occ/drivers/cia402.py's ``stats``), its bus load, its last fault and each
    node's state and last EMCY; None when no driver does."""
    drivers = stats.get("drivers")
    if not isinstance(drivers, dict):
        return None
    out = []
    for name, drv in drivers.items():
        if not isinstance(drv, dict) or not isinstance(drv.get("nodes"), dict):
            continue
        nodes = []
        for joint, node in drv["nodes"].items():
            if not isinstance(node, dict):
                continue
            raw = node.get("last_emcy")
            emcy = raw if isinstance(raw, dict) else None
            nodes.append({
                "joint": str(joint),
                "node_id": node.get("node_id"),
                "state": _text(node.get("cia402")),
                "statusword": _text(node.get("statusword")),
                "nmt": _text(node.get("nmt")),
                "last_emcy": None if emcy is None else {
                    "code": _text(emcy.get("code")),
                    "meaning": _text(emcy.get("meaning")),
                    "register": _text(emcy.get("register")),
                },
                "emcys": node.get("emcys"),
            })  # fmt: skip
        load = drv.get("bus_load")
        out.append({
            "driver": str(name),
            "bus_load": load if isinstance(load, int | float) and not isinstance(load, bool)
            else None,
            "last_fault": _text(drv.get("last_fault")),
            "nodes": nodes,
        })  # fmt: skip
    return out or None


def emcy_events(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    """A line for each node whose EMCY count grew between two answers, with its last EMCY."""
    lines = []
    before = {d["driver"]: d for d in drives_of(old) or []}
    for drv in drives_of(new) or []:
        prev = {n["joint"]: n for n in (before.get(drv["driver"]) or {"nodes": []})["nodes"]}
        for node in drv["nodes"]:
            count, was = node["emcys"], (prev.get(node["joint"]) or {}).get("emcys")
            if not isinstance(count, int) or not isinstance(was, int) or count <= was:
                continue
            emcy = node["last_emcy"] or {}
            what = f"{emcy.get('code')} ({emcy.get('meaning')})" if emcy else "error reset"
            lines.append(
                f"{drv['driver']}: node {node['node_id']} (joint {node['joint']}): EMCY {what}, "
                f"+{count - was} since the last poll; now {node['state']}"
            )
    return lines


#: the loss monitor's counters whose growth between two answers is logged as an event
LOSS_EVENTS = ("holds", "resumes", "trips", "lost_total")

ALERT_LOG = 200


def cell_of(stats: dict[str, Any]) -> dict[str, Any] | None:
    """The cell panel from one ``GetStats`` answer (occ/core/cell.py's ``cell``): the policy,
    this member's own stop, each member's state and when it was last heard, what holds this
    one and the last stop with its origin; None for a daemon in no cell or a malformed one."""
    cell = stats.get("cell")
    if not isinstance(cell, dict) or not isinstance(cell.get("members"), dict):
        return None
    members = []
    for name, m in cell["members"].items():
        if not isinstance(m, dict):
            continue
        members.append({
            "name": str(name),
            "state": m.get("state"),
            "heard_ms_ago": m.get("heard_ms_ago"),
            "cause": m.get("cause") or "",
            "origin": m.get("origin") or "",
            "left": bool(m.get("left")),
            "chain_ok": m.get("chain_ok"),
        })  # fmt: skip
    last = cell.get("last_stop") if isinstance(cell.get("last_stop"), dict) else None
    raw = cell.get("latched")
    latched: dict[Any, Any] = raw if isinstance(raw, dict) else {}
    return {
        "name": cell.get("name"),
        "me": cell.get("me"),
        "policy": cell.get("policy"),
        "left": bool(cell.get("left")),
        "cause": cell.get("cause") or "",
        "origin": cell.get("origin") or "",
        "members": members,
        "latched": {str(k): str(v) for k, v in latched.items()},
        "last_stop": last,
    }


def _number(value: Any) -> float:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else 0.0


def rebin(buckets: dict[int, int], edges: tuple[float, ...] = HIST_EDGES_US) -> list[int]:
    """Counts of raw histogram buckets (``{index: count}``) in the bins ``edges`` (a bucket
    goes to the bin holding its lower bound)."""
    counts = [0] * (len(edges) - 1)
    for idx, n in buckets.items():
        lo, _ = bucket_bounds(idx)
        # the few edges: a linear scan is as fast as bisect here
        for b in range(len(counts)):
            if lo < edges[b + 1]:
                counts[b] += n
                break
    return counts


def parse_state_text(text: str) -> dict[str, str]:
    """``"state=RUNNING; alert=...; reason=..."`` (GetState's answer) as a dict."""
    out: dict[str, str] = {}
    for part in text.split("; "):
        key, sep, value = part.partition("=")
        if sep and key.strip() in ("state", "alert", "reason"):
            out[key.strip()] = value.strip()
    return out


@dataclass
class LogEntry:
    """One line of a daemon's log in the console."""

    t: float  # wall time (the daemon's timestamp where it gave one)
    kind: str  # "state", "alert", "loss", "reply", "link"
    name: str  # the STATUS name (state or alert kind), the command, or "LINK"
    text: str
    code: int = 0

    def as_dict(self) -> dict[str, Any]:
        return {"t": self.t, "kind": self.kind, "name": self.name, "text": self.text,
                "code": self.code}  # fmt: skip


class DaemonView:
    """One daemon as the console sees it (module docstring)."""

    def __init__(self, ident: str, host: str, port: int, *, window_s: float = 10.0) -> None:
        self.id = ident
        self.host = host
        self.port = port
        self.window_s = window_s
        self.lock = threading.Lock()
        self.name = ""
        self.connected = False
        self.connects = 0
        self.link_error = ""
        self.link_since = 0.0
        self.state = ""
        self.state_since = 0.0
        self.reason = ""
        self.last_alert = ""
        self.stats: dict[str, Any] = {}
        #: the forces panel (:func:`forces_of`) of the last answer
        self.forces: dict[str, Any] = {}
        self.stats_at = 0.0  # wall time of the last answer
        self.stats_answers = 0
        self.restarts = 0
        self.rates: dict[str, dict[str, float]] = {}
        self.log: deque[LogEntry] = deque(maxlen=ALERT_LOG)
        self.last_reply: dict[str, Any] | None = None
        self.unauthenticated = 0
        self.bad_stats = 0
        # (monotonic time, raw lateness buckets) of recent answers: the live histogram's window
        self._hist: deque[tuple[float, dict[int, int]]] = deque()
        self._hist_view: dict[str, Any] | None = None  # histogram() of the answers above
        self._prev: tuple[float, dict[str, Any]] | None = None

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    # ------------------------------------------------------------------ link events
    def on_connect(self, now: float) -> None:
        self.connected = True
        self.connects += 1
        self.link_error = ""
        self.link_since = now
        self._log(now, "link", "LINK", f"connected to {self.address}")

    def on_disconnect(self, now: float, reason: str) -> None:
        if self.connected:
            self._log(now, "link", "LINK", f"connection lost: {reason}")
        self.connected = False
        self.link_error = reason
        self.link_since = now
        # whatever comes back may be a new daemon: its counters start again
        self._prev = None
        self._hist.clear()
        self._hist_view = None
        self.rates = {}

    def on_link_error(self, reason: str) -> None:
        self.link_error = reason

    # ------------------------------------------------------------------ daemon messages
    def on_status(self, t: float, device: str, code: int, name: str, text: str) -> None:
        """A STATUS from the daemon: the greeting, a state change, or an alert."""
        if device and not self.name:
            self.name = device
        if not name and not text:
            return  # a keep-alive
        if name in STATES:
            if name != self.state:
                self.state_since = t
            self.state = name
            # a transition reads "OLD -> NEW: reason"; the greeting "slave is READY"
            if "->" in text:
                _, _, reason = text.partition(": ")
                self.reason = reason
                self._log(t, "state", name, text, code)
            return
        self._log(t, "alert", name, text, code)
        if name in ("ALERT", "SUPERVISOR", "WATCHDOG"):
            self.last_alert = text

    def on_state_reply(self, t: float, text: str) -> None:
        """GetState's answer: the state, the alert behind it and the reason of the last
        change (asked on connecting: a late joiner must not wait for the next change)."""
        parts = parse_state_text(text)
        state = parts.get("state", "")
        if state in STATES:
            if state != self.state:
                self.state_since = t
            self.state = state
        self.reason = parts.get("reason", self.reason)
        self.last_alert = parts.get("alert", "")

    def on_reply(self, t: float, command: str, ok: bool, text: str) -> None:
        self.last_reply = {"t": t, "command": command, "ok": ok, "message": text}
        self._log(t, "reply", command, f"{'SUCCESS' if ok else 'FAIL'}: {text}")

    def on_stats(self, t: float, mono: float, stats: dict[str, Any]) -> None:
        """One GetStats answer (``Format="json"``, with the lateness buckets)."""
        raw = stats.pop("lateness_buckets", None)
        buckets: dict[int, int] | None = None
        if isinstance(raw, dict):
            try:
                buckets = {int(k): int(v) for k, v in raw.items()}
                for idx in buckets:
                    bucket_bounds(idx)  # a ValueError for an index out of range
            except (TypeError, ValueError):
                self.bad_stats += 1
                buckets = None
        prev = self._prev
        if prev is not None and _number(stats.get("ticks")) < _number(prev[1].get("ticks")):
            # the tick counter went down: a new daemon behind the same port
            self.restarts += 1
            self._log(t, "link", "LINK", "the daemon restarted (its counters started again)")
            prev = None
            self._hist.clear()
            self._hist_view = None
            self.rates = {}
        if isinstance(stats.get("robot"), str):
            self.name = stats["robot"]
        state = stats.get("state")
        if isinstance(state, str) and state in STATES and state != self.state:
            self.state, self.state_since = state, t
        if isinstance(stats.get("last_alert"), str):
            self.last_alert = stats["last_alert"]
        if prev is not None:
            self._derive(t, mono - prev[0], prev[1], stats)
        self._prev = (mono, stats)
        self.stats = stats
        self.forces = forces_of(stats, self.forces if prev is not None else None)
        self.stats_at = t
        self.stats_answers += 1
        if buckets is not None:
            self._hist_view = None
            self._hist.append((mono, buckets))
            # keep one answer older than the window: the window's start
            while len(self._hist) > 2 and self._hist[1][0] <= mono - self.window_s:
                self._hist.popleft()

    def _derive(self, t: float, dt: float, old: dict[str, Any], new: dict[str, Any]) -> None:
        if dt <= 0.0:
            return
        rates: dict[str, dict[str, float]] = {}
        old_if = old.get("interfaces") or {}
        for name, itf in (new.get("interfaces") or {}).items():
            before = old_if.get(name)
            if not isinstance(itf, dict) or not isinstance(before, dict):
                continue
            rates[name] = {
                key: max(0.0, (_number(itf.get(key)) - _number(before.get(key))) / dt)
                for key in ("received", "sent", "dropped", "refused", "malformed")
            }
        self.rates = rates
        loss_new, loss_old = new.get("loss"), old.get("loss")
        if isinstance(loss_new, dict) and isinstance(loss_old, dict):
            grew = {
                key: int(_number(loss_new.get(key)) - _number(loss_old.get(key)))
                for key in LOSS_EVENTS
            }
            grew = {k: v for k, v in grew.items() if v > 0}
            if grew:
                what = ", ".join(f"{k} +{v}" for k, v in grew.items())
                totals = ", ".join(f"{k} {int(_number(loss_new.get(k)))}" for k in grew)
                self._log(t, "loss", "LOSS", f"{what} in {dt:.1f} s (totals: {totals})")
        for line in emcy_events(old, new):
            self._log(t, "alert", "EMCY", line)

    def _log(self, t: float, kind: str, name: str, text: str, code: int = 0) -> None:
        self.log.append(LogEntry(t, kind, name, text, code))

    # ------------------------------------------------------------------ views
    def histogram(self) -> dict[str, Any] | None:
        """The live lateness histogram: the last ``window_s`` seconds (since the daemon's
        start until two answers are in)."""
        if not self._hist:
            return None
        if self._hist_view is None:  # once per answer, however often the page asks
            self._hist_view = self._histogram()
        return self._hist_view

    def _histogram(self) -> dict[str, Any]:
        t1, newest = self._hist[-1]
        t0, oldest = self._hist[0]
        if len(self._hist) > 1:
            diff = {i: n - oldest.get(i, 0) for i, n in newest.items()}
            diff = {i: n for i, n in diff.items() if n > 0}
            span: float | None = t1 - t0
        else:
            diff, span = newest, None
        h = Histogram.from_buckets(diff)
        summary = {k: round(v, 1) for k, v in h.summary().items()} if h.count else {}
        return {
            "window_s": None if span is None else round(span, 2),
            "edges_us": [e if math.isfinite(e) else None for e in HIST_EDGES_US],
            "counts": rebin(diff),
            "ticks": h.count,
            "summary": summary,
        }

    def highlights(self) -> dict[str, Any]:
        found: dict[str, Any] = {}
        ctrl = self.stats.get("controller")
        for source in (self.stats, ctrl if isinstance(ctrl, dict) else {}):
            for key in HIGHLIGHT_KEYS:
                if key in source and key not in found:
                    found[key] = source[key]
        return found

    def snapshot(self, now: float | None = None) -> dict[str, Any]:
        """Everything the page shows of this daemon, JSON-ready."""
        now = time.time() if now is None else now
        s = self.stats
        streams = []
        for name, itf in (s.get("interfaces") or {}).items():
            if not isinstance(itf, dict):
                continue
            rate = self.rates.get(name, {})
            streams.append({
                "interface": name,
                "transport": itf.get("transport"),
                "role": itf.get("role"),
                "peers": itf.get("peers"),
                "received": itf.get("received"),
                "sent": itf.get("sent"),
                "dropped": itf.get("dropped"),
                "refused": itf.get("refused"),
                "rx_per_s": round(rate["received"], 1) if "received" in rate else None,
                "tx_per_s": round(rate["sent"], 1) if "sent" in rate else None,
                "types": itf.get("streams") or {},
            })  # fmt: skip
        loop = {
            key: s.get(key)
            for key in (
                "rate_hz",
                "ticks",
                "duration_s",
                "cpu_percent",
                "overruns",
                "late_over_1ms",
                "missed_ticks",
                "lateness_us",
                "period_us",
                "compute_us",
                "realtime",
            )  # fmt: skip
            if key in s
        }
        return {
            "id": self.id,
            "address": self.address,
            "name": self.name or self.address,
            "connected": self.connected,
            "link": {
                "connects": self.connects,
                "error": self.link_error,
                "since": self.link_since,
                "restarts": self.restarts,
                "unauthenticated": self.unauthenticated,
                "bad_stats": self.bad_stats,
            },
            "state": self.state or None,
            "state_since": self.state_since or None,
            "reason": self.reason,
            "last_alert": self.last_alert,
            "stats_age_s": round(now - self.stats_at, 2) if self.stats_at else None,
            "loop": loop,
            "histogram": self.histogram(),
            "streams": streams,
            "loss": s.get("loss"),
            "watchdog": s.get("watchdog"),
            "supervisor": s.get("supervisor"),
            "commands": s.get("commands"),
            "highlights": self.highlights(),
            "forces": self.forces or None,
            "cell": cell_of(s),
            "drives": drives_of(s),
            "controller": s.get("controller"),
            "log": [e.as_dict() for e in self.log],
            "last_reply": self.last_reply,
        }
