"""The cell link (occ/net/celllink.py) and the cell's judgement of what it brings: what a
heartbeat is on the wire, and what is refused (counted, never acted on)."""

from __future__ import annotations

import dataclasses
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import igtl
from igtl.messages.ndarray import NDArrayMessage
from occ.config import DaemonConfig
from occ.config.cell import CellConfig, CellMember, cell_problems
from occ.core.safety import RobotState
from occ.net.celllink import Beat, BeatError, CellLink, pack_beat, unpack_beat
from occ_testkit.testing import SimRobot, wait_until
from tests.occ.test_cell import _udp_ports, member_config

KEY = "a cell key of at least sixteen bytes"

BEAT = Beat(
    cell="or1", member="arm1", boot=1, seq=0, state="RUNNING", cause="", origin="",
    stop_wall=0.0, chain="abc", q=(0.1, 0.2, 0.3),
    base=(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.5, 0.0, 0.0),
)  # fmt: skip


def test_a_heartbeat_is_an_ndarray_with_its_sequence_and_metadata() -> None:
    msg = pack_beat(dataclasses.replace(BEAT, seq=7, sent_wall=123.5), None)
    wire = msg.pack()
    back = igtl.unpack(wire)
    assert back.message_type == "NDARRAY" and back.device_name == "CELL"
    assert back.header_version == 2 and back.message_id == 7
    assert back.metadata["member"] == "arm1" and back.metadata["state"] == "RUNNING"
    assert len(back.metadata) <= 8  # igtl/wire.py caches such metadata: packed once
    assert list(back.array) == [*BEAT.q, *BEAT.base, BEAT.stop_wall]
    beat = unpack_beat(back, 9.0)
    assert beat.q == BEAT.q and beat.base == BEAT.base and beat.seq == 7 and beat.t_rx == 9.0


@pytest.mark.req("SR-CELL-3")
@pytest.mark.parametrize(
    "change, why",
    [
        (lambda m: dataclasses.replace(m, device_name="OTHER"), "not a heartbeat"),
        (lambda m: dataclasses.replace(m, header_version=1), "header version 1"),
        (lambda m: dataclasses.replace(m, array=np.zeros(12)), "without its base"),
        (lambda m: dataclasses.replace(m, metadata={**m.metadata, "boot": "x"}), "bad value"),
        (
            lambda m: dataclasses.replace(m, metadata={k: v for k, v in m.metadata.items()
                                                        if k != "state"}),
            "without 'state'",
        ),
        (lambda m: dataclasses.replace(m, array=np.full(16, np.nan)), "not finite"),
    ],
)  # fmt: skip
def test_a_malformed_heartbeat_says_what_is_wrong(change: object, why: str) -> None:
    msg = change(pack_beat(BEAT, None))  # type: ignore[operator]
    with pytest.raises(BeatError, match=why):
        unpack_beat(msg, 0.0)


class Pair:
    """Our link ``arm0`` and a raw socket at arm1's address that sends what a test makes.
    The link is polled (as in simulated time: ``take`` reads the socket itself) and ``send``
    takes until the datagram has been judged (received, or refused by the endpoint), so each
    one's verdict is in the counters when ``send`` returns, whatever the machine's load."""

    def __init__(
        self, key: str | None = None, wall: Callable[[], float] = time.time, **more_peers: Any
    ) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(5.0)
        (port0,) = _udp_ports(1)
        self.link = CellLink(
            "or1", "arm0", ("127.0.0.1", port0), {"arm1": self.sock.getsockname(), **more_peers},
            key_text=key, now=time.monotonic, wall=wall, polled=True,
        )  # fmt: skip
        self.link.start()
        self.address = ("127.0.0.1", port0)

    def send(self, msg: igtl.Message | bytes, sock: socket.socket | None = None) -> list[Beat]:
        data = msg if isinstance(msg, bytes) else msg.pack()
        c = self.link.counters
        before = (c.received, c.refused)
        (sock or self.sock).sendto(data, self.address)
        deadline = time.monotonic() + 5.0
        out = self.link.take()
        while not out and (c.received, c.refused) == before and time.monotonic() < deadline:
            time.sleep(0.001)
            out = self.link.take()
        return out

    def close(self) -> None:
        self.link.stop()
        self.sock.close()


