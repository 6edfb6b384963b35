"""The ``robot`` section: kinematic model, joints, drivers, realtime settings."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, model_validator

from occ.config.base import (
    Bool,
    BuiltinModel,
    ExistingFile,
    Float,
    Int,
    Loc,
    Name,
    NonNegFloat,
    PosFloat,
    Str,
    Vec3,
    _did_you_mean,
    _Model,
    _num,
    _raise_problems,
)

#: packages of robot descriptions a config may name (``robot.frame.package``): where each keeps
#: its files, relative to its installed distribution
URDF_PACKAGES = {"example-robot-data": "cmeel.prefix/share/example-robot-data"}


def package_dir(package: str) -> Path:
    """The directory of an installed robot-description package (:data:`URDF_PACKAGES`);
    ValueError when it is not installed."""
    from importlib import metadata

    try:
        dist = metadata.distribution(package)
    except metadata.PackageNotFoundError:
        raise ValueError(f"package {package!r} is not installed (pip install {package})") from None
    return Path(str(dist.locate_file(URDF_PACKAGES[package])))


class _Failed(Exception):
    def __init__(self, err: BaseException, said: str) -> None:
        super().__init__(str(err))
        self.err, self.said = err, said


def _quietly(call: Any) -> tuple[Any, str]:
    """``call()`` with the process's C-level stderr captured (a C++ parser's messages), as
    (its result, what it said); _Failed(err, said) when it raised."""
    import tempfile

    sys_stderr = sys.stderr
    sys_stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            result = call()
            failure = None
        except (RuntimeError, ValueError) as err:
            result, failure = None, err
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        tmp.seek(0)
        said = tmp.read().decode("utf-8", "replace")
    if failure is not None:
        raise _Failed(failure, said)
    return result, said


def _urdf_problems(cfg: FrameConfig) -> tuple[list[tuple[Loc, str]], tuple[str, ...]]:
    """Load the configured URDF as the daemon will (pinocchio), for ``occd --check``: the
    problems (at the ``urdf`` or link key) and the model's joint names."""
    import pinocchio as pin

    key: Loc = ("urdf",) if cfg.urdf is not None else ("package_urdf",)
    path = Path(str(cfg.urdf)) if cfg.urdf is not None else None
    if cfg.package_urdf is not None:
        if cfg.package is None:
            return [(("package",), "required with 'package_urdf'")], ()
        try:
            path = package_dir(cfg.package) / cfg.package_urdf
        except ValueError as err:
            return [(("package",), str(err))], ()
        if not path.is_file():
            return [(key, f"no file {cfg.package_urdf!r} in package {cfg.package!r}")], ()
    assert path is not None
    try:
        model, said = _quietly(lambda: pin.buildModelFromUrdf(str(path)))
    except _Failed as failed:
        # urdfdom says why on the C stderr ("Error: Joint [j] ... does not specify limits /
        # at line 607 in .../joint.cpp"): its first lines, without the parser's own source lines
        why = [ln.strip().removeprefix("Error:").strip() for ln in failed.said.splitlines()]
        why = [w for w in why if w and not w.startswith("at line ")][:3]
        text = "; ".join(why) or " ".join(str(failed.err).split())
        return [(key, f"the URDF does not load: {text[:300]}")], ()
    problems: list[tuple[Loc, str]] = []
    for link_key in ("tip_link", "base_link"):
        link = getattr(cfg, link_key)
        if link is not None and not model.existFrame(link):
            links = sorted({f.name for f in model.frames if f.type == pin.FrameType.BODY})
            problems.append(
                ((link_key,), f"no link {link!r} in the URDF (links: {', '.join(links)})")
            )
    if model.nq != model.nv:
        problems.append((key, "only revolute and prismatic joints are supported"))
    return problems, tuple(model.names[1:])


