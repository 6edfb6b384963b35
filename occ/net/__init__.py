"""Network I/O: where OpenIGTLink messages come in and go out.

One transport and thread per configured interface and their queues (``interfaces``), the
stream inputs the loop drains or polls (``streams``), the decoding of every message a
controller takes into a typed event (``decoders``) and the packing of every typed output
(``packers``, ``outputs``), operator requests and their replies (``commands``, ``operators``)
and who drives a slave (``collab``).

With the recording, the only room that may import ``igtl``; controllers and their helpers
see typed values only (tests/test_imports.py names the modules allowed).
"""
