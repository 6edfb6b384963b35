"""The log-line budget (igtl's :class:`~igtl.transport.common.RateLimit`: at most
``per_second`` events a second pass, the rest counted in ``suppressed``), named here for the
loop's modules that must not import the wire library themselves (the controllers and their
helpers: tests/test_imports.py). It is a counter, no wire type: one implementation serves both.
"""

from __future__ import annotations

from igtl.transport.common import RateLimit

__all__ = ["RateLimit"]
