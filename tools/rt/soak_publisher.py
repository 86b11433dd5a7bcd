"""Soak source for `hapcloud run zenoh`: two depth cameras (sensor_msgs/Image 16UC1 +
CameraInfo on rmw_zenoh keys, wall-clock stamps, the swaying plane of interop.py) through a
Zenoh router, with faults injected on a one-minute cycle:

- every 20th frame of each camera dropped (a lossy link),
- at 10-10.5 s a burst: each camera publishes at 4x its rate (the node's per-camera frame
  slots drop the excess),
- at 20-22 s camera 1 silent, at 40-41 s both cameras silent (fusion goes stale: the
  constraints go off, then come back),
- every 10 s a malformed image (garbage CDR) on camera 0,
- every 15 s a frame of camera 1 stamped 1 s in the past (out of order: refused),
- every 20 s a frame of camera 0 stamped an hour in the future (bad stamp: refused).

Usage: python3 tools/rt/soak_publisher.py PORT SECONDS RATE_HZ WIDTH HEIGHT
Prints one JSON line with what it sent and injected.
"""

import json
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "interop"))
import interop  # noqa: E402  (the ROS 2 types, keys, camera poses and the plane's depth)
import numpy as np  # noqa: E402


def main():
    port, seconds, rate = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
    w, h = int(sys.argv[4]), int(sys.argv[5])
    s = interop.session(port, "client")
    import zenoh

    store = interop.STORE
    drop = zenoh.CongestionControl.DROP
    Header = store.types["std_msgs/msg/Header"]
    Image = store.types["sensor_msgs/msg/Image"]
    Time = store.types["builtin_interfaces/msg/Time"]
    TF = store.types["tf2_msgs/msg/TFMessage"]
    TS = store.types["geometry_msgs/msg/TransformStamped"]
    Tr = store.types["geometry_msgs/msg/Transform"]
    V3 = store.types["geometry_msgs/msg/Vector3"]
    Q = store.types["geometry_msgs/msg/Quaternion"]
    fx = fy = 0.7 * w
    cx, cy = (w - 1) / 2, (h - 1) / 2
    pubs = []
    for n in range(2):
        pubs.append((
            s.declare_publisher(interop.key(f"/cam{n}/depth/image_rect_raw", "sensor_msgs/msg/Image"),
                                congestion_control=drop),
            s.declare_publisher(interop.key(f"/cam{n}/depth/camera_info", "sensor_msgs/msg/CameraInfo"),
                                congestion_control=drop)))
    tf = TF(transforms=[TS(header=Header(stamp=Time(sec=0, nanosec=0), frame_id="world"),
                           child_frame_id=f"cam{n}_depth_optical_frame",
                           transform=Tr(translation=V3(x=p[0], y=p[1], z=p[2]),
                                        rotation=Q(x=0.0, y=0.0, z=0.0, w=1.0)))
                        for n, p in enumerate(interop.CAM_POSES)])
    tf_pub = s.declare_publisher(interop.key("/tf_static", "tf2_msgs/msg/TFMessage"))
    tf_bytes = bytes(store.serialize_cdr(tf, "tf2_msgs/msg/TFMessage"))
    interop.wait_matching([p for pair in pubs for p in pair], 10.0)
    frames = [np.frombuffer(interop.plane_depth_mm(w, h, fx, fy, cx, cy, j / 8).astype("<u2").tobytes(),
                            dtype=np.uint8) for j in range(8)]
    counts = {"sent": 0, "dropped": 0, "burst_extra": 0, "silent": 0, "malformed": 0,
              "out_of_order": 0, "future": 0}

    def publish(n, t, stamp_t):
        img_pub, info_pub = pubs[n]
        st = Time(sec=int(stamp_t), nanosec=int((stamp_t - int(stamp_t)) * 1e9))
        hd = Header(stamp=st, frame_id=f"cam{n}_depth_optical_frame")
        img = Image(header=hd, height=h, width=w, encoding="16UC1", is_bigendian=0,
                    step=w * 2, data=frames[int(t * 8) % 8])
        img_pub.put(bytes(store.serialize_cdr(img, "sensor_msgs/msg/Image")))
        info_pub.put(bytes(store.serialize_cdr(interop.camera_info(hd, w, h, fx, fy, cx, cy),
                                               "sensor_msgs/msg/CameraInfo")))

    start = time.time()
    next_due = start
    k = 0
    last_second = -1
    while True:
        now = time.time()
        if next_due > now:
            time.sleep(next_due - now)
        t = time.time() - start
        if t >= seconds:
            break
        cycle = t % 60.0
        burst = 10.0 <= cycle < 10.5
        next_due += 1.0 / (rate * (4 if burst else 1))
        second = int(t)
        if second != last_second:
            tf_pub.put(tf_bytes)
        for n in range(2):
            silent = (20.0 <= cycle < 22.0 and n == 1) or 40.0 <= cycle < 41.0
            if silent:
                counts["silent"] += 1
                continue
            if k % 20 == 7 + n:
                counts["dropped"] += 1
                continue
            stamp_t = time.time()
            if second != last_second and second % 10 == 5 and n == 0:
                pubs[0][0].put(b"\x00\x01\x00\x00\x07\x00\x00\x00garbage")
                counts["malformed"] += 1
                continue
            if second != last_second and second % 15 == 7 and n == 1:
                stamp_t -= 1.0
                counts["out_of_order"] += 1
            if second != last_second and second % 20 == 13 and n == 0:
                stamp_t += 3600.0
                counts["future"] += 1
            publish(n, t, stamp_t)
            counts["sent"] += 1
            counts["burst_extra"] += int(burst)
        last_second = second
        k += 1
    print(json.dumps(counts), flush=True)
    time.sleep(0.2)
    s.close()


if __name__ == "__main__":
    main()
