"""Operator requests: parsing (COMMAND, PLUS-style STRING, queries) and the reply each sender
expects (occ/net/commands.py). Pure functions: no robot, no sockets.

Each expectation here is one the operators rely on (the reply names the request it answers, in
the form its sender speaks, with the refusal's reason); several were written to catch faults
the robot-level tests let through (mutation testing, docs/VERIFICATION.md).
"""

from __future__ import annotations

import pytest

import igtl
from occ.net.commands import (
    MAX_XML_BYTES,
    Deferred,
    Request,
    error_reply,
    parse_request,
    safe_name,
    success_reply,
)
from occ.errors import CommandError


def command(name: str = "", xml: str = "", **kw) -> igtl.Message:
    return igtl.CommandMessage(
        command_id=kw.pop("command_id", 41),
        command_name=name,
        command=xml,
        device_name=kw.pop("device_name", "Slicer"),
        header_version=2,
        message_id=kw.pop("message_id", 9),
        **kw,
    )


def string(text: str, device: str = "CMD_17", version: int = 2) -> igtl.Message:
    return igtl.StringMessage(text, device_name=device, header_version=version, message_id=5)


# ------------------------------------------------------------------------------- parsing
def test_command_name_from_the_field_or_the_xml():
    assert parse_request(command("  Run ")) == Request("command", "Run", {}, command("  Run "))
    req = parse_request(command("Ignored", '<Command Name="Enable" Speed="2" />'))
    assert (req.kind, req.name, req.args) == ("command", "Enable", {"Speed": "2"})
    req = parse_request(command("Stop", '<Command Speed="2" />'))  # no name in the XML
    assert (req.name, req.args) == ("Stop", {"Speed": "2"})
    req = parse_request(command("", '<Command name="Reset" />'))  # lower-case attribute
    assert (req.name, req.args) == ("Reset", {})
    req = parse_request(command("Hold", '<Command Name="" name="Run" To="x" />'))
    assert (req.name, req.args) == ("Run", {"To": "x"})
    with pytest.raises(CommandError, match="^COMMAND without a command name$"):
        parse_request(command("", '<Command Speed="2" />'))
    with pytest.raises(CommandError, match="^COMMAND without a command name$"):
        parse_request(command("  "))


def test_plus_style_strings():
    req = parse_request(string(" Enable "))
    assert (req.kind, req.name, req.args) == ("string", "Enable", {})
    req = parse_request(string('<Command Name="GetStats" Format="json"/>'))
    assert (req.kind, req.name, req.args) == ("string", "GetStats", {"Format": "json"})
    with pytest.raises(CommandError, match="^empty command in STRING 'CMD_17'$"):
        parse_request(string("   "))
    with pytest.raises(CommandError, match="^empty command in STRING 'CMD_17'$"):
        parse_request(string('<Command Speed="1"/>'))


def test_queries_and_what_is_not_a_request():
    for mtype in ("GET_STATUS", "STT_TDATA", "STP_TDATA"):
        msg = igtl.RawMessage(type_name=mtype, device_name="d")
        req = parse_request(msg)
        assert (req.kind, req.name, req.args, req.msg) == ("query", mtype, {}, msg)
    with pytest.raises(CommandError, match="^TRANSFORM is not an operator request$"):
        parse_request(igtl.TransformMessage())


def test_xml_limits_exactly():
    pad = MAX_XML_BYTES - len('<Command Name="Run" A="" />')
    fits = f'<Command Name="Run" A="{"x" * pad}" />'
    assert len(fits) == MAX_XML_BYTES
    assert parse_request(string(fits)).name == "Run"
    over = fits.replace('A="', 'A="x', 1)
    with pytest.raises(CommandError) as e:
        parse_request(string(over))
    assert str(e.value) == f"XML command too long ({MAX_XML_BYTES + 1} characters, limit 8192)"
    with pytest.raises(CommandError) as e:
        parse_request(string('<!DOCTYPE x><Command Name="Run"/>'))
    assert str(e.value) == "XML command refused: DOCTYPE, ENTITY and CDATA are not accepted"
    with pytest.raises(CommandError, match="^malformed XML command: "):
        parse_request(string('<Command Name="Run"'))


# ------------------------------------------------------------------------------- replies
def test_a_command_is_answered_by_rts_command_naming_it():
    req = parse_request(command("Run"))
    ok = success_reply(req, "IDLE -> RUNNING", timestamp=12.5)
    assert ok.message_type == "RTS_COMMAND"
    assert (ok.command_id, ok.command_name, ok.device_name) == (41, "Run", "Slicer")
    assert (ok.header_version, ok.message_id, ok.timestamp) == (2, 9, 12.5)
    assert ok.metadata == {"Status": "SUCCESS", "Message": "IDLE -> RUNNING"}
    assert ok.command == '<CommandReply Name="Run" Status="SUCCESS" Message="IDLE -&gt; RUNNING" />'
    bad = error_reply(command("Run"), "not now", timestamp=3.0)
    assert bad.message_type == "RTS_COMMAND" and bad.command_name == "Run"
    assert (bad.command_id, bad.message_id, bad.timestamp) == (41, 9, 3.0)
    assert bad.metadata == {"Status": "FAIL", "Message": "not now", "Error": "not now"}
    assert bad.command == (
        '<CommandReply Name="Run" Status="FAIL" Error="not now" Message="not now" />'
    )
    nameless = error_reply(command(""), "COMMAND without a command name")
    assert nameless.command_name == "" and nameless.command.startswith(
        '<CommandReply Status="FAIL"'
    )


