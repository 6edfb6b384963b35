"""Kinematics, trajectories and collision: geometry, no robot, no loop, no wire.

The kinematic model on pinocchio (``frame``), keyframe plans (``trajectory``), the trajectory
library (``trajlib``), keyframe items from their typed inputs (``keyframe_inputs``) and
whole-arm collision checking on coal (``collision``).

May import the vocabulary of ``occ`` (errors, clock, joint, samples, events) and the
configuration's models; never ``igtl``, ``occ.core``, ``occ.net`` or a controller.
"""
