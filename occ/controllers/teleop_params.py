"""The teleop controllers' pydantic parameter models (moved out of teleop.py so that teleop.py
can be compiled with mypyc: mypyc cannot compile a BaseModel subclass with ``Field`` defaults)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

from occ.config import Bool, DeviceName, Float, Int, Name, PosFloat, Str, Vec3


class _Params(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class FixtureFile(_Params):
    """A 3D Slicer markups file loaded at start."""

    file: Str = Field(description="Path of the `.mrk.json` file (relative: to the config file).")
    kind: Literal["accessible", "forbidden", "guide"] = Field(
        "accessible",
        description="What its point lists are (lines, curves, planes are guides "
        "and planes whatever this says).",
    )
    radius_mm: PosFloat = Field(5.0, description="Radius of the sphere around each point (mm).")
    stiffness: Annotated[Float, Field(ge=0)] = Field(1.0, description="N per master mm.")
    damping: Annotated[Float, Field(ge=0)] = Field(0.0, description="N s/mm.")


class MasterGripper(_Params):
    """Where the master's gripper value comes from (occ/haptics/gripper.py)."""

    source: Literal["joint", "command", "sim"] = Field(
        description="`joint`: a master joint (a handle's grip or switch read as a position); "
        "`command`: the operators' `Grip` command (the handle's switch on an operator client); "
        "`sim`: the simulated operator closes and opens it every `period_s`."
    )
    joint: Name | None = Field(None, description="`joint`: the master joint (its name).")
    open: Float = Field(0.0, description="`joint`: its position with the gripper open.")
    closed: Float = Field(1.0, description="`joint`: its position with the gripper closed.")
    period_s: PosFloat = Field(4.0, description="`sim`: one close and open (s).")


