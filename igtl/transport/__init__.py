"""Transports: the only part of :mod:`igtl` that touches sockets.

- :class:`TCPServer`: many clients on one I/O thread, per-client header-version negotiation,
  bounded per-client send queues, access list, client limit, idle timeout.
- :class:`TCPClient`: one connection, reconnecting with capped exponential back-off.
- :class:`UDPEndpoint`: one message per datagram; large messages through the reference RTP
  fragmentation (:mod:`igtl.rtp`).

All of them decode with :mod:`igtl.codec`, never block the sender, count everything in plain
counters (``stats()``, :class:`Peer`), and run user callbacks on their I/O thread, guarded. See
each module's docstring for the exact behaviour on bad input.
"""

from .common import Peer
from .tcp import TCPClient, TCPServer
from .udp import UDPEndpoint

__all__ = ["Peer", "TCPClient", "TCPServer", "UDPEndpoint"]