class FrameConfig(_Model):
    """Kinematic model: exactly one of a built-in model, a URDF file, or a URDF of an installed
    robot-description package."""

    model: BuiltinModel | None = Field(
        None, description="Built-in kinematic model name. Exclusive with `urdf`."
    )
    urdf: ExistingFile | None = Field(
        None,
        description="URDF file, relative to the config file's directory; must exist and load "
        "(checked at load, with its line). Exclusive with `model`.",
    )
    package: Literal["example-robot-data"] | None = Field(
        None,
        description="An installed package of robot descriptions (`pip install "
        "example-robot-data`) whose URDF `package_urdf` names.",
    )
    package_urdf: Str | None = Field(
        None,
        description="The URDF inside `package`, e.g. "
        "`robots/ur_description/urdf/ur5_joint_limited_robot.urdf` (kinematics only: no "
        "meshes are read).",
    )
    tip_link: Str | None = Field(
        None, description="URDF link whose pose is the tool tip. Required with `urdf`."
    )
    base_link: Str | None = Field(
        None, description="URDF link used as the base frame; null = the URDF root link."
    )

    @model_validator(mode="after")
    def _exactly_one_source(self) -> FrameConfig:
        problems: list[tuple[Loc, str]] = []
        sources = [k for k in ("model", "urdf", "package_urdf") if getattr(self, k) is not None]
        if len(sources) != 1:
            which = f"{' and '.join(sources)} are set" if sources else "none is set"
            problems.append(
                ((), f"exactly one of 'model', 'urdf' or 'package_urdf' is required ({which})")
            )
        elif sources[0] != "model":
            if self.tip_link is None:
                problems.append((("tip_link",), f"required when '{sources[0]}' is set"))
            else:
                found, _ = _urdf_problems(self)
                problems += found
        _raise_problems(problems)
        return self

    def urdf_path(self) -> Path | None:
        """The URDF file to load (None for a built-in model)."""
        if self.urdf is not None:
            return Path(str(self.urdf))
        if self.package is not None and self.package_urdf is not None:
            return package_dir(self.package) / self.package_urdf
        return None


class JointLimits(_Model):
    """Position, velocity and effort limits of one joint (SI units)."""

    min: Float = Field(description="Lower position limit (rad or m).")
    max: Float = Field(description="Upper position limit (rad or m); must be > `min`.")
    velocity: PosFloat = Field(description="Velocity limit (rad/s or m/s), > 0.")
    effort: PosFloat | None = Field(
        None, description="Effort limit (N·m or N); null = not limited here."
    )

    @model_validator(mode="after")
    def _ordered(self) -> JointLimits:
        if not self.min < self.max:
            _raise_problems(
                [(("max",), f"must be greater than min ({_num(self.min)}), got {_num(self.max)}")]
            )
        return self


class PidGains(_Model):
    """Per-joint servo law, used when the driver takes effort commands."""

    kp: NonNegFloat = Field(description="Proportional gain, >= 0.")
    ki: NonNegFloat = Field(0.0, description="Integral gain, >= 0.")
    kd: NonNegFloat = Field(0.0, description="Derivative gain, >= 0.")
    i_limit: NonNegFloat | None = Field(
        None, description="Clamp of the integral term (anti-windup); null = unclamped."
    )
    out_limit: PosFloat | None = Field(
        None, description="Clamp of the output effort; null = the joint's effort limit."
    )


class JointConfig(_Model):
    """One joint of the robot."""

    name: Name = Field(description="Joint name, unique within the robot.")
    type: Literal["revolute", "prismatic"] = Field(
        "revolute", description="Revolute (radians) or prismatic (metres)."
    )
    limits: JointLimits = Field(description="Joint limits.")
    home: Float = Field(0.0, description="Home position; must lie within the limits.")
    pid: PidGains | None = Field(None, description="Servo gains; null = no servo law.")

    @model_validator(mode="after")
    def _home_within_limits(self) -> JointConfig:
        lo, hi = self.limits.min, self.limits.max
        if not lo <= self.home <= hi:
            _raise_problems(
                [(("home",), f"{_num(self.home)} is outside the limits [{_num(lo)}, {_num(hi)}]")]
            )
        return self


class DriverConfig(_Model):
    """One hardware driver (plugin) and the joints it drives."""

    name: Name = Field(description="Driver name, unique within the robot.")
    plugin: Str = Field(
        description="Driver plugin name (`sim`, `can`, ...), looked up when the robot is built."
    )
    joints: Annotated[tuple[Name, ...], Field(min_length=1)] = Field(
        description="Joints this driver drives; each must be declared in `robot.joints`."
    )
    on_limit: Literal["clamp", "fault"] = Field(
        "clamp", description="What a command beyond a joint limit does: clamp it, or fault."
    )
    params: dict[str, Any] = Field({}, description="Free-form parameters passed to the plugin.")