@pytest.mark.req("SR-CELL-3")
def test_a_keyed_link_takes_only_signed_fresh_heartbeats_of_its_members() -> None:
    pair = Pair(KEY)
    try:
        good = dataclasses.replace(BEAT, sent_wall=time.time())
        assert pair.send(pack_beat(good, KEY.encode()))  # signed: taken
        assert not pair.send(pack_beat(good, None))  # unsigned
        assert not pair.send(pack_beat(good, b"another key of sixteen bytes"))
        assert pair.link.counters.unauthenticated == 2
        old = dataclasses.replace(BEAT, sent_wall=time.time() - 60.0)
        assert not pair.send(pack_beat(old, KEY.encode()))  # recorded a minute ago
        assert pair.link.counters.stale == 1
        # the refusals above have their own counts, not `refused`'s
        assert pair.link.counters.refused == 0
        # another cell's heartbeat, or another member's name at arm1's address
        assert not pair.send(pack_beat(dataclasses.replace(good, cell="or2"), KEY.encode()))
        assert not pair.send(pack_beat(dataclasses.replace(good, member="arm2"), KEY.encode()))
        assert pair.link.counters.refused == 2
        assert not pair.send(b"\x00" * 70)  # not a message: the endpoint's error, counted once
        assert pair.link.counters.refused == 3
        # from an address that is no member's (a socket of the same host, another port)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other:
            other.bind(("127.0.0.1", 0))
            assert not pair.send(pack_beat(good, KEY.encode()), other)
        assert pair.link.stats() == {
            "sent": 0, "send_failed": 0, "received": 7, "refused": 4, "unauthenticated": 2,
            "stale": 1,
        }  # fmt: skip
    finally:
        pair.close()


def _link_pair_sims() -> tuple[SimRobot, CellLink, socket.socket]:
    ports = _udp_ports(2)
    members = [{"name": f"arm{i}", "address": f"127.0.0.1:{p}"} for i, p in enumerate(ports)]
    sim = SimRobot(member_config("arm0", members))
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", ports[1]))
    cell = sim.robot.cell
    assert cell is not None
    return sim, cell.link, sock


@pytest.mark.req("SR-CELL-3")
def test_duplicates_and_older_heartbeats_are_refused_a_restart_is_taken() -> None:
    sim, link, sock = _link_pair_sims()
    addr = link.endpoint.address
    try:

        def send(seq: int, boot: int = 5, state: str = "RUNNING") -> None:
            beat = dataclasses.replace(BEAT, seq=seq, boot=boot, state=state, cell="or1")
            sock.sendto(pack_beat(beat, None).pack(), addr)
            time.sleep(0.01)
            sim.tick()

        send(10)
        send(10)  # the same again: a replay
        send(9)  # older
        send(13)  # two lost between
        m = sim.robot.snapshot()["cell"]["members"]["arm1"]
        assert (m["stale"], m["lost"], m["state"]) == (2, 2, "RUNNING")
        send(1, boot=4, state="FAULT")  # an earlier boot: refused
        assert sim.robot.snapshot()["cell"]["members"]["arm1"]["state"] == "RUNNING"
        send(1, boot=6, state="READY")  # restarted: taken from its first number
        m = sim.robot.snapshot()["cell"]["members"]["arm1"]
        assert (m["state"], m["restarts"], m["stale"]) == ("READY", 1, 3)
    finally:
        sock.close()
        sim.close()


@pytest.mark.req("SR-CELL-3")
def test_the_cell_section_is_checked_at_load(tmp_path: Path) -> None:
    members = [
        {"name": "arm0", "address": "127.0.0.1:18950"},
        {"name": "arm1", "address": "127.0.0.1:18951"},
    ]
    with pytest.raises(ValueError, match="'armX' is not among the members"):
        member_config("armX", members)
    with pytest.raises(ValueError, match="duplicate member 'arm0'"):
        member_config("arm0", [members[0], {**members[1], "name": "arm0"}])
    with pytest.raises(ValueError, match="members\\[0\\]'s too"):
        member_config("arm0", [members[0], {**members[1], "address": "127.0.0.1:18950"}])
    with pytest.raises(ValueError, match="at least 3 heartbeat periods"):
        member_config("arm0", members, grace_ms=12.0)
    with pytest.raises(ValueError, match="period_ms"):
        member_config("arm0", members, period_ms=10.0)
    with pytest.raises(ValueError, match="policy"):
        member_config("arm0", members, policy="stop-some")
    cfg = member_config("arm0", members).model_dump(mode="json")
    cfg["interfaces"].append(
        {"name": "master", "transport": "udp", "host": "127.0.0.1", "port": 18950}
    )
    with pytest.raises(ValueError, match="is interface 'master''s"):
        DaemonConfig.model_validate(cfg)


