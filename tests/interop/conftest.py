"""Interop fixtures: reference C++ peers, pyigtl, and our own transports, all on 127.0.0.1.

Skip / require logic
--------------------
- The reference peers are the OpenIGTLink example programs built by
  ``bash scripts/install_reference_peers.sh`` into ``$OCC_IGTL_EXAMPLES/bin`` (default
  ``.cache/igtl-examples/bin``). pyigtl comes from the ``test`` extra.
- When a peer is missing (the whole bin folder, one program, or pyigtl), the tests that need it
  are *skipped* with the reason, e.g. "reference OpenIGTLink examples not built: run bash
  scripts/install_reference_peers.sh".
- With ``OCC_REQUIRE_INTEROP=1`` (CI) the same situation *fails* those tests instead (the session
  fixture raises ``pytest.fail``), so a CI run cannot go green without interop.

Every subprocess is started through the ``ref`` fixtures and killed (by its own pid) in
teardown; ports are picked free; synchronisation polls with timeouts, never fixed sleeps.
"""

from __future__ import annotations

import signal
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from . import helpers as h

#: programs whose absence means "the examples were not built at all"
CORE_PROGRAMS = ("TrackerClient", "TrackerServer", "ReceiveServer")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    here = Path(__file__).parent
    for item in items:
        if here in Path(str(item.fspath)).parents:
            item.add_marker(pytest.mark.interop)


def pytest_report_header(config: pytest.Config) -> str:
    b = h.examples_bin()
    n = len(list(b.iterdir())) if b.is_dir() else 0
    try:
        import pyigtl

        py = getattr(pyigtl, "__version__", "installed")
    except ImportError:
        py = "missing"
    return (
        f"interop: reference examples {b} ({n} programs), pyigtl {py}, "
        f"{h.REQUIRE_ENV}={'1' if h.interop_required() else '0'}"
    )


# --------------------------------------------------------------------------------------------
# peers available?
@pytest.fixture(scope="session")
def reference_bin() -> Path:
    """The folder with the reference example programs; skip (or fail under CI) if not built."""
    b = h.examples_bin()
    missing = [p for p in CORE_PROGRAMS if not (b / p).is_file()]
    if missing:
        h.skip_or_fail(
            f"reference OpenIGTLink examples not built: {h.INSTALL_HINT} "
            f"(looked in {b}, missing {', '.join(missing)}; override with {h.EXAMPLES_ENV})"
        )
    return b


@pytest.fixture(scope="session")
def pyigtl() -> Any:
    try:
        import pyigtl as mod
    except ImportError as err:
        h.skip_or_fail(f"pyigtl is not importable ({err}): pip install -e '.[test]'")
    return mod


@pytest.fixture(scope="session")
def transport() -> Any:
    """Our transports. Not a peer: if it is missing or broken the tests error out."""
    from igtl import transport as t

    return t


# --------------------------------------------------------------------------------------------
# reference peer processes
@pytest.fixture
def ref(reference_bin: Path) -> Iterator[Callable[..., h.RefPeer]]:
    """``ref("TrackerClient", "127.0.0.1", port, 50)`` starts a program; killed at teardown."""
    peers: list[h.RefPeer] = []

    def start(program: str, *args: Any) -> h.RefPeer:
        exe = reference_bin / program
        if not exe.is_file():
            h.skip_or_fail(
                f"reference program {program} not built in {reference_bin}: {h.INSTALL_HINT}"
            )
        peer = h.RefPeer(exe, args)
        peers.append(peer)
        return peer

    yield start
    for peer in peers:
        peer.stop()
        # shown by pytest only when the test failed
        print(f"--- {peer.describe()}")


@pytest.fixture
def ref_server(ref: Callable[..., h.RefPeer]) -> Callable[..., tuple[h.RefPeer, int]]:
    """``peer, port = ref_server("TrackerServer", "{port}", 50)``: a reference *server* on a free
    port, returned once it listens (polled via /proc, no probe connection)."""

    def start(program: str, *args: Any) -> tuple[h.RefPeer, int]:
        last = ""
        for _attempt in range(3):  # a free port can be taken between pick and bind
            port = h.free_port()
            peer = ref(program, *(str(a).format(port=port) for a in args))
            ok = h.poll(lambda: h.is_listening(port) is not False or not peer.alive(), 5.0)
            if ok and peer.alive():
                return peer, port
            last = peer.describe()
            peer.stop()
        pytest.fail(f"{program} did not start listening: {last}")

    return start


# --------------------------------------------------------------------------------------------
# our transports
@pytest.fixture
def igtl_server(transport: Any) -> Iterator[Callable[..., Any]]:
    servers: list[Any] = []

    def make(**kw: Any) -> Any:
        srv = transport.TCPServer(host="127.0.0.1", port=0, **kw)
        servers.append(srv)
        srv.start()
        return srv

    yield make
    for srv in servers:
        srv.stop()


@pytest.fixture
def igtl_client(transport: Any) -> Iterator[Callable[..., Any]]:
    clients: list[Any] = []

    def make(port: int, host: str = "127.0.0.1", connect: bool = True, **kw: Any) -> Any:
        cli = transport.TCPClient(host, port, **kw)
        clients.append(cli)
        cli.start()
        if connect:
            assert cli.wait_connected(h.WAIT), f"TCPClient could not connect to {host}:{port}"
        return cli

    yield make
    for cli in clients:
        cli.stop()


# --------------------------------------------------------------------------------------------
# pyigtl peers
@pytest.fixture
def pyigtl_server(pyigtl: Any) -> Iterator[Callable[[], tuple[Any, int]]]:
    """A pyigtl server on 127.0.0.1:<free>; returns (server, port). Stopped at teardown and its
    SIGINT/SIGTERM handlers (pyigtl installs its own) restored."""
    made: list[Any] = []
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}

    def make() -> tuple[Any, int]:
        srv = pyigtl.OpenIGTLinkServer(port=0, local_server=True)
        made.append(srv)
        return srv, srv.server_address[1]

    yield make
    for srv in made:
        srv.stop()
    for s, handler in saved.items():
        signal.signal(s, handler)


@pytest.fixture
def pyigtl_client(pyigtl: Any) -> Iterator[Callable[[int], Any]]:
    made: list[Any] = []

    def make(port: int) -> Any:
        cli = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=port)
        made.append(cli)
        assert h.poll(cli.is_connected), f"pyigtl client could not connect to port {port}"
        return cli

    yield make
    for cli in made:
        cli.stop()
