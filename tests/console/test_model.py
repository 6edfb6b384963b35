"""What the console derives from a daemon's messages (pure: no sockets, no threads)."""

from __future__ import annotations

import math
from typing import Any

import pytest

from occ.core.stats import Histogram, bucket_bounds
from occ_console.link import parse_endpoint
from occ_console.model import HIST_EDGES_US, DaemonView, parse_state_text, rebin


def stats(ticks: int, received: int, sent: int = 0, **extra: Any) -> dict[str, Any]:
    s: dict[str, Any] = {
        "ticks": ticks,
        "robot": "slave",
        "state": "RUNNING",
        "last_alert": "",
        "interfaces": {"master": {"received": received, "sent": sent, "dropped": 0}},
    }
    s.update(extra)
    return s


def buckets_of(values: list[float]) -> dict[str, int]:
    h = Histogram()
    for v in values:
        h.add(v)
    return {str(k): v for k, v in h.buckets().items()}  # as JSON carries them


def test_bucket_bounds_match_the_histogram() -> None:
    for v in (0.0, 0.05, 99.95, 100.0, 999.5, 1000.0, 12345.0, 999_999.0, 5e6):
        (idx,) = buckets_of([v]).keys()
        lo, hi = bucket_bounds(int(idx))
        assert lo <= v < hi or (v >= 1e6 and hi == math.inf), (v, lo, hi)
    with pytest.raises(ValueError):
        bucket_bounds(-1)
    with pytest.raises(ValueError):
        bucket_bounds(10**6)


def test_rebin_puts_each_value_in_its_bin() -> None:
    values = [5.0, 15.0, 15.5, 150.0, 999.0, 1500.0, 60_000.0, 2e6]
    counts = rebin({int(k): v for k, v in buckets_of(values).items()})
    assert sum(counts) == len(values)
    for v in values:
        b = next(i for i in range(len(counts)) if v < HIST_EDGES_US[i + 1])
        assert counts[b] >= 1, (v, b, counts)
    assert counts[1] == 2  # 15.0 and 15.5 in [10, 20)
    assert counts[-1] == 1  # 2 s: the overflow bin


def test_status_messages_set_state_cause_and_alerts() -> None:
    v = DaemonView("0", "127.0.0.1", 18947)
    v.on_status(1.0, "slave", 1, "READY", "slave is READY")  # the greeting
    assert (v.name, v.state, v.reason, len(v.log)) == ("slave", "READY", "", 0)
    v.on_status(2.0, "slave", 1, "RUNNING", "ENABLED -> RUNNING: operator Run")
    assert (v.state, v.reason, v.state_since) == ("RUNNING", "operator Run", 2.0)
    v.on_status(3.0, "slave", 0, "", "")  # a keep-alive: nothing to say
    v.on_status(4.0, "slave", 14, "STREAM", "stream master: stream back after 8.0 ms")
    assert v.state == "RUNNING" and v.last_alert == ""
    v.on_status(5.0, "slave", 10, "ALERT", "packet loss on master: 3 consecutive")
    assert v.last_alert == "packet loss on master: 3 consecutive"
    v.on_status(5.0, "slave", 11, "STOPPED", "RUNNING -> STOPPED: packet loss on master")
    assert (v.state, v.reason) == ("STOPPED", "packet loss on master")
    kinds = [(e.kind, e.name) for e in v.log]
    assert kinds == [("state", "RUNNING"), ("alert", "STREAM"), ("alert", "ALERT"),
                     ("state", "STOPPED")]  # fmt: skip


def test_get_state_reply_is_parsed() -> None:
    assert parse_state_text("state=STOPPED; alert=loss: x=3; reason=operator Stop") == {
        "state": "STOPPED", "alert": "loss: x=3", "reason": "operator Stop"}  # fmt: skip
    v = DaemonView("0", "h", 1)
    v.on_state_reply(1.0, "state=FAULT; alert=driver sim: boom; reason=driver sim: boom")
    assert (v.state, v.last_alert, v.reason) == ("FAULT", "driver sim: boom", "driver sim: boom")
    v.on_state_reply(2.0, "state=NONSENSE")
    assert v.state == "FAULT"


