"""An rclpy node (rclpy, its executor and Fast DDS are the parts nobody here wrote)
watching `muster sim --ros2`: prints one JSON object of what it saw, for tests/ros2.rs
to check. ROS_DOMAIN_ID comes from the environment; argv[1] is the robot's name."""

import json
import math
import sys
import time

import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import (DurabilityPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)

from geometry_msgs.msg import Twist
from nav_msgs.msg import OccupancyGrid, Odometry
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import LaserScan, Range
from visualization_msgs.msg import MarkerArray

robot = sys.argv[1]
rclpy.init()
node = Node("muster_sim_check", parameter_overrides=[Parameter("use_sim_time", Parameter.Type.BOOL, True)])
seen = {"scan": [], "odom": [], "truth": [], "clock": [], "map": [], "people": [], "sonar": []}

node.create_subscription(LaserScan, f"/{robot}/scan", lambda m: seen["scan"].append(m), qos_profile_sensor_data)
node.create_subscription(Odometry, f"/{robot}/odom", lambda m: seen["odom"].append(m), 10)
node.create_subscription(Odometry, f"/{robot}/ground_truth", lambda m: seen["truth"].append(m), 10)
node.create_subscription(Range, f"/{robot}/sonar", lambda m: seen["sonar"].append(m), 50)
node.create_subscription(Clock, "/clock", lambda m: seen["clock"].append(m), 10)
node.create_subscription(MarkerArray, "/people", lambda m: seen["people"].append(m), 10)
latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
node.create_subscription(OccupancyGrid, "/map", lambda m: seen["map"].append(m), latched)
cmd = node.create_publisher(Twist, f"/{robot}/cmd_vel", 10)


def spin_until(cond, timeout):
    end = time.monotonic() + timeout
    while time.monotonic() < end and not cond():
        rclpy.spin_once(node, timeout_sec=0.05)
    return cond()


def spin_for(seconds):
    spin_until(lambda: False, seconds)


def secs(t):
    return t.sec + t.nanosec * 1e-9


def stamp(h):
    return secs(h.stamp)


def yaw(q):
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))


out = {}
ok = spin_until(lambda: all(seen[k] for k in seen) and len({m.header.frame_id for m in seen["sonar"]}) >= 16, 30)
out["all_seen"] = ok
out["missing"] = [k for k in seen if not seen[k]]
if seen["scan"]:
    s = seen["scan"][-1]
    out["scan"] = {
        "frame_id": s.header.frame_id, "stamp": stamp(s.header),
        "angle_min": s.angle_min, "angle_max": s.angle_max, "angle_increment": s.angle_increment,
        "range_min": s.range_min, "range_max": s.range_max, "scan_time": s.scan_time,
        "n": len(s.ranges), "ranges": [r if math.isfinite(r) else "inf" for r in s.ranges],
        "stamps_increase": all(stamp(a.header) < stamp(b.header) for a, b in zip(seen["scan"], seen["scan"][1:])),
    }
if seen["odom"]:
    o = seen["odom"][-1]
    out["odom"] = {"frame_id": o.header.frame_id, "child_frame_id": o.child_frame_id,
                   "x": o.pose.pose.position.x, "y": o.pose.pose.position.y, "yaw": yaw(o.pose.pose.orientation),
                   "stamp": stamp(o.header)}
if seen["truth"]:
    t = seen["truth"][-1]
    out["truth"] = {"frame_id": t.header.frame_id, "x": t.pose.pose.position.x, "y": t.pose.pose.position.y,
                    "yaw": yaw(t.pose.pose.orientation)}
if seen["clock"]:
    out["clock"] = secs(seen["clock"][-1].clock)
    out["clock_increases"] = all(secs(a.clock) <= secs(b.clock) for a, b in zip(seen["clock"], seen["clock"][1:]))
if seen["map"]:
    m = seen["map"][-1]
    out["map"] = {"frame_id": m.header.frame_id, "width": m.info.width, "height": m.info.height,
                  "resolution": m.info.resolution, "origin": [m.info.origin.position.x, m.info.origin.position.y],
                  "occupied": sum(1 for v in m.data if v == 100), "free": sum(1 for v in m.data if v == 0),
                  "corner": m.data[0], "centre": m.data[(m.info.height // 2) * m.info.width + m.info.width // 2]}
if seen["people"]:
    p = seen["people"][-1]
    out["people"] = [{"ns": k.ns, "type": k.type, "text": k.text, "frame_id": k.header.frame_id,
                      "x": k.pose.position.x, "y": k.pose.position.y, "rgba": [k.color.r, k.color.g, k.color.b, k.color.a]}
                     for k in p.markers]
if seen["sonar"]:
    frames = sorted({m.header.frame_id for m in seen["sonar"]})
    s = seen["sonar"][-1]
    out["sonar"] = {"frames": frames, "radiation_type": s.radiation_type, "max_range": s.max_range,
                    "field_of_view": s.field_of_view}

# The node's own clock follows /clock (use_sim_time).
if seen["clock"]:
    out["node_clock"] = node.get_clock().now().nanoseconds * 1e-9
    out["clock_at_node_clock"] = secs(seen["clock"][-1].clock)

# Node names travel on their own discovery topic (ros_discovery_info) and may come
# after the endpoints did: wait for the simulator's node a while (bounded) before
# reading the graph once. It still fails if the node never shows.
spin_until(lambda: "muster_sim" in node.get_node_names(), 10.0)
out["topics"] = {name: types for name, types in node.get_topic_names_and_types()}
out["nodes"] = node.get_node_names()

# Drive: 0.5 m/s ahead for 1.5 s of wall time, then stop sending (the deadman stops it).
before = seen["truth"][-1].pose.pose.position.x if seen["truth"] else None
t = Twist()
t.linear.x = 0.5
end = time.monotonic() + 1.5
while time.monotonic() < end:
    cmd.publish(t)
    spin_for(0.05)
spin_for(1.5)
stopped_at = seen["truth"][-1].pose.pose.position.x if seen["truth"] else None
spin_for(1.0)
later = seen["truth"][-1].pose.pose.position.x if seen["truth"] else None
out["drive"] = {"before": before, "stopped_at": stopped_at, "later": later,
                "twist_after_stop": seen["odom"][-1].twist.twist.linear.x if seen["odom"] else None}
print(json.dumps(out), flush=True)
node.destroy_node()
rclpy.shutdown()
