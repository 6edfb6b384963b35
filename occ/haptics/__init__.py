"""Haptics and forces: what the hands feel and what the instruments touch.

Virtual fixtures (``fixtures`` the primitives and the force law, ``fixture_defs`` the
definitions in the patient frame, ``master_fixtures`` the master's run-time set), the slave's
contact force (``forces``, its display ``forceviz``), the simulated tissue (``contact``),
two-port passivity (``passivity``), the gripper channel (``gripper``) and the return link's
rules (``returnlink``).

Pure computation on typed values: may import the vocabulary of ``occ``, the configuration's
models and ``occ.kinematics``; never ``igtl``, ``occ.core`` or ``occ.net``.
"""
