"""The ``igtl`` command: usage errors, dump of the reference vectors, bench, and real loopback
round trips (listen/connect/send over TCP and UDP, ephemeral ports, no sleeps used to sync).

In-process runs call ``igtl.cli.main([...])`` and read its exit code and captured output; the
listening side of a round trip runs as a subprocess (``python -m igtl.cli``) whose bound port
is read from its "listening on" line on stderr.
"""

from __future__ import annotations

import json
import os
import queue
import re
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import igtl
from igtl import cli

ROOT = Path(__file__).resolve().parents[2]
#: Generous bound for anything that should take milliseconds (a slow CI box, a cold import).
BOUND = 20.0


def _vector_dir() -> Path | None:
    candidates = [
        os.environ.get("IGTL_VECTORS"),
        ROOT / "tests" / "data" / "igtl-vectors",
    ]
    for c in candidates:
        if c and (Path(c) / "MANIFEST.json").is_file():
            return Path(c)
    return None


VECTORS = _vector_dir()
needs_vectors = pytest.mark.skipif(
    VECTORS is None,
    reason="reference vectors not found (tests/data/igtl-vectors, or set IGTL_VECTORS)",
)


def _manifest() -> list[dict[str, Any]]:
    assert VECTORS is not None
    return json.loads((VECTORS / "MANIFEST.json").read_text())


def _manifest_type(entry: dict[str, Any]) -> str:
    m = re.search(r"type='([^']*)'", entry.get("header", ""))
    assert m, entry
    return m.group(1)


@pytest.fixture()
def transport() -> Any:
    try:
        from igtl.transport import TCPClient, TCPServer, UDPEndpoint  # noqa: F401
    except ImportError as err:
        pytest.skip(f"igtl.transport not available yet: {err}")
    import igtl.transport

    return igtl.transport


def _json_lines(text: str) -> list[dict[str, Any]]:
    return [json.loads(line) for line in text.splitlines() if line.strip()]


