"""rclpy's side of `muster bench ros2` (rclpy, its executor and Fast DDS: the parts
nobody here wrote). Every stamp is CLOCK_MONOTONIC (time.monotonic_ns), the clock muster
stamps with, so one-way latencies across processes of this host are comparable.

Modes (ROS_DOMAIN_ID from the environment), each printing JSON lines:
  pub TOPIC RATE COUNT      std_msgs/String "SEQ SENT_NS" at RATE Hz, COUNT of them,
                            then untimed ones at 10 Hz until stopped
  sub TOPIC COUNT SECONDS   the same topic's one-way latencies, us (a JSON list)
  goals TOPIC SECONDS       each geometry_msgs/PoseStamped: {"x": .., "recv_ns": ..}
  scans N SECONDS           /R0/scan../R{N-1}/scan and /clock: scans received, the
                            simulator's real-time factor over the window
"""

import json
import sys
import time

import rclpy
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data

mode = sys.argv[1]
rclpy.init()
node = Node("muster_bench_" + mode)


def say(**kv):
    print(json.dumps(kv), flush=True)


def spin_for(seconds, until=lambda: False):
    end = time.monotonic() + seconds
    while time.monotonic() < end and not until():
        rclpy.spin_once(node, timeout_sec=0.01)


if mode == "pub":
    from std_msgs.msg import String
    topic, rate, count = sys.argv[2], float(sys.argv[3]), int(sys.argv[4])
    pub = node.create_publisher(String, topic, 100)
    say(event="ready")
    # Let every subscriber find us before the first sample counts.
    spin_for(3.0, lambda: pub.get_subscription_count() >= 2)
    say(event="matched", subscribers=pub.get_subscription_count())
    period = 1.0 / rate
    nxt = time.monotonic()
    for seq in range(count):
        pub.publish(String(data=f"{seq} {time.monotonic_ns()}"))
        nxt += period
        time.sleep(max(0.0, nxt - time.monotonic()))
    say(event="done", sent=count)
    # Then keep the topic alive (10 Hz, untimed) until stopped: muster's robot stays
    # "heard" while the other rows run.
    while True:
        pub.publish(String(data=f"-1 {time.monotonic_ns()}"))
        spin_for(0.1)
elif mode == "sub":
    from std_msgs.msg import String
    topic, count, seconds = sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
    lat = []

    def on(m):
        now = time.monotonic_ns()
        seq, sent = m.data.split()
        lat.append((now - int(sent)) / 1000.0)

    node.create_subscription(String, topic, on, 100)
    say(event="ready")
    spin_for(seconds, lambda: len(lat) >= count)
    say(latencies_us=lat)
elif mode == "goals":
    from geometry_msgs.msg import PoseStamped
    topic, seconds = sys.argv[2], float(sys.argv[3])
    node.create_subscription(
        PoseStamped, topic,
        lambda m: say(x=m.pose.position.x, recv_ns=time.monotonic_ns()), 100)
    say(event="ready")
    spin_for(seconds)
elif mode == "scans":
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import LaserScan
    n, seconds = int(sys.argv[2]), float(sys.argv[3])
    got = [0] * n
    clock = []
    for k in range(n):
        node.create_subscription(
            LaserScan, f"/R{k}/scan",
            lambda m, k=k: got.__setitem__(k, got[k] + 1), qos_profile_sensor_data)
    node.create_subscription(
        Clock, "/clock",
        lambda m: clock.append((time.monotonic(), m.clock.sec + m.clock.nanosec * 1e-9)), 10)
    say(event="ready")
    # Discovery first: wait until every robot's scans flow (or give up after 60 s).
    spin_for(60.0, lambda: all(got))
    say(event="flowing", robots_flowing=sum(1 for g in got if g))
    start_got = list(got)
    clock.clear()
    t0 = time.monotonic()
    spin_for(seconds)
    wall = time.monotonic() - t0
    rtf = None
    if len(clock) >= 2:
        (w0, s0), (w1, s1) = clock[0], clock[-1]
        rtf = (s1 - s0) / (w1 - w0) if w1 > w0 else None
    recv = sum(g - s for g, s in zip(got, start_got))
    say(robots=n, wall_s=wall, scans=recv, scans_per_robot_per_s=recv / n / wall,
        robots_flowing=sum(1 for g in start_got if g), realtime_factor=rtf)
node.destroy_node()
rclpy.shutdown()
