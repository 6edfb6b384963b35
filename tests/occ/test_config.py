"""Tests of occ.config: loading, strictness, located error messages, cross-field rules, docs."""

from __future__ import annotations

import ipaddress
import json
import re
from pathlib import Path

import pydantic
import pytest

from occ.config import DaemonConfig, InterfaceConfig
from occ.configdoc import DOC_BEGIN, DOC_END, config_reference_markdown
from occ.errors import ConfigError, OCCError
from occ.core.loader import load_config, parse_config

DATA = Path(__file__).parent / "data"
ROOT = Path(__file__).resolve().parents[2]

MINIMAL_ROBOT = """\
robot:
  name: r
  frame: {model: occ_slave}
  joints:
    - {name: a, limits: {min: -1, max: 1, velocity: 1}}
  drivers:
    - {name: d, plugin: sim, joints: [a]}
"""


def errors_of(text: str, **kwargs: object) -> list[str]:
    with pytest.raises(ConfigError) as info:
        parse_config(text, source="c.yaml", **kwargs)  # type: ignore[arg-type]
    assert str(info.value) == "\n".join(info.value.errors)
    return info.value.errors


# ---------------------------------------------------------------------------- valid files


def test_valid_slave_loads_with_every_section() -> None:
    cfg = load_config(DATA / "valid_slave.yaml")
    robot = cfg.robot
    assert robot.name == "slave" and robot.rate_hz == 1000 and robot.period_s == 0.001
    assert robot.joint_names == ("yaw", "insertion")
    yaw = robot.joint("yaw")
    assert yaw.limits.effort == 10.0 and yaw.pid is not None and yaw.pid.kd == 5.0
    assert robot.joint("insertion").type == "prismatic"
    assert robot.joint("insertion").pid is None
    assert robot.drivers[0].on_limit == "fault" and robot.drivers[0].params == {"noise_std": 0.0}
    assert (robot.realtime.fifo_priority, robot.realtime.cpu) == (80, 2)
    slicer, master = cfg.interfaces
    assert cfg.interface("master") is master
    assert slicer.role == "operator" and [o.device for o in slicer.outputs] == ["Tip", "Base"]
    assert slicer.allowed_peers == (
        ipaddress.ip_network("127.0.0.1/32"),
        ipaddress.ip_network("10.0.0.0/8"),
    )
    assert slicer.peer_allowed("10.1.2.3") and not slicer.peer_allowed("192.168.0.1")
    assert not slicer.peer_allowed("not an ip")
    assert master.remote_address == ("127.0.0.1", 18946)
    assert master.inputs[0].queue == "stream" and master.inputs[0].device is None
    assert cfg.safety.watchdog.policy == "fault" and cfg.safety.watchdog.budget_us == 800
    assert cfg.safety.loss.input == "master" and cfg.safety.loss.deadline_ms == 20
    assert cfg.controller is None


def test_master_defaults() -> None:
    cfg = load_config(DATA / "valid_master.yaml")
    assert cfg.robot.rate_hz == 1000
    assert cfg.robot.frame.model == "master3" and cfg.robot.frame.urdf is None
    joint = cfg.robot.joints[0]
    assert (joint.home, joint.pid, joint.limits.effort) == (0.0, None, None)
    driver = cfg.robot.drivers[0]
    assert (driver.on_limit, driver.params) == ("clamp", {})
    rt = cfg.robot.realtime
    assert (rt.fifo_priority, rt.cpu, rt.gc) == (None, None, "freeze")
    assert cfg.interfaces == ()
    wd = cfg.safety.watchdog
    assert (wd.budget_us, wd.alert_run, wd.stop_run, wd.hard_gap_ms, wd.policy) == (
        1000,
        1,
        5,
        10.0,
        "hold",
    )
    loss = cfg.safety.loss
    assert (loss.enabled, loss.input, loss.period_ms, loss.max_consecutive) == (
        True,
        None,
        2.0,
        2,
    )
    assert (loss.deadline_ms, loss.policy) == (None, "hold")
    rec = cfg.recording
    assert (rec.path, rec.rate_hz, rec.include_messages) == (None, 100.0, True)
    assert cfg.stats.log_every_s == 10.0 and cfg.controller is None


