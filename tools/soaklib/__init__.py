"""The parts of ``tools/soak.py`` (the entry point), one module per mode of the soak.

- :mod:`soaklib.common`: the requirement judged (2 tolerated, 3 stop, within 7 ms);
- :mod:`soaklib.sim`: ``sim``, the slave in simulated time with an exact oracle;
- :mod:`soaklib.daemons`: the daemons' configs on free ports, their processes;
- :mod:`soaklib.real`: ``real``, the daemons on loopback through the loss proxy;
- :mod:`soaklib.realcheck`: a ``real`` run's stops matched to the proxy's drops;
- :mod:`soaklib.hogs`: CPU hogs beside a run, a process's CPU time;
- :mod:`soaklib.series`: ``real --runs N --hogs H``, repeated runs judged against a bar;
- :mod:`soaklib.report`: the report folder (runs.csv, plots, report.json, report.md);
- :mod:`soaklib.paper`: ``paper --real``, the OCC stability protocol against the daemons.

The modules import the other tools (``loopback``, ``loss_proxy``, ``soakreport``...) as
top-level modules: ``tools/`` is on ``sys.path`` (``tools/soak.py`` puts it there).
"""