def test_rates_loss_events_and_restart() -> None:
    v = DaemonView("0", "h", 1)
    loss0 = {"holds": 2, "resumes": 2, "trips": 0, "lost_total": 0}
    v.on_stats(10.0, 100.0, stats(1000, 500, loss=loss0))
    assert v.rates == {}  # one answer: no rate yet
    loss1 = {"holds": 5, "resumes": 4, "trips": 0, "lost_total": 3}
    v.on_stats(10.5, 100.5, stats(1500, 750, sent=10, loss=loss1))
    assert v.rates["master"]["received"] == pytest.approx(500.0)
    assert v.rates["master"]["sent"] == pytest.approx(20.0)
    (event,) = [e for e in v.log if e.kind == "loss"]
    assert event.text.startswith("holds +3, resumes +2, lost_total +3 in 0.5 s")
    snap = v.snapshot(11.0)
    assert snap["streams"][0]["rx_per_s"] == 500.0 and snap["stats_age_s"] == 0.5
    # the tick counter went down: a new daemon; no rate from the old one's counters
    v.on_stats(11.0, 101.0, stats(200, 100, loss=loss0))
    assert v.restarts == 1 and v.rates == {}
    assert any("restarted" in e.text for e in v.log)
    v.on_stats(11.5, 101.5, stats(700, 300, loss=loss0))
    assert v.rates["master"]["received"] == pytest.approx(400.0)


def test_live_histogram_is_the_window_not_the_total() -> None:
    v = DaemonView("0", "h", 1, window_s=10.0)
    early = [20.0] * 1000
    v.on_stats(0.0, 0.0, stats(1000, 0, lateness_buckets=buckets_of(early)))
    h = v.histogram()
    assert h is not None and h["window_s"] is None and h["ticks"] == 1000  # since start
    for k in range(1, 31):  # 30 s, two answers a second: 500 ticks each, late by 3 ms later on
        late = 3000.0 if k > 20 else 20.0
        total = early + [20.0] * 500 * min(k, 20) + [late] * 500 * max(0, k - 20)
        v.on_stats(k, k, stats(1000 + 500 * k, 0, lateness_buckets=buckets_of(total)))
    h = v.histogram()
    assert h is not None
    assert h["window_s"] == pytest.approx(10.0, abs=1.0)
    assert h["ticks"] == pytest.approx(5000, abs=500)  # the window's ticks only
    late_bin = next(i for i in range(len(h["counts"])) if 3000.0 < HIST_EDGES_US[i + 1])
    assert h["counts"][late_bin] == h["ticks"]  # the window holds only the late ticks
    assert h["summary"]["p50"] == pytest.approx(3000.0, rel=0.05)


def test_bad_buckets_are_counted_not_fatal() -> None:
    v = DaemonView("0", "h", 1)
    v.on_stats(0.0, 0.0, stats(1, 0, lateness_buckets={"x": 1}))
    v.on_stats(0.5, 0.5, stats(2, 0, lateness_buckets={"999999": 1}))
    assert v.bad_stats == 2 and v.histogram() is None
    assert v.snapshot()["name"] == "slave"


def test_highlights_found_wherever_the_daemon_puts_them() -> None:
    v = DaemonView("0", "h", 1)
    v.on_stats(0.0, 0.0, stats(1, 0, owner="console@ward", controller={
        "fixtures": 2, "fixture_force_n": [0.0, 1.5, 0.0], "tool_mm": [1, 2, 3],
        "seq": 9}))  # fmt: skip
    assert v.highlights() == {"owner": "console@ward", "fixtures": 2,
                              "fixture_force_n": [0.0, 1.5, 0.0], "tool_mm": [1, 2, 3]}  # fmt: skip