def test_interface_defaults() -> None:
    itf = InterfaceConfig(name="x", transport="tcp-server")
    assert (itf.host, itf.port, itf.remote) == ("127.0.0.1", 18944, None)
    assert itf.allowed_peers == (ipaddress.ip_network("127.0.0.1"),)
    assert (itf.role, itf.header_version, itf.max_clients, itf.send_queue) == (
        "none",
        2,
        8,
        256,
    )
    assert (itf.idle_timeout_s, itf.inputs, itf.outputs) == (None, (), ())
    cfg = parse_config(
        MINIMAL_ROBOT + "interfaces:\n  - {name: s, transport: udp, inputs: [{type: POSITION}]}\n"
    )
    inp = cfg.interfaces[0].inputs[0]
    assert (inp.device, inp.queue, inp.depth) == (None, "stream", 10)


def test_models_are_frozen_and_lists_are_tuples() -> None:
    cfg = load_config(DATA / "valid_slave.yaml")
    with pytest.raises(pydantic.ValidationError):
        cfg.robot.rate_hz = 10  # type: ignore[misc]
    assert isinstance(cfg.robot.joints, tuple) and isinstance(cfg.interfaces, tuple)


def test_dump_and_revalidate_round_trip() -> None:
    cfg = load_config(DATA / "valid_slave.yaml")
    again = DaemonConfig.model_validate_json(cfg.model_dump_json())
    assert again == cfg


def test_controller_params_are_validated_with_lines() -> None:
    cfg = parse_config(MINIMAL_ROBOT + "controller: {plugin: teleop-slave, params: {scale: 0.2}}\n")
    assert cfg.controllers[0].plugin == "teleop-slave" and cfg.controllers[0].params == {
        "scale": 0.2
    }
    text = MINIMAL_ROBOT + (
        "controller:\n  plugin: teleop-slave\n  params:\n    scael: 0.2\n"
        "    input_interface: nope\n    phase_lock_us: fast\n"
    )
    with pytest.raises(ConfigError) as exc:
        parse_config(text, source="c.yaml")
    n = MINIMAL_ROBOT.count("\n")
    assert exc.value.errors == [
        f"c.yaml:{n + 4} controller.params.scael: unknown field 'scael' (did you mean 'scale'?)",
        f"c.yaml:{n + 6} controller.params.phase_lock_us: expected a number, got 'fast'",
    ]
    with pytest.raises(ConfigError) as exc:
        parse_config(text.replace("    scael: 0.2\n", "").replace("    phase_lock_us: fast\n", ""))
    assert "controller.params.input_interface: unknown interface 'nope'" in str(exc.value)
    with pytest.raises(ConfigError, match=r"controller.plugin: unknown controller plugin 'telep'"):
        parse_config(MINIMAL_ROBOT + "controller: {plugin: telep}\n")


def test_driver_params_are_checked_at_load() -> None:
    """A driver parameter typo fails `occd --check` with its line, not the daemon at start."""
    text = MINIMAL_ROBOT.replace("joints: [a]}", "joints: [a], params: {bandwith_hz: 30}}")
    with pytest.raises(
        ConfigError, match=r"robot.drivers\[0\].params: .*unknown params \['bandwith_hz'\]"
    ):
        parse_config(text)


# ---------------------------------------------------------------------------- paths


def test_relative_urdf_resolves_against_the_config_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)  # the working directory must not matter
    cfg = load_config(DATA / "valid_slave.yaml")
    assert cfg.robot.frame.urdf == (DATA / "robots" / "tiny.urdf").absolute()
    assert cfg.robot.frame.urdf.is_absolute()
    # recording.path is resolved (and normalised) the same way but need not exist
    assert cfg.recording.path == (DATA.parent / "out" / "slave.rec").absolute()


