"""Recording: every message in and out and the loop's state in one file, and its readers.

The recorder (``record``), the operators' StartRecording/StopRecording (``control``), the
exports to 3D Slicer's sequence files, ROS 2 bags and CSV (``export``), the plot (``plot``),
the black box and its dumps (``blackbox``, ``dump``), why a dump was written (``why``,
``whytext``) and the ``occ-record`` command (``cli``).

May import ``igtl`` (a recording holds wire messages), the vocabulary, ``occ.core.data`` and
the force display's parser; the loop only appends to the recorder's queue.
"""
