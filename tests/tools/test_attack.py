"""CI version of the attack harness (tools/attack.py --quick): every hostile-input case against
running daemons on loopback, about a second each.

Only the deterministic verdicts are asserted: the daemon is alive, answers a GET_STATUS on a
fresh connection, nothing moved that should not (READY: the Tip bit for bit; RUNNING: the slave
follows its master only), and the case's own counter shows the attack seen and refused. Loop
lateness and RSS are reported by the tool, never judged here (a loaded 2-core machine).

``no-read`` and ``udp-flood`` were the two cases the daemon once lost (clients that never
read held their slots for minutes of kernel buffers; a flood crowded the master's datagrams out
of the stream socket's buffer). Both are resisted now: a client's shrinking receive window
shows it does not read, and the stream socket is pinned to its master, so the kernel drops
other senders' datagrams. ``KNOWN_FAILING`` stays as the place for a case that must be marked
``xfail(strict=True)`` (the day it passes, the test says so).
"""

from __future__ import annotations

import pytest

from .tooling import load_tool

attack = load_tool("attack")

KNOWN_FAILING: set[str] = set()


@pytest.fixture(scope="module")
def rows(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    out = tmp_path_factory.mktemp("attack")
    st = attack.Settings(
        quick=True,
        baseline_s=0.5,
        attack_s=1.0,
        out=out,
        message_timeout_s=1.5,
        send_stall_timeout_s=1.0,
    )
    result, finals = attack.run(list(attack.CASES), st)
    # exit codes are reported, not asserted: a VM pause can fault a daemon (exit 3) by itself
    print(attack.table(result), finals)
    return {r.case: r for r in result}


@pytest.mark.realtime
@pytest.mark.parametrize(
    "case",
    [
        pytest.param(c, marks=pytest.mark.xfail(strict=True, reason="see the module docstring"))
        if c in KNOWN_FAILING
        else c
        for c in attack.CASES
    ],
)
def test_the_daemon_resists(rows: dict[str, object], case: str) -> None:
    row = rows[case]
    if row.skipped:  # type: ignore[attr-defined]
        pytest.skip(row.skipped)  # type: ignore[attr-defined]
    assert row.alive, f"{case}: the daemon died"  # type: ignore[attr-defined]
    assert row.answered, f"{case}: no GET_STATUS answer after the attack"  # type: ignore[attr-defined]
    assert row.not_moved, f"{case}: {row.moved}"  # type: ignore[attr-defined]
    assert row.check, f"{case}: {row.counter}; {row.note}"  # type: ignore[attr-defined]


def test_raw_names_and_headers_are_what_a_hostile_peer_sends() -> None:
    import igtl

    data = attack.cmd_string('<Command Name="GetState"/>').pack()
    forged = attack.with_device_name(data, b"CMD_" + b"\xff" * 16)
    assert forged[14:34] == b"CMD_" + b"\xff" * 16 and forged[34:] == data[34:]
    head = attack.header_only("IMAGE", 200 * 1024 * 1024)
    assert len(head) == 58
    dec = igtl.StreamDecoder(max_body_size=1024 * 1024)  # the daemon's default limit
    dec.feed(head)
    with pytest.raises(igtl.BodyTooLargeError):
        dec.next_message()
    blob = igtl.unpack(attack.raw_message("ATTACKBLOB", b"x" * 100))
    assert blob.message_type == "ATTACKBLOB"
