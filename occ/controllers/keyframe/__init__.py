"""Keyframe trajectories on the robot (issue 11): plan, check, preview, acknowledge, run.

After the German Heart Center system: an operator puts poses on a timeline (keyframes), the
planner (:mod:`occ.kinematics.trajectory`) fills in the motion, and the plan runs only once it has
passed its checks, been shown in 3D Slicer and been acknowledged. Plugin name ``keyframe``.

Keyframes
    A *keyframe set* is one timeline: times in seconds from the start of the run, and poses
    either in joint space (one value per joint, SI: rad, m) or Cartesian (the tip position in
    mm, in the world frame that the ``tip`` output and 3D Slicer use). The controller keeps one
    set; each source replaces it, ``KeyframeAdd`` inserts into it:

    - the YAML (``params.keyframes``) or a keyframe file (``params.file``), read at start-up;
    - ``KeyframeLoad File=NAME``: a file in ``params.keyframe_dir`` (nothing outside it);
    - a Slicer point list (POINT) or a TRAJ (entry/target points, in that order) on an
      interface that lists the type among its ``inputs`` with ``queue: command``. Cartesian.
      Times come from the v2 metadata ``times`` (seconds, comma-separated, one per point), else
      every ``point_interval_s`` (the first at ``point_interval_s``). Hidden points (alpha 0,
      as Slicer marks them) are left out with their times. A message that cannot be used is
      refused, counted (``inputs_refused``) and logged; the set is then unchanged;
    - ``KeyframeAdd T=SECONDS Pose="a b c" [Label=..] [Space=joint|cartesian]``.

    ``KeyframeList`` lists the set and the plan; ``KeyframeClear`` forgets both.

    The run starts where the robot is: a set whose first keyframe is later than t = 0 gets an
    implicit keyframe at t = 0, the robot's commanded pose (so the robot moves to the first
    keyframe in the time given); a first keyframe at t = 0 must be within
    ``start_tolerance`` / ``start_tolerance_mm`` of it and is then replaced by it exactly.

Plan, check and preview (offline mode, the paper's safety rule)
    ``KeyframePlan [Interpolation=linear|spline] [Mode=stop|continuous] [Steepness=n]
    [Ramp=r]`` plans the set (defaults from the params) and checks every tick of it as it would
    run: each joint within its position limits, each step within ``velocity_scale`` x the
    joint's velocity limit over one period (what the drivers check), the tip inside
    ``workspace_mm`` (base frame) and reachable within the joint limits (Cartesian plans go
    through the Frame's IK, ``ik_clamped``, seeded with the previous tick as at run time), and
    the tip outside every forbidden region (:class:`ForbiddenCheck`, see below). Planning and
    checking run on a planner thread (a spline plan takes milliseconds, a check 30-70 us a
    tick of motion), SCHED_FIFO one below the loop when the loop has it and paced into the
    quiet part of each period (:class:`~.pacer.Pacer`); the command is answered
    when they finish (:class:`~occ.net.commands.Deferred`): the plan's number and summary, or the
    refusal naming the keyframe (or the segment between two) and the limit. A plan that passed
    is previewed: output source ``keyframe-path`` (POLYDATA: the tip's path as a polyline, world
    mm) and ``keyframe-points`` (POINT: the keyframes), both with v2 metadata
    ``MRMLNodeName`` (the output's device name) so Slicer names its nodes; sent once per new
    plan and again every ``preview_repeat_s`` (a Slicer that connects later sees it too); an
    empty one when the plan is dropped.

Acknowledge and run
    ``KeyframeAck Plan=N`` (the number the plan's reply and ``KeyframeList`` give) starts plan N
    while the robot is RUNNING, if the robot is still where the plan starts (else: replan).
    Each tick the loop samples the plan at ``now - start`` (no thread): joint plans directly,
    Cartesian ones through ``ik_clamped``. At the end the robot rests at the last keyframe and
    the controller holds. A new set or plan never changes a running plan.

    A run is announced to every viewer and operator (the controller context's ``alert``): a
    STATUS named :data:`STATUS_RUNNING` (``KEYFRAME_RUNNING``, code OK) when it starts and
    :data:`STATUS_ENDED` (``KEYFRAME_ENDED``; code OK when it completed, DISABLED when it was
    dropped, below) when it ends, the text saying which plan and how. ROS 2's CRTK
    ``is_busy`` (occ_ros2) is true between the two.

Stop
    An operator's Stop (or anything that takes the robot out of RUNNING: fault, e-stop, Hold)
    during a run *drops* the plan: the robot holds where it was stopped (the robot's own Stop)
    and the run is never resumed mid-way (its timeline would restart at speed, mid-ramp). The
    keyframes stay stored: ``KeyframePlan`` (which now starts from where the robot stopped)
    and ``KeyframeAck`` run them again. The refused, stopped or finished state is in
    ``KeyframeList`` and the statistics.

The trajectory library (issue 28; :mod:`occ.kinematics.trajlib`, ``params.library``)
    ``KeyframeSave Set=N [Replace=1]`` keeps the stored set in an SQLite file under a name,
    with the settings of the plan that ran it, the robot's name and the hash of its kinematic
    configuration; only a set whose plan was acknowledged (and not changed since) is saved; a
    name taken needs ``Replace=1``. ``KeyframeLibrary`` lists the file's sets (robot, count,
    duration, time saved), ``KeyframeDelete Set=N`` deletes one of this robot's.
    ``KeyframeLoad Set=N`` makes a saved set the stored one, as ``KeyframeLoad File=...``
    does, its plan settings the defaults of the next ``KeyframePlan``; it never runs on load:
    it is planned, checked, previewed and acknowledged again. A set saved by another robot, or
    with another kinematic configuration, is refused with the reason. The file work runs on
    the planner thread, answered by a :class:`~occ.net.commands.Deferred` like a plan (a request
    while it is busy is refused "busy"). The argument is ``Set``, not ``Name``: in the XML form
    ``Name`` is the command's own name (PlusServer's convention, :mod:`occ.net.commands`).

Forbidden regions (the collision check)
    :class:`ForbiddenCheck`: any callable taking a tip position (metres, robot base frame) and
    returning something false when it is free, or True / a short description (named in the
    refusal) when it is forbidden. Checks are added with :meth:`KeyframeController.
    add_forbidden_check`, each called for every tick of a plan being checked (on the planner
    thread: it must be thread-safe, e.g. read an immutable snapshot). When the regions change,
    :meth:`KeyframeController.invalidate_plan` makes a checked but unacknowledged plan unusable
    (it must be planned again), as the paper requires of a plan that would now collide.
    A :class:`PathCheck` (anything with ``check_path``, e.g. the whole-arm check of
    ``safety.collision``, occ/kinematics/collision.py, added at configure) gets the plan's joint
    samples after the per-tick checks and names the first that fails.

A laparoscopic tool's port (issue 40; ``params.rcm_mm``)
    With a port (a 6-DOF arm; the patient frame, mm, as ``teleop-slave``'s ``rcm_mm``) every
    plan turns the tool about it (:mod:`occ.kinematics.port`): the tip's path as planned, the
    tool's axis (its z) from the port through the tip at every tick, the roll the keyframes'
    (interpolated) or, none given, the one the tool has where the plan starts. A joint set is
    planned through the port as the tool's poses (forward kinematics of its keyframes), and
    each keyframe's joints must then be reached (0.1 rad: not another arm configuration).
    Refused when planned, naming why: the tool's shaft more than 0.05 mm from the port where
    the plan starts; a keyframe whose own orientation is more than ``rcm_tolerance_deg`` off
    the axis through the port and its tip (named, with the angle; within it, turned onto the
    axis); a tip less than ``rcm_min_depth_mm`` from the port at a keyframe or a sample; the
    shaft more than 0.05 mm from the port at any sample (the joints' forward kinematics; the
    worst sample named). At run time each tick's joints are held to the same 0.05 mm: past
    it the run ends (``port_stops``) and the robot holds.

A cell keyframe set (issue 40, item 5; :mod:`.cellset`, :mod:`occ.kinematics.cellpaths`)
    A file with one timeline per arm of the cell, on one time base, by member name
    (``{cell, space, plan: {interpolation, mode, steepness, ramp}, arms: {<member>:
    {space, keyframes}}}``, at least two parts). ``KeyframeLoad File=`` on a member (its name
    in the cell, ``ControllerContext.cell_member``) makes its own part the stored set and keeps
    the whole file; the set's digest (SHA-256 of its canonical content) is the same on every
    member. Each member then:

    - ``KeyframePlan``: plans and checks its part as any plan (the other arms standing where
      they are), keeping its sampled joint path and the path's digest (a part is at most 65535
      samples: an NDARRAY's dimension);
    - ``KeyframeCellPath Plan=N``: answers that path as an NDARRAY ``CellPath`` (metadata
      ``member``, ``set``, ``plan``, ``digest``, ``period``, ``base``), sent by the operator
      desk's worker, then the reply;
    - takes the other members' ``CellPath`` messages as inputs (its operator interface lists
      ``NDARRAY`` ``CellPath`` with ``queue: command``); one of another set or not another
      member's is refused to its sender;
    - ``KeyframeCellCheck Plan=N`` (planner thread): checks each path given against its digest,
      then its own path against each at the same times (the collision model's peer geometry
      and margin; every other arm anywhere within ``cell_skew_ms`` of the aligned time), and
      answers the identity of the cell plan (a hash of the set's digest and every member's path
      digest) or the refusal naming both arms, both links and the time. Another arm's plan is
      never planned here: what is checked is what that arm will run, byte for byte;
    - ``KeyframeAck Plan=N StartAt=<unix time> Cell=<identity>``: a part runs only with the
      identity of its own passed cross-check and a common start; it holds at the plan's start
      until the first tick of the loop at or after ``StartAt`` (on the loop's tick grid: the
      samples are the checked ones), then runs. A ``StartAt`` in the past or more than
      ``cell_start_max_s`` ahead is refused (``StartAt`` works for a plain plan too).

    Stopped as one: a cell plan's run that ends other than by completing (an operator's Stop, a
    fault, a cell hold, a failed tick; before or after its start) calls
    ``ControllerContext.cell_stop``: every other member holds, which drops its own run (never
    resumed). A run dropped while this robot stays RUNNING (a failed tick) keeps the others
    held until this member is stopped and run again. ``policy: alert-only`` cells do not hold:
    their members' parts then run on. The coordinator is occ_testkit/cellplan.py
    (tools/cell_plan.py over TCP).

Layout
    :mod:`.controller` the controller on the loop thread (the set, the commands, the
    acknowledgement, the run); :mod:`.params` its parameters and their checks; :mod:`.sets`
    keyframe sets and files; :mod:`.plan` the plan request, ``build_plan`` and its checks;
    :mod:`.planner` the planner thread and its jobs; :mod:`.pacer` the Pacer; :mod:`.preview`
    the preview outputs; :mod:`.library` the trajectory library's commands; :mod:`.cellset`
    cell keyframe sets and this member's side of their exchange.
"""

from occ.controllers.keyframe.controller import STATUS_ENDED, STATUS_RUNNING, KeyframeController
from occ.controllers.keyframe.params import KeyframeParams

__all__ = ["STATUS_ENDED", "STATUS_RUNNING", "KeyframeController", "KeyframeParams"]