# ------------------------------------------------------------------------------------------
# help and usage errors (exit 0 / 2)
@pytest.mark.parametrize("command", [[], ["listen"], ["connect"], ["send"], ["dump"], ["bench"]])
def test_help_everywhere_lists_exit_codes(
    command: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli.main([*command, "--help"]) == 0
    out = capsys.readouterr().out
    assert "usage: igtl" in out
    assert "exit codes:" in out and "3    timeout" in out
    assert "5    send: the peer answered a request FAIL" in out


def test_no_command_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main([]) == cli.EXIT_USAGE
    assert "COMMAND" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "hint"),
    [
        (["send", "localhost", "--type", "STRING"], "HOST:PORT"),
        (["send", "localhost:99999", "--type", "STRING"], "1..65535"),
        (["send", "127.0.0.1:1", "--device", "x"], "--type"),
        (["send", "127.0.0.1:1", "--type", "STRING", "--matrix", *["1"] * 16], "--matrix applies"),
        (["send", "127.0.0.1:1", "--type", "TRANSFORM", "--matrix", "1", "2"], "--matrix"),
        (
            ["send", "127.0.0.1:1", "--type", "STRING", "--meta", "a=b", "--header-version", "1"],
            "--header-version 2",
        ),
        (["send", "127.0.0.1:1", "--type", "STRING", "--meta", "novalue"], "KEY=VALUE"),
        (["send", "127.0.0.1:1", "--type", "NOSUCHTYPE"], "--json-body"),
        (["send", "127.0.0.1:1", "--type", "TOO_LONG_TYPE_NAME"], "1..12"),
        (["send", "127.0.0.1:1", "--type", "STRING", "--device", "d" * 21], "device"),
        (["send", "127.0.0.1:1", "--type", "STATUS", "--status-code", "NOPE"], "status code"),
        (["send", "127.0.0.1:1", "--type", "STRING", "--count", "0"], ">= 1"),
        (["send", "127.0.0.1:1", "--type", "STRING", "--rate", "-5"], "positive"),
        (["listen", "--port", "70000"], "0..65535"),
        (["listen", "--count", "x"], "whole number"),
        (["dump"], "FILE"),
        (["bench", "--type", "NOPE"], "no benchmark"),
        (["frobnicate"], "invalid choice"),
    ],
)
def test_usage_errors_exit_2_with_a_helpful_message(
    argv: list[str], hint: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli.main(argv) == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert "usage: igtl" in err
    assert hint in err


def test_json_body_with_unknown_field_is_a_usage_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    body = tmp_path / "body.json"
    body.write_text(json.dumps({"string": "hi", "colour": "red"}))
    argv = ["send", "127.0.0.1:1", "--type", "STRING", "--json-body", str(body)]
    assert cli.main(argv) == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert "colour" in err and "string" in err  # names the bad key and lists the good ones


# ------------------------------------------------------------------------------------------
# building messages from options (no sockets)
def _built(*options: str) -> igtl.Message:
    args = cli.build_parser().parse_args(["send", "127.0.0.1:1", *options])
    if args.header_version is None:
        args.header_version = 2 if (args.meta or args.message_id is not None) else 1
    args.message_id = args.message_id or 0
    return cli.build_message(args)


def test_matrix_option_is_row_major() -> None:
    rows = [[0, -1, 0, 10], [1, 0, 0, 20], [0, 0, 1, 30], [0, 0, 0, 1]]
    msg = _built(
        "--type", "TRANSFORM", "--device", "Tip", "--matrix", *(str(v) for row in rows for v in row)
    )
    assert isinstance(msg, igtl.TransformMessage)
    assert msg.matrix.tolist() == [[float(v) for v in row] for row in rows]
    assert msg.device_name == "Tip"


def test_position_quaternion_for_transform_and_position() -> None:
    t = _built(
        "--type",
        "transform",
        "--position",
        "1",
        "2",
        "3",
        "--quaternion",
        "0",
        "0",
        "0.7071067811865476",
        "0.7071067811865476",
    )
    assert t.matrix[:3, 3].tolist() == [1.0, 2.0, 3.0]
    assert t.matrix[0, 1] == pytest.approx(-1.0)  # 90 degrees about z
    p = _built("--type", "POSITION", "--position", "1", "2", "3")
    assert isinstance(p, igtl.PositionMessage) and p.position == (1.0, 2.0, 3.0)


def test_a_query_type_is_sent_as_named() -> None:
    """GET_TRANS, STP_TDATA, RTS_TDATA share a class each with their siblings: the message is
    the type named on the command line, not the class's default (GET_STATUS)."""
    for name in ("GET_TRANS", "GET_STATUS", "STP_TDATA", "RTS_TDATA"):
        assert _built("--type", name).message_type == name
        assert igtl.unpack(_built("--type", name).pack()).message_type == name


def test_meta_switches_to_header_version_2() -> None:
    msg = _built("--type", "STRING", "--string", "hi", "--meta", "k=v", "--meta", "e=")
    assert msg.header_version == 2 and dict(msg.metadata) == {"k": "v", "e": ""}


def test_status_code_by_name() -> None:
    msg = _built("--type", "STATUS", "--status-code", "not_ready", "--status-message", "wait")
    assert isinstance(msg, igtl.StatusMessage)
    assert (msg.code, msg.status_message) == (igtl.StatusCode.NOT_READY, "wait")


def test_json_body_for_a_known_and_an_unknown_type(tmp_path: Path) -> None:
    body = tmp_path / "t.json"
    body.write_text(json.dumps({"elements": list(range(12))}))
    t = _built("--type", "TRANSFORM", "--json-body", str(body))
    assert isinstance(t, igtl.TransformMessage) and t.elements == tuple(range(12))
    assert igtl.unpack(t.pack()).elements == tuple(float(v) for v in range(12))
    raw = tmp_path / "r.json"
    raw.write_text(json.dumps({"content": {"hex": "00ff10"}}))
    r = _built("--type", "X_VENDOR", "--json-body", str(raw))
    assert isinstance(r, igtl.RawMessage)
    assert (r.message_type, r.content) == ("X_VENDOR", b"\x00\xff\x10")


def test_json_body_arrays_and_nested_records(tmp_path: Path) -> None:
    image = tmp_path / "image.json"
    image.write_text(json.dumps({"pixels": [[1, 2, 3], [4, 5, 6]]}))
    img = _built("--type", "IMAGE", "--json-body", str(image))
    assert img.pixels.shape == (1, 2, 3, 1)  # type: ignore[attr-defined]
    assert str(img.pixels.dtype) == "int32"  # type: ignore[attr-defined]  JSON ints: not int64
    image.write_text(json.dumps({"pixels": {"data": [[1, 2], [3, 4]], "dtype": "uint16"}}))
    back = igtl.unpack(_built("--type", "IMAGE", "--json-body", str(image)).pack())
    assert back.pixels.reshape(2, 2).tolist() == [[1, 2], [3, 4]]  # type: ignore[attr-defined]
    assert back.pixels.dtype.itemsize == 2  # type: ignore[attr-defined]
    points = tmp_path / "points.json"
    points.write_text(json.dumps({"points": [{"name": "p1", "position": [1, 2, 3]}]}))
    pts = igtl.unpack(_built("--type", "POINT", "--json-body", str(points)).pack())
    assert pts.points[0].name == "p1"  # type: ignore[attr-defined]
    assert tuple(pts.points[0].position) == (1.0, 2.0, 3.0)  # type: ignore[attr-defined]


def test_command_options() -> None:
    msg = _built(
        "--type",
        "COMMAND",
        "--command-name",
        "MoveTo",
        "--command-text",
        "<x/>",
        "--command-id",
        "9",
    )
    back = igtl.unpack(msg.pack())
    assert (back.command_id, back.command_name, back.command) == (9, "MoveTo", "<x/>")  # type: ignore[attr-defined]


# ------------------------------------------------------------------------------------------
# dump (exit 0 / 1 / 4)
@needs_vectors
def test_dump_every_reference_vector_as_json(capsys: pytest.CaptureFixture[str]) -> None:
    assert VECTORS is not None
    entries = [e for e in _manifest() if e["file"] != "rtpwrapper.bin"]
    files = [str(VECTORS / e["file"]) for e in entries]
    assert cli.main(["dump", "--json", *files]) == cli.EXIT_OK
    records = _json_lines(capsys.readouterr().out)
    assert len(records) == len(entries)
    for entry, record in zip(entries, records, strict=True):
        assert record["file"].endswith(entry["file"])
        assert record["type"] == _manifest_type(entry)
        assert record["offset"] == 0
        assert record["device"] == re.search(r"device='([^']*)'", entry["header"]).group(1)
        assert record["header_version"] == int(entry["header"].split(",")[0].split("=")[1])
        assert isinstance(record["content"], dict)
    by_type = {r["type"]: r for r in records if r["header_version"] == 1}
    assert by_type["STRING"]["content"]["string"] == "Welcome to OpenIGTLink"
    assert by_type["TRANSFORM"]["content"]["elements"][9] == pytest.approx(46.0531, abs=1e-4)
    v2 = next(r for r in records if r["type"] == "TRANSFORM" and r["header_version"] == 2)
    assert v2["metadata"] == {"First patient age": "22", "Second patient age": "25"}
    assert v2["message_id"] == 1
    bind = by_type["BIND"]  # its children decoded, each like a message of its own
    assert [(c["type"], c["device"]) for c in bind["children"]] == [
        ("TRANSFORM", "ChildTrans"),
        ("IMAGE", "ChildImage"),
        ("SENSOR", "ChildSensor"),
    ]
    assert isinstance(bind["children"][0]["content"], dict)


@needs_vectors
def test_dump_reports_errors_with_offsets_and_continues(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert VECTORS is not None
    transform = (VECTORS / "transform.bin").read_bytes()
    string = (VECTORS / "string.bin").read_bytes()
    bad = bytearray(transform)
    bad[70] ^= 0xFF  # inside the body: CRC mismatch, header still sound
    path = tmp_path / "recording.bin"
    path.write_bytes(bytes(bad) + string + transform[:30])  # then a truncated message
    assert cli.main(["dump", str(path)]) == cli.EXIT_DECODE
    out, err = capsys.readouterr()
    assert out.splitlines()[0].startswith(f"@{len(transform)} STRING")  # continued past the error
    assert "CRCError at offset 58" in err
    assert f"TruncatedMessageError at offset {len(transform) + len(string)}" in err


@needs_vectors
def test_dump_unframeable_data_exits_4(capsys: pytest.CaptureFixture[str]) -> None:
    assert VECTORS is not None
    # Three RTP datagrams, not a message stream: the first "header" has version 0x8000.
    assert cli.main(["dump", str(VECTORS / "rtpwrapper.bin")]) == cli.EXIT_DECODE
    assert "UnknownHeaderVersionError at offset 0" in capsys.readouterr().err


def test_dump_missing_file_exits_1(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["dump", str(tmp_path / "nope.bin")]) == cli.EXIT_ERROR
    assert "cannot read" in capsys.readouterr().err


def test_dump_of_our_own_recording(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    msgs = [
        igtl.TransformMessage.from_position((1, 2, 3), device_name="Tip", timestamp=1.5),
        igtl.StringMessage(
            string="héllo", device_name="Cmd", header_version=2, metadata={"k": "v"}, message_id=7
        ),
        igtl.RawMessage(type_name="VENDOR_X", content=b"\x01\x02"),
    ]
    path = tmp_path / "rec.bin"
    path.write_bytes(b"".join(m.pack() for m in msgs))
    assert cli.main(["dump", "--json", str(path)]) == cli.EXIT_OK
    records = _json_lines(capsys.readouterr().out)
    assert [r["type"] for r in records] == ["TRANSFORM", "STRING", "VENDOR_X"]
    assert records[1]["content"]["string"] == "héllo"
    assert (records[1]["metadata"], records[1]["message_id"]) == ({"k": "v"}, 7)
    assert records[0]["timestamp"] == pytest.approx(1.5)


# ------------------------------------------------------------------------------------------
# bench
def test_bench_runs_and_prints_a_table(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["bench", "--type", "TRANSFORM", "--type", "string", "--n", "20", "--repeat", "1"]
    assert cli.main(argv) == cli.EXIT_OK
    out = capsys.readouterr().out
    assert "TRANSFORM" in out and "STRING" in out and "pack+unpack" in out


def test_bench_json(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["bench", "--type", "POSITION", "--n", "10", "--repeat", "1", "--json"]) == 0
    rows = _json_lines(capsys.readouterr().out)
    assert rows[0]["type_name"] == "POSITION" and rows[0]["impl"] == "igtl"
    assert rows[0]["unpack_us"] > 0


# ------------------------------------------------------------------------------------------
# real sockets on 127.0.0.1
class Listener:
    """``python -m igtl.cli listen ...`` as a subprocess; knows its bound address.

    Both pipes are read by threads of ours (never by ``communicate``, which would steal lines).
    """

    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "igtl.cli", "listen", "--port", "0", *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=ROOT,
        )
        self._err: queue.Queue[str | None] = queue.Queue()
        self.err_lines: list[str] = []
        self.out_lines: list[str] = []
        assert self.proc.stdout is not None and self.proc.stderr is not None
        self._threads = [
            threading.Thread(
                target=self._pump, args=(self.proc.stderr, self._err.put), daemon=True
            ),
            threading.Thread(
                target=self._pump, args=(self.proc.stdout, self.out_lines.append), daemon=True
            ),
        ]
        for t in self._threads:
            t.start()
        self.port = self._wait_port()

    @staticmethod
    def _pump(stream: Any, sink: Any) -> None:
        for line in stream:
            sink(line)
        sink(None)

    def _wait_port(self) -> int:
        while True:
            try:
                line = self._err.get(timeout=BOUND)
            except queue.Empty:
                raise AssertionError("listener did not report its port") from None
            if line is None:
                raise AssertionError(f"listener exited: {''.join(self.err_lines)}")
            self.err_lines.append(line)
            m = re.search(r"listening on \w+ .*:(\d+)$", line.strip())
            if m:
                return int(m.group(1))

    def finish(self) -> tuple[int, str, str]:
        """Wait for the listener to exit; its exit code, stdout and stderr."""
        try:
            self.proc.wait(timeout=BOUND)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()
        for t in self._threads:
            t.join(BOUND)
        while True:
            line = self._err.get(timeout=BOUND)
            if line is None:
                break
            self.err_lines.append(line)
        out = "".join(line for line in self.out_lines if line is not None)
        return self.proc.returncode, out, "".join(self.err_lines)


@pytest.fixture()
def listeners() -> Iterator[list[Listener]]:
    started: list[Listener] = []
    yield started
    for lst in started:
        if lst.proc.poll() is None:
            lst.proc.kill()
            lst.proc.wait()


@pytest.mark.slow  # a CLI subprocess
def test_listen_and_send_round_trip_tcp(transport: Any, listeners: list[Listener]) -> None:
    lst = Listener("--json", "--count", "3", "--timeout", str(BOUND))
    listeners.append(lst)
    target = f"127.0.0.1:{lst.port}"
    assert (
        cli.main(
            ["send", target, "--type", "TRANSFORM", "--device", "Tip", "--position", "1", "2", "3"]
        )
        == 0
    )
    assert (
        cli.main(
            [
                "send",
                target,
                "--type",
                "STRING",
                "--device",
                "Cmd",
                "--string",
                "héllo",
                "--meta",
                "MRMLNodeName=Cmd",
                "--message-id",
                "41",
                "--count",
                "2",
                "--rate",
                "200",
            ]
        )
        == 0
    )
    code, out, err = lst.finish()
    assert code == 0, err
    records = _json_lines(out)
    assert [r["type"] for r in records] == ["TRANSFORM", "STRING", "STRING"]
    assert records[0]["device"] == "Tip"
    assert records[0]["content"]["elements"][9:] == [1.0, 2.0, 3.0]
    assert records[0]["header_version"] == 1 and records[0]["timestamp"] > 1e9
    assert records[1]["content"]["string"] == "héllo"
    assert records[1]["metadata"] == {"MRMLNodeName": "Cmd"}
    assert [r["message_id"] for r in records[1:]] == [41, 42]
    assert all(r["peer"].startswith("127.0.0.1:") for r in records)


@pytest.mark.slow  # a CLI subprocess
def test_listen_and_send_round_trip_udp(transport: Any, listeners: list[Listener]) -> None:
    lst = Listener("--udp", "--json", "--count", "2", "--timeout", str(BOUND))
    listeners.append(lst)
    assert (
        cli.main(
            [
                "send",
                f"127.0.0.1:{lst.port}",
                "--udp",
                "--type",
                "POSITION",
                "--device",
                "Master",
                "--position",
                "4",
                "5",
                "6",
                "--header-version",
                "2",
                "--count",
                "2",
                "--rate",
                "500",
            ]
        )
        == 0
    )
    code, out, err = lst.finish()
    assert code == 0, err
    records = _json_lines(out)
    assert [r["content"]["position"] for r in records] == [[4.0, 5.0, 6.0]] * 2
    assert [r["message_id"] for r in records] == [0, 1]


@pytest.mark.slow  # a CLI subprocess
def test_send_many_over_tcp_delivers_every_message(
    transport: Any, listeners: list[Listener]
) -> None:
    # More messages than the client's send queue holds: send must pace itself, not drop.
    n = 3000
    lst = Listener("--json", "--count", str(n), "--timeout", str(BOUND))
    listeners.append(lst)
    argv = ["send", f"127.0.0.1:{lst.port}", "--type", "TRANSFORM", "--message-id", "0"]
    assert cli.main([*argv, "--count", str(n)]) == 0
    code, out, err = lst.finish()
    assert code == 0, err
    assert [r["message_id"] for r in _json_lines(out)] == list(range(n))


@pytest.mark.slow  # a CLI subprocess
def test_listen_human_output_and_peer_errors_on_stderr(
    transport: Any, listeners: list[Listener]
) -> None:
    lst = Listener("--count", "1", "--timeout", str(BOUND))
    listeners.append(lst)
    bad = bytearray(igtl.StringMessage(string="x", device_name="Bad").pack())
    bad[-1] ^= 0xFF  # CRC mismatch: the peer's error, reported, stream stays in sync
    good = igtl.StatusMessage(code=1, status_message="fine", device_name="Dev").pack()
    with socket.create_connection(("127.0.0.1", lst.port), timeout=BOUND) as s:
        s.sendall(bytes(bad) + good)
        code, out, err = lst.finish()
    assert code == 0, err
    line = out.strip()
    assert "STATUS" in line and "'Dev'" in line and "v1" in line and "fine" in line
    assert re.search(r"error from 127\.0\.0\.1:\d+: CRCError", err), err


def test_connect_to_a_server(transport: Any, capsys: pytest.CaptureFixture[str]) -> None:
    msgs = [igtl.TransformMessage.from_position((i, 0, 0), device_name="Base") for i in range(3)]

    def greet(peer: Any) -> None:
        for m in msgs:
            server.send(m, peer=peer)

    server = transport.TCPServer("127.0.0.1", 0, on_connect=greet)
    server.start()
    try:
        host, port = server.address[:2]
        code = cli.main(
            ["connect", f"{host}:{port}", "--json", "--count", "3", "--timeout", str(BOUND)]
        )
    finally:
        server.stop()
    out, err = capsys.readouterr()
    assert code == 0, err
    records = _json_lines(out)
    assert [r["content"]["elements"][9] for r in records] == [0.0, 1.0, 2.0]
    assert {r["device"] for r in records} == {"Base"}


def _refusing_port() -> socket.socket:
    """A bound TCP socket that does not listen: connecting to its port is refused at once."""
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.bind(("127.0.0.1", 0))
    return s


@pytest.mark.parametrize("command", ["connect", "send"])
def test_connection_refused_exits_1(
    transport: Any, command: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with _refusing_port() as s:
        target = f"127.0.0.1:{s.getsockname()[1]}"
        extra = ["--type", "STRING", "--string", "x"] if command == "send" else []
        code = cli.main([command, target, *extra, "--connect-timeout", "3"])
    assert code == cli.EXIT_ERROR
    assert f"cannot connect to {target}" in capsys.readouterr().err


def test_listen_timeout_with_fewer_than_count_exits_3(
    transport: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli.main(["listen", "--port", "0", "--count", "1", "--timeout", "0.2"]) == 3
    assert "received 0 of 1" in capsys.readouterr().err


def test_connect_timeout_with_fewer_than_count_exits_3(
    transport: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    server = transport.TCPServer("127.0.0.1", 0)
    server.start()
    try:
        host, port = server.address[:2]
        code = cli.main(["connect", f"{host}:{port}", "--count", "1", "--timeout", "0.2"])
    finally:
        server.stop()
    assert code == cli.EXIT_TIMEOUT
    assert "received 0 of 1" in capsys.readouterr().err


def test_listen_port_in_use_exits_1(transport: Any, capsys: pytest.CaptureFixture[str]) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        code = cli.main(["listen", "--port", str(s.getsockname()[1]), "--timeout", "0.1"])
    assert code == cli.EXIT_ERROR
    assert "cannot listen" in capsys.readouterr().err


def test_send_prints_the_answer_to_a_request(capsys: pytest.CaptureFixture[str]) -> None:
    """`igtl send` of a COMMAND waits for its RTS_COMMAND and prints it (a stream the server
    sends meanwhile is not an answer); --no-wait prints nothing."""
    from igtl.transport import TCPServer

    def answer(peer: object, msg: igtl.Message) -> None:
        server.send(igtl.TransformMessage.from_position((1, 2, 3), device_name="Tip"), peer)
        if msg.message_type == "COMMAND":
            reply = igtl.REGISTRY["RTS_COMMAND"](
                command_id=msg.command_id,
                command_name=msg.command_name,
                command='<CommandReply Status="SUCCESS"/>',
            )
            server.send(reply, peer)

    server = TCPServer("127.0.0.1", 0, on_message=answer).start()
    try:
        target = f"127.0.0.1:{server.address[1]}"
        assert cli.main(["send", target, "--type", "COMMAND", "--command-name", "GetState"]) == 0
        out = capsys.readouterr().out
        assert out.count("RTS_COMMAND") == 1 and "TRANSFORM" not in out
        assert "SUCCESS" in out
        assert (
            cli.main(
                ["send", target, "--type", "COMMAND", "--command-name", "GetState", "--no-wait"]
            )
            == 0
        )
        assert capsys.readouterr().out == ""
    finally:
        server.stop()


def _refusing_daemon(status: str, error: str) -> Any:
    """A TCP server answering each request as the OCC daemon's operator desk does
    (occ/net/commands.py: RTS_COMMAND with metadata and XML, ACK_ STRING with XML, an error
    STATUS to a query), with ``status`` (SUCCESS or FAIL) and ``error``."""
    from igtl.transport import TCPServer
    from occ.net.commands import Request, error_reply, success_reply

    def answer(peer: object, msg: igtl.Message) -> None:
        if msg.message_type == "COMMAND":
            req = Request("command", msg.command_name, msg=msg)  # type: ignore[attr-defined]
        elif msg.message_type == "STRING":
            req = Request("string", "Run", msg=msg)
        else:
            server.send(error_reply(msg, error), peer)
            return
        ok = status == "SUCCESS"
        server.send(
            success_reply(req, "ENABLED -> RUNNING") if ok else error_reply(msg, error), peer
        )

    server = TCPServer("127.0.0.1", 0, on_message=answer).start()
    return server


@pytest.mark.req("SR-REPLY-4")
@pytest.mark.parametrize(
    "request_args",
    [
        ["--type", "COMMAND", "--command-name", "Run"],
        ["--type", "COMMAND", "--command-name", "Run", "--header-version", "2"],
        ["--type", "STRING", "--device", "CMD_7", "--string", '<Command Name="Run"/>'],
    ],
)
def test_send_exits_5_when_the_daemon_answers_fail(
    request_args: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    """A FAIL answer (RTS_COMMAND Status=FAIL, an ACK_ STRING saying FAIL) is exit 5 with the
    reply's error on stderr; the reply itself is printed as any answer; SUCCESS is exit 0."""
    why = "the robot is READY; send Enable first"
    server = _refusing_daemon("FAIL", why)
    try:
        target = f"127.0.0.1:{server.address[1]}"
        assert cli.main(["send", target, *request_args]) == cli.EXIT_REFUSED == 5
        out, err = capsys.readouterr()
        assert "FAIL" in out  # the reply, as printed for any answer
        (line,) = err.splitlines()
        assert line.startswith("igtl: ") and line.endswith(f": FAIL: {why}"), line
    finally:
        server.stop()
    server = _refusing_daemon("SUCCESS", "")
    try:
        target = f"127.0.0.1:{server.address[1]}"
        assert cli.main(["send", target, *request_args]) == cli.EXIT_OK
        assert capsys.readouterr().err == ""
    finally:
        server.stop()


@pytest.mark.req("SR-REPLY-4")
def test_send_exits_5_on_a_refused_query_but_not_on_a_status_answer(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A query refused with an error STATUS is a refusal; GET_STATUS's answer is a STATUS
    whatever its code, never one."""
    server = _refusing_daemon("FAIL", "no such device")
    try:
        target = f"127.0.0.1:{server.address[1]}"
        assert cli.main(["send", target, "--type", "GET_TRANS", "--device", "Nope"]) == 5
        assert "no such device" in capsys.readouterr().err
        assert cli.main(["send", target, "--type", "GET_STATUS"]) == cli.EXIT_OK
    finally:
        server.stop()


@pytest.mark.req("SR-REPLY-4")
def test_refusal_reads_every_reply_form() -> None:
    cmd = igtl.CommandMessage(command_id=1, command_name="Run", command="", header_version=2)
    rts = igtl.REGISTRY["RTS_COMMAND"]
    # metadata first, the XML content when there is none (a v1 reply), the reference's bare one
    meta = rts(command_id=1, command_name="Run", command="", header_version=2,
               metadata={"Status": "FAIL", "Error": "no"})  # fmt: skip
    assert cli.refusal(meta, cmd) == "Run: FAIL: no"
    xml = rts(command_id=1, command_name="Run",
              command='<CommandReply Status="FAIL" Message="not now" />')  # fmt: skip
    assert cli.refusal(xml, cmd) == "Run: FAIL: not now"
    bare = rts(command_id=1, command_name="Run", command='<CommandReply Status="FAIL" />')
    assert cli.refusal(bare, cmd) == "Run: FAIL: (no reason given)"
    ok = rts(command_id=1, command_name="Run", command='<CommandReply Status="SUCCESS" />')
    assert cli.refusal(ok, cmd) is None
    assert cli.refusal(rts(command_id=1, command_name="Run", command="not xml <"), cmd) is None
    ack = igtl.StringMessage('<CommandReply Name="Run" Status="FAIL" Error="x" />',
                             device_name="ACK_1")  # fmt: skip
    assert cli.refusal(ack, cmd) == "Run: FAIL: x"


def test_send_says_when_a_request_is_not_answered(capsys: pytest.CaptureFixture[str]) -> None:
    from igtl.transport import TCPServer

    server = TCPServer("127.0.0.1", 0, on_message=lambda p, m: None).start()
    try:
        target = f"127.0.0.1:{server.address[1]}"
        code = cli.main(["send", target, "--type", "GET_STATUS", "--wait", "0.3"])
        assert code == 0
        assert "1 of 1 request(s) not answered within 0.3 s" in capsys.readouterr().err
    finally:
        server.stop()
