#!/usr/bin/env python3
"""A screenshot of the staff console watching the demo's pair (the README's picture).

Starts the slave and master daemons on free loopback ports (``--start running``), ``occ-console``
on both operator ports, and headless Chromium (Debian's chromium and chromium-driver, driven by
selenium); waits ``--settle`` seconds for rates and the histogram to fill, then saves the page.

    python tools/console_screenshot.py --out docs/console.png
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

from loopback import pair_configs, stop_processes, wait_port, write_yaml  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "console.png")
    p.add_argument("--settle", type=float, default=15.0, help="seconds before the picture")
    p.add_argument("--size", default="1280,900", help="window size W,H")
    args = p.parse_args(argv)
    chromium, driver = shutil.which("chromium"), shutil.which("chromedriver")
    if not chromium or not driver:
        print("needs chromium and chromium-driver (scripts/install_browser.sh)", file=sys.stderr)
        return 1
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    tmp = Path(tempfile.mkdtemp(prefix="occ-console-shot-"))
    slave_cfg, master_cfg, ports = pair_configs()
    procs: list[subprocess.Popen[bytes]] = []
    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--hide-scrollbars"):
        opts.add_argument(arg)
    opts.add_argument(f"--window-size={args.size}")
    # the browser first: its start-up takes both cores for a moment, which on this 2-core
    # machine made running daemons miss ticks (a supervisor FAULT in the picture)
    browser = webdriver.Chrome(service=Service(executable_path=driver), options=opts)
    try:
        for name, cfg, port in (
            ("slave", slave_cfg, ports["slave_op"]),
            ("master", master_cfg, ports["master_tcp"]),
        ):
            path = write_yaml(tmp / f"{name}.yaml", cfg)
            cmd = [sys.executable, "-m", "occ.cli", str(path), "--start", "running"]
            proc = subprocess.Popen([*cmd, "--log-level", "WARNING"], cwd=ROOT)
            procs.append(proc)
            if not wait_port(port, 20.0, proc):
                print(f"the {name} did not start", file=sys.stderr)
                return 1
        watch = [f"127.0.0.1:{ports['slave_op']}", f"127.0.0.1:{ports['master_tcp']}"]
        console = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "occ_console.cli",
                "--port",
                "0",
                "--connect",
                watch[0],
                "--connect",
                watch[1],
            ],  # fmt: skip
            cwd=ROOT,
            stdout=subprocess.PIPE,
        )
        procs.append(console)
        assert console.stdout is not None
        url = console.stdout.readline().decode().split()[1]
        browser.get(url)
        time.sleep(args.settle)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        browser.save_screenshot(str(args.out))
        print(f"{args.out}: {args.out.stat().st_size} bytes")
    finally:
        browser.quit()
        stop_processes(procs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
