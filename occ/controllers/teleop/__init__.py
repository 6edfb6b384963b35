"""Master-slave teleoperation (the system of Arata et al., IJCARS 2010).

Master daemon (:class:`MasterController`)
    The operator moves the master handle. The handle target comes from one of:

    - ``input: sim``: simulated operator motion, the paper's test: X = A·sin(2πft),
      Y = A·cos(2πft), Z constant (defaults A = 50 mm, f = 0.1 Hz, Z = 20 mm), relative to
      the handle position at zero joint values (the workspace centre);
    - ``input: igtl``: a TRANSFORM or POSITION stream (a tracker, a haptic-device server, a
      script) arriving on ``input_interface``;
    - ``input: driver``: the master's own drivers read a real device moved by hand (e.g. the
      ``can`` driver); the controller commands no motion.

    A master whose joint home is (0, A, Z) starts on the simulated trajectory without a jump; ``t``
    counts time spent RUNNING only, so after a Stop the motion resumes where it was held.
    The master's joints follow the target (IK on the master's Frame), and the *measured* handle
    position (FK) is streamed by the output source ``teleop``: POSITION, 24-byte variant
    (position + 3-element quaternion, as the OCC paper sends), header version 2, the message ID a
    sequence number (+1 per packet, for the slave's loss monitor), and metadata ``run`` (``1``
    while the master is RUNNING) and ``clutch`` (``1`` while the operator has the clutch pressed).
    The stream never stops while the daemon runs, so the slave can tell a stopped master from a
    dead one.

    Virtual fixtures (:mod:`occ.haptics.fixtures`, :mod:`occ.haptics.fixture_defs`,
    :mod:`occ.haptics.master_fixtures`): the
    OCC paper's accessible spheres (the default meaning of VFIXTURE), forbidden spheres and
    planes, guides; defined by VFIXTURE, Slicer Markups (POINT, TRANSFORM and POLYDATA with
    metadata) and ``.mrk.json`` files (``fixture_files``), all in the patient frame (3D
    Slicer's RAS, the frame of the slave's ``Tip``). The tool is where the slave measures it:
    its tip, sent back on the stream link at the stream rate (``SlaveTip``,
    :mod:`occ.haptics.returnlink`), judged by a loss monitor (late: the force fades out; lost: zero
    and an alert). Fixtures and tool are mapped into the master's force frame by the slave's
    own ``map`` (its base rotation x scale x rotation), so the clutch, re-indexing and a
    hand-over change nothing; a new tip gives a new force (a proxy per contact, clamped to
    ``max_force_n``), displayed while the slave follows this master. With ``force_output`` it
    is written to the master's effort command interfaces (a haptic master: ``sim-hand``, or
    ``can`` with ``command_interface: effort``), so the operator's hand feels it;
    position-commanded masters (``sim``, ``igtl``) report it only. ``tool_mm`` (patient) and
    ``force_n`` are in the stats with the return link's state (``slave_tip``); the output
    sources ``fixtures`` (POLYDATA models, on change and on ``GetFixtures``) and ``contact``
    (the proxy, while in contact and once after) show them in 3D Slicer; ``force`` sends the
    displayed force itself (N, the master's axes; SENSOR with the unit N, or NDARRAY) at its
    rate: ROS 2's ``measured_cf`` (occ_ros2).

Slave daemon (:class:`SlaveController`)
    Follows the master's POSITION stream: ``target = slave_ref + scale · R · (master - master_ref)``
    with motion scaling ``scale`` (default 0.1, i.e. 10:1) and an optional master-to-slave
    rotation ``R``. References are re-taken (clutch re-indexing, as OCC re-references and dVRK
    re-aligns) whenever following (re)starts: on entering RUNNING, when the master's ``run``
    becomes 1, and when its clutch is released. So the slave never jumps: it keeps its pose and
    follows from there. Inverse kinematics on the RCM model every tick; a target outside the
    workspace is clamped to the limits (counted). The base pose comes from the config
    (``base_mm``) or from a tracker's TRANSFORM (``base_interface``, device ``base_device``).

The package: :mod:`.master` (the master's controller), :mod:`.slave` (the slave's) and the
collaborators they build, each in a module of its own.
"""

from __future__ import annotations

from occ.controllers.teleop.master import MasterController
from occ.controllers.teleop.slave import SlaveController

__all__ = ["MasterController", "SlaveController"]
