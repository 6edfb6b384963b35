"""Open Core Control: the robot controller daemon (docs/ARCHITECTURE.md)."""

# Decides, before any hot-path module is imported, whether the mypyc-compiled build or the pure
# sources run (occ/_native.py).
from occ._native import BUILD as BUILD