class RealtimeConfig(_Model):
    """Operating-system scheduling of the control loop."""

    fifo_priority: Annotated[Int, Field(ge=1, le=99)] | None = Field(
        None, description="SCHED_FIFO priority 1..99; null = normal scheduling."
    )
    cpu: Annotated[Int, Field(ge=0)] | None = Field(
        None, description="CPU core to pin the loop to; null = no pinning."
    )
    spin_us: Annotated[Float, Field(ge=0, le=1000)] = Field(
        0.0,
        description="The loop sleeps until this long before each deadline, then spins: "
        "less jitter for more CPU (200 us = 20 % of a core at 1 kHz). 0 = sleep only: with "
        "SCHED_FIFO the wake-up is early enough and the master-to-slave latency the same "
        "(docs/BENCHMARKS.md).",
    )
    poll_streams: Bool = Field(
        True,
        description="The loop reads its UDP stream sockets itself, at most 4 datagrams a tick "
        "(no thread wake-up per datagram; a flood costs the tick a bounded amount). false = "
        "an interface thread receives them (docs/BENCHMARKS.md compares both).",
    )
    switch_interval_us: Annotated[Float, Field(ge=50, le=100000)] | None = Field(
        None,
        description="Python's thread switch interval during the run (sys.setswitchinterval): "
        "how long an interface thread may keep the interpreter when the loop wants it; "
        "null = Python's default (5000 us).",
    )
    gc: Literal["freeze", "off", "default"] = Field(
        "freeze",
        description="Garbage collector: `freeze` after start-up, `off` entirely, or `default`.",
    )


class RobotConfig(_Model):
    """The robot: kinematics, joints, drivers and loop timing."""

    name: Name = Field(description="Robot name (used in logs and STATUS messages).")
    rate_hz: Annotated[Int, Field(ge=1, le=10000)] = Field(
        1000, description="Control loop rate in Hz."
    )
    frame: FrameConfig = Field(description="Kinematic model.")
    joints: Annotated[tuple[JointConfig, ...], Field(min_length=1)] = Field(
        description="Joints, in kinematic order; names unique."
    )
    drivers: Annotated[tuple[DriverConfig, ...], Field(min_length=1)] = Field(
        description="Drivers; every joint is driven by exactly one driver."
    )
    realtime: RealtimeConfig = Field(RealtimeConfig(), description="Loop scheduling.")
    base_mm: Vec3 | None = Field(
        None,
        description="Where the robot's base stands in the patient frame (3D Slicer's, mm): the "
        "world pose of its `Tip`, its forbidden regions' frame, and where the other arms of "
        "its cell see it; null = at the origin. A controller may set it otherwise "
        "(teleop-slave's `base_mm`, a tracked base).",
    )
    base_rpy_deg: Vec3 = Field(
        (0.0, 0.0, 0.0),
        description="With `base_mm`: the base's orientation in the patient frame, roll, pitch, "
        "yaw about the fixed x, y, z axes (degrees).",
    )

    @property
    def period_s(self) -> float:
        """The control period in seconds."""
        return 1.0 / self.rate_hz

    @property
    def joint_names(self) -> tuple[str, ...]:
        return tuple(j.name for j in self.joints)

    def joint(self, name: str) -> JointConfig:
        for j in self.joints:
            if j.name == name:
                return j
        raise KeyError(name)

    @model_validator(mode="after")
    def _joints_and_drivers(self) -> RobotConfig:
        problems: list[tuple[Loc, str]] = []
        first_joint: dict[str, int] = {}
        for i, j in enumerate(self.joints):
            if j.name in first_joint:
                problems.append(
                    (
                        ("joints", i, "name"),
                        f"duplicate joint name '{j.name}' (first at joints[{first_joint[j.name]}])",
                    )
                )
            else:
                first_joint[j.name] = i
        first_driver: dict[str, int] = {}
        driven_by: dict[str, str] = {}
        for d, drv in enumerate(self.drivers):
            if drv.name in first_driver:
                problems.append(
                    (
                        ("drivers", d, "name"),
                        f"duplicate driver name '{drv.name}' "
                        f"(first at drivers[{first_driver[drv.name]}])",
                    )
                )
            else:
                first_driver[drv.name] = d
            for k, jname in enumerate(drv.joints):
                loc: Loc = ("drivers", d, "joints", k)
                if jname not in first_joint:
                    problems.append(
                        (loc, f"unknown joint '{jname}'" + _did_you_mean(jname, list(first_joint)))
                    )
                elif jname in driven_by:
                    problems.append(
                        (loc, f"joint '{jname}' is already driven by driver '{driven_by[jname]}'")
                    )
                else:
                    driven_by[jname] = drv.name
        for jname, i in first_joint.items():
            if jname not in driven_by:
                problems.append(
                    (("joints", i, "name"), f"joint '{jname}' is not driven by any driver")
                )
        fc = self.frame
        if fc.model is None and fc.tip_link is not None:
            found, model_joints = _urdf_problems(fc)
            names = tuple(j.name for j in self.joints)
            if not found and model_joints != names:
                problems.append(
                    (
                        ("joints",),
                        f"the joints {list(names)} are not the URDF's {list(model_joints)} "
                        "(same names, same order)",
                    )
                )
        _raise_problems(problems)
        return self
