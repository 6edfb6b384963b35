"""The feedback checks every driver runs on every reading (issue 36).

A :class:`FeedbackChecks` belongs to one :class:`~occ.drivers.base.Driver`: it holds the
per-joint figures of the checks (from the driver's parameters and what its backend knows of
its encoders and servo) and their memory (where a joint last moved, since when its following
error is outside its window, the commanded speed), and decides which readings the joints take.
The rules (lost, out of range, jump, following error, frozen) are in the "Feedback checks" part
of :mod:`occ.drivers.base`'s docstring; the driver latches FAULT on the first failed one.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from occ.joint import Joint

__all__ = ["FeedbackChecks", "FOLLOWING_WINDOW", "LIMIT_MARGIN", "DEFAULT_LAG_S", "FROZEN_AWAY"]

#: the following-error window's default: far beyond a healthy servo's error at rest
FOLLOWING_WINDOW = {"revolute": 0.005, "prismatic": 0.0005}
#: how far a joint may be measured outside its limits before its feedback is not believed
LIMIT_MARGIN = {"revolute": 0.02, "prismatic": 0.002}
#: a healthy servo's lag behind a moving command, when the backend does not know its own
DEFAULT_LAG_S = 0.020

#: How far (rad, m) the command must be from a joint that has not moved at all for
#: ``frozen_feedback_ms`` before its feedback is called frozen: far beyond the tracking lag of
#: a healthy servo at the velocity limits, so a joint holding still never trips it.
FROZEN_AWAY = {"revolute": 0.005, "prismatic": 0.0005}


class FeedbackChecks:
    """The feedback checks of one driver's ``joints`` (see the module docstring).

    ``jump``: ``feedback_jump``; ``frozen_ms``: ``frozen_feedback_ms``; ``noise`` and
    ``margin``: ``feedback_noise`` and ``limit_margin`` per joint (None: the defaults);
    ``following``: ``following_error`` checked (None: off); ``period``: the loop's, s.
    """

    def __init__(
        self,
        joints: Sequence[Joint],
        jump: float,
        frozen_ms: float,
        noise: list[float] | None,
        margin: list[float] | None,
        following: dict[str, Any] | None,
        period: float,
    ) -> None:
        n = len(joints)
        self.joints = list(joints)
        self.period = period
        self.following = following
        # per joint: max speed for a plausible step, distance for "frozen"
        self.jump = jump
        self._jump_speed = [jump * j.limits.velocity for j in joints]
        self._frozen_s = frozen_ms * 1e-3
        self._frozen_away = [FROZEN_AWAY.get(j.type, 0.005) for j in joints]
        self._changed_at = [math.nan] * n
        #: where each joint was when its reading last moved by more than its noise
        self._anchor = [math.nan] * n
        self.noise_cfg = noise
        self.noise = [0.0] * n  # set by setup (the backend may know it)
        margins = margin or [LIMIT_MARGIN.get(j.type, 0.02) for j in joints]
        #: the measured range each joint must stay in: its limits widened by its margin
        self._range = [
            (j.limits.min - m, j.limits.max + m, m) for j, m in zip(joints, margins, strict=True)
        ]
        # following error (per joint): window, lag (s), 1 / stiffness (0: no load term), the
        # average of the commanded speed, since when the error is outside the window
        self._fe_window = [0.0] * n
        self._fe_lag = [0.0] * n
        self._fe_compliance = [0.0] * n
        self._fe_time = 0.0
        #: the commanded speed per joint, averaged over the servo's lag (the driver's write
        #: keeps it, with ``fade``: 1 / that lag)
        self.cmd_speed = [0.0] * n
        self.fade = [0.0] * n
        #: each joint's last commanded step (the next reading may show it whole)
        self.last_step = [0.0] * n
        self._fe_since = [math.nan] * n
        #: the drive has been commanded since its activation
        self.commanded = False

    def setup(
        self,
        noise: Sequence[float] | None,
        model: tuple[Sequence[float], Sequence[float | None]] | None,
    ) -> None:
        """The per-joint figures, from the parameters and what the backend knows: ``noise``
        its encoders' (used when ``feedback_noise`` is not configured; None: 0), ``model``
        its servo's lag and stiffness per joint (None: unknown)."""
        n = len(self.joints)
        if self.noise_cfg is not None:
            noise = self.noise_cfg
        self.noise = list(noise) if noise and len(noise) == n else [0.0] * n
        fe = self.following
        lags: list[float] = [DEFAULT_LAG_S] * n
        stiff: list[float | None] = [None] * n
        if model is not None:
            lags = [float(v) for v in model[0]]
            stiff = list(model[1])
        if fe is not None:
            if fe["lag"] is not None:
                lags = list(fe["lag"])
            if fe["stiffness"] is not None:
                stiff = list(fe["stiffness"])
            window = fe["window"] or [FOLLOWING_WINDOW.get(j.type, 0.005) for j in self.joints]
            # the encoder's own noise never counts as an error
            self._fe_window = [w + 2.0 * e for w, e in zip(window, self.noise, strict=True)]
            self._fe_time = float(fe["time_s"])
        self._fe_lag = lags
        self._fe_compliance = [0.0 if k is None else 1.0 / k for k in stiff]
        self.fade = [1.0 / max(lag, self.period) for lag in lags]

    def restart(self) -> None:
        """At activation: frozen feedback watched from the next reading on, no following
        error yet, nothing commanded."""
        n = len(self.joints)
        self._changed_at = [math.nan] * n
        self._fe_since = [math.nan] * n
        self.cmd_speed = [0.0] * n
        self.last_step = [0.0] * n
        self.commanded = False

    def forget(self) -> None:
        """At a fault's reset: where the joints last moved is forgotten."""
        self._anchor = [math.nan] * len(self.joints)

    def apply(
        self,
        positions: Sequence[float],
        velocities: Sequence[float],
        efforts: Sequence[float],
        now: float,
        active: bool,
        judged: bool,
        effort: bool,
    ) -> str | None:
        """Judge one reading at ``now`` and give each joint whose reading is believed its
        new state; the first failed check's words (None: none failed). ``active``: the drive
        is ACTIVE; ``judged``: it is not in FAULT (then only lost and out-of-range readings
        are reported); ``effort``: it takes efforts (no frozen or following-error check)."""
        ranges = self._range
        frozen_s = self._frozen_s if active else 0.0
        # the following error: only for a drive that is servoing our commands
        following = active and self.commanded and self.following is not None
        if effort:
            frozen_s = 0.0  # the hand, not a servo, moves an effort-driven joint
            following = False
        # a jump is judged on a powered drive: powered off, a joint moved by hand goes as fast
        # as the hand (the velocity limit bounds commands), and Enable holds a fresh reading
        jumps = active and self.jump > 0.0
        bad: str | None = None  # the first failed check: returned once every joint is read
        anchor, changed, noises = self._anchor, self._changed_at, self.noise
        for i, joint in enumerate(self.joints):
            x = positions[i]
            if x - x != 0.0:  # NaN or inf (math.isfinite without a call)
                if joint.measured and bad is None:
                    bad = f"joint {joint.name}: feedback lost (position {x})"
                continue  # not reported yet: the joint stays unmeasured
            lo, hi, margin = ranges[i]
            if x < lo or x > hi:
                if bad is None:
                    bad = (
                        f"joint {joint.name}: measured position {x:.6g} outside its limits "
                        f"[{joint.limits.min:.6g}, {joint.limits.max:.6g}] by more than "
                        f"{margin:.6g} (limit_margin)"
                    )
                continue  # not believed: the joint keeps its last reading
            why = ""
            if joint.measured and judged:
                if x != joint.position and jumps:
                    why = self._jump(i, joint, x, now)
                ref = anchor[i]
                if ref != ref or x - ref > noises[i] or ref - x > noises[i]:
                    anchor[i] = x  # moved beyond the encoder's noise: not frozen (inlined:
                    changed[i] = now  # every moving joint, every tick)
                elif frozen_s > 0.0:  # still for how long (inlined as well)
                    since = changed[i]
                    if since != since:
                        changed[i] = now
                    elif now - since > frozen_s:
                        why = self._frozen(i, joint, x, now - since) or why
            else:
                anchor[i] = x
                changed[i] = now
            if following and not why:
                why = self._following_error(i, joint, x, efforts[i], now)
            if why:
                if bad is None:
                    bad = why
                continue  # not believed: the joint keeps its last reading
            # Joint.set_measured, inlined: this runs for every joint every tick
            joint.position = x
            joint.velocity = velocities[i]
            joint.effort = efforts[i]
            joint.measured = True
            joint.stamp = now
        return bad

    def _jump(self, i: int, joint: Joint, x: float, now: float) -> str:
        """Joint ``i``'s step from its last reading to ``x`` (see "Jump" in the base's doc):
        '' when plausible, else the fault's words."""
        prev = joint.position
        jump_factor = self.jump
        noise = self.noise[i]
        step = x - prev if x > prev else prev - x
        dt = now - joint.stamp
        if dt < self.period:
            dt = self.period
        # the speed this joint may have: its limit, or faster while a command catches up
        # after a stall of the loop (the servo follows a step)
        speed = self._jump_speed[i]
        catching_up = jump_factor * self.cmd_speed[i]
        if catching_up > speed:
            speed = catching_up
        # a reading shows the step commanded over the previous write's interval, which a late
        # tick made longer than this reading's: that step is plausible
        reach = speed * dt
        stepped = jump_factor * self.last_step[i]
        if stepped > reach:
            reach = stepped
        reach += 2.0 * noise
        if step > reach:
            return (
                f"joint {joint.name}: feedback jump of {step:.6g} in "
                f"{dt * 1e3:.3g} ms (at most {reach:.6g}: feedback_jump "
                f"{jump_factor:g} x {speed / jump_factor:.6g}/s, the speed it may "
                f"have, plus twice the noise {noise:.3g})"
            )
        return ""

    def _frozen(self, i: int, joint: Joint, x: float, still_s: float) -> str:
        """Joint ``i``'s reading ``x``, not moved beyond its noise for ``still_s``, longer
        than ``frozen_feedback_ms`` (``apply`` checks both, inline; see "Frozen" in the base's
        doc): frozen ('' not) when the joint is commanded far enough away to move."""
        away = joint.command_position - x
        if away > self._frozen_away[i] or -away > self._frozen_away[i]:
            return (
                f"joint {joint.name}: feedback frozen at {x:.6g} for {still_s * 1e3:.0f} ms "
                f"while commanded {away:+.6g} away (no move beyond its noise, "
                f"{self.noise[i]:.3g})"
            )
        return ""

    def _following_error(self, i: int, joint: Joint, x: float, effort: float, now: float) -> str:
        """The following error of joint ``i`` (see "Following error" in the base's doc): ''
        while within its window, or the fault's words once outside it for ``time_ms``."""
        error = joint.command_position - x
        if error < 0.0:
            error = -error
        load = effort if effort >= 0.0 else -effort
        window = (
            self._fe_window[i] + self._fe_lag[i] * self.cmd_speed[i] + load * self._fe_compliance[i]
        )
        if error <= window:
            self._fe_since[i] = math.nan
            return ""
        since = self._fe_since[i]
        if since != since:
            self._fe_since[i] = since = now
        if now - since < self._fe_time:
            return ""
        return (
            f"joint {joint.name}: following error {error:.6g} beyond its window "
            f"{window:.6g} for {(now - since) * 1e3:.3g} ms (following_error: measured "
            f"{x:.6g}, commanded {joint.command_position:.6g}, time_ms {self._fe_time * 1e3:g})"
        )