class MasterParams(_Params):
    """Parameters of ``teleop-master``. Lengths in mm, as on the wire."""

    input: Literal["sim", "igtl", "driver"] = Field(
        "sim",
        description="Where the operator's motion comes from: `sim` (the OCC paper's test "
        "motion), `igtl` (a TRANSFORM/POSITION stream), `driver` (a hand-moved device read by "
        "the master's drivers, e.g. CAN).",
    )
    amplitude_mm: Vec3 = Field(
        (50.0, 50.0, 0.0), description="`sim`: amplitudes of X = A sin, Y = A cos, Z (mm)."
    )
    offset_mm: Vec3 = Field(
        (0.0, 0.0, 20.0),
        description="`sim`: constant offset (mm) from the handle at zero joint values.",
    )
    frequency_hz: PosFloat = Field(0.1, description="`sim`: frequency of the motion (Hz).")
    orientation_amplitude_deg: Vec3 = Field(
        (0.0, 0.0, 0.0),
        description="`sim`: the handle also turns, about x, y, z by these amplitudes (degrees) "
        "times sin(2 pi f t) (a 6-DOF master's gimbal; sent as the stream's quaternion).",
    )
    clutch: Bool = Field(False, description="Clutch pressed at start.")
    fixture_radius_mm: PosFloat = Field(
        5.0,
        description="Radius (patient mm) of the sphere around each Markups point received as "
        "POINT (used when neither the point nor the metadata `radius` gives one, as 3D Slicer "
        "sends them).",
    )
    fixture_hardness: Annotated[Float, Field(ge=0)] = Field(
        1.0,
        description="Stiffness (N per mm of the master's motion) of fixtures defined without "
        "one (POINT, TRANSFORM, POLYDATA without metadata `stiffness`; files).",
    )
    fixture_damping: Annotated[Float, Field(ge=0)] = Field(
        0.0, description="Damping (N s/mm) of fixtures defined without one."
    )
    vfixture_kind: Literal["accessible", "forbidden"] = Field(
        "accessible",
        description="What a VFIXTURE sphere without metadata `kind` is: `accessible` (the OCC "
        "paper: no force inside, a spring back outside) or `forbidden`.",
    )
    point_kind: Literal["accessible", "forbidden", "guide"] = Field(
        "accessible",
        description="What a POINT list without metadata `kind` is: spheres (`accessible`, "
        "`forbidden`) or one polyline `guide` through its points.",
    )
    force_output: Bool = Field(
        False,
        description="Write the fixture force to the joints' effort command interfaces (a "
        "haptic master whose drivers take efforts: `sim-hand`, `can` with "
        "`command_interface: effort`); needs `input: driver`.",
    )
    max_force_n: PosFloat = Field(
        10.0,
        description="Clamp of the displayed force, fixtures and feedback summed (N); 10 N is "
        "the OCC paper's figure.",
    )
    force_feedback: Bool = Field(
        True,
        description="Display the slave's contact force (its return channel's `force_n`, a "
        "slave with `force`) with the fixture force: bilateral teleoperation. Late or lost, "
        "held and faded out by `feedback_fade_ms`.",
    )
    feedback_fade_ms: PosFloat = Field(
        300.0,
        description="While the return link is late or lost, or the slave stops following "
        "(a stop, the clutch), the slave's force is held and fades out within this time, "
        "passivated all along (never dropped to zero and snapped back: issue 37); it comes "
        "back within `tip_fade_ms` when the slave follows again.",
    )
    force_scale: Annotated[Float, Field(ge=0, le=100)] = Field(
        1.0,
        description="N displayed per N at the slave's instrument (its own scale, not the "
        "motion scaling).",
    )
    external_force_device: DeviceName | None = Field(
        "ServoCF",
        description="A SENSOR of this device name from an operator (N, the master's axes, "
        "3 or 6 values: CRTK `servo_cf` through `occ-ros2`) is displayed with the slave's "
        "force, passivated, while RUNNING; null = none taken.",
    )
    external_force_timeout_ms: PosFloat = Field(
        100.0, description="An external force older than this is no longer displayed."
    )
    passivity: Bool = Field(
        True,
        description="Two-port time-domain passivity (Ryu, Artigas and Preusche 2010; "
        "occ/haptics/passivity.py): the master's port controller keeps the energy the hand gets"
        " below what the slave's tissue gave back, and the master sends its energy with the "
        "stream so the slave's keeps what it puts into the tissue below what the hand put in; "
        "whatever the delay and loss. Off: observed only (statistics), and no energy sent.",
    )
    passivity_max_damping: PosFloat = Field(
        200.0,
        description="The master port's largest damper (N s/m); beyond it the controller cuts "
        "the force's component along the handle's motion instead (counted apart), never "
        "more than that component.",
    )
    max_torque_nm: PosFloat = Field(
        0.5,
        description="A master with rotational axes (6 or more joints, `force_output`): clamp "
        "of the displayed torque (N m), a 6-axis sensor's torque from the slave (its return "
        "channel's `torque_nm`) times `force_scale`; masters without them record it only.",
    )
    passivity_max_rot_damping: PosFloat = Field(
        2.0,
        description="The largest rotational damping (N m s/rad) of the displayed torque's own "
        "passivity controller (the handle's angular velocity).",
    )
    fixture_slide_mm: PosFloat = Field(
        1.0,
        description="Longest move of a contact's proxy per tick (mm): bounds the force step "
        "when the contact changes sphere or guide segment.",
    )
    max_fixtures: Annotated[Int, Field(ge=1, le=1024)] = Field(
        64, description="Most primitives in all; a definition beyond is refused."
    )
    max_planes: Annotated[Int, Field(ge=0, le=64)] = Field(
        8, description="Most forbidden planes (the SAW's fixed number); beyond is refused."
    )
    fixture_files: tuple[FixtureFile, ...] = Field(
        (), description="3D Slicer markups files (`.mrk.json`, LPS) loaded at start."
    )
    scale: Annotated[Float, Field(gt=0, le=10)] = Field(
        0.1,
        description="The slave's motion scaling (its `scale`): maps patient fixtures onto the "
        "master only for a slave that does not send its `map` on the return channel (the "
        "shipped slave does).",
    )
    rotation: tuple[Vec3, Vec3, Vec3] | None = Field(
        None,
        description="The slave's master-to-slave rotation (its `rotation`; null = identity): "
        "used as `scale` is.",
    )
    slave_base_device: DeviceName = Field(
        "Base",
        description="Device name of a registration TRANSFORM (the slave's base pose in the "
        "patient frame): its rotation maps fixtures onto the master when the slave does not "
        "send its own `map` on the return channel.",
    )
    slave_tip_device: DeviceName = Field(
        "SlaveTip",
        description="Device name of the slave's return stream (POSITION/TRANSFORM, patient "
        "frame, sequence-numbered: the slave's `teleop-return` output), taken on the "
        "interfaces this master streams to. Its tip is the tool of the virtual fixtures.",
    )
    tip_period_ms: PosFloat = Field(
        2.0,
        description="Period of the slave's return stream (its `teleop-return` rate: 500 Hz "
        "= 2 ms); late after 3 periods + a quarter.",
    )
    tip_grace_ms: PosFloat = Field(
        100.0,
        description="A return stream silent this long is lost (a dead slave): fixture force "
        "zero and an ALERT; so are 3 or more consecutive sequence numbers missing.",
    )
    tip_fade_ms: Annotated[Float, Field(ge=0)] = Field(
        20.0,
        description="The fixture force fades out within this time when the slave's tip is "
        "late or the slave stops following this master (the clutch, a hand-over), and back "
        "in when it follows again; 0 = at once.",
    )
    first_seq: Annotated[Int, Field(ge=0, le=0xFFFFFFFF)] = Field(
        0, description="Sequence number before the first POSITION (the first is +1)."
    )
    input_interface: Name | None = Field(
        None, description="`igtl`: interface of the input stream (required with `igtl`)."
    )
    input_device: DeviceName | None = Field(
        None, description="Only samples with this device name are used (null = any)."
    )
    slaves: tuple[Name, ...] = Field(
        (),
        description="One master driving several slaves: the interfaces of its `teleop` "
        "outputs, one per slave; only the selected one carries `run=1` (the others hold). "
        "Empty = every `teleop` output drives.",
    )
    slave: Name | None = Field(
        None, description="The slave selected at start (one of `slaves`; null = the first)."
    )
    gripper: MasterGripper | None = Field(
        None,
        description="Send a gripper value (0 open to 1 closed) with every sample, metadata "
        "`gripper`: the slave's jaw follows it (its `gripper`); null = none sent.",
    )
    toggle_tap_ms: PosFloat | None = Field(
        300.0,
        description="With several `slaves`: a clutch pressed and released within this time "
        "selects the next slave (the da Vinci's tap); null = only the `Select`/`Toggle` "
        "commands.",
    )


