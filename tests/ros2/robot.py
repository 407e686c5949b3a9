"""A ROS 2 robot written in rclpy, nobody's muster code: a differential-drive integrator
that publishes `odom` (nav_msgs/Odometry, 20 Hz), `chatter` (std_msgs/String, 2 Hz),
`scan` (sensor_msgs/LaserScan, 2 Hz: four beams reading 1, 2, no return, 4.5 m) and, once
at its start, `status` (std_msgs/String "ready", transient-local: latched) in its
namespace, obeys `cmd_vel` (geometry_msgs/Twist), and, like a navigation stack,
drives itself at 0.5 m/s towards each `goal_pose` (geometry_msgs/PoseStamped) it gets,
and reports each LaserScan it is sent on `scan_relay`.

Prints one JSON line per event (goals and velocity commands received) for tests/ros2.rs.
Arguments: NAMESPACE X,Y [--duration S] [--wrong-type] [--malformed N] [--room W,H]
  --room W,H     its `scan` is a real one instead (10 Hz, 181 beams over 180 deg, 8 m):
                 the walls of a W x H m room (one 5 cm cell thick along its edges)
  --wrong-type   also publishes `battery` as std_msgs/String (the config says Float32)
  --malformed N  publishes N truncated Odometry samples on `odom` first (raw CDR bytes)
  --oversized    also publishes `bigscan`: LaserScans of 2000 beams (8 KB), at 2 Hz
"""

import argparse
import json
import math
import signal
import time

import rclpy
from geometry_msgs.msg import PoseStamped, Twist
from nav_msgs.msg import Odometry
from sensor_msgs.msg import LaserScan
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from std_msgs.msg import String

ap = argparse.ArgumentParser()
ap.add_argument("namespace")
ap.add_argument("start")
ap.add_argument("--duration", type=float, default=120.0)
ap.add_argument("--wrong-type", action="store_true")
ap.add_argument("--malformed", type=int, default=0)
ap.add_argument("--room", default=None)
ap.add_argument("--oversized", action="store_true")
a = ap.parse_args()

x, y = (float(v) for v in a.start.split(","))
room = tuple(float(v) for v in a.room.split(",")) if a.room else None


def room_scan(px, py, th):
    """Ranges from (px, py) heading th to the room's inner walls, right to left."""
    lo_x, lo_y, hi_x, hi_y = 0.05, 0.05, room[0] - 0.05, room[1] - 0.05
    out = []
    for k in range(181):
        ang = th + math.radians(-90 + k)
        dx, dy = math.cos(ang), math.sin(ang)
        t = math.inf
        if dx > 1e-12:
            t = min(t, (hi_x - px) / dx)
        if dx < -1e-12:
            t = min(t, (lo_x - px) / dx)
        if dy > 1e-12:
            t = min(t, (hi_y - py) / dy)
        if dy < -1e-12:
            t = min(t, (lo_y - py) / dy)
        out.append(t if t <= 8.0 else math.inf)
    return out

theta = 0.0
rclpy.init()
node = Node("fake_robot", namespace=a.namespace)
odom_pub = node.create_publisher(Odometry, "odom", 10)
chatter = node.create_publisher(String, "chatter", 10)
scan_pub = node.create_publisher(LaserScan, "scan", 10)
battery = node.create_publisher(String, "battery", 10) if a.wrong_type else None
bigscan = node.create_publisher(LaserScan, "bigscan", 10) if a.oversized else None
# Sent once, kept for late subscribers (as a map or a robot's description is).
status = node.create_publisher(String, "status", QoSProfile(
    depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
    reliability=ReliabilityPolicy.RELIABLE))
status.publish(String(data="ready"))
cmd = {"v": 0.0, "w": 0.0, "at": -1.0}
goal = {"xy": None}


def say(**kv):
    kv["t"] = time.monotonic()
    print(json.dumps(kv), flush=True)


def on_cmd(m):
    cmd.update(v=m.linear.x, w=m.angular.z, at=time.monotonic())
    say(event="cmd_vel", v=m.linear.x, w=m.angular.z)


def on_goal(m):
    goal["xy"] = (m.pose.position.x, m.pose.position.y)
    say(event="goal", x=m.pose.position.x, y=m.pose.position.y, frame=m.header.frame_id,
        z=m.pose.orientation.z, w=m.pose.orientation.w)


node.create_subscription(Twist, "cmd_vel", on_cmd, 10)
node.create_subscription(PoseStamped, "goal_pose", on_goal, 10)
node.create_subscription(
    LaserScan, "scan_relay",
    lambda m: say(event="relayed", frame=m.header.frame_id,
                  ranges=[r if math.isfinite(r) else "inf" for r in m.ranges]), 10)

if a.malformed:
    # Raw bytes on the Odometry topic: a CDR header and a cut-off message.
    good = serialize_message(Odometry())
    for _ in range(a.malformed):
        odom_pub.publish(good[:24])

dt = 0.05
n = 0
end = time.monotonic() + a.duration
stopping = []
signal.signal(signal.SIGTERM, lambda *_: stopping.append(1))
say(event="up")
while time.monotonic() < end and not stopping:
    now = time.monotonic()
    if now - cmd["at"] < 0.5:
        v, w = cmd["v"], cmd["w"]
    elif goal["xy"] is not None:
        gx, gy = goal["xy"]
        d = math.hypot(gx - x, gy - y)
        if d < 0.2:
            goal["xy"] = None
            v, w = 0.0, 0.0
        else:
            theta = math.atan2(gy - y, gx - x)
            v, w = 0.5, 0.0
    else:
        v, w = 0.0, 0.0
    x += v * math.cos(theta) * dt
    y += v * math.sin(theta) * dt
    theta += w * dt
    o = Odometry()
    o.header.frame_id = "odom"
    o.header.stamp = node.get_clock().now().to_msg()
    o.child_frame_id = "base_link"
    o.pose.pose.position.x = x
    o.pose.pose.position.y = y
    o.pose.pose.orientation.z = math.sin(theta / 2)
    o.pose.pose.orientation.w = math.cos(theta / 2)
    o.twist.twist.linear.x = v
    o.twist.twist.angular.z = w
    odom_pub.publish(o)
    if room is not None and n % 2 == 0:
        sc = LaserScan()
        sc.header.frame_id = "laser"
        sc.header.stamp = o.header.stamp
        sc.angle_min, sc.angle_max = -math.pi / 2, math.pi / 2
        sc.angle_increment = math.pi / 180
        sc.scan_time, sc.range_min, sc.range_max = 0.1, 0.0, 8.0
        sc.ranges = room_scan(x, y, theta)
        scan_pub.publish(sc)
    if n % 10 == 0:
        chatter.publish(String(data=f"hello {n // 10}"))
        if room is None:
            sc = LaserScan()
            sc.header.frame_id = "laser"
            sc.header.stamp.sec = 7
            sc.header.stamp.nanosec = n
            sc.angle_min, sc.angle_max, sc.angle_increment = -0.75, 0.75, 0.5
            sc.range_min, sc.range_max = 0.1, 8.0
            sc.ranges = [1.0, 2.0, math.inf, 4.5]
            scan_pub.publish(sc)
        if battery is not None:
            battery.publish(String(data="full"))
        if bigscan is not None:
            big = LaserScan()
            big.header.frame_id = "laser"
            big.ranges = [1.0] * 2000
            bigscan.publish(big)
    n += 1
    rclpy.spin_once(node, timeout_sec=0)
    time.sleep(dt)
node.destroy_node()
rclpy.shutdown()