def test_disconnect_forgets_counters() -> None:
    v = DaemonView("0", "h", 1)
    v.on_connect(1.0)
    v.on_stats(1.0, 1.0, stats(100, 10))
    v.on_stats(1.5, 1.5, stats(600, 260))
    assert v.rates
    v.on_disconnect(2.0, "closed by peer")
    assert not v.connected and v.rates == {} and v.link_error == "closed by peer"
    v.on_connect(3.0)
    v.on_stats(3.0, 3.0, stats(50, 5))  # the new daemon: lower counters, not a "restart"
    assert v.restarts == 0 and v.connects == 2
    assert [e.text for e in v.log if e.kind == "link"] == [
        "connected to h:1", "connection lost: closed by peer", "connected to h:1"]  # fmt: skip


def test_parse_endpoint() -> None:
    assert parse_endpoint("127.0.0.1:18947") == ("127.0.0.1", 18947)
    assert parse_endpoint("[::1]:18947") == ("::1", 18947)
    for bad in ("18947", "host:", "host:x", ":1", "h:0", "h:70000"):
        with pytest.raises(ValueError):
            parse_endpoint(bad)


# ------------------------------------------------------------------------------ forces
def _get_stats(pair: Any, op: Any) -> dict[str, Any]:
    """A daemon's GetStats answer as the console asks it (JSON), through its operator port."""
    import json

    from occ_testkit.testing import wait_until

    before = len(op.messages("STRING", "STATS"))
    op.send_command("GetStats", '<Command Name="GetStats" Format="json" Histogram="lateness"/>')
    pair.step(1)  # the worker answers from its own thread
    assert wait_until(lambda: len(op.messages("STRING", "STATS")) > before, timeout=10.0)
    return dict(json.loads(op.messages("STRING", "STATS")[-1].string))


def test_forces_of_the_wall_pair() -> None:
    """The wall pair (occ_testkit.testing.SimPair: configs/master.yaml + configs/wall.yaml) pressing
    into the tissue: the slave's panel has its contact force, the master's the force on the
    hand, the slave's feedback and the passivity controller, from the daemons' own answers."""
    import yaml

    from occ_testkit.testing import CONFIGS, SimPair

    cfg = yaml.safe_load((CONFIGS / "wall.yaml").read_text())
    with SimPair(CONFIGS / "master.yaml", cfg, delay_ms=40.0) as p:
        p.start()
        views = {"slave": DaemonView("0", "127.0.0.1", 18947),
                 "master": DaemonView("1", "127.0.0.1", 18945)}  # fmt: skip
        ops = {"slave": p.s_op, "master": p.m_op}
        pressed = snap = None
        for k in range(40):  # 4 s, a poll every 0.1 s: the motion reaches the wall
            p.run_for(0.1)
            for name, view in views.items():
                view.on_stats(1000.0 + k * 0.1, k * 0.1, _get_stats(p, ops[name]))
            snap = {n: v.snapshot(now=1000.0 + k * 0.1) for n, v in views.items()}
            contact = snap["slave"]["forces"]["contact"]
            if contact["magnitude_n"] > 0.5 and pressed is None:
                pressed = snap
        master_ctl: Any = p.master.robot.controller.controllers[0]
        passivity = master_ctl.display.passivity.stats()
    assert pressed is not None
    contact = pressed["slave"]["forces"]["contact"]
    assert contact["source"] == "tissue" and contact["sources"] == ["tissue", "effort"]
    assert contact["force_n"][0] < -0.4  # the wall pushes back: -x
    assert contact["magnitude_n"] == pytest.approx(math.hypot(*contact["force_n"]), abs=1e-3)
    assert "hand" not in pressed["slave"]["forces"]
    hand = pressed["master"]["forces"]["hand"]
    assert "contact" not in pressed["master"]["forces"]
    assert hand["force_feedback"] is True and hand["force_scale"] == 1.0
    assert hand["feedback_magnitude_n"] > 0.3 and hand["displayed_magnitude_n"] > 0.3
    assert hand["fixture_n"] == [0.0, 0.0, 0.0]  # no fixture: the hand feels the slave only
    assert hand["passivity"]["on"] is True
    # 40 ms each way: the passivity controller works; the panel says when it did since the
    # last poll, and its counters are the controller's own
    assert snap is not None
    last = snap["master"]["forces"]["hand"]["passivity"]
    assert last["active_ticks"] == passivity["active_ticks"] > 0
    assert last["dissipated_mj"] == passivity["dissipated_mj"]


