"""The console against a robot's real operator interface on 127.0.0.1, and its HTTP API
served by uvicorn: what a script or the page gets, and what the daemon is sent."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("starlette", reason="pip install -e .[console] (the test extra has it)")
pytest.importorskip("httpx", reason="pip install -e .[test]")

import httpx  # noqa: E402

from igtl.auth import load_key  # noqa: E402
from igtl.transport import TCPServer  # noqa: E402
from occ.core.safety import RobotState  # noqa: E402
from occ_console.link import CommandTimeout, Console  # noqa: E402

from .conftest import TickedRobot, WebServer, free_port, poll  # noqa: E402

JSON = {"Content-Type": "application/json"}


@pytest.fixture
def served(slave: TickedRobot) -> Iterator[tuple[TickedRobot, Console, WebServer]]:
    console = Console([("127.0.0.1", slave.port)], poll_hz=10.0)
    web = WebServer(console)  # its lifespan starts and stops the console
    try:
        yield slave, console, web
    finally:
        web.stop()


def daemons(web: WebServer) -> list[dict[str, Any]]:
    r = httpx.get(f"{web.url}/api/daemons")
    assert r.status_code == 200
    return list(r.json())


def test_api_shows_state_stats_and_histogram(
    served: tuple[TickedRobot, Console, WebServer],
) -> None:
    slave, _, web = served
    d = poll(lambda: next((d for d in daemons(web) if d["stats_age_s"] is not None
                           and d["histogram"] and d["histogram"]["window_s"]), None))  # fmt: skip
    assert d, daemons(web)
    assert d["connected"] and d["name"] == "slave" and d["state"] == "READY"
    assert d["address"] == f"127.0.0.1:{slave.port}"
    assert d["loop"]["rate_hz"] == 1000.0
    names = {s["interface"]: s for s in d["streams"]}
    assert set(names) == {"operator", "master"}
    assert names["operator"]["rx_per_s"] > 0  # our own polls, measured between two answers
    assert d["loss"] is not None and d["loss"]["holds"] == 0
    h = d["histogram"]
    assert len(h["counts"]) == len(h["edges_us"]) - 1 and h["edges_us"][-1] is None
    # ticked by the test, this robot's loop statistics are empty (the real daemon's are not:
    # test_page.py); the bins add up to the window's ticks all the same
    assert sum(h["counts"]) == h["ticks"]
    assert "master_run" in d["highlights"]  # the teleop-slave controller reports it
    assert any(e["kind"] == "link" and "connected" in e["text"] for e in d["log"])
    one = httpx.get(f"{web.url}/api/daemons/0").json()
    assert one["id"] == "0" and one["name"] == "slave"
    assert httpx.get(f"{web.url}/api/daemons/7").status_code == 404


def test_buttons_change_the_state(served: tuple[TickedRobot, Console, WebServer]) -> None:
    slave, _, web = served
    assert poll(lambda: daemons(web)[0]["state"] == "READY")
    r = httpx.post(f"{web.url}/api/daemons/0/Enable", headers=JSON)
    assert r.status_code == 200, r.text
    assert r.json() == {"command": "Enable", "ok": True, "message": "READY -> ENABLED"}
    assert slave.robot.state_machine.state is RobotState.ENABLED
    # the state change reaches the console as the daemon's STATUS, with its cause
    d = poll(lambda: next((d for d in daemons(web) if d["state"] == "ENABLED"), None))
    assert d and d["reason"] == "operator Enable"
    assert any(e["kind"] == "state" and e["name"] == "ENABLED" for e in d["log"])
    assert any(e["kind"] == "reply" and e["name"] == "Enable" for e in d["log"])
    # E-Stop, then what the daemon refuses: its reason comes back with 409
    assert httpx.post(f"{web.url}/api/daemons/0/estop", headers=JSON).status_code == 200
    assert poll(lambda: daemons(web)[0]["state"] == "ESTOP")
    r = httpx.post(f"{web.url}/api/daemons/0/Run", headers=JSON)
    assert r.status_code == 409 and not r.json()["ok"] and "ESTOP" in r.json()["message"]
    assert slave.robot.state_machine.state is RobotState.ESTOP
    assert httpx.post(f"{web.url}/api/daemons/0/Reset", headers=JSON).json()["ok"]
    assert poll(lambda: daemons(web)[0]["state"] == "READY")


def test_api_refuses_what_it_must(served: tuple[TickedRobot, Console, WebServer]) -> None:
    slave, _, web = served
    assert poll(lambda: daemons(web)[0]["connected"])
    # not a button: nothing is sent
    assert httpx.post(f"{web.url}/api/daemons/0/GetStats", headers=JSON).status_code == 404
    assert httpx.post(f"{web.url}/api/daemons/9/Enable", headers=JSON).status_code == 404
    # a form post (what another site's page could send without asking) is refused
    r = httpx.post(f"{web.url}/api/daemons/0/Enable", content=b"x", headers={
        "Content-Type": "application/x-www-form-urlencoded"})  # fmt: skip
    assert r.status_code == 415
    # a request for another host name (DNS rebinding) is refused
    assert httpx.get(f"{web.url}/api/daemons", headers={"Host": "evil.example"}).status_code == 400
    assert slave.robot.state_machine.state is RobotState.READY


def test_server_sent_events_carry_the_daemons(
    served: tuple[TickedRobot, Console, WebServer],
) -> None:
    _, _, web = served
    got: list[Any] = []
    with httpx.stream("GET", f"{web.url}/api/events", timeout=10.0) as r:
        assert r.headers["content-type"].startswith("text/event-stream")
        event = ""
        for line in r.iter_lines():
            if line.startswith("event: "):
                event = line[7:]
            elif line.startswith("data: ") and event == "daemons":
                got = json.loads(line[6:])
                if got[0]["state"] == "READY":
                    break
    assert got and got[0]["name"] == "slave"


def test_unreachable_daemon_is_shown_and_commands_get_503(slave: TickedRobot) -> None:
    nobody = free_port()  # nothing listens there
    console = Console([("127.0.0.1", slave.port), ("127.0.0.1", nobody)], poll_hz=10.0)
    web = WebServer(console)
    try:
        assert poll(lambda: daemons(web)[0]["connected"])
        down = daemons(web)[1]
        assert not down["connected"] and down["state"] is None
        assert poll(lambda: daemons(web)[1]["link"]["error"]), "the connect failure is shown"
        r = httpx.post(f"{web.url}/api/daemons/1/Enable", headers=JSON)
        assert r.status_code == 503 and not r.json()["ok"]
    finally:
        web.stop()


def test_console_reconnects_to_a_restarted_daemon() -> None:
    first = TickedRobot()
    port = first.port
    console = Console([("127.0.0.1", port)], poll_hz=10.0).start()
    second = None
    try:
        view = console.links[0].view
        assert poll(lambda: view.stats_answers >= 2)
        first.stop()
        assert poll(lambda: not view.connected)
        assert console.snapshot()[0]["link"]["error"]
        second = TickedRobot(port=port)  # the daemon restarted on its port
        assert poll(lambda: view.connected and view.connects == 2, 15.0)
        answers = view.stats_answers
        assert poll(lambda: view.stats_answers > answers + 1)
        assert view.state == "READY"
    finally:
        console.stop()
        if second is not None:
            second.stop()


def test_console_follows_each_answer_with_a_keepalive(slave: TickedRobot) -> None:
    """The daemon closes a client whose advertised receive window stays short by
    ``unread_limit_kib`` (16 KiB) for ``send_stall_timeout_s`` (5 s): one that does not read.
    The ACK of a long GetStats answer (15-30 KiB with the lateness buckets) can advertise a
    window short by that answer, read a moment later; without a newer segment from the console
    that stale window stood until the next poll, and the real slave closed the console every
    10-40 s (``evicted_not_reading``; occ_console/link.py). So the console sends a keep-alive (an
    empty STATUS, only counted by the daemon's interface thread) after every answer."""
    console = Console([("127.0.0.1", slave.port)], poll_hz=10.0).start()
    try:
        view = console.links[0].view
        assert poll(lambda: view.stats_answers >= 5)
        console.stop()  # no more polls: the counts below are final
        answers = view.stats_answers
        itf = slave.robot.interfaces["operator"]
        assert poll(lambda: itf.stats()["keepalive"] >= answers, 5.0), (itf.stats(), answers)
        assert itf.stats()["keepalive"] == answers
        assert itf.stats()["evicted_not_reading"] == 0
    finally:
        console.stop()


def test_signed_operator_link(tmp_path: Path) -> None:
    """An operator interface with a shared key: the console with the key is served; one
    without it is refused (counted by the daemon), and one with another key counts the
    daemon's messages as unauthenticated instead of believing them."""
    key = tmp_path / "operator.key"
    key.write_text("a shared secret of the ward, 32 bytes\n")
    robot = TickedRobot(extra=f"header_version: 2, auth_key_file: {key}")
    consoles = {
        "right": Console(
            [("127.0.0.1", robot.port)], poll_hz=10.0, auth_key=load_key(key.read_text())
        ),  # fmt: skip
        "none": Console([("127.0.0.1", robot.port)], poll_hz=10.0),
        "wrong": Console(
            [("127.0.0.1", robot.port)], poll_hz=10.0, auth_key=b"another key, at least 16 bytes"
        ),  # fmt: skip
    }
    try:
        for c in consoles.values():
            c.start()
        right = consoles["right"].links[0]
        assert poll(lambda: right.view.stats_answers >= 2 and right.view.state == "READY")
        assert right.command("Enable").result(5.0)["ok"]
        assert poll(lambda: right.view.state == "ENABLED")
        # the daemon's broadcast of that change, signed with its key, is not believed
        wrong = consoles["wrong"].links[0].view
        assert poll(lambda: wrong.unauthenticated >= 2)
        assert wrong.stats_answers == 0 and wrong.state == ""
        itf = robot.robot.interfaces["operator"]
        assert poll(lambda: itf.stats()["unauthenticated"] >= 4)  # GetState, GetStats ...
        assert consoles["none"].links[0].view.stats_answers == 0
        # the daemon greets a new client before it has spoken version 2, so in version 1,
        # which has no metadata and so no tag: the greeting is the one message not believed
        assert right.view.unauthenticated <= 1
    finally:
        for c in consoles.values():
            c.stop()
        robot.stop()


def test_a_silent_daemon_is_not_sent_a_queue_of_requests() -> None:
    """A daemon that answers nothing (stuck worker, overloaded): one GetStats outstanding at a
    time, however fast the console polls; a command fails after its timeout."""
    got: list[Any] = []
    server = TCPServer("127.0.0.1", 0, on_message=lambda peer, msg: got.append(msg)).start()
    console = Console([("127.0.0.1", server.address[1])], poll_hz=10.0).start()
    try:
        link = console.links[0]
        assert poll(lambda: link.view.connected)
        fut = link.command("Enable", timeout=0.3)
        with pytest.raises(CommandTimeout):
            fut.result(5.0)
        time.sleep(1.0)  # ten polls' worth: still the one request
        names = [getattr(m, "command_name", "") for m in got]
        assert names.count("GetStats") == 1, names
        assert names.count("GetState") == 1 and names.count("Enable") == 1
        snap = console.snapshot()[0]
        assert snap["link"]["stats_asked"] == 1
        assert any(e["kind"] == "link" for e in snap["log"])
    finally:
        console.stop()
        server.stop()


def test_event_stream_repeats_the_snapshot_when_nothing_changes() -> None:
    """A daemon that went quiet changes nothing the console hears of; the page must still see
    the age of its statistics grow, so the stream sends the snapshot at least every second."""
    console = Console([("127.0.0.1", free_port())], poll_hz=10.0)  # nobody there
    web = WebServer(console)
    try:
        events = 0
        with httpx.stream("GET", f"{web.url}/api/events", timeout=10.0) as r:
            for line in r.iter_lines():
                if line.startswith("data: "):
                    events += 1
                    if events == 3:
                        break
        assert events == 3
    finally:
        web.stop()
