"""Fixtures of the staff console's tests: a slave robot with real TCP interfaces on 127.0.0.1,
the console's web server on a free loopback port, and (for the page) headless Chromium.

The robot runs on a SimClock, ticked by a background thread about once a millisecond of real
time: a daemon as the console sees it (its own code from socket to reply), without the
real-time loop or a subprocess. The console needs the ``console`` extra (installed by the
``test`` extra); the page test needs Debian's chromium and chromium-driver
(scripts/install_browser.sh), and skips with the reason without them, except with
``OCC_REQUIRE_INTEROP=1`` (CI), where it fails.
"""

from __future__ import annotations

import asyncio
import os
import shutil
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from occ.clock import SimClock
from occ.core.loader import parse_config
from occ.core.robot import Robot, build_robot
from occ_testkit.testing import wait_until as poll

ROOT = Path(__file__).resolve().parents[2]

#: the shipped slave's interfaces, the operator's on a free port (or the given one)
INTERFACES = """
interfaces:
  - {{name: operator, transport: tcp-server, host: 127.0.0.1, port: {port}, role: operator,
     max_clients: 4{extra}}}
  - name: master
    transport: udp
    host: 127.0.0.1
    port: 0
    inputs: [{{type: POSITION, queue: stream, depth: 10}}]
"""


def slave_config_text(port: int = 0, extra: str = "") -> str:
    text = (ROOT / "configs" / "slave.yaml").read_text()
    head, _, rest = text.partition("interfaces:")
    _, _, tail = rest.partition("\nsafety:")
    body = INTERFACES.format(port=port, extra=f", {extra}" if extra else "")
    return head + body.lstrip("\n") + "safety:" + tail


class TickedRobot:
    """A robot on a SimClock ticked by a thread (1 ms of simulated time per ~1 ms of real)."""

    def __init__(self, port: int = 0, extra: str = "") -> None:
        cfg = parse_config(slave_config_text(port, extra), base_dir=ROOT / "configs")
        self.clock = SimClock()
        self.robot: Robot = build_robot(cfg, clock=self.clock)
        self.robot.configure()
        self.robot.activate()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="test-ticker", daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        address = self.robot.interfaces["operator"].address
        assert address is not None
        return address[1]

    def _run(self) -> None:
        k = 0
        while not self._stop.is_set():
            k += 1
            self.robot.tick(self.clock.now(), k)
            self.clock.advance(0.001)
            time.sleep(0.001)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.robot.shutdown()


@pytest.fixture
def slave() -> Iterator[TickedRobot]:
    r = TickedRobot()
    try:
        yield r
    finally:
        r.stop()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class WebServer:
    """``create_app(console)`` served by uvicorn on a free loopback port, in a thread."""

    def __init__(self, console: Any) -> None:
        import uvicorn

        from occ_console.app import create_app

        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self.sock.getsockname()[1]}"
        config = uvicorn.Config(
            create_app(console), log_level="warning", timeout_graceful_shutdown=1
        )
        self.app = config.app
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(
            target=lambda: asyncio.run(self.server.serve(sockets=[self.sock])),
            name="test-uvicorn",
            daemon=True,
        )
        self.thread.start()
        assert poll(lambda: self.server.started, 10.0), "uvicorn did not start"

    def stop(self) -> None:
        from occ_console.app import begin_shutdown

        begin_shutdown(self.app)
        self.server.should_exit = True
        self.thread.join(timeout=10.0)
        self.sock.close()


def require_browser() -> tuple[str, str]:
    """(chromium, chromedriver) paths, or skip (fail under OCC_REQUIRE_INTEROP=1)."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    missing = [n for n, p in (("chromium", chromium), ("chromium-driver", driver)) if not p]
    if missing:
        why = (
            f"{' and '.join(missing)} not installed (apt-get install -y chromium "
            "chromium-driver; scripts/install_browser.sh)"
        )
        if os.environ.get("OCC_REQUIRE_INTEROP") == "1":
            pytest.fail(why)
        pytest.skip(why)
    if os.environ.get("OCC_REQUIRE_INTEROP") != "1":
        pytest.importorskip("selenium", reason="pip install -e .[test] (installs selenium)")
    assert chromium is not None and driver is not None
    return chromium, driver
