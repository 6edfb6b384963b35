"""Collaborative control (the Surgical Assistant Workstation's mentoring): who drives the slave.

Slave side (:class:`Collaboration`)
    A slave configured with ``collaboration.masters`` takes one POSITION stream per master, each
    on its own interface with its own loss monitor; exactly one master, the *owner*, moves the
    robot. The others' samples are judged (sequence numbers, timestamps, deadlines) and counted
    but never reach the controller. The loss rule applies to the owner's stream only (hold, then
    the latched stop with an alert); a non-owner's failure is an alert, and the robot keeps
    following its owner.

    ``Handover`` (``<Command Name="Handover" To="trainee"/>`` or a COMMAND named ``Handover``
    with ``To``) moves ownership, answered like every command and announced to every operator
    with a STATUS ``HANDOVER``. Who may ask is a policy from YAML, keyed by the operator
    interface the command arrives on (each master's ``console``):

    - the ``supervisor``'s console may always hand control to anyone, itself included (take it
      back), whoever has it;
    - the owner's console may give control away when its master is listed in ``grant``;
    - a console may take control for its own master when listed in ``request``;
    - an operator on an interface that is nobody's console (the bedside's port) acts as the
      supervisor, or is refused (``others: refuse``).

    While RUNNING a hand-over to a master whose stream is not live (no accepted sample since
    the last Run or Reset, holding, or latched) is refused: control is never handed to a
    silent console. The new owner's motion is re-indexed (the slave controller re-takes its
    references on the new owner's first sample) and the robot re-joins the new target at half
    its velocity limits, so the slave never jumps.

Master side (:class:`SlaveSelector`)
    One master driving two slaves (the da Vinci's PSM toggle, or a left/right pair): each slave
    has its own ``teleop`` output; only the selected one carries ``run=1``, the others carry
    ``run=0`` (the stream never stops, so their loss monitors stay quiet and the slaves hold).
    A newly selected slave sees ``run`` rise and re-indexes: no jump. Selected by the operator
    commands ``Select`` (``To=INTERFACE``) and ``Toggle``, or by a clutch tap (pressed and
    released within ``toggle_tap_ms``).
"""

from __future__ import annotations

import difflib
from collections import deque
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from occ.errors import CommandError

if TYPE_CHECKING:
    from occ.config import CollaborationConfig


def _unknown(what: str, name: str, known: Sequence[str]) -> CommandError:
    close = difflib.get_close_matches(name, list(known), n=1)
    hint = f" (did you mean '{close[0]}'?)" if close else ""
    return CommandError(f"{what} '{name}' is not one of {list(known)}{hint}")


class Collaboration:
    """The owner of a collaborative slave and the hand-over policy (module docstring)."""

    def __init__(self, cfg: CollaborationConfig) -> None:
        self.masters: tuple[str, ...] = cfg.names()
        self.owner: str = cfg.owner if cfg.owner is not None else self.masters[0]
        self.supervisor = cfg.supervisor
        self.may_request = frozenset(cfg.request)
        self.may_grant = frozenset(cfg.grant) if cfg.grant is not None else frozenset(self.masters)
        self.others = cfg.others
        #: operator interface -> the master it speaks for
        self.console_of = {m.console: m.input for m in cfg.masters if m.console is not None}
        self.handovers = 0
        self.refused = 0
        #: the last hand-overs: (daemon time, from, to, by)
        self.history: deque[tuple[float, str, str, str]] = deque(maxlen=16)

    def code(self, name: str | None = None) -> int:
        """The owner's (or ``name``'s) index among the masters: the State Data Table's number."""
        return self.masters.index(self.owner if name is None else name)

    def authorize(self, interface: str, to: str) -> str:
        """Who is asking (for the STATUS), or CommandError saying why they may not."""
        if to not in self.masters:
            raise _unknown("master", to, self.masters)
        who = self.console_of.get(interface)
        if who is None:
            if self.others == "supervisor":
                return f"operator on {interface}"
            raise CommandError(
                f"operators on {interface} may not hand over control (no master's console; "
                "collaboration.others is refuse)"
            )
        if who == self.supervisor:
            return f"{who} (supervisor)"
        if who == self.owner and who in self.may_grant:
            return who
        if to == who and who in self.may_request:
            return who
        if who == self.owner:
            raise CommandError(f"{who} has control but may not give it away (not in grant)")
        if to == who:
            raise CommandError(
                f"{who} may not take control itself (not in request): ask {self.owner} or the "
                "supervisor to hand it over"
            )
        raise CommandError(f"{who} does not have control: only {self.owner} may give it away")

    def switch(self, to: str, by: str, now: float) -> str:
        """Make ``to`` the owner; the old owner's name."""
        old = self.owner
        self.owner = to
        self.handovers += 1
        self.history.append((now, old, to, by))
        return old

    def stats(self) -> dict[str, Any]:
        return {
            "owner": self.owner,
            "masters": list(self.masters),
            "supervisor": self.supervisor,
            "handovers": self.handovers,
            "refused": self.refused,
            "history": [
                {"t": round(t, 6), "from": a, "to": b, "by": by} for t, a, b, by in self.history
            ],
        }


class SlaveSelector:
    """Which of a master's ``teleop`` outputs drives its slave (module docstring)."""

    def __init__(
        self, slaves: Sequence[str], selected: str | None = None, tap_s: float | None = None
    ) -> None:
        self.slaves = tuple(slaves)
        if selected is not None and selected not in self.slaves:
            raise ValueError(f"selected slave {selected!r} is not one of {list(self.slaves)}")
        #: the interface whose output carries run=1 (None: every output drives, one slave)
        self.selected: str | None = selected or (self.slaves[0] if self.slaves else None)
        self.tap_s = tap_s
        self._pressed_at: float | None = None
        self.switches = 0

    def drives(self, interface: str) -> bool:
        sel = self.selected
        return sel is None or interface == sel

    def select(self, name: str) -> str:
        if not self.slaves:
            raise CommandError("this master drives one slave: nothing to select")
        if name not in self.slaves:
            raise _unknown("slave interface", name, self.slaves)
        if name == self.selected:
            return f"{name} already selected"
        old, self.selected = self.selected, name
        self.switches += 1
        return f"slave {old} -> {name}"

    def toggle(self) -> str:
        if len(self.slaves) < 2:
            raise CommandError("this master drives one slave: nothing to toggle")
        assert self.selected is not None
        i = self.slaves.index(self.selected)
        return self.select(self.slaves[(i + 1) % len(self.slaves)])

    def on_clutch(self, pressed: bool, now: float) -> str | None:
        """A clutch press then release within ``tap_s`` toggles (the da Vinci's PSM swap)."""
        if pressed:
            self._pressed_at = now
            return None
        down, self._pressed_at = self._pressed_at, None
        if self.tap_s is None or down is None or len(self.slaves) < 2:
            return None
        if now - down <= self.tap_s:
            return self.toggle()
        return None

    def stats(self) -> dict[str, Any]:
        return {"slaves": list(self.slaves), "selected": self.selected, "switches": self.switches}
