"""A master link authenticated with a shared key (interfaces[].auth_key_file), over real UDP
on 127.0.0.1: the master signs what it sends, the slave takes only what carries a valid tag."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

import igtl
from igtl.auth import sign, verify
from igtl.transport import UDPEndpoint
from occ.clock import SimClock
from occ.errors import ConfigError
from occ.core.loader import parse_config
from occ.core.robot import Robot, build_robot
from occ_testkit.testing import wait_until

ROOT = Path(__file__).resolve().parents[2]
KEY = "a shared key for the master link"


def _with_key(name: str, tmp_path: Path, edit: Callable[[str], str]) -> Robot:
    (tmp_path / "link.key").write_text(KEY + "\n")
    text = edit((ROOT / "configs" / name).read_text())
    cfg = parse_config(text, base_dir=ROOT / "configs")
    cfg = cfg.model_copy(
        update={
            "interfaces": tuple(
                i.model_copy(update={"auth_key_file": tmp_path / "link.key"})
                if i.transport == "udp"
                else i.model_copy(update={"port": 0})
                for i in cfg.interfaces
            )
        }
    )
    robot = build_robot(cfg, clock=SimClock())
    robot.configure()
    robot.activate()
    return robot


@pytest.mark.req("SR-AUTH-1")
def test_slave_takes_only_signed_samples(tmp_path: Path) -> None:
    slave = _with_key("slave.yaml", tmp_path, lambda t: t.replace("port: 18946", "port: 0"))
    sender = UDPEndpoint("127.0.0.1", 0).start()
    try:
        port = slave.interfaces["master"].address[1]  # type: ignore[index]
        key = KEY.encode()

        def pos(seq: int) -> igtl.Message:
            return igtl.PositionMessage(
                (0.0, 50.0, 270.0),
                (0.0, 0.0, 0.0, 1.0),
                24,
                device_name="Master",
                header_version=2,
                message_id=seq,
                metadata={"run": "1", "clutch": "0"},
            )

        for seq in range(1, 16):
            if seq % 3 == 1:
                msg = sign(pos(seq), key)
            elif seq % 3 == 2:
                msg = pos(seq)  # no tag
            else:
                msg = sign(pos(seq), b"the wrong key, 16 bytes+")
            assert sender.send(msg, ("127.0.0.1", port))
        iface = slave.interfaces["master"]
        k = [0]

        def tick() -> None:
            k[0] += 1
            slave.tick(slave.clock.now(), k[0])
            slave.clock.advance(0.001)  # type: ignore[attr-defined]

        assert wait_until(lambda: iface.counters.received == 15, 5.0, 0.001, each=tick)
        assert iface.counters.unauthenticated == 10
        assert iface.stats()["streams"]["POSITION"]["received"] == 5
        assert slave.snapshot()["interfaces"]["master"]["unauthenticated"] == 10
    finally:
        sender.stop()
        slave.shutdown()


@pytest.mark.req("SR-AUTH-1")
def test_master_signs_its_stream(tmp_path: Path) -> None:
    got: list[igtl.Message] = []
    receiver = UDPEndpoint("127.0.0.1", 0, on_message=lambda p, m: got.append(m)).start()
    port = receiver.address[1]
    master = _with_key(
        "master.yaml", tmp_path, lambda t: t.replace("127.0.0.1:18946", f"127.0.0.1:{port}")
    )
    try:
        master.state_machine.request("enable", "test")
        master.state_machine.request("run", "test")
        k = [0]

        def tick() -> None:
            k[0] += 1
            master.tick(master.clock.now(), k[0])
            master.clock.advance(0.001)  # type: ignore[attr-defined]

        assert wait_until(lambda: len(got) >= 10, 5.0, 0.001, each=tick)
        key = KEY.encode()
        assert all(verify(m, key) == "" for m in got)
        assert all(verify(m, b"the wrong key, 16 bytes+") == "wrong HMAC" for m in got)
    finally:
        master.shutdown()
        receiver.stop()


def test_unusable_key_is_a_config_error(tmp_path: Path) -> None:
    (tmp_path / "short.key").write_text("too short\n")
    text = (
        (ROOT / "configs" / "slave.yaml")
        .read_text()
        .replace(
            "    port: 18946\n", f"    port: 18946\n    auth_key_file: {tmp_path / 'short.key'}\n"
        )
    )
    with pytest.raises(ConfigError, match=r"auth_key_file: unusable key: the key must be at least"):
        parse_config(text, base_dir=ROOT / "configs")


@pytest.mark.req("SR-AUTH-1")
def test_a_new_client_of_a_keyed_interface_gets_a_signed_greeting(tmp_path: Path) -> None:
    """The STATUS a daemon greets a client with carries its tag, even before the client has
    spoken: a keyed interface answers in version 2 (its tag lives in v2 metadata) instead of
    the version a silent client is assumed to speak (1, which would drop the tag)."""
    from igtl.transport import TCPClient

    (tmp_path / "link.key").write_text(KEY + "\n")
    cfg = parse_config((ROOT / "configs" / "slave.yaml").read_text(), base_dir=ROOT / "configs")
    cfg = cfg.model_copy(
        update={
            "interfaces": tuple(
                i.model_copy(update={"auth_key_file": tmp_path / "link.key", "port": 0})
                if i.name == "operator"
                else i.model_copy(update={"port": 0})
                for i in cfg.interfaces
            )
        }
    )
    robot = build_robot(cfg, clock=SimClock())
    robot.configure()
    robot.activate()
    got: list[igtl.Message] = []
    port = robot.interfaces["operator"].address[1]  # type: ignore[index]
    client = TCPClient("127.0.0.1", port, on_message=lambda p, m: got.append(m)).start()
    try:
        assert wait_until(lambda: got, 5.0, 0.001)
        greeting = got[0]
        assert greeting.message_type == "STATUS" and greeting.header_version == 2
        assert verify(greeting, KEY.encode()) == ""
    finally:
        client.stop()
        robot.shutdown()


def _keyed_pair(tmp_path: Path, slave_keyed: bool = True) -> tuple[Robot, Robot]:
    """configs/slave.yaml and configs/master.yaml on 127.0.0.1 (free ports), each on its own
    SimClock, the master link keyed on the master and (``slave_keyed``) on the slave."""
    if slave_keyed:
        slave = _with_key("slave.yaml", tmp_path, lambda t: t.replace("port: 18946", "port: 0"))
    else:
        cfg = parse_config((ROOT / "configs" / "slave.yaml").read_text(), base_dir=ROOT / "configs")
        cfg = cfg.model_copy(
            update={"interfaces": tuple(i.model_copy(update={"port": 0}) for i in cfg.interfaces)}
        )
        slave = build_robot(cfg, clock=SimClock())
        slave.configure()
        slave.activate()
    port = slave.interfaces["master"].address[1]  # type: ignore[index]
    master = _with_key(
        "master.yaml", tmp_path, lambda t: t.replace("127.0.0.1:18946", f"127.0.0.1:{port}")
    )
    for r in (slave, master):
        r.state_machine.request("enable", "test")
        r.state_machine.request("run", "test")
    return slave, master


def _tick_both(slave: Robot, master: Robot) -> Callable[[], None]:
    k = [0]

    def tick() -> None:
        k[0] += 1
        for r in (master, slave):
            r.tick(r.clock.now(), k[0])
            r.clock.advance(0.001)  # type: ignore[attr-defined]

    return tick


@pytest.mark.req("SR-AUTH-1")
def test_the_return_channel_is_signed_when_the_link_is(tmp_path: Path) -> None:
    slave, master = _keyed_pair(tmp_path)
    try:
        ctrl = master.controller.controllers[0]
        tick = _tick_both(slave, master)
        assert wait_until(
            lambda: (ctrl.stats()["slave_tip"] or {}).get("samples", 0) >= 20, 5.0, 0.001, each=tick
        )
        assert master.interfaces["slave"].counters.unauthenticated == 0
        assert slave.interfaces["master"].counters.unauthenticated == 0
        assert ctrl.stats()["slave_tip"]["following"] is True
    finally:
        master.shutdown()
        slave.shutdown()


@pytest.mark.req("SR-AUTH-1")
def test_an_unsigned_return_channel_on_a_keyed_link_is_refused(tmp_path: Path) -> None:
    slave, master = _keyed_pair(tmp_path, slave_keyed=False)
    try:
        ctrl = master.controller.controllers[0]
        tick = _tick_both(slave, master)
        iface = master.interfaces["slave"]
        assert wait_until(lambda: iface.counters.unauthenticated >= 20, 5.0, 0.001, each=tick)
        st = ctrl.stats()["slave_tip"]
        assert st is None or st["samples"] == 0
        assert ctrl.stats()["tool_mm"] is None
    finally:
        master.shutdown()
        slave.shutdown()
