"""The loop's core: the Robot, its control loop and what runs beside it.

The :class:`~occ.core.robot.Robot` and its assembly from a configuration (``assembly``,
``loader``, ``build``), the loop (``loop``, ``stats``), the robot's state and its state
machine with the watchdog, supervisor and loss monitor (``data``, ``safety``, ``supervision``,
``alarms``), the drives as one unit (``hardware``) and the power-up of those whose activation
waits, off the loop thread (``powerup``), what the drives are told each tick
(``motion``), the State Data Table (``statetable``) and the narrow ports the front desk gets
(``ports``).

This room assembles the others: it may import every room of ``occ`` (the daemon's command,
``occ.cli``, excepted). Nothing in ``occ.drivers``, ``occ.kinematics`` or ``occ.haptics``
imports it (tests/test_imports.py).
"""