class SlaveForceParams(_Params):
    """The slave's tip force, sent to the master on the return channel (occ/haptics/forces.py)."""

    sources: tuple[Literal["effort", "sensor", "tissue"], ...] = Field(
        ("effort",),
        min_length=1,
        description="Where the force comes from, in order of preference (the first healthy "
        "one is sent; all are in the statistics): `effort` (the drives' efforts through the "
        "Jacobian transpose; the simulated tissue loads the `sim` drives), `sensor` (a SENSOR "
        "stream from a force sensor), `tissue` (simulation: the `environment`'s contact force, "
        "a simulated force sensor at the instrument).",
    )
    effort_damping: tuple[Annotated[Float, Field(ge=0)], ...] | None = Field(
        None,
        description="`effort`: each joint's viscous friction (N s/m, N m s/rad), taken out of "
        "its effort before the force is estimated; null = none.",
    )
    effort_inertia: tuple[Annotated[Float, Field(ge=0)], ...] | None = Field(
        None,
        description="`effort`: each joint's inertia (kg, kg m^2): its momentum change between "
        "estimates is taken out too (a momentum observer; the drives' efforts must be means "
        "over the stream period); null = none.",
    )
    sensor_interface: Name | None = Field(
        None, description="`sensor`: the interface its SENSOR stream comes in on."
    )
    sensor_device: DeviceName = Field("ForceSensor", description="`sensor`: its device name.")
    sensor_frame: Literal["patient", "base", "tip"] = Field(
        "patient",
        description="`sensor`: the frame of its readings (`tip`: rotated by the measured tip "
        "orientation).",
    )
    sensor_timeout_ms: PosFloat = Field(
        20.0, description="`sensor`: an older reading is not used (ALERT once)."
    )
    damping: PosFloat = Field(
        1e-4,
        description="`effort`: damped least squares factor (m) of the Jacobian inverse near a "
        "singular pose.",
    )
    display_mm_per_n: PosFloat = Field(
        10.0,
        description="The output source `force` (3D Slicer): length of the force arrow, mm per N "
        "(the POLYDATA arrow's length, the TRANSFORM's z axis; occ/haptics/forceviz.py).",
    )
    tool_mass_kg: Annotated[Float, Field(ge=0, le=20)] = Field(
        0.0,
        description="`sensor`: mass (kg) of what hangs beyond the force sensor (instrument, "
        "its drive, the gripper): its weight is removed from every reading at the pose the "
        "robot's kinematics give (force, and its moment for a 6-axis sensor); 0 = none.",
    )
    tool_com_mm: Vec3 = Field(
        (0.0, 0.0, 0.0),
        description="`sensor`: its centre of mass from the sensor's origin (mm, the tip "
        "frame's axes): the lever of its weight's moment on a 6-axis sensor.",
    )
    gravity_mps2: Vec3 = Field(
        (0.0, 0.0, -9.81),
        description="Gravity in the robot's base frame (m/s^2; a base mounted upside down or "
        "on a wall turns it): rotated into the sensor's frame for the weight compensation.",
    )
    tare_window_ms: Annotated[Float, Field(gt=0, le=2000)] = Field(
        100.0,
        description="`ForceTare`: the sensor's offset is the mean of its readings (the "
        "tool's weight removed) over this last stretch of time.",
    )
    tare_max_speed_mm_s: PosFloat = Field(
        0.5,
        description="`ForceTare` is refused while the tip moves faster than this, now or on "
        "average over the window (mm/s): a tare is taken at rest.",
    )
    tare_max_spread_n: PosFloat = Field(
        0.05,
        description="`ForceTare` is refused when a reading in the window is farther than "
        "this from their mean (N): a force that varies is a contact or a vibration.",
    )
    tare_max_offset_n: PosFloat = Field(
        1.0,
        description="`ForceTare` is refused when more than this is left once the tool's "
        "weight is removed (N): a load on the instrument (a tare in contact would hide it) "
        "or a wrong tool model, not the sensor's zero.",
    )