def test_forces_engaged_only_when_the_passivity_controller_acted_since_the_last_poll() -> None:
    def master(active: int, on: bool = True) -> dict[str, Any]:
        ctl = {"force_n": [0.0, 0.0, 1.0], "feedback_n": [0.0, 0.0, 1.0],
               "fixture_force_n": [0.0, 0.0, 0.0], "force_feedback": True,
               "passivity": {"on": on, "active_ticks": active, "energy_mj": 0.0,
                             "dissipated_mj": 0.5, "damping": 0.0}}  # fmt: skip
        return stats(100 + active, 0, controller=ctl)

    v = DaemonView("0", "h", 1)
    v.on_stats(1.0, 1.0, master(5))
    assert v.snapshot(1.0)["forces"]["hand"]["passivity"]["engaged"] is False  # first answer
    v.on_stats(2.0, 2.0, master(9))
    assert v.snapshot(2.0)["forces"]["hand"]["passivity"]["engaged"] is True
    v.on_stats(3.0, 3.0, master(9))
    assert v.snapshot(3.0)["forces"]["hand"]["passivity"]["engaged"] is False
    # a daemon without forces, or with statistics that are not numbers: no panel, no crash
    v = DaemonView("0", "h", 1)
    v.on_stats(1.0, 1.0, stats(1, 0, controller={"force": {"force_n": ["x", 1, 2]}}))
    assert v.snapshot(1.0)["forces"] == {
        "contact": {"force_n": None, "magnitude_n": None, "source": "none", "sources": None,
                    "tared": None},
    }  # fmt: skip
    v.on_stats(2.0, 2.0, stats(2, 0, controller={"seq": 1}))
    assert v.snapshot(2.0)["forces"] is None


# ------------------------------------------------------------------------------ cell
def test_the_cell_panel_shows_members_states_and_the_last_stops_origin() -> None:
    """Two members of a cell (tests/occ/test_cell.py's), one EStopped: the other's panel names
    the origin, what holds it, and the members as it hears them, from its own GetStats."""
    from tests.occ.test_cell import Cell

    c = Cell(2)
    try:
        c.run_all()
        c.command(0, "EStop")
        c.step(2)
        view = DaemonView("0", "127.0.0.1", 18947)
        view.on_stats(1000.0, 0.0, c.cell_stats_full(1))
        panel = view.snapshot(now=1000.0)["cell"]
        assert panel["name"] == "or1" and panel["me"] == "arm1" and panel["policy"] == "stop-all"
        assert panel["origin"] == "arm0" and "ESTOP" in panel["cause"]
        (m,) = panel["members"]
        assert m["name"] == "arm0" and m["state"] == "ESTOP" and m["heard_ms_ago"] is not None
        assert "arm0" in panel["latched"] and panel["last_stop"]["origin"] == "arm0"
    finally:
        c.close()
    assert DaemonView("1", "127.0.0.1", 1).snapshot(now=0.0)["cell"] is None
    bad = DaemonView("2", "127.0.0.1", 2)
    bad.on_stats(1.0, 0.0, {"cell": {"members": "nonsense"}})
    assert bad.snapshot(now=1.0)["cell"] is None


# ------------------------------------------------------------------------------ drives
def _as_sent(value: dict[str, Any]) -> dict[str, Any]:
    """What the console gets of a GetStats answer: JSON, as the daemon sends it."""
    import json

    return dict(json.loads(json.dumps(value)))


