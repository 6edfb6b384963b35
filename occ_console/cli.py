"""``occ-console``: the staff console, a web page on this machine watching and commanding daemons.

Examples::

    occ-console --connect 127.0.0.1:18947 --connect 127.0.0.1:18945      # slave and master
    occ-console --connect 127.0.0.1:18947 --port 8080 --poll-hz 5
    occ-console --connect robot-pc:18947 --auth-key-file operator.key      # a signed link

then open http://127.0.0.1:8765/. Each ``--connect`` is a daemon's *operator* interface
(``role: operator``; 18947 on the shipped slave, 18945 on the master): the console is an
ordinary OpenIGTLink operator client there. It serves on a loopback address only.
"""

from __future__ import annotations

import argparse
import ipaddress
import logging
import socket
import sys
from pathlib import Path
from typing import Any

from .link import Console, parse_endpoint


def _endpoint(text: str) -> tuple[str, int]:
    try:
        return parse_endpoint(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from err


def _loopback(text: str) -> str:
    try:
        ok = text == "localhost" or ipaddress.ip_address(text).is_loopback
    except ValueError:
        ok = False
    if not ok:
        raise argparse.ArgumentTypeError(
            f"the console serves on this machine only (a loopback address), not {text!r}: "
            "its buttons stop the robots"
        )
    return "127.0.0.1" if text == "localhost" else text


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="occ-console",
        description="Web staff console: watch and command OCC daemons over their operator "
        "interfaces (OpenIGTLink).",
    )
    p.add_argument(
        "--connect",
        action="append",
        type=_endpoint,
        default=[],
        metavar="HOST:PORT",
        help="a daemon's operator interface (repeatable), e.g. 127.0.0.1:18947",
    )
    p.add_argument("--port", type=int, default=8765, help="HTTP port (default 8765; 0: any free)")
    p.add_argument(
        "--host",
        type=_loopback,
        default="127.0.0.1",
        help="loopback address to serve on (default 127.0.0.1)",
    )
    p.add_argument(
        "--poll-hz",
        type=float,
        default=2.0,
        help="GetStats requests per second and daemon (0.1..10, default 2)",
    )
    p.add_argument(
        "--window-s",
        type=float,
        default=10.0,
        help="seconds of loop timing in the live histogram (default 10)",
    )
    p.add_argument(
        "--auth-key-file",
        type=Path,
        default=None,
        help="shared key of the operator interfaces (their auth_key_file): sign and check "
        "every message",
    )
    p.add_argument("--log-level", default="WARNING")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(name)s %(message)s")
    if not args.connect:
        print("occ-console: give at least one --connect HOST:PORT", file=sys.stderr)
        return 2
    if not 0.1 <= args.poll_hz <= 10.0:
        print("occ-console: --poll-hz must be 0.1..10", file=sys.stderr)
        return 2
    if args.window_s <= 0:
        print("occ-console: --window-s must be positive", file=sys.stderr)
        return 2
    key = None
    if args.auth_key_file is not None:
        from igtl.auth import load_key

        try:
            key = load_key(args.auth_key_file.read_text(encoding="utf-8"))
        except (OSError, ValueError) as err:
            print(f"occ-console: --auth-key-file: {err}", file=sys.stderr)
            return 2
    try:
        import uvicorn

        from .app import begin_shutdown, create_app
    except ImportError as err:
        print(f"occ-console: {err.name} is missing: pip install 'occ-igtl[console]'",
              file=sys.stderr)  # fmt: skip
        return 2
    console = Console(args.connect, poll_hz=args.poll_hz, window_s=args.window_s, auth_key=key)
    family = socket.AF_INET6 if ":" in args.host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((args.host, args.port))
    except OSError as err:
        print(f"occ-console: cannot serve on {args.host}:{args.port}: {err}", file=sys.stderr)
        return 1
    # listening before the address is printed: a browser (or a script) that connects at once
    # waits in the backlog until the server accepts, instead of being refused (seen in CI)
    sock.listen(128)
    port = sock.getsockname()[1]
    host = f"[{args.host}]" if family == socket.AF_INET6 else args.host
    daemons = ", ".join(f"{h}:{p}" for h, p in args.connect)
    print(f"occ-console: http://{host}:{port}/ watching {daemons}", flush=True)
    app = create_app(console)

    class Server(uvicorn.Server):
        def handle_exit(self, sig: int, frame: Any) -> None:
            begin_shutdown(app)  # the pages' event streams end first
            super().handle_exit(sig, frame)

    config = uvicorn.Config(
        app,
        log_level=args.log_level.lower(),
        access_log=False,
        # the event streams never end by themselves: Ctrl-C closes them after a second
        timeout_graceful_shutdown=1,
    )
    try:
        Server(config).run(sockets=[sock])
    except KeyboardInterrupt:  # uvicorn hands Ctrl-C back once it has shut down
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