@pytest.mark.req("SR-CELL-3")
def test_the_cell_sections_checks_name_each_repeat_and_bound_the_grace() -> None:
    """The section's checks themselves (occ/config/cell.py): every repeat of a name or an
    address is a problem naming the first one given, and the grace may be 3 periods, not less;
    this daemon's name in the cell is its ``member`` entry, else its robot's name."""
    a, b = "127.0.0.1:18950", "127.0.0.1:18951"
    members = tuple(
        CellMember(name=n, address=addr)
        for n, addr in (("arm0", a), ("arm1", b), ("arm0", "127.0.0.1:18952"), ("arm0", b))
    )
    assert cell_problems(members, 5.0, 100.0) == [
        (("members", 2, "name"), "duplicate member 'arm0' (members[0])"),
        (("members", 3, "name"), "duplicate member 'arm0' (members[0])"),
        (("members", 3, "address"), f"{b} is members[1]'s too"),
    ]
    assert cell_problems(members[:2], 2.5, 7.5) == []
    assert cell_problems(members[:2], 2.5, 7.49) == [
        (("grace_ms",), "must be at least 3 heartbeat periods (7.5 ms)")
    ]
    cfg = CellConfig(name="or1", members=members[:2], member="arm1")
    assert cfg.me("robot") == "arm1" and cfg.entry("arm1") is members[1]
    assert CellConfig(name="or1", members=members[:2]).me("arm0") == "arm0"
    with pytest.raises(KeyError, match="arm7"):
        cfg.entry("arm7")


@pytest.mark.req("SR-CELL-3")
def test_every_field_of_a_heartbeat_comes_back_and_the_optional_ones_default() -> None:
    full = dataclasses.replace(
        BEAT, seq=(1 << 32) + 9, state="STOPPED", cause="ESTOP: pedal", origin="arm2",
        stop_wall=1_700_000_000.5, leaving=True, sent_wall=1_700_000_001.25,
    )  # fmt: skip
    back = unpack_beat(igtl.unpack(pack_beat(full, None).pack()), 4.5)
    assert back == dataclasses.replace(full, seq=9, t_rx=4.5)  # the sequence is uint32
    # only what a heartbeat must carry: no stop, no chain, not leaving; no joints is 13 numbers
    bare = NDArrayMessage(
        device_name="CELL", header_version=2, timestamp=1_700_000_002.5, message_id=4,
        metadata={"cell": "or1", "member": "arm1", "boot": "3", "state": "READY",
                  "leaving": "0"},
        array=np.arange(13, dtype=np.float64),
    )  # fmt: skip
    assert unpack_beat(igtl.unpack(bare.pack()), 0.0) == Beat(
        cell="or1", member="arm1", boot=3, seq=4, state="READY", cause="", origin="",
        stop_wall=12.0, chain="", q=(), base=tuple(float(v) for v in range(12)),
        leaving=False, sent_wall=1_700_000_002.5, t_rx=0.0,
    )  # fmt: skip


@pytest.mark.req("SR-CELL-3")
def test_a_keyed_heartbeat_is_fresh_within_two_seconds_either_side() -> None:
    wall = 1_700_000_000.0
    pair = Pair(KEY, wall=lambda: wall)
    try:
        for sent, taken in ((-2.0, True), (2.0, True), (-2.5, False), (3.0, False)):
            beat = dataclasses.replace(BEAT, sent_wall=wall + sent)
            assert bool(pair.send(pack_beat(beat, KEY.encode()))) is taken, sent
        assert pair.link.counters.stale == 2
    finally:
        pair.close()


@pytest.mark.req("SR-CELL-3")
def test_a_link_numbers_its_heartbeats_from_one_and_counts_what_it_could_not_send() -> None:
    pair = Pair(wall=lambda: 1_700_000_123.25, arm2=("127.0.0.1", 0))  # arm2: no such port
    try:
        assert pair.link.send(BEAT) == 1 and pair.link.send(BEAT) == 1
        msgs = [igtl.unpack(pair.sock.recv(65536)) for _ in range(2)]
        assert [m.message_id for m in msgs] == [1, 2]
        assert unpack_beat(msgs[1], 0.0) == dataclasses.replace(
            BEAT, seq=2, sent_wall=1_700_000_123.25
        )
        assert pair.link.stats() == {
            "sent": 2, "send_failed": 2, "received": 0, "refused": 0, "unauthenticated": 0,
            "stale": 0,
        }  # fmt: skip
    finally:
        pair.close()


