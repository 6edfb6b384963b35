"""The ``cell`` section: the daemons of one cell (several arms around one patient) and how a
stop in one reaches the others (occ/core/cell.py, occ/net/celllink.py)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, model_validator

from occ.config.base import (
    ExistingFile,
    Float,
    Loc,
    Name,
    PosFloat,
    Remote,
    _Model,
    _raise_problems,
)
from occ.config.robot import FrameConfig


class CellMember(_Model):
    """One daemon of the cell: its name, the address of its cell link and, for the arm-against-
    arm check, its kinematic model."""

    name: Name = Field(description="The member's name in the cell (each member's own `member`).")
    address: Remote = Field(
        description="`host:port` of the member's cell link (UDP): where it listens for its peers' "
        "heartbeats (this daemon's own entry: where it binds)."
    )
    frame: FrameConfig | None = Field(
        None,
        description="The member's URDF (the robot section's `frame:` schema). Its kinematic "
        "chain's hash must match the one the member announces; its links are checked against "
        "this robot's (`safety.collision`). null = no geometry: the member's stops still stop "
        "this one, its arm is not checked.",
    )
    velocities: tuple[PosFloat, ...] | None = Field(
        None,
        description="The member's joint velocity limits (rad/s or m/s, its URDF's joint order): "
        "how far its arm can move between two heartbeats, in the arm-against-arm check; null "
        "= its URDF's (often far above what its own file allows: give its `robot.joints` "
        "limits).",
    )
    tool_mm: tuple[PosFloat, PosFloat] | None = Field(
        None,
        description="The member's tool on its tip link, a capsule (length, radius in mm) checked "
        "with its links; null = none.",
    )


class CellConfig(_Model):
    """One cell: every member heartbeats every other at least every `period_ms` over OpenIGTLink
    on UDP (sequence-numbered, signed with `auth_key_file`); a member that leaves RUNNING for
    a safety reason, or falls silent past `grace_ms`, stops every other (`policy: stop-all`)."""

    name: Name = Field(description="The cell's name (every member's heartbeat carries it).")
    member: Name | None = Field(
        None, description="This daemon's entry in `members`; null = the robot's `name`."
    )
    members: tuple[CellMember, ...] = Field(
        min_length=2,
        description="Every daemon of the cell, this one included (the same list in each "
        "member's file); names and addresses unique.",
    )
    policy: Literal["stop-all", "alert-only"] = Field(
        "stop-all",
        description="`stop-all`: a member's safety stop or silence holds every other member "
        "(STOPPED) until an operator's `Run` once the origin runs again or left the cell; "
        "`alert-only`: the alert without the hold.",
    )
    period_ms: Annotated[Float, Field(ge=1.0, le=5.0)] = Field(
        5.0, description="Heartbeat period (ms): at most 5; a change of state goes out at once."
    )
    grace_ms: Annotated[Float, Field(ge=10.0, le=1000.0)] = Field(
        100.0,
        description="A member heard from no later than this (ms) is alive; past it, it is "
        "silent (a stop of the cell).",
    )
    auth_key_file: ExistingFile | None = Field(
        None,
        description="Shared key file (as an interface's `auth_key_file`): every heartbeat is "
        "signed and an unsigned or wrongly signed one is refused and counted.",
    )

    def me(self, robot_name: str) -> str:
        """This daemon's name in the cell: ``member``, else the robot's name."""
        return self.member or robot_name

    def entry(self, name: str) -> CellMember:
        for m in self.members:
            if m.name == name:
                return m
        raise KeyError(name)

    @model_validator(mode="after")
    def _unique(self) -> CellConfig:
        _raise_problems(cell_problems(self.members, self.period_ms, self.grace_ms))
        return self


def cell_problems(
    members: tuple[CellMember, ...], period_ms: float, grace_ms: float
) -> list[tuple[Loc, str]]:
    """What is wrong with a cell's members and timing: a name or an address given twice (each
    repeat names the first), a grace shorter than 3 heartbeat periods. A plain function, not
    the validator's body: mutation testing (mutmut 3) leaves decorated functions alone."""
    problems: list[tuple[Loc, str]] = []
    names: dict[str, int] = {}
    addresses: dict[str, int] = {}
    for i, m in enumerate(members):
        if m.name in names:
            problems.append(
                (("members", i, "name"), f"duplicate member {m.name!r} (members[{names[m.name]}])")
            )
        names.setdefault(m.name, i)
        if m.address in addresses:
            problems.append(
                (("members", i, "address"), f"{m.address} is members[{addresses[m.address]}]'s too")
            )
        addresses.setdefault(m.address, i)
    if grace_ms < 3 * period_ms:
        problems.append(
            (("grace_ms",), f"must be at least 3 heartbeat periods ({3 * period_ms:g} ms)")
        )
    return problems


__all__ = ["CellConfig", "CellMember", "cell_problems"]
