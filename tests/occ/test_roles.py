"""Interface roles over real loopback sockets: a viewer may look, only an operator may act.

The robot runs on a SimClock and is ticked by the test; its interfaces are real TCP servers on
127.0.0.1 (ephemeral ports), and the clients are igtl TCPClients, so routing, replies and the
slot reservation are the daemon's own, not a capture.
"""

from __future__ import annotations

import json
import socket
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

import igtl
from igtl.transport import TCPClient, TCPServer
from igtl.transport.common import HostLogLimits
from occ.clock import SimClock
from occ.errors import ConfigError
from occ.core.loader import parse_config
from occ.core.robot import Robot, build_robot
from occ.core.safety import RobotState
from occ_testkit.testing import wait_until as wait_for

ROOT = Path(__file__).resolve().parents[2]

INTERFACES = """
interfaces:
  - {name: viewer, transport: tcp-server, host: 127.0.0.1, port: 0, role: viewer}
  - {name: operator, transport: tcp-server, host: 127.0.0.1, port: 0, role: operator}
  - {name: mixed, transport: tcp-server, host: 127.0.0.1, port: 0, role: operator,
     operators: [10.9.9.9], allowed_peers: [127.0.0.1, 10.0.0.0/8], max_clients: 3}
  - {name: link, transport: tcp-server, host: 127.0.0.1, port: 0}
  - name: master
    transport: udp
    host: 127.0.0.1
    port: 0
    inputs: [{type: POSITION, queue: stream, depth: 10}]
"""


def _config_text() -> str:
    text = (ROOT / "configs" / "slave.yaml").read_text()
    head, _, rest = text.partition("interfaces:")
    _, _, tail = rest.partition("\nsafety:")
    return head + INTERFACES.lstrip("\n") + "safety:" + tail


@pytest.fixture
def robot() -> Iterator[Robot]:
    cfg = parse_config(_config_text(), base_dir=ROOT / "configs")
    clock = SimClock()
    r = build_robot(cfg, clock=clock)
    r.configure()
    r.activate()
    try:
        yield r
    finally:
        r.shutdown()


class Client:
    def __init__(self, robot: Robot, iface: str) -> None:
        self.robot = robot
        port = robot.interfaces[iface].address[1]  # type: ignore[index]
        self.got: list[igtl.Message] = []
        self.c = TCPClient("127.0.0.1", port, on_message=lambda p, m: self.got.append(m))
        self.c.start()
        assert self.c.wait_connected(5.0)
        self._id = 0

    def command(self, name: str) -> igtl.Message:
        """Send a COMMAND, tick the robot until its RTS_COMMAND comes back; return it."""
        self._id += 1
        cid = self._id
        self.c.send(
            igtl.CommandMessage(command_id=cid, command_name=name, command="", header_version=2)
        )
        return self._await(lambda m: m.message_type == "RTS_COMMAND" and m.command_id == cid)

    def query(self, mtype: str) -> igtl.Message:
        # a v2 request: the reply echoes its message ID (the connect greeting does not)
        self._id += 1
        mid = 1000 + self._id
        self.c.send(igtl.REGISTRY[mtype](type_name=mtype, header_version=2, message_id=mid))
        return self._await(lambda m: m.message_id == mid)

    def _await(self, match: Callable[[igtl.Message], bool]) -> igtl.Message:
        found: list[igtl.Message] = []
        k = [0]

        def step() -> bool:
            k[0] += 1
            now = self.robot.clock.now()
            self.robot.tick(now, k[0])
            self.robot.clock.advance(0.001)  # type: ignore[attr-defined]
            for m in list(self.got):
                if match(m):
                    found.append(m)
                    self.got.remove(m)
                    return True
            return False

        assert wait_for(step), f"no reply; got {[m.message_type for m in self.got]}"
        return found[0]

    def close(self) -> None:
        self.c.stop()


def _status(reply: igtl.Message) -> str:
    return str(reply.metadata.get("Status", ""))


@pytest.mark.req("SR-ROLE-1")
def test_viewer_queries_but_cannot_command(robot: Robot) -> None:
    viewer = Client(robot, "viewer")
    try:
        st = viewer.query("GET_STATUS")
        assert st.message_type == "STATUS" and "state=READY" in st.status_message
        refused = viewer.command("Enable")
        assert _status(refused) == "FAIL" and "viewer" in refused.metadata.get("Error", "")
        assert robot.state is RobotState.READY
        assert robot.interfaces["viewer"].counters.refused == 1
        state = viewer.command("GetState")
        assert _status(state) == "SUCCESS" and "READY" in state.metadata.get("Message", "")
    finally:
        viewer.close()