def test_a_plus_string_is_answered_by_its_ack():
    req = parse_request(string("Enable"))
    ok = success_reply(req, "done", timestamp=1.0)
    assert ok.message_type == "STRING" and ok.device_name == "ACK_17"
    assert (ok.header_version, ok.message_id, ok.timestamp) == (2, 5, 1.0)
    assert ok.string == '<CommandReply Name="Enable" Status="SUCCESS" Message="done" />'
    bad = error_reply(string("Enable", version=1), "refused <why>")
    assert bad.message_type == "STRING" and bad.device_name == "ACK_17"
    assert bad.header_version == 1 and bad.message_id == 5
    assert bad.string == (
        '<CommandReply Status="FAIL" Error="refused &lt;why&gt;" Message="refused &lt;why&gt;" />'
    )
    with pytest.raises(ValueError, match="^queries are answered with the requested message type$"):
        success_reply(Request("query", "GET_STATUS", {}, igtl.StatusMessage()))


def test_a_refused_stream_request_gets_its_rts_with_an_error_status():
    for mtype in ("STT_TDATA", "STP_TDATA"):
        msg = igtl.RawMessage(type_name=mtype, device_name="Trk", header_version=2)
        reply = error_reply(msg, "no", timestamp=4.0)
        assert reply.message_type == "RTS_TDATA"
        assert (reply.status, reply.device_name, reply.header_version, reply.timestamp) == (
            1,
            "Trk",
            2,
            4.0,
        )


def test_anything_else_is_answered_by_a_status_with_the_code_and_reason():
    msg = igtl.unpack(
        igtl.RawMessage(
            type_name="GET_STATUS", device_name="Q", header_version=2, message_id=77
        ).pack()
    )
    reply = error_reply(
        msg, "GET_STATUS is not supported by arm", code=igtl.StatusCode.ACCESS_DENIED, timestamp=2.0
    )
    assert reply.message_type == "STATUS"
    assert (reply.code, reply.subcode, reply.error_name) == (
        int(igtl.StatusCode.ACCESS_DENIED),
        0,
        "ACCESS_DENIED",
    )
    assert reply.status_message == "GET_STATUS is not supported by arm"
    assert (reply.device_name, reply.header_version, reply.message_id, reply.timestamp) == (
        "Q",
        2,
        77,
        2.0,
    )
    assert error_reply(msg, "x").code == int(igtl.StatusCode.UNKNOWN_ERROR)
    # a STRING that is not CMD_ is not answered as a PLUS command
    plain = error_reply(string("Run", device="Note"), "not a command")
    assert plain.message_type == "STATUS" and plain.device_name == "Note"
    # an STT_ without an RTS_ class of the query family: a STATUS too
    odd = igtl.unpack(igtl.RawMessage(type_name="STT_NOPE", device_name="N").pack())
    assert error_reply(odd, "unknown").message_type == "STATUS"
    # a STRING named CMD_ by a non-STRING type is not an ACK either
    status = error_reply(igtl.StatusMessage(device_name="CMD_1"), "no")
    assert status.message_type == "STATUS"


def test_names_are_always_packable():
    assert safe_name("Tip") == "Tip"
    assert safe_name("x" * 20) == "x" * 20
    assert safe_name("x" * 21) == "x" * 20
    assert safe_name("é" * 11) == "é" * 10  # 22 bytes cut at a character boundary
    assert safe_name("ab\ud800") == "ab?"  # a lone surrogate cannot be encoded
    assert safe_name("x" * 200, 128) == "x" * 128
    reply = success_reply(parse_request(command("", f'<Command Name="{"R" * 200}"/>')), "ok")
    assert reply.command_name == "R" * 128
    reply.pack()  # packs: names cut to what the wire holds
    ack = error_reply(string("Run", device="CMD_" + "u" * 16), "no")
    assert ack.device_name == "ACK_" + "u" * 16
    ack = error_reply(string("Run", device="CMD_" + "é" * 8), "no")
    assert ack.device_name == "ACK_" + "é" * 8
    undecodable = success_reply(Request("command", "Run\ud800", {}, command("Run")), "m\udcff")
    assert undecodable.command_name == "Run?"
    undecodable.pack()


# ------------------------------------------------------------------------------ Deferred
def test_a_deferred_answer_is_delivered_once_bound_or_not():
    d = Deferred()
    assert not d.done and d.result is None
    got: list = []
    d.bind(lambda ok, text: got.append((ok, text)))
    d.fail("no path")
    d.resolve("late")  # the first answer stands
    assert got == [(False, "no path")] and d.done and d.result == (False, "no path")
    d = Deferred()
    d.resolve("planned")
    got = []
    d.bind(lambda ok, text: got.append((ok, text)))
    assert got == [(True, "planned")]


def test_a_name_cut_through_a_character_loses_the_broken_character_only():
    from occ.net.commands import safe_name

    name = "a" + "é" * 10  # 21 bytes: the 20-byte cut falls inside the last é
    assert safe_name(name) == "a" + "é" * 9
    assert safe_name("é" * 10) == "é" * 10  # exactly 20 bytes: kept whole


def test_reply_builders_default_to_an_empty_message_and_no_timestamp():
    """Called without them, the builders stamp nothing (0: the reference's "unused") and say
    nothing beyond the status: callers that want a time or a text pass it."""
    from occ.net.commands import error_reply, parse_request, success_reply

    cmd = igtl.CommandMessage(command_id=3, command_name="Ping", device_name="CMD", command="")
    req = parse_request(cmd)
    ok = success_reply(req)
    assert ok.timestamp == 0.0
    assert ok.metadata == {"Status": "SUCCESS", "Message": ""}
    bad = error_reply(cmd, "no")
    assert bad.timestamp == 0.0 and bad.metadata["Error"] == "no"
    status = error_reply(igtl.StringMessage("x", device_name="TXT"), "refused")
    assert status.timestamp == 0.0
    assert status.code == int(igtl.StatusCode.UNKNOWN_ERROR)
