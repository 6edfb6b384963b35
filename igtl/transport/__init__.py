"""Transports: the only part of :mod:`igtl` that touches sockets (in-process: stands in).

- :class:`TCPServer`: many clients on one I/O thread, per-client header-version negotiation,
  bounded per-client send queues, access list, client limit, idle timeout.
- :class:`TCPClient`: one connection, reconnecting with capped exponential back-off.
- :class:`UDPEndpoint`: one message per datagram; large messages through the reference RTP
  fragmentation (:mod:`igtl.rtp`).
- :class:`InprocTransport`: endpoints on a named in-process channel (python-can's ``virtual``
  bus for OpenIGTLink): the real codec, no sockets, synchronous delivery (simulated time).

Every transport sends with ``send(msg, peer=None) -> int``: the number of peers the message was
queued for (0: dropped). ``peer`` None means every client (server), the server (client), the
``remote`` (UDP) or every endpoint on the channel (in-process); a :class:`Peer` from a callback
addresses that one sender, so a reply reaches whoever asked whatever the transport.

All of them decode with :mod:`igtl.codec`, never block the sender, count everything in plain
counters (``stats()``, :class:`Peer`), and run user callbacks guarded (on their I/O thread;
in-process: on the sender's). See
each module's docstring for the exact behaviour on bad input.
"""

from .common import Peer
from .inproc import InprocTransport
from .tcp import TCPClient, TCPServer
from .udp import UDPEndpoint

__all__ = ["InprocTransport", "Peer", "TCPClient", "TCPServer", "UDPEndpoint"]