@pytest.mark.req("SR-ROLE-1")
def test_operator_commands(robot: Robot) -> None:
    op = Client(robot, "operator")
    try:
        assert _status(op.command("Enable")) == "SUCCESS"
        assert robot.state is RobotState.ENABLED
    finally:
        op.close()


def _stats_of(client: Client) -> dict[str, object]:
    reply = client.command("GetStats")
    assert _status(reply) == "SUCCESS"
    return json.loads(reply.metadata["Message"])


@pytest.mark.req("SR-ROLE-1")
def test_stats_hide_sequence_numbers_from_viewers(robot: Robot) -> None:
    viewer, op = Client(robot, "viewer"), Client(robot, "operator")
    try:
        full, seen = json.dumps(_stats_of(op)), json.dumps(_stats_of(viewer))
        assert '"last_seq"' in full and '"stream_owner"' in full
        assert '"last_seq"' not in seen and '"stream_owner"' not in seen
        assert '"state"' in seen  # the rest is there
    finally:
        viewer.close()
        op.close()


@pytest.mark.req("SR-ROLE-1")
def test_operators_list_makes_other_hosts_viewers(robot: Robot) -> None:
    # 127.0.0.1 is allowed on "mixed" but is not in its operators list (10.9.9.9)
    c = Client(robot, "mixed")
    try:
        assert _status(c.command("Enable")) == "FAIL"
        assert _status(c.command("GetState")) == "SUCCESS"
        assert robot.state is RobotState.READY
    finally:
        c.close()


@pytest.mark.req("SR-ROLE-1")
def test_data_link_takes_no_requests(robot: Robot) -> None:
    c = Client(robot, "link")
    try:
        st = c.query("GET_STATUS")
        assert st.code == igtl.StatusCode.ACCESS_DENIED
        assert robot.interfaces["link"].counters.refused == 1
    finally:
        c.close()


@pytest.mark.req("SR-ROLE-1")
def test_reserved_slot_refuses_non_operators() -> None:
    """max_clients 3 with 1 reserved: the third non-operator is turned away; an operator
    address would still get in (here the operator list names 127.0.0.2, also on loopback)."""
    server = TCPServer(
        "127.0.0.1",
        0,
        max_clients=3,
        reserved_slots=1,
        privileged_peers=["127.0.0.2"],
        on_message=lambda p, m: None,
    ).start()
    port = server.address[1]
    socks: list[socket.socket] = []
    try:
        for _ in range(3):
            socks.append(socket.create_connection(("127.0.0.1", port)))
        assert wait_for(lambda: server.stats()["rejected"] == 1)
        assert len(server.peers) == 2
        socks.append(socket.create_connection(("127.0.0.1", port), source_address=("127.0.0.2", 0)))
        assert wait_for(lambda: len(server.peers) == 3)
        assert {p.address[0] for p in server.peers} == {"127.0.0.1", "127.0.0.2"}
        assert server.stats()["rejected"] == 1
    finally:
        for s in socks:
            s.close()
        server.stop()


def test_reserved_slots_need_privileged_peers() -> None:
    with pytest.raises(ValueError, match="privileged_peers"):
        TCPServer("127.0.0.1", 0, max_clients=3, reserved_slots=1)
    with pytest.raises(ValueError, match="below|< max_clients"):
        TCPServer("127.0.0.1", 0, max_clients=2, reserved_slots=2, privileged_peers=[])


def test_log_budget_is_per_host_and_survives_reconnects() -> None:
    limits = HostLogLimits(per_second=2, max_hosts=2)
    first = limits.get("10.0.0.1")
    assert first.allow() and first.allow() and not first.allow()
    again = limits.get("10.0.0.1")  # a new connection from the same host
    assert again is first and not again.allow()
    limits.get("10.0.0.2")
    limits.get("10.0.0.3")  # bounded: the least recently used host is forgotten
    assert limits.get("10.0.0.1") is not first


def test_config_roles_checked() -> None:
    text = _config_text()
    with pytest.raises(ConfigError, match="`commands` was replaced by `role`"):
        parse_config(text.replace("role: viewer}", "commands: true}"), base_dir=ROOT / "configs")
    with pytest.raises(ConfigError, match="operators: needs role 'operator'"):
        parse_config(
            text.replace("role: viewer}", "role: viewer, operators: [127.0.0.1]}"),
            base_dir=ROOT / "configs",
        )
