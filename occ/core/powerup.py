"""Power-up off the loop thread: the drives whose activation waits, brought up on threads of
their own while the loop goes on ticking (issue 38).

A CiA 402 drive's activation walks every node through its state machine, several SYNC round
trips, up to ``state_timeout_ms`` (300 ms) of wall clock; run in a tick, it would stall a 1 kHz
loop that long. A driver says so (:attr:`occ.drivers.base.Driver.activation_waits`), and an
Enable then goes in two steps (:class:`occ.core.transitions.StateEffects` runs them):

1. On the loop thread, the request is checked as the state machine would (its table and its
   guards); the waiting drives are marked busy in the :class:`~occ.core.hardware.HardwareSet`
   (no read, write, activate, deactivate or reset of the loop touches them: their joints keep
   their last reading, the robot stays READY) and a :class:`PowerUp` runs each one's
   ``activate`` on a thread of its own. The operator's reply waits (a
   :class:`~occ.net.commands.Deferred`).
2. When every one of those threads has ended, the loop (never the other thread) releases the
   drives and completes the transition with the HardwareSet's rule: all or nothing (a drive
   that failed switches every other one off again and vetoes the Enable, the robot FAULT
   naming the drive and its cause), then ``verify``, then ENABLED; the reply says which.

While it runs, what stops the robot wins. A Disable or a Stop cancels it
(:meth:`~occ.drivers.base.Driver.cancel_activation`: each drive ends switched off, INACTIVE;
the robot stays READY). An EStop, a Fault, the shutdown or the supervisor's safe stop stop it
(:meth:`~occ.drivers.base.Driver.safe_stop`: the driver base switches the power stage off as
soon as it is up and latches FAULT). Either way the pending Enable is answered with a refusal,
and whatever came up is switched off again when the loop collects the power-up.

A Reset out of FAULT or ESTOP with such drives latched FAULT goes the same way
(``action="reset"``: each one's fault reset, which waits for its nodes as well, on a thread of
its own; the loop then completes the Reset: the other drives' resets, the fresh checked read,
READY, or FAULT naming the node whose cause persists). A transition meanwhile (an EStop) only
discards its result: a fault reset leaves the power stages off.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING

from occ.core.hardware import HardwareFailure
from occ.drivers.base import Driver, DriverState

if TYPE_CHECKING:
    from occ.net.commands import Deferred

__all__ = ["PowerUp"]


def _cause(err: BaseException) -> str:
    text = str(err)
    return text if text else type(err).__name__


class PowerUp:
    """The activation of ``drivers`` (their activation waits), each on a thread of its own
    (module docstring). Started, polled (:attr:`done`) and collected by the loop thread;
    :meth:`cancel` from the loop thread too. ``answer`` is the operator's reply, if any."""

    def __init__(
        self,
        drivers: Sequence[Driver],
        reason: str,
        answer: Deferred | None = None,
        action: str = "activate",
    ) -> None:
        self.drivers = list(drivers)
        #: ``activate`` (an Enable) or ``reset`` (a Reset: each drive's fault reset, which
        #: waits the same way; its power stages stay off)
        self.action = action
        #: why it was asked (the Enable's reason: ``operator Enable``, ``--start``)
        self.reason = reason
        self.answer = answer
        #: why it was cancelled or stopped (None: it goes on, or ended as asked)
        self.cancelled: str | None = None
        #: stopped (EStop, Fault, shutdown): the drives' safe stop, not a plain cancel
        self.stopped = False
        self._failures: dict[str, HardwareFailure] = {}
        self._lock = threading.Lock()
        self._threads: list[threading.Thread] = []
        self.started_at = time.perf_counter()
        #: wall-clock seconds from start to the last thread's end (None until then)
        self.took_s: float | None = None
        self._left = len(self.drivers)

    def start(self) -> PowerUp:
        for d in self.drivers:
            t = threading.Thread(
                target=self._activate, args=(d,), name=f"occ-power-up-{d.name}", daemon=True
            )
            self._threads.append(t)
            t.start()
        return self

    def _activate(self, driver: Driver) -> None:
        try:
            if self.cancelled is None:  # cancelled before it began: not powered at all
                if self.action == "reset":
                    driver.reset()
                else:
                    driver.activate()
        except Exception as err:  # noqa: BLE001 - every drive's failure is named
            with self._lock:
                failure = HardwareFailure(driver.name, self.action, _cause(err))
                self._failures[driver.name] = failure
        finally:
            with self._lock:
                # the time first: the loop reads `done` without the lock, then `took_s`
                if self._left == 1:
                    self.took_s = time.perf_counter() - self.started_at
                self._left -= 1

    @property
    def done(self) -> bool:
        """Every drive's activation has ended (successfully or not)."""
        return self._left == 0

    def wait(self, timeout: float) -> bool:
        """Wait (at most ``timeout`` seconds) for every activation to end; :attr:`done`."""
        give_up = time.perf_counter() + timeout
        for t in self._threads:
            t.join(max(0.0, give_up - time.perf_counter()))
        return self.done

    def failures(self) -> list[HardwareFailure]:
        """What failed, in the drives' order (call once :attr:`done`)."""
        with self._lock:
            return [self._failures[d.name] for d in self.drivers if d.name in self._failures]

    def cancel(self, why: str, stop: bool) -> None:
        """It is not wanted any more: ``stop`` (EStop, Fault, shutdown) safe-stops each drive
        (it latches FAULT, its power stage off as soon as it is up), else (Disable, Stop) each
        activation is cancelled (the drive ends INACTIVE). The pending reply is a refusal.
        Idempotent; a stop after a cancel still stops."""
        first = self.cancelled is None
        if first:
            self.cancelled = why
        if self.action == "reset":
            pass  # a fault reset leaves the power stages off: its result is only discarded
        elif stop and not self.stopped:
            self.stopped = True
            for d in self.drivers:
                d.safe_stop(why)  # honoured by the base while its activation runs
        elif first:
            for d in self.drivers:
                d.cancel_activation(why)
        if first and self.answer is not None:
            what = "Reset" if self.action == "reset" else "Enable"
            self.answer.fail(f"{what} cancelled while the drives worked: {why}")

    def leftovers(self) -> list[Driver]:
        """Once :attr:`done`: the drives that came up all the same (an activation that had
        already ended when it was cancelled)."""
        return [d for d in self.drivers if d.state is DriverState.ACTIVE]