def test_relative_config_path_is_made_absolute(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(DATA)
    cfg = load_config("valid_slave.yaml")
    assert cfg.robot.frame.urdf == DATA.absolute() / "robots" / "tiny.urdf"


def test_parse_config_base_dir_and_missing_urdf(tmp_path: Path) -> None:
    (tmp_path / "arm.urdf").write_text(
        "<robot name='arm'><link name='base'/><link name='tip'/>"
        "<joint name='a' type='revolute'><parent link='base'/><child link='tip'/>"
        "<axis xyz='0 0 1'/><limit lower='-1' upper='1' effort='1' velocity='1'/></joint></robot>"
    )
    text = MINIMAL_ROBOT.replace("{model: occ_slave}", "{urdf: arm.urdf, tip_link: tip}")
    cfg = parse_config(text, base_dir=tmp_path)
    assert cfg.robot.frame.urdf == tmp_path / "arm.urdf"
    assert cfg.robot.frame.tip_link == "tip"
    assert errors_of(text, base_dir=tmp_path / "elsewhere") == [
        f"c.yaml:3 robot.frame.urdf: file not found: {tmp_path / 'elsewhere' / 'arm.urdf'}"
    ]


# ---------------------------------------------------------------------------- broken files

BROKEN = {
    "bad_types.yaml": [
        "2 robot.name: expected a name of letters, digits, '_' and '-', got 'slave arm'",
        "3 robot.rate_hz: expected an integer, got '1000'",
        "7 robot.joints[0].type: must be one of revolute | prismatic, got 'spherical'",
        "8 robot.joints[0].limits.max: expected a number, got 'abc'",
        "8 robot.joints[0].limits.velocity: must be > 0, got 0",
        "14 interfaces[0].port: must be <= 65535, got 70000",
        "15 interfaces[0].allowed_peers[1]: expected an IP address or CIDR network, "
        "got 'not-an-ip'",
        "16 interfaces[0].role: must be one of none | viewer | operator, got 'maybe'",
        "18 safety.watchdog.policy: must be one of hold | fault, got 'explode'",
        "19 stats.log_every_s: expected a number, got a list",
    ],
    "bad_unknown_key.yaml": [
        "3 robot.rate_hx: unknown field 'rate_hx' (did you mean 'rate_hz'?)",
        "8 robot.joints[0].hone: unknown field 'hone' (did you mean 'home'?)",
        "11 saftey: unknown field 'saftey' (did you mean 'safety'?)",
    ],
    "bad_missing.yaml": [
        "1 robot.name: missing required field",
        "2 robot.frame.tip_link: required when 'urdf' is set",
        "8 robot.joints[0].limits.max: must be greater than min (-1), got -2",
        "11 robot.joints[1].home: 0 is outside the limits [0.1, 0.2]",
        "16 interfaces[0].remote: required for transport 'tcp-client'",
        "18 interfaces[1].name: missing required field",
    ],
    "bad_robot_cross.yaml": [
        "7 robot.joints[1].name: joint 'pitch' is not driven by any driver",
        "9 robot.joints[2].name: joint 'roll' is not driven by any driver",
        "11 robot.joints[3].name: duplicate joint name 'yaw' (first at joints[0])",
        "16 robot.drivers[0].joints[1]: unknown joint 'pitchh' (did you mean 'pitch'?)",
        "19 robot.drivers[1].joints[0]: joint 'yaw' is already driven by driver 'sim0'",
    ],
    "bad_daemon_cross.yaml": [
        "15 interfaces[0].outputs[0].rate_hz: 1000 Hz exceeds the loop rate (robot.rate_hz = 500)",
        "16 interfaces[1].name: duplicate interface name 'slicer' (first at interfaces[0])",
        "18 interfaces[1].port: tcp-server bind 127.0.0.1:18944 conflicts with 0.0.0.0:18944 "
        "of interface 'slicer' (interfaces[0])",
        "23 safety.loss.input: unknown interface 'mastr' (did you mean 'master'?)",
        "24 recording.rate_hz: 2000 Hz exceeds the loop rate (robot.rate_hz = 500)",
    ],
    "bad_syntax.yaml": [
        "4 invalid YAML: expected ',' or '}', but got ':' (column 9)",
    ],
}


@pytest.mark.parametrize("name", sorted(BROKEN))
def test_broken_file_reports_every_error_with_file_line_and_path(name: str) -> None:
    path = DATA / name
    with pytest.raises(ConfigError) as info:
        load_config(path)
    expected = [f"{path}:{line}" for line in BROKEN[name]]
    assert info.value.errors == expected
    assert str(info.value) == "\n".join(expected)
    assert isinstance(info.value, OCCError)


def test_all_errors_are_reported_at_once_in_line_order() -> None:
    with pytest.raises(ConfigError) as info:
        load_config(DATA / "bad_types.yaml")
    errors = info.value.errors
    assert len(errors) == 10  # one per problem, across robot, interfaces, safety and stats
    lines = [int(e.split(":")[1].split()[0]) for e in errors]
    assert lines == sorted(lines)


def test_unknown_key_without_a_close_match_has_no_suggestion() -> None:
    assert errors_of(MINIMAL_ROBOT + "zzz: 1\n") == ["c.yaml:8 zzz: unknown field 'zzz'"]


def test_yaml_syntax_error_inline() -> None:
    assert errors_of("robot:\n  name: [a\n") == [
        "c.yaml:3 invalid YAML: expected ',' or ']', but got '<stream end>' (column 1)"
    ]
    assert errors_of("a: 1\n---\nb: 2\n")[0].startswith("c.yaml:2 invalid YAML: ")


def test_duplicate_keys_are_errors() -> None:
    text = MINIMAL_ROBOT.replace("  name: r\n", "  name: r\n  name: q\n")
    assert errors_of(text) == ["c.yaml:3 robot.name: duplicate key (first at line 2)"]


def test_empty_and_non_mapping_documents() -> None:
    assert errors_of("# nothing\n") == [
        "c.yaml:1 (top level): the file is empty; expected a mapping with a 'robot' section"
    ]
    assert errors_of("- a\n") == ["c.yaml:1 (top level): expected a mapping, got a list"]
    assert errors_of("robot:\n") == ["c.yaml:1 robot: expected a mapping, got null"]


def test_missing_file_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        load_config(tmp_path / "nope.yaml")
    assert info.value.errors[0].startswith(f"{tmp_path / 'nope.yaml'}: cannot read configuration")


def test_strict_scalars() -> None:
    text = MINIMAL_ROBOT.replace("velocity: 1}", "velocity: .nan}").replace("name: r", "name: 12")
    assert errors_of(text) == [
        "c.yaml:2 robot.name: expected a string, got 12",
        "c.yaml:5 robot.joints[0].limits.velocity: expected a finite number, got nan",
    ]
    # true is not a number, and an integer is accepted where a number is expected
    assert errors_of(MINIMAL_ROBOT.replace("max: 1,", "max: true,")) == [
        "c.yaml:5 robot.joints[0].limits.max: expected a number, got true"
    ]


def test_empty_lists_and_nulls() -> None:
    text = MINIMAL_ROBOT.replace("joints: [a]", "joints: []")
    assert errors_of(text) == ["c.yaml:7 robot.drivers[0].joints: must not be empty"]
    text = MINIMAL_ROBOT.replace("frame: {model: occ_slave}", "frame: {}")
    assert errors_of(text) == [
        "c.yaml:3 robot.frame: exactly one of 'model', 'urdf' or 'package_urdf' is required (none is set)"
    ]


def test_frame_model_and_urdf_are_exclusive() -> None:
    text = MINIMAL_ROBOT.replace(
        "{model: occ_slave}", "{model: occ_slave, urdf: robots/tiny.urdf, tip_link: tool_tip}"
    )
    assert errors_of(text, base_dir=DATA) == [
        "c.yaml:3 robot.frame: exactly one of 'model', 'urdf' or 'package_urdf' is required (model and urdf are set)"
    ]
    assert errors_of(MINIMAL_ROBOT.replace("occ_slave", "puma")) == [
        "c.yaml:3 robot.frame.model: must be one of occ_slave | master3, got 'puma'"
    ]


INTERFACE = "interfaces:\n  - {name: i, transport: %s, %s}\n"


@pytest.mark.parametrize(
    ("transport", "fields", "message"),
    [
        ("tcp-client", "remote: nohost", "expected 'host:port', got 'nohost'"),
        ("tcp-client", "remote: 'h:70000'", "remote port must be 1..65535, got 70000"),
        ("udp", "host: ''", None),
        ("pipe", "port: 1", None),
    ],
)
def test_interface_field_errors(transport: str, fields: str, message: str | None) -> None:
    errors = errors_of(MINIMAL_ROBOT + INTERFACE % (transport, fields))
    assert len(errors) == 1 and errors[0].startswith("c.yaml:9 interfaces[0].")
    if message is not None:
        assert errors[0] == f"c.yaml:9 interfaces[0].remote: {message}"


def test_tcp_client_remote_and_ipv6() -> None:
    cfg = parse_config(MINIMAL_ROBOT + INTERFACE % ("tcp-client", "remote: '[::1]:18944'"))
    assert cfg.interfaces[0].remote_address == ("::1", 18944)


def test_binds_port_zero_and_different_transports_do_not_conflict() -> None:
    text = MINIMAL_ROBOT + (
        "interfaces:\n"
        "  - {name: a, transport: tcp-server, port: 0}\n"
        "  - {name: b, transport: tcp-server, port: 0}\n"
        "  - {name: c, transport: udp, port: 18944}\n"
        "  - {name: d, transport: tcp-server, port: 18944}\n"
        "  - {name: e, transport: tcp-server, host: 10.0.0.1, port: 18944}\n"
        "  - {name: f, transport: tcp-client, port: 18944, remote: 'h:1'}\n"
    )
    assert [i.name for i in parse_config(text).interfaces] == list("abcdef")


def test_duplicate_inputs_and_watchdog_runs() -> None:
    text = MINIMAL_ROBOT + (
        "interfaces:\n"
        "  - name: i\n"
        "    transport: udp\n"
        "    inputs:\n"
        "      - {type: POSITION}\n"
        "      - {type: POSITION, queue: command}\n"
        "safety:\n"
        "  watchdog: {alert_run: 3, stop_run: 2}\n"
    )
    assert errors_of(text) == [
        "c.yaml:13 interfaces[0].inputs[1]: duplicate input POSITION/* (first at inputs[0])",
        "c.yaml:15 safety.watchdog.stop_run: must be >= alert_run (3), got 2",
    ]


# ---------------------------------------------------------------------------- schema and docs


def test_json_schema_is_usable() -> None:
    schema = DaemonConfig.model_json_schema()
    json.dumps(schema)
    assert schema["additionalProperties"] is False
    assert schema["required"] == ["robot"]
    robot = schema["$defs"]["RobotConfig"]
    assert robot["properties"]["rate_hz"]["default"] == 1000


def _config_md() -> str:
    return (ROOT / "docs" / "CONFIG.md").read_text(encoding="utf-8")


def test_config_md_reference_is_up_to_date() -> None:
    text = _config_md()
    block = text.split(DOC_BEGIN, 1)[1].split(DOC_END, 1)[0]
    assert block.strip() == config_reference_markdown().strip(), (
        "docs/CONFIG.md is stale: run python -m occ.configdoc --update-docs docs/CONFIG.md"
    )


def test_reference_lists_every_field() -> None:
    table = config_reference_markdown()
    for path in (
        "robot.joints[].limits.max",
        "robot.drivers[].on_limit",
        "robot.realtime.gc",
        "interfaces[].outputs[].rate_hz",
        "interfaces[].allowed_peers",
        "safety.loss.max_consecutive",
        "recording.include_messages",
        "stats.log_every_s",
        "controller",
        "controller.params.scale",  # a plugin's own parameters are listed too
        "controller.params.amplitude_mm",
    ):
        assert f"| `{path}` |" in table


def test_config_md_example_is_valid() -> None:
    example = re.search(r"```yaml\n(.*?)```", _config_md(), re.DOTALL)
    assert example is not None
    cfg = parse_config(example.group(1), source="CONFIG.md example")
    assert cfg.robot.joint_names == ("yaw", "pitch", "insertion")
    # it works with the shipped master: the port it streams to, a controller that follows
    master = load_config(ROOT / "configs" / "master.yaml")
    streams_to = next(i.remote_address for i in master.interfaces if i.transport == "udp")
    assert streams_to is not None and cfg.interface("master").port == streams_to[1]
    assert [c.plugin for c in cfg.controllers] == ["teleop-slave"]


def test_an_empty_allowed_peers_list_is_refused_with_a_clear_error(tmp_path) -> None:
    from occ.core.loader import load_config as _load

    text = (
        (ROOT / "configs" / "slave.yaml")
        .read_text()
        .replace("    port: 18944\n", "    port: 18944\n    allowed_peers: []\n", 1)
    )
    path = tmp_path / "slave.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        _load(path)
    assert any(
        "allowed_peers: an empty list would refuse every peer" in e for e in info.value.errors
    )


def test_two_controllers_owning_one_joint_are_refused_at_load() -> None:
    text = MINIMAL_ROBOT + "controller: [{plugin: hold}, {plugin: hold}]\n"
    with pytest.raises(
        ConfigError, match=r"controller\[1\]: command interface 'a/position' is claimed"
    ):
        parse_config(text)


def test_base_60_numbers_are_not_read_as_numbers() -> None:
    """YAML 1.1 reads `10:1` as 601: a ratio meant as 10:1 must be an error with its line, not
    a scale of 601 (nor `1:30` a period of 90)."""
    text = MINIMAL_ROBOT + "controller:\n  plugin: teleop-slave\n  params:\n    scale: 10:1\n"
    errors = errors_of(text)
    assert errors == [
        f"c.yaml:{MINIMAL_ROBOT.count(chr(10)) + 4} controller.params.scale: "
        "expected a number, got '10:1'"
    ]
    # and exponents are numbers, as YAML 1.2 reads them
    cfg = parse_config(MINIMAL_ROBOT.replace("velocity: 1}", "velocity: 1e-1}"))
    assert cfg.robot.joints[0].limits.velocity == 0.1
