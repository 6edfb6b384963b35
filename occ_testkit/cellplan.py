"""The coordinator of a cell keyframe set (issue 40, item 5): plans every member, exchanges
their paths, has each cross-check its own against the others', and acknowledges all or none.

It talks to each member's operator port as any OpenIGTLink operator does (COMMANDs, their
RTS_COMMAND replies, NDARRAY messages), through a :class:`MemberLink`: tools/cell_plan.py's over
TCP to running daemons, the tests' over in-process channels to robots in simulated time. The
steps (:func:`coordinate`):

1. ``KeyframeLoad File=<set>`` on every member (each takes its own part);
2. ``KeyframePlan`` on every member (each plans and checks its part as always);
3. ``KeyframeCellPath Plan=N`` on every member: its plan's path, an NDARRAY ``CellPath``;
4. every member is given every other member's ``CellPath`` (the message as received);
5. ``KeyframeCellCheck Plan=N`` on every member: its path against the others' at the same
   times; each answers the identity of the cell plan (the set's digest and every path's);
6. the identities must be one; then ``KeyframeAck Plan=N StartAt=<now + lead> Cell=<id>`` on
   every member. A member that refuses its Ack makes the coordinator ``Stop`` every member it
   acknowledged already (a cell plan dropped in one member stops the cell: none runs).

Any refusal before step 6 acknowledges none.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

__all__ = ["CellOutcome", "MemberLink", "coordinate"]


class MemberLink(Protocol):
    """One member's operator port."""

    name: str

    def ask(self, command: str, **args: str) -> tuple[bool, str]:
        """Send COMMAND ``command`` with ``args``; (succeeded, its message or error)."""
        ...

    def last_array(self, device: str) -> Any:
        """The last NDARRAY message ``device`` received from the member (None: none)."""
        ...

    def give(self, msg: Any) -> None:
        """Send ``msg`` (an OpenIGTLink message) to the member."""
        ...


@dataclass
class CellOutcome:
    """What the coordinator did: acknowledged (every member runs at ``start_at``) or not,
    why, each step's replies by member."""

    ok: bool
    why: str = ""
    identity: str = ""
    start_at: float = 0.0
    plans: dict[str, int] = field(default_factory=dict)
    replies: list[tuple[str, str, bool, str]] = field(default_factory=list)


def coordinate(
    members: Sequence[MemberLink],
    file: str,
    wall: Callable[[], float],
    lead_s: float = 1.0,
    **plan_args: str,
) -> CellOutcome:
    """Plan, cross-check and acknowledge the cell set ``file`` on ``members`` (module
    docstring); ``wall`` the unix time, ``lead_s`` how far ahead the common start is."""
    out = CellOutcome(ok=False)

    def ask(m: MemberLink, command: str, **args: str) -> str | None:
        ok, text = m.ask(command, **args)
        out.replies.append((m.name, command, ok, text))
        if not ok:
            out.why = f"{m.name}: {command} refused: {text}"
            return None
        return text

    for m in members:
        if ask(m, "KeyframeLoad", File=file) is None:
            return out
    for m in members:
        text = ask(m, "KeyframePlan", **plan_args)
        if text is None:
            return out
        found = re.match(r"plan (\d+):", text)
        if found is None:
            out.why = f"{m.name}: KeyframePlan answered no plan number: {text}"
            return out
        out.plans[m.name] = int(found.group(1))
    paths = {}
    for m in members:
        if ask(m, "KeyframeCellPath", Plan=str(out.plans[m.name])) is None:
            return out
        paths[m.name] = m.last_array("CellPath")
        if paths[m.name] is None:
            out.why = f"{m.name}: KeyframeCellPath sent no CellPath"
            return out
    for m in members:
        for other, msg in paths.items():
            if other != m.name:
                m.give(msg)
    identities = {}
    for m in members:
        text = ask(m, "KeyframeCellCheck", Plan=str(out.plans[m.name]))
        if text is None:
            return out
        found = re.match(r"cell plan ([0-9a-f]{64}):", text)
        if found is None:
            out.why = f"{m.name}: KeyframeCellCheck answered no identity: {text}"
            return out
        identities[m.name] = found.group(1)
    if len(set(identities.values())) != 1:
        out.why = f"the members disagree on the cell plan: {identities}"
        return out
    out.identity = next(iter(identities.values()))
    out.start_at = wall() + lead_s
    acked: list[MemberLink] = []
    for m in members:
        plan = str(out.plans[m.name])
        if ask(m, "KeyframeAck", Plan=plan, StartAt=repr(out.start_at), Cell=out.identity) is None:
            for done in acked:  # none runs: a dropped cell plan stops the cell
                ok, text = done.ask("Stop")
                out.replies.append((done.name, "Stop", ok, text))
            return out
        acked.append(m)
    out.ok = True
    return out
