"""The root of the schema: :class:`DaemonConfig`, the whole configuration of one daemon,
and its checks across sections.
"""

from __future__ import annotations

from typing import Any

from pydantic import Field, model_validator

from occ.config.base import _WILDCARD_HOSTS, Loc, _did_you_mean, _Model, _num, _raise_problems
from occ.config.blackbox import BlackBoxConfig
from occ.config.cell import CellConfig
from occ.config.collaboration import CollaborationConfig
from occ.config.controllers import ControllerConfig
from occ.config.environment import EnvironmentConfig
from occ.config.interfaces import InterfaceConfig
from occ.config.recording import RecordingConfig, StateTableConfig, StatsConfig
from occ.config.robot import RobotConfig, _Failed, _quietly
from occ.config.safety import SafetyConfig


class DaemonConfig(_Model):
    """The whole configuration of one daemon."""

    robot: RobotConfig = Field(description="The robot.")
    interfaces: tuple[InterfaceConfig, ...] = Field(
        (), description="OpenIGTLink interfaces; names and binds unique."
    )
    safety: SafetyConfig = Field(SafetyConfig(), description="Safety monitors.")
    recording: RecordingConfig = Field(RecordingConfig(), description="Recorder.")
    stats: StatsConfig = Field(StatsConfig(), description="Timing statistics.")
    collaboration: CollaborationConfig | None = Field(
        None, description="Several masters for one slave (hand-over); null = one master."
    )
    cell: CellConfig | None = Field(
        None,
        description="The cell this daemon is a member of (several arms around one patient: a "
        "stop in one stops all, arms checked against each other); null = none.",
    )
    state_table: StateTableConfig = Field(
        StateTableConfig(), description="State Data Table (`GetStateTable`)."
    )
    black_box: BlackBoxConfig = Field(
        BlackBoxConfig(),
        description="The flight recorder: always on, dumped when the robot stops for a safety "
        "reason, faults or is emergency-stopped, and on `DumpBlackBox`.",
    )
    environment: EnvironmentConfig | None = Field(
        None,
        description="A simulated world for `sim` drives (tissue the tool presses on); null = "
        "free space. Needs one `sim` driver with every joint.",
    )
    controller: ControllerConfig | tuple[ControllerConfig, ...] | None = Field(
        None,
        description="The controller plugin, or a list of them run in order (each command "
        "interface owned by one); null = `hold` (keep position).",
    )

    def with_params(self, **params: Any) -> DaemonConfig:
        """A copy whose (single) controller has ``params`` updated (for tests and tools)."""
        if len(self.controllers) != 1:
            raise ValueError("with_params needs exactly one controller in the config")
        (cc,) = self.controllers
        new = ControllerConfig(plugin=cc.plugin, params={**cc.params, **params})
        return self.model_copy(update={"controller": new})

    @property
    def controllers(self) -> tuple[ControllerConfig, ...]:
        """``controller`` as a tuple (empty when none is configured)."""
        c = self.controller
        if c is None:
            return ()
        return c if isinstance(c, tuple) else (c,)

    def interface(self, name: str) -> InterfaceConfig:
        for itf in self.interfaces:
            if itf.name == name:
                return itf
        raise KeyError(name)

    @model_validator(mode="before")
    @classmethod
    def _paths_of_the_file(cls, data: Any) -> Any:
        """A ``black_box`` the file leaves out is validated like one it gives, so its ``dir``
        is relative to the file's directory (a default model's paths are the import's)."""
        if isinstance(data, dict) and "black_box" not in data:
            data = {**data, "black_box": {}}
        return data

    @model_validator(mode="after")
    def _cross_sections(self) -> DaemonConfig:
        problems: list[tuple[Loc, str]] = []
        loop_hz = self.robot.rate_hz
        switch_us = self.robot.realtime.switch_interval_us
        sup = self.safety.supervisor
        if sup.enabled and switch_us is not None and switch_us * 1e-3 >= sup.timeout_ms / 2:
            # a thread waits up to the switch interval for the interpreter lock: the supervisor
            # must get it well within its timeout, or a hung loop looks like a paused machine
            problems.append(
                (
                    ("robot", "realtime", "switch_interval_us"),
                    f"must be below half of safety.supervisor.timeout_ms "
                    f"({sup.timeout_ms * 500:g} us), got {switch_us:g}",
                )
            )
        problems.extend(self._interface_problems())
        names = list(dict.fromkeys(itf.name for itf in self.interfaces))
        if self.recording.rate_hz > loop_hz:
            problems.append(
                (
                    ("recording", "rate_hz"),
                    f"{_num(self.recording.rate_hz)} Hz exceeds the loop rate "
                    f"(robot.rate_hz = {loop_hz})",
                )
            )
        loss_input = self.safety.loss.input
        if loss_input is not None and loss_input not in names:
            problems.append(
                (
                    ("safety", "loss", "input"),
                    f"unknown interface '{loss_input}'" + _did_you_mean(loss_input, names),
                )
            )
        if self.collaboration is not None:
            problems.extend(self._collab_problems())
        if self.safety.collision is not None:
            problems.extend(self._collision_problems())
        if self.cell is not None:
            problems.extend(self._cell_problems())
        _raise_problems(problems)
        return self

    def _interface_problems(self) -> list[tuple[Loc, str]]:
        """The interfaces against each other (names, binds) and their outputs against the loop."""
        problems: list[tuple[Loc, str]] = []
        names: dict[str, int] = {}
        binds: list[tuple[int, InterfaceConfig]] = []
        loop_hz = self.robot.rate_hz
        for i, itf in enumerate(self.interfaces):
            if itf.name in names:
                problems.append(
                    (
                        ("interfaces", i, "name"),
                        f"duplicate interface name '{itf.name}' "
                        f"(first at interfaces[{names[itf.name]}])",
                    )
                )
            else:
                names[itf.name] = i
            if itf.transport not in ("tcp-client", "inproc") and itf.port != 0:
                for j, other in binds:
                    if (
                        other.transport == itf.transport
                        and other.port == itf.port
                        and (
                            other.host == itf.host
                            or other.host in _WILDCARD_HOSTS
                            or itf.host in _WILDCARD_HOSTS
                        )
                    ):
                        problems.append(
                            (
                                ("interfaces", i, "port"),
                                f"{itf.transport} bind {itf.host}:{itf.port} conflicts with "
                                f"{other.host}:{other.port} of interface '{other.name}' "
                                f"(interfaces[{j}])",
                            )
                        )
                        break
                binds.append((i, itf))
            for k, out in enumerate(itf.outputs):
                if out.rate_hz > loop_hz:
                    problems.append(
                        (
                            ("interfaces", i, "outputs", k, "rate_hz"),
                            f"{_num(out.rate_hz)} Hz exceeds the loop rate "
                            f"(robot.rate_hz = {loop_hz})",
                        )
                    )
        return problems

    def _collision_problems(self) -> list[tuple[Loc, str]]:
        """The links a collision region excludes, against the robot's URDF."""
        import pinocchio as pin

        cc = self.safety.collision
        assert cc is not None
        fc = self.robot.frame
        try:
            path = fc.urdf_path()
            if path is None:
                from occ.kinematics.frame import BUILTIN_MODELS, robots_dir

                assert fc.model is not None
                path = robots_dir() / BUILTIN_MODELS[fc.model][0]
            model, _said = _quietly(lambda: pin.buildModelFromUrdf(str(path)))
        except (_Failed, ValueError):
            return []  # the frame's own check says why
        links = {f.name for f in model.frames if f.type == pin.FrameType.BODY} | {"tool"}
        out: list[tuple[Loc, str]] = []
        for i, rc in enumerate(cc.regions):
            for k, name in enumerate(rc.exclude_links):
                if name not in links:
                    out.append(
                        (
                            ("safety", "collision", "regions", i, "exclude_links", k),
                            f"no link {name!r} in the URDF" + _did_you_mean(name, sorted(links)),
                        )
                    )
        return out

    def _cell_problems(self) -> list[tuple[Loc, str]]:
        """This daemon among the cell's members, and its link's port among the interfaces."""
        cell = self.cell
        assert cell is not None
        me = cell.me(self.robot.name)
        names = [m.name for m in cell.members]
        if me not in names:
            where = "member" if cell.member is not None else "member (null: the robot's name)"
            return [
                (
                    ("cell", where.split(" ")[0]),
                    f"{me!r} is not among the members" + _did_you_mean(me, names),
                )
            ]
        host, port = cell.entry(me).address.rsplit(":", 1)
        for i, itf in enumerate(self.interfaces):
            if (
                itf.transport == "udp"
                and itf.port == int(port)
                and (itf.host == host or itf.host in _WILDCARD_HOSTS)
            ):
                return [
                    (
                        ("cell", "members", names.index(me), "address"),
                        f"udp {host}:{port} is interface '{itf.name}''s (interfaces[{i}])",
                    )
                ]
        return []

    def _collab_problems(self) -> list[tuple[Loc, str]]:
        """The collaboration's names against the interfaces and each other."""
        co = self.collaboration
        assert co is not None
        out: list[tuple[Loc, str]] = []
        by_name = {itf.name: itf for itf in self.interfaces}
        names = list(by_name)
        masters = co.names()
        seen: set[str] = set()
        for i, m in enumerate(co.masters):
            loc: Loc = ("collaboration", "masters", i)
            itf = by_name.get(m.input)
            if itf is None:
                out.append(
                    (
                        (*loc, "input"),
                        f"unknown interface '{m.input}'" + _did_you_mean(m.input, names),
                    )
                )
            elif not any(inp.queue == "stream" for inp in itf.inputs):
                out.append(((*loc, "input"), f"interface '{m.input}' has no stream input"))
            if m.input in seen:
                out.append(((*loc, "input"), f"master '{m.input}' listed twice"))
            seen.add(m.input)
            if m.console is not None:
                con = by_name.get(m.console)
                if con is None:
                    out.append(
                        (
                            (*loc, "console"),
                            f"unknown interface '{m.console}'" + _did_you_mean(m.console, names),
                        )
                    )
                elif con.role != "operator":
                    out.append(
                        ((*loc, "console"), f"interface '{m.console}' needs role 'operator'")
                    )
        refs: list[tuple[Loc, str | None]] = [
            (("collaboration", "owner"), co.owner),
            (("collaboration", "supervisor"), co.supervisor),
            *((("collaboration", "request", i), n) for i, n in enumerate(co.request)),
            *((("collaboration", "grant", i), n) for i, n in enumerate(co.grant or ())),
        ]
        for loc, ref in refs:
            if ref is not None and ref not in masters:
                out.append((loc, f"'{ref}' is not one of the masters {list(masters)}"))
        loss_input = self.safety.loss.input
        if loss_input is not None and loss_input not in masters:
            out.append(
                (
                    ("safety", "loss", "input"),
                    f"with collaboration, must be null or one of the masters {list(masters)}",
                )
            )
        return out
