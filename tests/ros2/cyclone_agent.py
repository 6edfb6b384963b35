"""A Cyclone DDS participant for the bridge's namespace tests: the topics rclpy cannot read here.

crtk_msgs and tf2_msgs have no rclpy packages on PyPI, so ``operating_state``,
``state_command`` (crtk_msgs) and ``/tf``, ``/tf_static`` (tf2_msgs) are read and written by
this process, with the project's type definitions (checked byte for byte against rosbags in
test_msgs.py) and the bridge's shipped DDS configuration: a second DDS participant that meets
the bridge in any start order (Cyclone to Cyclone). Run as a subprocess inside the test's
network namespace::

    python cyclone_agent.py NAMESPACE

JSON lines on stdin, one JSON line answered on stdout for each:

- ``{"op": "snapshot"}``: ``operating_state`` samples as ``[t, stamp, state, is_homed,
  is_busy]`` (t: receive time, seconds since the agent started), ``measured_cp`` as ``[t,
  stamp, frame_id, x, y, z]``, the last ``/tf`` and ``/tf_static`` messages as lists of
  ``[parent, child, x, y, z, qx, qy, qz, qw]``, and the number of each;
- ``{"op": "state_command", "data": "enable"}``: one crtk_msgs/StringStamped;
- ``{"op": "matched"}``: subscriptions matched by the state_command writer;
- ``{"op": "exit"}``.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from typing import Any

from cyclonedds.core import ReadCondition, SampleState, WaitSet
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from occ_ros2 import msgs
from occ_ros2.bridge import (
    DEFAULT_CONFIG,
    QOS_DEFAULT,
    QOS_LATCHED,
    QOS_TF,
    QOS_TF_STATIC,
    topic_name,
    typed_qos,
)

T0 = time.monotonic()


def now() -> float:
    return time.monotonic() - T0


def tf_rows(m: Any) -> list[list[Any]]:
    out = []
    for t in m.transforms:
        v, q = t.transform.translation, t.transform.rotation
        out.append([t.header.frame_id, t.child_frame_id, v.x, v.y, v.z, q.x, q.y, q.z, q.w])
    return out


def main() -> int:
    ns = sys.argv[1].rstrip("/")
    domain = Domain(0, DEFAULT_CONFIG.read_text())
    dp = DomainParticipant(0)

    def reader(name: str, cls: type[Any], qos: Any) -> DataReader[Any]:
        return DataReader(dp, Topic(dp, name, cls), typed_qos(qos, cls))

    op_state = reader(topic_name(ns, "operating_state"), msgs.OperatingState, QOS_LATCHED)
    cp = reader(topic_name(ns, "measured_cp"), msgs.PoseStamped, QOS_DEFAULT)
    tf = reader("rt/tf", msgs.TFMessage, QOS_TF)
    tf_static = reader("rt/tf_static", msgs.TFMessage, QOS_TF_STATIC)
    cmd = DataWriter(
        dp,
        Topic(dp, topic_name(ns, "state_command"), msgs.StringStamped),
        typed_qos(QOS_DEFAULT, msgs.StringStamped),
    )
    lock = threading.Lock()
    seen: dict[str, Any] = {"operating_state": [], "measured_cp": [], "tf": [], "tf_static": [],
                            "tf_count": 0, "tf_static_count": 0}  # fmt: skip
    stop = threading.Event()
    ws = WaitSet(dp)
    for r in (op_state, cp, tf, tf_static):
        ws.attach(ReadCondition(r, SampleState.NotRead))

    def pump() -> None:
        while not stop.is_set():
            ws.wait(duration(milliseconds=50))
            t = now()
            with lock:
                for s in op_state.take(N=64):
                    st = s.header.stamp.to_seconds()
                    seen["operating_state"].append([t, st, s.state, s.is_homed, s.is_busy])
                for s in cp.take(N=64):
                    p = s.pose.position
                    row = [t, s.header.stamp.to_seconds(), s.header.frame_id, p.x, p.y, p.z]
                    seen["measured_cp"].append(row)
                del seen["measured_cp"][:-200]
                for s in tf.take(N=64):
                    seen["tf"] = tf_rows(s)
                    seen["tf_count"] += 1
                for s in tf_static.take(N=64):
                    seen["tf_static"] = tf_rows(s)
                    seen["tf_static_count"] += 1

    thread = threading.Thread(target=pump, daemon=True)
    thread.start()

    def answer(obj: dict[str, Any]) -> None:
        sys.stdout.write(json.dumps(obj) + "\n")
        sys.stdout.flush()

    answer({"ready": True, "t": now()})
    for line in sys.stdin:
        try:
            req = json.loads(line)
        except ValueError:
            answer({"error": f"not JSON: {line!r}"})
            continue
        op = req.get("op")
        if op == "snapshot":
            with lock:
                answer({"t": now(), **seen})
        elif op == "state_command":
            stamp = msgs.Time.from_seconds(time.time())
            cmd.write(msgs.StringStamped(header=msgs.Header(stamp=stamp), string=req["data"]))
            answer({"t": now(), "published": req["data"]})
        elif op == "matched":
            answer({"t": now(), "matched": cmd.get_publication_matched_status().current_count})
        elif op == "exit":
            answer({"t": now(), "bye": True})
            break
        else:
            answer({"error": f"unknown op {op!r}"})
    stop.set()
    thread.join(2.0)
    del domain  # the participant goes with the process
    return 0


if __name__ == "__main__":
    sys.exit(main())
