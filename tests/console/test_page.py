"""The page in a real browser: headless Chromium (Debian's chromium and chromium-driver, driven
by selenium) on ``occ-console`` watching a real slave daemon (``occd``), both subprocesses on
loopback. The page shows the daemon's state and its loop timing, a button changes the state,
and the change and its cause come back through the page.

Skips with the reason when chromium, its driver or selenium is missing, except with
``OCC_REQUIRE_INTEROP=1`` (CI), where that fails the test (scripts/install_browser.sh).
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from .conftest import WebServer, free_port, poll, require_browser

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))

from loopback import pair_configs, stop_processes, wait_port, write_yaml  # noqa: E402

pytestmark = pytest.mark.slow  # subprocesses: a daemon, the console, a browser


@pytest.fixture
def browser() -> Iterator[Any]:
    chromium, driver = require_browser()
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
                "--disable-gpu", "--window-size=1300,1000"):  # fmt: skip
        opts.add_argument(arg)
    b = webdriver.Chrome(service=Service(executable_path=driver), options=opts)
    try:
        yield b
    finally:
        b.quit()


@pytest.fixture
def console_on_slave(tmp_path: Path) -> Iterator[str]:
    slave_cfg, _, ports = pair_configs()
    yield from _console_on(tmp_path, slave_cfg, ports)


@pytest.fixture
def console_on_tissue_slave(tmp_path: Path) -> Iterator[str]:
    """The slave of configs/wall.yaml in miniature, alone: its tissue wall 1 mm behind the tip
    at home (0.5 N/mm: 0.5 N on the tool at rest), the force from the simulated sensor
    (``tissue``) and sent to Slicer's port as ``TipForce``, which estimates it at 10 Hz without
    a master."""
    import yaml

    from occ_testkit.testing import CONFIGS, SimRobot

    slave_cfg, _, ports = pair_configs()
    wall = yaml.safe_load((CONFIGS / "wall.yaml").read_text())
    with SimRobot(wall) as probe:
        tip_x = float(probe.robot.data.world_tip()[0, 3]) * 1e3
    env = wall["environment"]
    env["contacts"][0]["point_mm"] = [tip_x - 1.0, 0.0, 0.0]
    slave_cfg["environment"] = env
    slave_cfg["controller"]["params"]["force"] = {"sources": ["tissue"]}
    slicer = next(i for i in slave_cfg["interfaces"] if i["name"] == "slicer")
    slicer["outputs"].append(
        {"type": "TRANSFORM", "device": "TipForce", "source": "force", "rate_hz": 10}
    )
    yield from _console_on(tmp_path, slave_cfg, ports)


def _console_on(tmp_path: Path, slave_cfg: dict[str, Any], ports: dict[str, int]) -> Iterator[str]:
    # what is tested is the page, not the daemon's timing: on a machine loaded enough to stall
    # the loop for tens of milliseconds the slave would fault (supervisor, watchdog, the
    # drive's heartbeat) before the browser saw READY, so those limits are wide here
    safety = slave_cfg["safety"]
    safety["supervisor"] = {"timeout_ms": 5000.0}
    safety["watchdog"].update(hard_gap_ms=5000.0, stop_run=1_000_000, alert_run=1_000_000)
    slave_cfg["robot"]["drivers"][0]["params"]["heartbeat_ms"] = 0
    write_yaml(tmp_path / "slave.yaml", slave_cfg)
    procs: list[subprocess.Popen[bytes]] = []
    try:
        slave = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "occ.cli",
                str(tmp_path / "slave.yaml"),
                "--log-level",
                "WARNING",
            ],  # fmt: skip
            cwd=ROOT,
        )
        procs.append(slave)
        assert wait_port(ports["slave_op"], 20.0, slave), "the slave did not start"
        console = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "occ_console.cli",
                "--connect",
                f"127.0.0.1:{ports['slave_op']}",
                "--port",
                "0",
                "--poll-hz",
                "5",
            ],  # fmt: skip
            cwd=ROOT,
            stdout=subprocess.PIPE,
        )
        procs.append(console)
        assert console.stdout is not None
        line = console.stdout.readline().decode()  # "occ-console: http://127.0.0.1:N/ ..."
        assert line.startswith("occ-console: http://127.0.0.1:"), line
        yield line.split()[1]
    finally:
        stop_processes(procs)


def test_page_shows_the_daemon_and_its_buttons_act(browser: Any, console_on_slave: str,
                                                    tmp_path: Path) -> None:  # fmt: skip
    from selenium.webdriver.common.by import By

    b = browser
    b.get(console_on_slave)
    card = '[data-daemon="0"]'

    def text(sel: str) -> str:
        found = b.find_elements(By.CSS_SELECTOR, f"{card} {sel}")
        return str(found[0].text) if found else ""

    assert poll(lambda: text(".state") == "READY", 20.0), b.page_source[:2000]
    assert text(".name") == "slave"
    # the loop's timing: the daemon's own lateness, binned (a real loop: ticks in it)
    assert poll(lambda: b.find_elements(By.CSS_SELECTOR, f"{card} .hist rect.bar"), 10.0)
    assert poll(lambda: "ticks" in text(".hist") and " 0 ticks" not in text(".hist"), 10.0)
    assert "master" in text(".streams") and "operator" in text(".streams")
    assert "holds" in text(".loss")

    def press(command: str) -> None:
        b.find_element(By.CSS_SELECTOR, f'{card} button[data-command="{command}"]').click()

    press("Enable")
    assert poll(lambda: text(".state") == "ENABLED", 10.0), text(".reply")
    assert poll(lambda: "READY -> ENABLED" in text(".reply"), 5.0), text(".reply")
    assert "operator Enable" in text(".cause")
    press("EStop")
    assert poll(lambda: text(".state") == "ESTOP", 10.0), text(".reply")
    assert poll(lambda: "ENABLED -> ESTOP" in text(".log"), 5.0), text(".log")
    press("Run")  # refused in ESTOP: the daemon's reason is shown, the state stays
    assert poll(lambda: "Run: FAIL" in text(".reply"), 5.0), text(".reply")
    assert text(".state") == "ESTOP"
    press("Reset")
    assert poll(lambda: text(".state") == "READY", 10.0), text(".reply")
    b.save_screenshot(str(tmp_path / "console.png"))
    assert (tmp_path / "console.png").stat().st_size > 10_000


def test_page_shows_the_contact_force(browser: Any, console_on_tissue_slave: str) -> None:
    """A slave whose tool rests 1 mm into the tissue: the Forces panel shows its contact force
    (0.5 N along -x) and its source."""
    from selenium.webdriver.common.by import By

    b = browser
    b.get(console_on_tissue_slave)
    card = '[data-daemon="0"]'

    def forces() -> str:
        found = b.find_elements(By.CSS_SELECTOR, f"{card} .forces")
        return str(found[0].text) if found else ""

    assert poll(lambda: "contact force (instrument)" in forces(), 20.0), b.page_source[:2000]
    assert poll(lambda: "0.50 N (-0.500, 0, 0)" in forces(), 10.0), forces()
    assert "tissue" in forces()
    assert "displayed (hand)" not in forces()  # a slave: no hand


def test_page_shows_each_drives_state_and_last_emcy(browser: Any) -> None:
    """The Drives panel drawn from the cia402 driver's own statistics (three nodes emulated
    in-process, tests/occ/test_cia402.py's rig, one faulted by an EMCY), put in the console's
    view of a daemon as GetStats would: the page names each node's state and pitch's EMCY."""
    import json

    from selenium.webdriver.common.by import By

    from occ_console.link import Console
    from tests.occ.test_cia402 import Rig

    r = Rig([1, 2, 3], {})
    try:
        r.enabled()
        r.ticks(20, r.here())
        r.emu.inject_emcy(2, 0x2310)
        r.until_fault(20, lambda k: r.here())
        r.ticks(2)
        answer = json.loads(json.dumps({"ticks": 1, "drivers": {"arm": r.drv.stats()}}))
    finally:
        r.close()
    console = Console([("127.0.0.1", free_port())], poll_hz=5.0)  # nobody there: no link
    web = WebServer(console)
    try:
        view = console.links[0].view
        with view.lock:
            view.on_stats(time.time(), 0.0, answer)
        console._changed()
        b = browser
        b.get(web.url)

        def drives() -> str:
            found = b.find_elements(By.CSS_SELECTOR, '[data-daemon="0"] .drives')
            return str(found[0].text) if found else ""

        assert poll(lambda: "pitch" in drives(), 20.0), b.page_source[:2000]
        text = drives()
        assert "arm · bus load 57 %" in text, text
        assert "0x2310 continuous overcurrent" in text, text
        rows = {line.split()[0]: line for line in text.splitlines() if line.split()}
        assert " 2 FAULT " in rows["pitch"], rows
        assert "OPERATION ENABLED" not in rows["yaw"] and "OPERATIONAL" in rows["yaw"], rows
        assert "last fault: cia402 driver 'arm': node 2 (joint pitch): EMCY 0x2310" in text
    finally:
        web.stop()
