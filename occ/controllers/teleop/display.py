"""The master's haptic display: what the operator's hand feels. The virtual fixtures' force
(gated by the slave's return link), the slave's force (bilateral teleoperation) and an external
one, passivated (occ/haptics/passivity.py), clamped, turned into the drives' efforts (``J^T F``)
with a 6-axis sensor's torque on a master with rotational axes."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from occ.controllers.teleop.common import STATUS_TIME_OUT, apply_jt
from occ.core.safety import RobotState
from occ.errors import CommandError
from occ.events import InputEvent, VectorOut
from occ.haptics.forces import sensor_force
from occ.haptics.passivity import MasterPort, OnePort

if TYPE_CHECKING:
    from occ.controllers import ControllerContext
    from occ.core.data import RobotData
    from occ.haptics.master_fixtures import MasterFixtures
    from occ.haptics.returnlink import ReturnLink
    from occ.net.outputs import Output

Vec3 = tuple[float, float, float]
ZERO: Vec3 = (0.0, 0.0, 0.0)


class HapticDisplay:
    """The force displayed on the master's handle, tick by tick (the controller owns one).

    ``p`` the master's parameters (MasterParams), ``fixtures`` its virtual fixtures (their
    force, and the slave's map into the master's axes), ``alert`` the controller's alert."""

    def __init__(
        self, p: Any, fixtures: MasterFixtures, alert: Callable[[str, str, int], None]
    ) -> None:
        self.fixtures = fixtures
        self._alert = alert
        self.force_output = p.force_output
        self._fade_s = p.tip_fade_ms * 1e-3
        #: the share of the computed fixture force displayed (0..1: fades on a stale tip, the
        #: clutch, a slave not following this master; 0 at once when the tip is lost)
        self.gain = 0.0
        self._t_gain = math.nan
        self._jt: list[list[float]] | None = None  # J^T of a Cartesian master (constant)
        self._efforts: list[float] = []
        #: bilateral teleoperation: the slave's force displayed (occ/haptics/passivity.py keeps
        #: the loop passive); the displayed force is fixtures + feedback, clamped, passivated
        self.force_feedback = p.force_feedback
        self.force_scale = p.force_scale
        self.max_force = p.max_force_n
        self.passivity_on = p.passivity
        #: the master's port of the two-port passivity scheme (occ/haptics/passivity.py)
        self.passivity = MasterPort(p.passivity_max_damping)
        #: the share of the slave's force displayed (0..1): rises within ``tip_fade_ms`` while
        #: the slave follows with a fresh link, falls within ``feedback_fade_ms`` otherwise
        self.feedback_gain = 0.0
        self._feedback_fade_s = p.feedback_fade_ms * 1e-3
        self._x_handle: Vec3 | None = None
        #: the driving slave's state as its return link last said, and its force then (N)
        self._slave_state = ""
        self.external_device = p.external_force_device
        self._external_timeout = p.external_force_timeout_ms * 1e-3
        #: the external force (CRTK servo_cf: N, the master's axes) and when it came
        self.external_n: Vec3 = ZERO
        self._t_external = -math.inf
        self.external_samples = 0
        self._feedback_raw: Vec3 = ZERO
        self.feedback_n: Vec3 = ZERO
        self.displayed_n: Vec3 = ZERO
        self.clamped_ticks = 0
        #: a 6-axis sensor's torque from the slave (N m, the master's axes): displayed on a
        #: master with rotational axes (:meth:`torque`), in the stats for the others
        self.max_torque = p.max_torque_nm
        self.torque_passivity = OnePort(p.passivity_max_rot_damping)
        self.rotational = False
        self.feedback_torque_nm: Vec3 = ZERO
        self.displayed_torque_nm: Vec3 = ZERO
        self._t_torque = math.nan
        self._clamped_by = 1.0  # the last clamp's factor
        self._t_handle = math.nan
        self.data: RobotData | None = None
        self.ctx: ControllerContext | None = None

    def bind(self, data: RobotData, ctx: ControllerContext) -> None:
        """At configure: the robot's data and context, the efforts' buffer, the rotational
        axes, and a Cartesian master's constant Jacobian (efforts = J^T F, worked out once)."""
        self.data, self.ctx = data, ctx
        n = len(data.joint_names)
        self._efforts = [0.0] * n
        self.rotational = self.force_output and ctx.frame.nq >= 6
        if self.force_output:
            j0 = ctx.frame.jacobian([0.0] * n)[:3]
            j1 = ctx.frame.jacobian(data.q)[:3]
            if np.allclose(j0, j1, atol=1e-12) and any(abs(v) > 1e-6 for v in data.q):
                self._jt = j0.T.tolist()

    def external(self, event: InputEvent, now: float) -> bool:
        """The external force (a SENSOR ``external_force_device``: CRTK ``servo_cf``): True
        when ``event`` was one."""
        if self.external_device is None or event.device != self.external_device:
            return False
        force, error = sensor_force(event)
        if force is None:
            raise CommandError(f"{event.describe()}: {error}")
        self.external_n = force
        self._t_external = now
        self.external_samples += 1
        return True

    def reset(self) -> None:
        """A state change: nothing displayed, the gains and the ports from zero."""
        self.gain = 0.0
        self._t_gain = math.nan
        self.fixtures.displayed(ZERO)
        self.feedback_n = self.displayed_n = ZERO
        self._t_handle = math.nan
        self._x_handle = None
        self.feedback_gain = 0.0
        self.passivity.reset()
        self.feedback_torque_nm = self.displayed_torque_nm = ZERO
        self._t_torque = math.nan
        self.torque_passivity.reset()

    def tick(self, now: float, link: ReturnLink | None, clutch: bool) -> list[float] | None:
        """This tick's display, ``link`` the driving slave's return link: the efforts to
        command with ``force_output`` (``J^T F`` and the torque's), else None."""
        fx, fy, fz = self.show(now, self.fixture_force(now, link, clutch))
        if not self.force_output:
            self.torque(now, link, None)
            return None
        data, ctx = self.data, self.ctx
        assert data is not None and ctx is not None
        eff = self._efforts
        jt = self._jt
        if jt is not None:
            for i, (a, b, c) in enumerate(jt):
                eff[i] = a * fx + b * fy + c * fz
        else:
            jac = ctx.frame.jacobian(data.q)[:3]
            eff[:] = (jac.T @ np.array([fx, fy, fz])).tolist()
        self.torque(now, link, eff)
        return eff

    def fixture_force(self, now: float, link: ReturnLink | None, clutch: bool) -> Vec3:
        """The virtual-fixture force to display this tick (N, the master's axes).

        Computed where the slave's tool is: the tip of the driving slave's return stream
        (patient frame), each time a new one arrives. Displayed x ``gain``: the gain rises to
        1 within ``tip_fade_ms`` while the tip is fresh and the slave follows this master (the
        clutch released), and falls to 0 within ``tip_fade_ms`` otherwise, holding the last
        force computed from a fresh tip (never one from a stale pose); a lost or missing tip
        makes it 0 at once."""
        fixtures = self.fixtures
        last = self._t_gain
        dt = now - last if last == last else 0.0
        self._t_gain = now
        if link is None:
            self.gain = 0.0
            fixtures.displayed(ZERO)
            return fixtures.force_n
        status = link.status
        if link.new and link.tip is not None:
            link.new = False
            fixtures.step(link.tip, link.t_tip)
            self._feedback(link)
            self._slave_news(link)
        following = status == "fresh" and link.following and not clutch
        self._gains(status, following, dt)
        g = self.gain
        rx, ry, rz = fixtures.raw_force_n
        fixtures.displayed((g * rx, g * ry, g * rz))
        bx, by, bz = self._feedback_raw
        h = self.feedback_gain
        self.feedback_n = (h * bx, h * by, h * bz)
        return fixtures.force_n

    def _feedback(self, link: ReturnLink) -> None:
        """A new sample's force (the slave's, in the master's axes x ``force_scale``), and its
        energy into the master's port."""
        f = link.force
        if f is None or not self.force_feedback:
            self._feedback_raw = ZERO
            return
        k = self.force_scale
        mapping = self.fixtures.mapping
        mx, my, mz = mapping.force(f)
        self._feedback_raw = (k * mx, k * my, k * mz)
        if link.energy is not None and k > 0.0:
            # J at the instrument -> J at the handle: kf / kp (occ/haptics/passivity.py)
            self.passivity.account.receive(link.energy * k / mapping.factor)

    def _gains(self, status: str, following: bool, dt: float) -> None:
        """The fixtures' gain and the feedback's, ``dt`` after the last tick."""
        fade = self._fade_s
        if status == "lost" or status == "none":
            self.gain = 0.0
        else:
            step = 1.0 if fade <= 0.0 else dt / fade
            if following:
                self.gain = min(1.0, self.gain + step)
            else:
                self.gain = max(0.0, self.gain - step)
        # the slave's force: held and faded, never dropped (issue 37): a force dropped to zero
        # and snapped back gave the hand energy it never put in
        if status == "none":
            self.feedback_gain = 0.0
        elif following:
            self.feedback_gain = min(1.0, self.feedback_gain + (1.0 if fade <= 0.0 else dt / fade))
        else:
            self.feedback_gain = max(0.0, self.feedback_gain - dt / self._feedback_fade_s)

    def _slave_news(self, link: ReturnLink) -> None:
        """The hand is told when its slave stops while pressing on tissue (it lets go of it:
        teleop-slave ``release_*``), and the force it feels then fades out."""
        state = link.slave_state
        if state == self._slave_state:
            return
        before, self._slave_state = self._slave_state, state
        bx, by, bz = self._feedback_raw
        force = math.sqrt(bx * bx + by * by + bz * bz)
        if before == "RUNNING" and state in ("STOPPED", "FAULT", "ESTOP") and force > 0.2:
            data = self.data
            if data is not None and data.state is RobotState.RUNNING:
                self._alert(
                    "ALERT",
                    f"slave on {link.interface} {state} while pressing {force:.1f} N: it lets go "
                    f"of the tissue; its force fades out within "
                    f"{self._feedback_fade_s * 1e3:g} ms",
                    STATUS_TIME_OUT,
                )

    def show(self, now: float, fixture: Vec3) -> Vec3:
        """The force to display this tick: the slave's (feedback) through the passivity
        controller (occ/haptics/passivity.py) with the handle's velocity, plus the fixtures',
        clamped to ``max_force_n``.

        Only the feedback is passivated: a virtual fixture defined with the tool outside its
        region starts stretched and pulls the hand in, giving energy it never received (by
        design); the observer would take that for the network's and damp the guidance away.
        The fixtures' own stability under delay is their proxy's (``fixture_slide_mm``). An
        external force (``servo_cf``) is displayed with the feedback, passivated too, for
        ``external_force_timeout_ms`` after it came."""
        bx, by, bz = self.feedback_n
        if now - self._t_external <= self._external_timeout:
            ex, ey, ez = self.external_n
            bx, by, bz = bx + ex, by + ey, bz + ez
        t_last = self._t_handle
        self._t_handle = now
        port = self.passivity
        shown = port.shown
        if bx != 0.0 or by != 0.0 or bz != 0.0 or shown != ZERO:
            # (no feedback now or last tick: no power through the port, nothing to observe:
            # the common case costs nothing here)
            x = self.handle_position()
            last = self._x_handle
            self._x_handle = x
            if last is not None:
                # what the force displayed over the last tick did, exactly
                port.observe((x[0] - last[0], x[1] - last[1], x[2] - last[2]))
            if self.passivity_on and now > t_last:
                v = self.handle_velocity()
                bx, by, bz = port.step((bx, by, bz), v, now - t_last)
        else:
            self._x_handle = None
        fx, fy, fz = fixture[0] + bx, fixture[1] + by, fixture[2] + bz
        self.displayed_n = self.clamp(fx, fy, fz)
        k = self._clamped_by
        port.displayed((k * bx, k * by, k * bz))
        return self.displayed_n

    def torque(self, now: float, link: ReturnLink | None, eff: list[float] | None) -> None:
        """The slave's torque (a 6-axis sensor's, the return channel's ``torque_nm``) in the
        master's axes, ``force_scale Q^T t``, gated as the force is (the same gain: faded
        when late, zero when lost, the clutch); on a master with rotational axes, passivated
        against the handle's angular velocity, clamped to ``max_torque_nm`` and added to the
        efforts ``eff`` through the Jacobian's angular rows. Without them it is only in the
        stats (and in the recording, with the return channel's samples)."""
        t = link.torque if link is not None and self.force_feedback else None
        if t is None or self.gain == 0.0:
            self.feedback_torque_nm = self.displayed_torque_nm = ZERO
            self._t_torque = now
            return
        k = self.force_scale * self.gain
        mx, my, mz = self.fixtures.mapping.force(t)  # a rotation, as for the force
        self.feedback_torque_nm = (k * mx, k * my, k * mz)
        if eff is None or not self.rotational:
            return
        data, ctx = self.data, self.ctx
        assert data is not None and ctx is not None
        jac = ctx.frame.jacobian(data.q)[3:]
        out = self.feedback_torque_nm
        last, self._t_torque = self._t_torque, now
        if now > last:  # (NaN: the first tick, nothing to observe yet)
            w = jac @ np.asarray(data.qdot, dtype=float)
            wv = (float(w[0]), float(w[1]), float(w[2]))
            if self.passivity_on:
                out = self.torque_passivity.step(out, wv, now - last)
            else:
                self.torque_passivity.observe(out, wv, now - last)
        mag = math.sqrt(out[0] * out[0] + out[1] * out[1] + out[2] * out[2])
        if mag > self.max_torque:
            c = self.max_torque / mag
            out = (out[0] * c, out[1] * c, out[2] * c)
        self.displayed_torque_nm = out
        for i, v in enumerate((jac.T @ np.array(out)).tolist()):
            eff[i] += v

    def handle_position(self) -> Vec3:
        """The handle's position (m, the master's axes; a Cartesian master's ``J q``: only its
        changes are used)."""
        data, ctx = self.data, self.ctx
        assert data is not None and ctx is not None
        q = data.q
        jt = self._jt
        if jt is not None:
            return apply_jt(jt, q)
        return tuple(float(v) for v in ctx.frame.tip_position(q))  # type: ignore[return-value]

    def handle_velocity(self) -> Vec3:
        """The handle's velocity (m/s, the master's axes) from the drives' joint velocities:
        ``J qdot`` (a Cartesian master's constant Jacobian, else the model's at ``q``)."""
        data, ctx = self.data, self.ctx
        assert data is not None and ctx is not None
        qd = data.qdot
        jt = self._jt
        if jt is not None:
            return apply_jt(jt, qd)
        v = ctx.frame.jacobian(data.q)[:3] @ np.asarray(qd, dtype=float)
        return (float(v[0]), float(v[1]), float(v[2]))

    def clamp(self, fx: float, fy: float, fz: float) -> Vec3:
        mag = math.sqrt(fx * fx + fy * fy + fz * fz)
        if mag > self.max_force:
            self.clamped_ticks += 1
            k = self._clamped_by = self.max_force / mag
            return (fx * k, fy * k, fz * k)
        self._clamped_by = 1.0
        return (fx, fy, fz)

    def energy_out(self) -> float | None:
        """The energy the hand has put into the channel (J at the slave's instrument: the
        stream's ``energy_j``), or None when this master sends none (no force displayed on a
        hand, or passivity off: the slave's port controller then stays off)."""
        k = self.force_scale
        if not (self.passivity_on and self.force_feedback and self.force_output and k > 0.0):
            return None
        return self.passivity.account.e_in * self.fixtures.mapping.factor / k

    def source_force(self, out: Output, now: float) -> VectorOut:
        """The output source ``force``: the displayed force (N, the master's axes: fixtures and
        the slave's feedback, as the hand feels it), every time."""
        assert self.ctx is not None
        meta = None
        if self.rotational:  # the displayed torque beside it (N m, the master's axes)
            t = self.displayed_torque_nm
            meta = {"torque_nm": f"{t[0]:.5f},{t[1]:.5f},{t[2]:.5f}"}
        return VectorOut(self.displayed_n, self.ctx.clock.wall_time(), "N", meta)

    def stats(self, now: float) -> dict[str, Any]:
        """The display's part of the master's GetStats (in its place there)."""
        return {
            # displayed on the hand: fixtures + feedback, clamped, passivated
            "force_n": [round(v, 4) for v in self.displayed_n],
            "fixture_force_n": [round(v, 4) for v in self.fixtures.force_n],
            "feedback_n": [round(v, 4) for v in self.feedback_n],
            "force_feedback": self.force_feedback,
            "force_scale": self.force_scale,
            # a 6-axis sensor's torque (N m, the master's axes): displayed with rotational axes
            "feedback_torque_nm": [round(v, 5) for v in self.feedback_torque_nm],
            "torque": {
                "displayed": self.rotational,
                "torque_nm": [round(v, 5) for v in self.displayed_torque_nm],
                "passivity": self.torque_passivity.stats(),
            },
            "external_n": [round(v, 4) for v in self.external_n],
            "external_samples": self.external_samples,
            "external_fresh": now - self._t_external <= self._external_timeout,
            "force_clamped_ticks": self.clamped_ticks,
            "passivity": {"on": self.passivity_on, **self.passivity.stats()},
            "feedback_gain": round(self.feedback_gain, 4),
            "fixture_gain": round(self.gain, 4),
            "force_output": self.force_output,
        }