class SlaveGripper(_Params):
    """The slave's jaw, driven by the master's gripper value (occ/haptics/gripper.py)."""

    joint: Name = Field(
        description="The jaw's joint (one of the robot's; it must not move the tool's tip)."
    )
    open: Float = Field(description="Its position with the gripper open (m or rad).")
    closed: Float = Field(description="Its position with the gripper closed (m or rad).")


class SlaveParams(_Params):
    """Parameters of ``teleop-slave``. Lengths in mm, as on the wire."""

    input_interface: Name | None = Field(
        None, description="Interface of the master's POSITION stream (null = any)."
    )
    input_device: DeviceName | None = Field(
        None, description="Only samples with this device name are used (null = any)."
    )
    scale: Annotated[Float, Field(gt=0, le=10)] = Field(
        0.1, description="Motion scaling, slave motion / master motion (0.1 = 10:1)."
    )
    rotation: tuple[Vec3, Vec3, Vec3] | None = Field(
        None, description="3x3 rotation from master to slave axes (rows); null = identity."
    )
    base_mm: Vec3 | None = Field(
        None, description="Base position in the world (mm), sent as TRANSFORM `Base`."
    )
    base_interface: Name | None = Field(
        None, description="Interface on which a tracker sends the base TRANSFORM."
    )
    base_device: DeviceName = Field("Base", description="Device name of that TRANSFORM.")
    orientation: Literal["off", "follow", "rcm"] = Field(
        "off",
        description="`follow` (a 6-DOF arm): the tool turns as the master's handle turns, the "
        "handle's rotation since the last re-index (the stream's quaternion) mapped through "
        "`rotation` and applied to the tool's orientation at the re-index; the full pose is "
        "solved (damped least squares). `rcm` (a laparoscopic tool on a 6-DOF arm): the "
        "tool's axis (its z) always passes through the port `rcm_mm`, pointing from it to the "
        "tip, the roll about it kept. `off`: position only (3-DOF arms).",
    )
    rcm_mm: Vec3 | None = Field(
        None,
        description="`rcm`: the port, the remote centre of motion the tool's axis passes "
        "through (patient frame, mm).",
    )
    rotation_scale: Annotated[Float, Field(gt=0, le=1)] = Field(
        1.0,
        description="`follow`: the share of the handle's rotation angle the tool makes (1: "
        "off, one degree is one degree).",
    )
    mapping: Literal["relative", "absolute"] = Field(
        "relative",
        description="How a sample moves the tip. `relative` (a master): the displacement "
        "since the last re-index, times `scale` and `rotation`; the clutch and `run` "
        "re-index. `absolute` (an external command source, e.g. CRTK `servo_cp` through "
        "`occ-ros2 --servo`): each sample is the tip's target position in the patient frame "
        "(mm; what 3D Slicer's `Tip` and ROS 2's `measured_cp` show), `scale` and `rotation` "
        "unused; every joint moves toward it together along the straight line, at no more "
        "than 0.9 of its velocity limit (with `orientation: follow` the tool keeps the "
        "orientation it had when the source took control; with `rcm` the tip goes along the "
        "straight way, the tool's axis through the port at every tick); a target farther than "
        "`max_jump_mm` from the tip is refused (hold and an ALERT); `run=0` or the clutch "
        "pressed holds.",
    )
    max_jump_mm: PosFloat = Field(
        10.0,
        description="`absolute`: the farthest a target may be from where the tip is told to "
        "be (mm); a farther one is refused, never clipped nor approached: the robot holds "
        "where it was told to be (on the way to an earlier target too), stays RUNNING, and the "
        "operators get one ALERT per run of refused samples (a servo command is a small step; "
        "a far goal is a `move_cp`, planned and acknowledged).",
    )
    force: SlaveForceParams | None = Field(
        None,
        description="The tip force, sent to the master on the return channel (`force_n`: "
        "bilateral teleoperation, the master displays it); null = no force sent.",
    )
    gripper: SlaveGripper | None = Field(
        None,
        description="A jaw that follows the master's gripper value (its stream's `gripper` "
        "metadata) at no more than 0.9 x its velocity limit, only while following; held "
        "otherwise, and on a late or lost stream like every joint. null = none.",
    )
    max_tissue_force_n: PosFloat | None = Field(
        10.0,
        description="The force limit at the instrument (N, the measured contact force: needs "
        "`force`; without one the default is not applied and setting it is an error). In "
        "contact the tool moves into the tissue no faster than 5 mm/s per N below 90 % of it, "
        "and backs out as fast per N above, whatever the master commands and whatever the "
        "delay; an ALERT `ForceLimit` each time 90 % is reached. null = no limit.",
    )
    passivity: Bool = Field(
        True,
        description="The slave's port of the two-port passivity scheme "
        "(occ/haptics/passivity.py): a step into the tissue that would put in more energy "
        "than the master's hand has put in (the "
        "master's `energy_j`, sent with its stream) is shortened; the difference is given back "
        "at `drift_return_mm_s` when the energy allows. Acts only on a stream that carries "
        "`energy_j` (a master with `passivity` and force feedback).",
    )
    drift_return_mm_s: PosFloat = Field(
        5.0,
        description="How fast (tip mm/s) the slave closes the gap the passivity controller "
        "and the force limit left between it and the master's command, when it may.",
    )
    release_speed_mm_s: PosFloat = Field(
        40.0,
        description="A latched stop in contact (the measured force over `release_force_n`): "
        "the tool backs out along the contact force at this speed (tip mm/s) until the force "
        "is under `release_force_n` (then it holds there, and backs out again if the tissue "
        "presses again): a stop lets go of the tissue rather than holding a position in it.",
    )
    release_force_n: PosFloat = Field(
        0.2, description="A stop lets go of the tissue until the contact force is under this (N)."
    )
    release_max_mm: PosFloat = Field(
        10.0,
        description="The farthest a stop backs the tool out (tip mm, in all); reached, it holds "
        "and alerts.",
    )
    phase_lock_us: Annotated[Float, Field(ge=0)] | None = Field(
        400.0,
        description="Shift the loop's deadlines so the master samples this long before a tick "
        "(by its POSITION timestamps): a sample then waits about this long, not up to a whole "
        "period, for the tick that uses it. Must cover the transport time; null = off.",
    )
