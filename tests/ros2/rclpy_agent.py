"""A real ROS 2 node for the bridge's tests: rclpy on ROS 2's default RMW (rmw_fastrtps_cpp).

Run as a subprocess (inside the test's network namespace) by tests/ros2/test_rclpy.py::
    python rclpy_agent.py NAMESPACE

It subscribes to the bridge's std_msgs, geometry_msgs and sensor_msgs topics of NAMESPACE with
ROS 2's usual QoS (the default profile; transient local for the state, as a late subscriber to
a latched topic asks) and publishes on ``NAMESPACE/command``. It is driven by JSON lines on
stdin and answers each with one JSON line on stdout:

- ``{"op": "snapshot"}``: what arrived so far (receive times on this process's monotonic
  clock, seconds since the agent started; header stamps; frames; replies);
- ``{"op": "publish", "data": "enable"}``: one std_msgs/String on ``NAMESPACE/command``;
- ``{"op": "move_jp", "name": [...], "position": [...]}``: one sensor_msgs/JointState on
  ``NAMESPACE/move_jp``; ``{"op": "move_cp", "frame": "world", "position": [x, y, z]}``: one
  geometry_msgs/PoseStamped (metres) on ``NAMESPACE/move_cp``; both answer the wall time of
  sending (``wall``: a CRTK client's ``start_time``) and the goal's stamp as the bridge names
  the move's reply (``id``);
- ``{"op": "servo", "frame": "world", "position": [x, y, z], "rate_hz": 100, "seconds": 5}``:
  geometry_msgs/PoseStamped on ``NAMESPACE/servo_cp`` at ``rate_hz`` for ``seconds`` (a CRTK
  servo client's stream; a new ``servo`` replaces the running one, ``{"op": "servo_stop"}``
  ends it); ``{"op": "servo_cf", "frame": "master_base", "force": [fx, fy, fz], ...}`` the same
  with geometry_msgs/WrenchStamped on ``NAMESPACE/servo_cf``;
- ``{"op": "matched"}``: how many subscriptions the command publisher has matched (and the
  move publishers), and how many publishers of ``command_reply`` this node's graph knows;
- ``{"op": "graph"}``: the publishers of ``NAMESPACE/measured_cp`` as this node's graph sees
  them (type name and the type hash from their USER_DATA), and this node's own hash of the type;
- ``{"op": "exit"}``.

crtk_msgs and tf2_msgs have no rclpy packages on PyPI (ros-jazzy-*), so the CRTK-typed topics
and /tf are read by the project's Cyclone reader in the tests, not here.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from typing import Any

import rclpy
from geometry_msgs.msg import PoseStamped, WrenchStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import String

T0 = time.monotonic()
KEEP = 400  # poses kept per topic (the newest)


def now() -> float:
    return time.monotonic() - T0


def stamp_id(stamp: Any) -> str:
    """The request id the bridge names a move's reply with: its goal's stamp (docs/ROS2.md)."""
    return f"{stamp.sec}.{stamp.nanosec:09d}"


def main() -> int:
    ns = sys.argv[1].rstrip("/")
    rclpy.init()
    node = rclpy.create_node("occ_test_probe")
    lock = threading.Lock()
    poses: dict[str, list[list[Any]]] = {
        "measured_cp": [],
        "local/measured_cp": [],
        "setpoint_cp": [],
    }
    joints: dict[str, list[list[Any]]] = {"measured_js": [], "setpoint_js": []}
    states: list[list[Any]] = []
    replies: list[list[Any]] = []
    statuses: list[list[Any]] = []
    wrenches: list[list[Any]] = []

    def on_pose(leaf: str) -> Any:
        def cb(m: PoseStamped) -> None:
            p = m.pose.position
            row = [now(), m.header.stamp.sec + m.header.stamp.nanosec * 1e-9,
                   m.header.frame_id, p.x, p.y, p.z]  # fmt: skip
            with lock:
                poses[leaf].append(row)
                del poses[leaf][:-KEEP]

        return cb

    def on_joints(leaf: str) -> Any:
        def cb(m: JointState) -> None:
            row = [now(), m.header.frame_id, list(m.name), list(m.position)]
            with lock:
                joints[leaf].append(row)
                del joints[leaf][:-KEEP]

        return cb

    def on_state(m: String) -> None:
        with lock:
            states.append([now(), m.data])

    def on_reply(m: String) -> None:
        with lock:
            replies.append([now(), m.data])

    def on_status(m: String) -> None:
        with lock:
            statuses.append([now(), m.data])
            del statuses[:-KEEP]

    def on_wrench(m: WrenchStamped) -> None:
        f = m.wrench.force
        row = [now(), m.header.stamp.sec + m.header.stamp.nanosec * 1e-9, m.header.frame_id,
               f.x, f.y, f.z]  # fmt: skip
        with lock:
            wrenches.append(row)
            del wrenches[:-KEEP]

    latched = QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=1,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
    for leaf in poses:
        node.create_subscription(PoseStamped, f"{ns}/{leaf}", on_pose(leaf), 10)
    for leaf in joints:
        node.create_subscription(JointState, f"{ns}/{leaf}", on_joints(leaf), 10)
    node.create_subscription(String, f"{ns}/state", on_state, latched)
    node.create_subscription(String, f"{ns}/command_reply", on_reply, 10)
    node.create_subscription(String, f"{ns}/status", on_status, 10)
    node.create_subscription(WrenchStamped, f"{ns}/measured_cf", on_wrench, 10)
    command = node.create_publisher(String, f"{ns}/command", 10)
    move_jp = node.create_publisher(JointState, f"{ns}/move_jp", 10)
    move_cp = node.create_publisher(PoseStamped, f"{ns}/move_cp", 10)
    servo_cp = node.create_publisher(PoseStamped, f"{ns}/servo_cp", 10)
    servo_cf = node.create_publisher(WrenchStamped, f"{ns}/servo_cf", 10)
    servo_stop = threading.Event()
    servo_thread: threading.Thread | None = None

    def servo(frame: str, values: list[float], rate_hz: float, seconds: float, kind: str) -> None:
        end = time.monotonic() + min(seconds, 60.0)  # bounded
        while not servo_stop.is_set() and time.monotonic() < end:
            if kind == "servo":
                pose = PoseStamped()
                pose.header.stamp = node.get_clock().now().to_msg()
                pose.header.frame_id = frame
                pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = values
                pose.pose.orientation.w = 1.0
                servo_cp.publish(pose)
            else:
                wrench = WrenchStamped()
                wrench.header.stamp = node.get_clock().now().to_msg()
                wrench.header.frame_id = frame
                f = wrench.wrench.force
                f.x, f.y, f.z = values
                servo_cf.publish(wrench)
            servo_stop.wait(1.0 / rate_hz)

    # a publisher of the same type in this node: its graph entry carries rclpy's own type hash
    own = node.create_publisher(PoseStamped, f"{ns}/probe_own_hash", 10)

    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()

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
                last_joints = {k: v[-5:] for k, v in joints.items()}
                answer({"t": now(), "poses": poses, "joints": last_joints, "states": states,
                        "replies": replies, "statuses": statuses[-50:],
                        "wrenches": wrenches[-50:]})  # fmt: skip
        elif op == "publish":
            command.publish(String(data=str(req["data"])))
            answer({"t": now(), "published": req["data"]})
        elif op == "move_jp":
            goal = JointState(name=list(req.get("name", [])),
                              position=[float(v) for v in req["position"]])  # fmt: skip
            goal.header.stamp = node.get_clock().now().to_msg()
            wall = time.time()
            move_jp.publish(goal)
            answer({"t": now(), "wall": wall, "id": stamp_id(goal.header.stamp)})
        elif op == "move_cp":
            pose = PoseStamped()
            pose.header.stamp = node.get_clock().now().to_msg()
            pose.header.frame_id = str(req.get("frame", "world"))
            x, y, z = (float(v) for v in req["position"])
            pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = x, y, z
            wall = time.time()
            move_cp.publish(pose)
            answer({"t": now(), "wall": wall, "id": stamp_id(pose.header.stamp)})
        elif op in ("servo", "servo_cf", "servo_stop"):
            servo_stop.set()
            if servo_thread is not None:
                servo_thread.join()
            servo_stop.clear()
            if op != "servo_stop":
                values = [float(v) for v in req["position" if op == "servo" else "force"]]
                rate = float(req.get("rate_hz", 100.0))
                frame = str(req.get("frame", "world"))
                args = (frame, values, rate, float(req.get("seconds", 5)), op)
                servo_thread = threading.Thread(target=servo, args=args, daemon=True)
                servo_thread.start()
            answer({"t": now(), "servo": op})
        elif op == "matched":
            answer({"t": now(), "matched": command.get_subscription_count(),
                    "move_jp": move_jp.get_subscription_count(),
                    "move_cp": move_cp.get_subscription_count(),
                    "servo_cp": servo_cp.get_subscription_count(),
                    "servo_cf": servo_cf.get_subscription_count(),
                    "reply_publishers": node.count_publishers(f"{ns}/command_reply")})  # fmt: skip
        elif op == "graph":

            def infos(topic: str) -> list[dict[str, str]]:
                return [
                    {"type": i.topic_type, "hash": str(i.topic_type_hash), "node": i.node_name}
                    for i in node.get_publishers_info_by_topic(topic)
                ]

            answer({"t": now(), "bridge": infos(f"{ns}/measured_cp"),
                    "own": infos(own.topic_name)})  # fmt: skip
        elif op == "exit":
            answer({"t": now(), "bye": True})
            break
        else:
            answer({"error": f"unknown op {op!r}"})
    servo_stop.set()
    executor.shutdown(timeout_sec=1.0)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