def test_the_drives_panel_shows_each_nodes_state_and_last_emcy() -> None:
    """The cia402 driver on three emulated nodes (tests/occ/test_cia402.py's rig), its
    statistics where GetStats carries them (``drivers.arm``): all OPERATION ENABLED, then an
    EMCY 0x2310 from node 2 faults the driver; the panel shows each node's CiA 402 and NMT
    state and pitch's EMCY with its meaning, and the log has a line for it."""
    from tests.occ.test_cia402 import Rig

    r = Rig([1, 2, 3], {})
    view = DaemonView("0", "127.0.0.1", 18947)
    try:
        r.enabled()
        r.ticks(20, r.here())  # a heartbeat from each (every 10 ms)
        view.on_stats(1000.0, 0.0, _as_sent(stats(100, 0, drivers={"arm": r.drv.stats()})))
        (arm,) = view.snapshot(now=1000.0)["drives"]
        assert arm["driver"] == "arm" and arm["bus_load"] == pytest.approx(0.57, abs=0.01)
        assert arm["last_fault"] is None
        assert [(n["joint"], n["node_id"]) for n in arm["nodes"]] == [
            ("yaw", 1), ("pitch", 2), ("insertion", 3)
        ]  # fmt: skip
        for n in arm["nodes"]:
            assert (n["state"], n["nmt"], n["last_emcy"], n["emcys"]) == (
                "OPERATION ENABLED", "OPERATIONAL", None, 0
            )  # fmt: skip
            assert n["statusword"] is not None and n["statusword"].startswith("0x")
        r.emu.inject_emcy(2, 0x2310)
        r.until_fault(20, lambda k: r.here())
        r.ticks(2)
        view.on_stats(1001.0, 1.0, _as_sent(stats(200, 0, drivers={"arm": r.drv.stats()})))
    finally:
        r.close()
    (arm,) = view.snapshot(now=1001.0)["drives"]
    nodes = {n["joint"]: n for n in arm["nodes"]}
    pitch = nodes["pitch"]
    assert pitch["state"] == "FAULT" and pitch["emcys"] == 1
    assert pitch["last_emcy"]["code"] == "0x2310"
    assert pitch["last_emcy"]["meaning"].startswith("continuous overcurrent")
    assert nodes["yaw"]["state"] != "OPERATION ENABLED" and nodes["yaw"]["last_emcy"] is None
    assert "node 2 (joint pitch): EMCY 0x2310" in arm["last_fault"]
    (line,) = [e for e in view.snapshot(now=1001.0)["log"] if e["name"] == "EMCY"]
    assert line["kind"] == "alert" and line["text"].startswith(
        "arm: node 2 (joint pitch): EMCY 0x2310 (continuous overcurrent"
    )
    assert line["text"].endswith("+1 since the last poll; now FAULT")


def test_the_drives_panel_is_empty_without_nodes_and_survives_nonsense() -> None:
    view = DaemonView("0", "h", 1)
    view.on_stats(1.0, 0.0, stats(1, 0, drivers={"sim": {"reads": 5, "writes": 5}}))
    assert view.snapshot(now=1.0)["drives"] is None  # the sim driver reports no nodes
    odd = {"arm": {"bus_load": True, "nodes": {"yaw": "x", "pitch": {"last_emcy": 7}}}}
    view.on_stats(2.0, 1.0, stats(2, 0, drivers=odd))
    (arm,) = view.snapshot(now=2.0)["drives"]
    assert arm["bus_load"] is None and [n["joint"] for n in arm["nodes"]] == ["pitch"]
    assert arm["nodes"][0]["last_emcy"] is None and arm["nodes"][0]["state"] is None
    view.on_stats(3.0, 2.0, stats(3, 0, drivers="nonsense"))
    assert view.snapshot(now=3.0)["drives"] is None
    assert not [e for e in view.log if e.name == "EMCY"]