@pytest.mark.req("SR-CELL-3")
def test_a_keyed_cell_signs_its_heartbeats_and_hears_only_signed_ones(tmp_path: Path) -> None:
    """Members sharing ``cell.auth_key_file`` hear each other (a stop goes round); a member
    whose heartbeats are not signed is never heard (Run refused: not heard yet)."""
    from tests.occ.test_cell import Cell, error_of, ok

    key = tmp_path / "cell.key"
    key.write_text(KEY, encoding="utf-8")
    c = Cell(2, auth_key_file=str(key))
    try:
        c.run_all()
        assert ok(c.command(0, "EStop"))
        c.step(1)
        assert c.state(1) is RobotState.STOPPED
        links = [s.robot.cell.link for s in c.sims]  # type: ignore[union-attr]
        assert all(link.counters.unauthenticated == 0 for link in links)
        links[0].key = None  # arm0 stops signing: arm1 hears nothing more of it
        c.step(150)
        assert links[1].counters.unauthenticated > 0
        assert "arm0 silent" in c.cell_stats(1)["latched"]["arm0"]
        assert "arm0" in error_of(c.command(1, "Run"))
    finally:
        c.close()


def test_a_members_address_is_resolved_once_or_used_as_written(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from occ.core import cell

    assert cell._address("localhost:18950") == ("127.0.0.1", 18950)
    assert cell._address("[::1]:18951") == ("::1", 18951)  # an IPv6 literal: as written
    # a host name is looked up as written, whatever its letters (a resolver of two names)
    names = {"XRAY-ARM": "10.0.0.7", "ARM-X": "10.0.0.8"}

    def resolve(host: str) -> str:
        if host not in names:
            raise OSError(f"unknown host {host}")
        return names[host]

    monkeypatch.setattr(cell.socket, "gethostbyname", resolve)
    assert cell._address("XRAY-ARM:18952") == ("10.0.0.7", 18952)
    assert cell._address("ARM-X:18953") == ("10.0.0.8", 18953)


@pytest.mark.req("SR-CELL-3")
def test_a_member_on_ipv6_is_heard_at_its_address() -> None:
    """An IPv6 datagram comes from (host, port, flow, scope): the member is found by host and
    port."""
    socks = [socket.socket(socket.AF_INET6, socket.SOCK_DGRAM) for _ in range(2)]
    for s in socks:
        s.bind(("::1", 0))
    port0 = socks[0].getsockname()[1]
    socks[0].close()
    peer = socks[1]
    link = CellLink(
        "or1", "arm0", ("::1", port0), {"arm1": ("::1", peer.getsockname()[1])},
        now=time.monotonic, polled=True,
    )  # fmt: skip
    link.start()
    try:
        peer.sendto(pack_beat(BEAT, None).pack(), ("::1", port0))
        deadline = time.monotonic() + 5.0
        taken = link.take()
        while not taken and link.counters.refused == 0 and time.monotonic() < deadline:
            time.sleep(0.001)
            taken = link.take()
        assert [b.member for b in taken] == ["arm1"] and link.counters.refused == 0
    finally:
        link.stop()
        peer.close()


@pytest.mark.req("SR-CELL-3")
def test_a_link_on_the_real_clock_receives_on_its_own_thread_from_member_hosts_only() -> None:
    """Built without ``polled`` (a daemon on the real clock) the link's I/O thread receives
    and judges each heartbeat as it comes, before any ``take``; a datagram from a host that is
    no member's (127.0.0.2: loopback, another host) is dropped by the endpoint, never judged."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    (port0,) = _udp_ports(1)
    link = CellLink(
        "or1", "arm0", ("127.0.0.1", port0), {"arm1": sock.getsockname()}, now=time.monotonic
    )
    link.start()
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as foreign:
            foreign.bind(("127.0.0.2", 0))
            foreign.sendto(pack_beat(BEAT, None).pack(), ("127.0.0.1", port0))
        sock.sendto(pack_beat(BEAT, None).pack(), ("127.0.0.1", port0))
        assert wait_until(lambda: link.counters.received == 1, timeout=5.0)  # no take yet
        beats: list[Beat] = []
        assert wait_until(lambda: beats.extend(link.take()) or beats, timeout=5.0)
        assert [b.member for b in beats] == ["arm1"]
        assert link.counters.received == 1 and link.counters.refused == 0
    finally:
        link.stop()
        sock.close()


def test_heartbeats_in_simulated_time_carry_the_simulated_wall_clock() -> None:
    """A member on a SimClock stamps its heartbeats with that clock's wall time (simulated
    runs, their black boxes and replays, have reproducible timestamps), never the host's."""
    from tests.occ.test_cell import Cell

    c = Cell(2)
    try:
        taken: list[Beat] = []
        c.sims[1].robot.cell.tap = lambda beat, source: taken.append(beat)  # type: ignore[union-attr]
        c.step(20)
        sender = c.sims[0].clock
        assert len(taken) >= 4
        for beat in taken:
            assert sender.wall_epoch <= beat.sent_wall <= sender.wall_time() + 1e-6
    finally:
        c.close()
