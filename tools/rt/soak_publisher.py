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
import interop  # noqa: E402  (the ROS 2 types, keys and the depth cameras)


def main():
    port, seconds, rate = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
    w, h = int(sys.argv[4]), int(sys.argv[5])
    s = interop.session(port, "client")
    cams = interop.DepthCameras(s, w, h)
    counts = {"sent": 0, "dropped": 0, "burst_extra": 0, "silent": 0, "malformed": 0,
              "out_of_order": 0, "future": 0}

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
            cams.put_tf()
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
                cams.put_garbage(0)
                counts["malformed"] += 1
                continue
            if second != last_second and second % 15 == 7 and n == 1:
                stamp_t -= 1.0
                counts["out_of_order"] += 1
            if second != last_second and second % 20 == 13 and n == 0:
                stamp_t += 3600.0
                counts["future"] += 1
            cams.publish(n, stamp_t, t)
            counts["sent"] += 1
            counts["burst_extra"] += int(burst)
        last_second = second
        k += 1
    print(json.dumps(counts), flush=True)
    time.sleep(0.2)
    s.close()


if __name__ == "__main__":
    main()
