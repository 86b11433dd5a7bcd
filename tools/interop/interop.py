#!/usr/bin/env python3
"""ROS 2 interop counterpart for tests/ros2_interop.rs, built on software hapcloud did not
write: eclipse-zenoh (router, publisher, subscriber) and rosbags (CDR, RIHS01 hashes, MCAP).

Subcommands (all print JSON on stdout, diagnostics on stderr):
  router PORT                 a Zenoh router on tcp/127.0.0.1:PORT (stands in for rmw_zenohd);
                              prints {"ready": true}, runs until stdin closes
  publish PORT N              N depth Image + CameraInfo pairs (camera topic
                              /camera/camera/depth/...) and N PointCloud2 (/lidar/points),
                              serialized by rosbags, on rmw_zenoh keys through the router
  listen PORT N SECONDS       decodes what hapcloud publishes on 0/hapcloud/** with rosbags,
                              and each attachment with zenoh-ext's deserializer as
                              (int64, int64, bytes); prints one JSON line per message, stops
                              after N or SECONDS
  stream PORT SECONDS RATE W H [garbage] [attach] [skip] [tfonce] [distorted]
                              two live depth cameras as realsense-ros publishes them: Image
                              16UC1 + CameraInfo of a tilted plane 0.6 m ahead, W x H at RATE
                              Hz (0: as fast as it can, a flood), stamped with the wall clock,
                              on /cam0/depth/... and /cam1/depth/..., their poses on
                              /tf_static (world -> camN_depth_optical_frame); with `garbage`,
                              every 10th image of cam0 is replaced by malformed CDR; with
                              `attach`, cam0's samples carry rmw_zenoh's attachment (sequence
                              number, source time stamp, GID; zenoh-ext serialized) and cam1's
                              3 bytes of junk; with `skip` too, cam0's publishers skip one
                              sequence number every 5th message; with `tfonce`, /tf_static
                              goes out once, at the start, through zenoh-ext's
                              AdvancedPublisher (cache, publisher detection), as rmw_zenoh
                              publishes a transient-local topic; with `distorted`, cam1's
                              CameraInfo has plumb_bob distortion (aligned depth's info);
                              prints {"sent": N, "skipped": N}
  liveliness PORT             the ROS 2 graph as rmw_zenoh reads it: queries @ros2_lv/**,
                              parses each token key by rmw_zenoh's rules (liveliness_utils.cpp
                              Entity::make, keyexpr_to_qos); prints {"entities": [...],
                              "errors": [...]}
  reset PORT N                N raw TCP connections to 127.0.0.1:PORT, each sending the start
                              of a Zenoh frame (a length prefix, part of the body) and then
                              resetting (RST); prints {"resets": N}
  hashes MSG_DIR              rosbags' hash_rihs01 of the standard types and of hapcloud_msgs
  write-bag DIR N             a realsense-like rosbag2 MCAP bag (zstd chunks): N depth frames
  read-mcap FILE              reads an MCAP with rosbags' AnyReader; prints per-topic counts
                              and decoded fields
  read-mcap-foxglove FILE     reads an MCAP with the `mcap` and `mcap-ros2-support` packages:
                              per channel its schema, message encoding, metadata
                              (offered_qos_profiles parsed as YAML, topic_type_hash) and the
                              message count, each message decoded; the profile
  record-order FILE           the MCAP's records in file order (Channel topics and the topic
                              of each Message), read with the `mcap` package
The frames follow frame_values() so the Rust side can rebuild them independently.
"""

import json
import sys
import time
from pathlib import Path

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

STORE = get_typestore(Stores.ROS2_JAZZY)
DEPTH_TOPIC = "/camera/camera/depth/image_rect_raw"
INFO_TOPIC = "/camera/camera/depth/camera_info"
POINTS_TOPIC = "/lidar/points"
W, H = 16, 12


def log(*a):
    print(*a, file=sys.stderr, flush=True)


def register_hapcloud(msg_dir):
    types = {}
    for path in sorted(Path(msg_dir).glob("*.msg")):
        types.update(get_types_from_msg(path.read_text(), f"hapcloud_msgs/msg/{path.stem}"))
    STORE.register(types)


def key(topic, msgtype):
    pkg, kind, name = msgtype.split("/")
    dds = f"{pkg}::{kind}::dds_::{name}_"
    return f"0/{topic.strip('/')}/{dds}/{STORE.hash_rihs01(msgtype)}"


def frame_values(i):
    """Depth in mm of frame i (0 = no return) and the points of cloud i."""
    v, u = np.mgrid[0:H, 0:W]
    depth = (400 + 7 * u + 11 * v + 13 * i).astype(np.uint16)
    depth[(u + v + i) % 9 == 0] = 0
    n = 20 + i
    k = np.arange(n, dtype=np.float32)
    pts = np.stack([0.01 * k, -0.02 * k + i, 0.5 + 0.001 * k * k], axis=1).astype(np.float32)
    pts[3] = np.nan
    return depth, pts


def stamp(i):
    T = STORE.types["builtin_interfaces/msg/Time"]
    return T(sec=100 + i, nanosec=250_000_000 + i)


def image_msgs(i):
    Header = STORE.types["std_msgs/msg/Header"]
    Image = STORE.types["sensor_msgs/msg/Image"]
    depth, _ = frame_values(i)
    h = Header(stamp=stamp(i), frame_id="camera_depth_optical_frame")
    img = Image(header=h, height=H, width=W, encoding="16UC1", is_bigendian=0, step=W * 2,
                data=np.frombuffer(depth.astype("<u2").tobytes(), dtype=np.uint8))
    return img, camera_info(h, W, H, 20.0, 21.0, 7.5, 5.5)


def camera_info(header, w, h, fx, fy, cx, cy):
    """A rectified pinhole CameraInfo as realsense-ros publishes it."""
    Info = STORE.types["sensor_msgs/msg/CameraInfo"]
    Roi = STORE.types["sensor_msgs/msg/RegionOfInterest"]
    return Info(header=header, height=h, width=w, distortion_model="plumb_bob",
                d=np.zeros(5), k=np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1.0]),
                r=np.eye(3).flatten(), p=np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1.0, 0]),
                binning_x=0, binning_y=0,
                roi=Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def cloud_msg(i):
    """x, y, z at offsets 0, 4, 8 and an intensity at 16 in a 32-byte point (padding)."""
    Header = STORE.types["std_msgs/msg/Header"]
    PC2 = STORE.types["sensor_msgs/msg/PointCloud2"]
    PF = STORE.types["sensor_msgs/msg/PointField"]
    _, pts = frame_values(i)
    n = len(pts)
    rec = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("_", "<f4"),
                             ("intensity", "<f4"), ("pad", "V12")])
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    rec["intensity"] = 1.0
    fields = [PF(name=nm, offset=o, datatype=7, count=1)
              for nm, o in (("x", 0), ("y", 4), ("z", 8), ("intensity", 16))]
    return PC2(header=Header(stamp=stamp(i), frame_id="lidar"), height=1, width=n,
               fields=fields, is_bigendian=False, point_step=32, row_step=32 * n,
               data=np.frombuffer(rec.tobytes(), dtype=np.uint8), is_dense=False)


def session(port, mode, timestamping=False):
    import zenoh
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    if timestamping:
        # As rmw_zenoh's session config: the advanced publisher's cache needs time stamps.
        conf.insert_json5("timestamping/enabled", "true")
    conf.insert_json5("scouting/multicast/enabled", "false")
    if mode == "router":
        conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        conf.insert_json5("connect/endpoints", "[]")
    else:
        conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    return zenoh.open(conf)


def cmd_router(port):
    s = session(port, "router")
    print(json.dumps({"ready": True}), flush=True)
    sys.stdin.read()
    s.close()


def wait_matching(pubs, seconds=10.0):
    end = time.time() + seconds
    while time.time() < end:
        if all(p.matching_status.matching for p in pubs):
            return True
        time.sleep(0.02)
    return False


def cmd_publish(port, n):
    s = session(port, "client")
    import zenoh
    block = zenoh.CongestionControl.BLOCK
    pubs = {t: s.declare_publisher(key(t, m), congestion_control=block) for t, m in (
        (DEPTH_TOPIC, "sensor_msgs/msg/Image"),
        (INFO_TOPIC, "sensor_msgs/msg/CameraInfo"),
        (POINTS_TOPIC, "sensor_msgs/msg/PointCloud2"))}
    if not wait_matching(list(pubs.values())):
        log("no subscriber matched")
        sys.exit(2)
    sent = 0
    for i in range(n):
        img, info = image_msgs(i)
        pubs[DEPTH_TOPIC].put(bytes(STORE.serialize_cdr(img, "sensor_msgs/msg/Image")))
        pubs[INFO_TOPIC].put(bytes(STORE.serialize_cdr(info, "sensor_msgs/msg/CameraInfo")))
        pubs[POINTS_TOPIC].put(bytes(STORE.serialize_cdr(cloud_msg(i),
                                                         "sensor_msgs/msg/PointCloud2")))
        sent += 1
        time.sleep(0.01)
    print(json.dumps({"sent": sent}), flush=True)
    time.sleep(0.2)
    s.close()


# Camera N's optical frame sits at CAM_POSES[N] (world, m; rotation identity: it looks down
# world +z), so a plane 0.6 m ahead is at world z = 1.6; the node's HIP is 5 cm before it.
CAM_POSES = [(0.0, 0.0, 1.0), (0.02, 0.0, 1.0)]


def plane_depth_mm(w, h, fx, fy, cx, cy, t):
    """Depth (mm) of a plane through (0, 0, 0.6) m in the camera frame, tilted and
    swaying slowly, for each pixel."""
    v, u = np.mgrid[0:h, 0:w]
    x, y = (u - cx) / fx, (v - cy) / fy
    a, b = 0.15, 0.1 + 0.05 * np.sin(t)
    z = 0.6 / (1.0 - a * x - b * y)
    return np.clip(z * 1000.0, 0, 65535).astype(np.uint16)


def rmw_attachment(seq, gid):
    """rmw_zenoh's attachment, serialized by zenoh-ext: (int64 sequence number, int64 source
    time stamp in ns, bytes GID)."""
    from zenoh.ext import Int64, z_serialize
    return z_serialize((Int64(seq), Int64(time.time_ns()), gid))


class DepthCameras:
    """Two realsense-ros-like depth cameras on one session: Image 16UC1 + CameraInfo
    publishers on rmw_zenoh keys (dropped when congested), their poses on /tf_static, and a
    second of the swaying plane's frames computed up front so a publisher keeps its rate."""

    def __init__(self, s, w, h, tf_once=False, distorted=False):
        import zenoh
        drop = zenoh.CongestionControl.DROP
        self.distorted = distorted
        self.w, self.h = w, h
        self.fx = self.fy = 0.7 * w
        self.cx, self.cy = (w - 1) / 2, (h - 1) / 2
        T = STORE.types
        self.Header, self.Image, self.Time = (T["std_msgs/msg/Header"], T["sensor_msgs/msg/Image"],
                                              T["builtin_interfaces/msg/Time"])
        self.pubs = [(s.declare_publisher(key(f"/cam{n}/depth/image_rect_raw", "sensor_msgs/msg/Image"),
                                          congestion_control=drop),
                      s.declare_publisher(key(f"/cam{n}/depth/camera_info", "sensor_msgs/msg/CameraInfo"),
                                          congestion_control=drop))
                     for n in range(2)]
        tf = T["tf2_msgs/msg/TFMessage"](transforms=[T["geometry_msgs/msg/TransformStamped"](
            header=self.Header(stamp=self.Time(sec=0, nanosec=0), frame_id="world"),
            child_frame_id=f"cam{n}_depth_optical_frame",
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=p[0], y=p[1], z=p[2]),
                rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)))
            for n, p in enumerate(CAM_POSES)])
        tf_key = key("/tf_static", "tf2_msgs/msg/TFMessage")
        if tf_once:
            # rmw_zenoh's transient-local publisher: a cache late joiners query, found
            # through its liveliness token.
            from zenoh.ext import CacheConfig, declare_advanced_publisher
            self.tf_pub = declare_advanced_publisher(s, tf_key, cache=CacheConfig(max_samples=1),
                                                     publisher_detection=True)
        else:
            self.tf_pub = s.declare_publisher(tf_key)
        self.tf_bytes = bytes(STORE.serialize_cdr(tf, "tf2_msgs/msg/TFMessage"))
        wait_matching([p for pair in self.pubs for p in pair], 10.0)
        self.frames = [np.frombuffer(plane_depth_mm(w, h, self.fx, self.fy, self.cx, self.cy, j / 8)
                                     .astype("<u2").tobytes(), dtype=np.uint8) for j in range(8)]

    def put_tf(self):
        """The poses again (transient-local in ROS; repeated here for late joiners)."""
        self.tf_pub.put(self.tf_bytes)

    def header(self, n, stamp_t):
        st = self.Time(sec=int(stamp_t), nanosec=int((stamp_t - int(stamp_t)) * 1e9))
        return self.Header(stamp=st, frame_id=f"cam{n}_depth_optical_frame")

    def put_info(self, n, stamp_t, **extra):
        """Camera n's camera info, stamped stamp_t."""
        info = camera_info(self.header(n, stamp_t), self.w, self.h, self.fx, self.fy, self.cx, self.cy)
        if self.distorted and n == 1:
            info.d = np.array([0.12, -0.25, 0.001, -0.0005, 0.1])
        self.pubs[n][1].put(bytes(STORE.serialize_cdr(info, "sensor_msgs/msg/CameraInfo")), **extra)

    def publish(self, n, stamp_t, phase_s, **extra):
        """Camera n's image (the plane at phase_s seconds) and camera info, stamped stamp_t."""
        img = self.Image(header=self.header(n, stamp_t), height=self.h, width=self.w,
                         encoding="16UC1", is_bigendian=0, step=self.w * 2,
                         data=self.frames[int(phase_s * 8) % 8])
        self.pubs[n][0].put(bytes(STORE.serialize_cdr(img, "sensor_msgs/msg/Image")), **extra)
        self.put_info(n, stamp_t, **extra)

    def publish_with(self, n, stamp_t, phase_s, extra_of):
        """publish(), each of the two publishers with its own extra arguments (extra_of(0)
        for the image, extra_of(1) for the info)."""
        img = self.Image(header=self.header(n, stamp_t), height=self.h, width=self.w,
                         encoding="16UC1", is_bigendian=0, step=self.w * 2,
                         data=self.frames[int(phase_s * 8) % 8])
        self.pubs[n][0].put(bytes(STORE.serialize_cdr(img, "sensor_msgs/msg/Image")), **extra_of(0))
        self.put_info(n, stamp_t, **extra_of(1))

    def put_garbage(self, n, **extra):
        """A malformed Image (garbage CDR) on camera n."""
        self.pubs[n][0].put(b"\x00\x01\x00\x00\x07\x00\x00\x00garbage", **extra)


def cmd_stream(port, seconds, rate, w, h, garbage, attach, skip, tf_once, distorted):
    s = session(port, "client", timestamping=tf_once)
    cams = DepthCameras(s, w, h, tf_once, distorted)
    if tf_once:
        cams.put_tf()
    start = time.time()
    period = 1.0 / rate if rate > 0 else 0.0
    sent = 0
    skipped = 0
    k = 0
    # Each publisher (cam0's image and info) has its own GID and sequence, from 1.
    gids = [bytes(range(16)), bytes(range(16, 32))]
    seq = 0
    while time.time() - start < seconds:
        due = start + k * period
        now = time.time()
        if due > now:
            time.sleep(due - now)
        if not tf_once and k % max(int(rate), 30) == 0:
            cams.put_tf()
        seq += 1
        if skip and k % 5 == 4:
            seq += 1
            skipped += 2
        for n in range(2):
            t = time.time()
            extra = {}
            if attach and n == 1:
                extra["attachment"] = b"\xff\x00\x07"
            if garbage and n == 0 and k % 10 == 5:
                cams.put_garbage(0, **with_attachment(extra, attach and n == 0, seq, gids[0]))
                cams.put_info(0, t, **with_attachment(extra, attach and n == 0, seq, gids[1]))
            elif attach and n == 0:
                cams.publish_with(0, t, t - start,
                                  lambda g, e=extra: with_attachment(e, True, seq, gids[g]))
            else:
                cams.publish(n, t, t - start, **extra)
            sent += 1
        k += 1
    print(json.dumps({"sent": sent, "skipped": skipped}), flush=True)
    time.sleep(0.2)
    s.close()


def with_attachment(extra, attach, seq, gid):
    return dict(extra, attachment=rmw_attachment(seq, gid)) if attach else extra


ENTITY_KINDS = {"NN": "node", "MP": "publisher", "MS": "subscription",
                "SS": "service", "SC": "client"}


def parse_qos(text):
    """keyexpr_to_qos: 6 ':'-parts; history, deadline, lifespan 2 ','-parts, liveliness 3;
    each value empty (the default) or a number."""
    parts = text.split(":")
    if len(parts) < 6:
        raise ValueError(f"QoS {text!r}: {len(parts)} parts")
    sub = [parts[0], parts[1]]
    for i, n in ((2, 2), (3, 2), (4, 2), (5, 3)):
        p = parts[i].split(",")
        if len(p) < n:
            raise ValueError(f"QoS {text!r}: part {i} has {len(p)} components")
        sub += p
    if not all(v == "" or v.isdigit() for v in sub):
        raise ValueError(f"QoS {text!r}: not numbers")
    return {"reliability": parts[0], "durability": parts[1], "history": sub[2],
            "depth": sub[3], "explicit": all(v != "" for v in sub)}


def parse_token(key):
    """Entity::make(keyexpr) of rmw_zenoh: @ros2_lv/<domain>/<zid>/<nid>/<id>/<kind>/
    <enclave>/<namespace>/<node>[/<topic>/<type>/<type hash>/<qos>], '%' for '/'."""
    parts = key.split("/")
    if len(parts) < 9:
        raise ValueError(f"{key}: {len(parts)} parts, at least 9")
    if any(p == "" for p in parts):
        raise ValueError(f"{key}: an empty part")
    if parts[0] != "@ros2_lv":
        raise ValueError(f"{key}: admin space {parts[0]}")
    if parts[5] not in ENTITY_KINDS:
        raise ValueError(f"{key}: entity {parts[5]}")
    dm = lambda p: p.replace("%", "/")
    out = {"domain": int(parts[1]), "zid": parts[2], "nid": parts[3], "id": parts[4],
           "kind": ENTITY_KINDS[parts[5]], "enclave": dm(parts[6]), "namespace": dm(parts[7]),
           "node": dm(parts[8])}
    if parts[5] != "NN":
        if len(parts) < 13:
            raise ValueError(f"{key}: a {out['kind']} token needs 13 parts")
        out.update(topic=dm(parts[9]), dds_type=dm(parts[10]), type_hash=dm(parts[11]),
                   qos=parse_qos(parts[12]))
        # <pkg>::msg::dds_::<Name>_ is <pkg>/msg/<Name>
        pkg, kind, _, name = out["dds_type"].split("::")
        out["type"] = f"{pkg}/{kind}/{name[:-1]}"
        out["hash_ok"] = (out["type"] in STORE.types
                          and STORE.hash_rihs01(out["type"]) == out["type_hash"])
    return out


def cmd_liveliness(port, msg_dir):
    register_hapcloud(msg_dir)
    s = session(port, "client")
    entities, errors = [], []
    for reply in s.liveliness().get("@ros2_lv/**", timeout=3.0):
        if reply.ok is None:
            continue
        key = str(reply.ok.key_expr)
        try:
            entities.append(parse_token(key))
        except ValueError as e:
            errors.append(str(e))
    print(json.dumps({"entities": entities, "errors": errors}), flush=True)
    s.close()


def cmd_reset(port, n):
    """Starts a Zenoh TCP frame (2-byte little-endian length, then fewer bytes than it
    says) and resets the connection (SO_LINGER 0)."""
    import socket
    import struct
    for i in range(n):
        c = socket.create_connection(("127.0.0.1", port), timeout=2.0)
        body = bytes([0x01, 0x09, 0x00]) + bytes(range(200 + i))
        c.sendall(struct.pack("<H", 60000) + body)
        time.sleep(0.05)
        c.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        c.close()
    print(json.dumps({"resets": n}), flush=True)


def plain(v):
    if isinstance(v, np.ndarray):
        return [plain(x) for x in v.tolist()]
    if isinstance(v, float):
        return v if np.isfinite(v) else str(v)
    if isinstance(v, (list, tuple)):
        return [plain(x) for x in v]
    if hasattr(v, "__dataclass_fields__"):
        return {f: plain(getattr(v, f)) for f in v.__dataclass_fields__ if f != "__msgtype__"}
    return v


def cmd_listen(port, n, seconds, msg_dir):
    register_hapcloud(msg_dir)
    by_dds = {}
    for t in STORE.types:
        pkg, kind, name = t.split("/")
        by_dds[f"{pkg}::{kind}::dds_::{name}_"] = t
    s = session(port, "client")
    got = []

    def on_sample(sample):
        k = str(sample.key_expr)
        parts = k.split("/")
        msgtype = by_dds[parts[-2]]
        expected = STORE.hash_rihs01(msgtype)
        msg = STORE.deserialize_cdr(bytes(sample.payload.to_bytes()), msgtype)
        att = sample.attachment
        decoded = None
        if att is not None:
            from zenoh.ext import Int64, z_deserialize
            seq, ts, gid = z_deserialize(tuple[Int64, Int64, bytes], att)
            decoded = {"sequence": int(seq), "time_ns": int(ts), "gid": bytes(gid).hex()}
        got.append({"key": k, "type": msgtype, "hash_ok": parts[-1] == expected,
                    "attachment_len": len(att.to_bytes()) if att is not None else 0,
                    "attachment": decoded, "msg": plain(msg)})

    sub = s.declare_subscriber("0/hapcloud/**", on_sample)
    print(json.dumps({"ready": True}), flush=True)
    end = time.time() + seconds
    while time.time() < end and len(got) < n:
        time.sleep(0.02)
    sub.undeclare()
    for g in list(got):
        print(json.dumps(g), flush=True)
    s.close()


def cmd_hashes(msg_dir):
    register_hapcloud(msg_dir)
    print(json.dumps({t: STORE.hash_rihs01(t) for t in sorted(STORE.types)
                      if t.startswith(("sensor_msgs/", "std_msgs/msg/Header", "builtin_interfaces/",
                                       "geometry_msgs/", "tf2_msgs/", "hapcloud_msgs/"))}))


def cmd_write_bag(path, n):
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
    writer = Writer(Path(path), version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with writer:
        TS = STORE.types["geometry_msgs/msg/TransformStamped"]
        TF = STORE.types["tf2_msgs/msg/TFMessage"]
        Header = STORE.types["std_msgs/msg/Header"]
        T = STORE.types["geometry_msgs/msg/Transform"]
        V = STORE.types["geometry_msgs/msg/Vector3"]
        Q = STORE.types["geometry_msgs/msg/Quaternion"]
        tf_conn = writer.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=STORE)
        img_conn = writer.add_connection(DEPTH_TOPIC, "sensor_msgs/msg/Image", typestore=STORE)
        # camera_link -> camera_depth_frame -> camera_depth_optical_frame, as realsense-ros.
        tf = TF(transforms=[
            TS(header=Header(stamp=stamp(0), frame_id="camera_link"),
               child_frame_id="camera_depth_frame",
               transform=T(translation=V(x=0.0, y=0.0, z=0.0),
                           rotation=Q(x=0.0, y=0.0, z=0.0, w=1.0))),
            TS(header=Header(stamp=stamp(0), frame_id="camera_depth_frame"),
               child_frame_id="camera_depth_optical_frame",
               transform=T(translation=V(x=0.0, y=0.0, z=0.0),
                           rotation=Q(x=-0.5, y=0.5, z=-0.5, w=0.5))),
        ])
        writer.write(tf_conn, 100 * 10**9,
                     bytes(STORE.serialize_cdr(tf, "tf2_msgs/msg/TFMessage")))
        info_conn = None
        for i in range(n):
            img, info = image_msgs(i)
            t = (100 + i) * 10**9 + 250_000_000 + i
            writer.write(img_conn, t, bytes(STORE.serialize_cdr(img, "sensor_msgs/msg/Image")))
            # A recorder adds a topic when its first message comes: the camera_info
            # connection (its channel record) after the first image.
            if info_conn is None:
                info_conn = writer.add_connection(INFO_TOPIC, "sensor_msgs/msg/CameraInfo",
                                                  typestore=STORE)
            writer.write(info_conn, t,
                         bytes(STORE.serialize_cdr(info, "sensor_msgs/msg/CameraInfo")))
    print(json.dumps({"bag": str(next(Path(path).glob("*.mcap")))}))


def cmd_read_mcap(path):
    from rosbags.highlevel import AnyReader
    out = {"topics": {}, "first": {}}
    with AnyReader([Path(path)]) as reader:
        for conn, _t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            out["topics"].setdefault(conn.topic, {"type": conn.msgtype, "count": 0})
            out["topics"][conn.topic]["count"] += 1
            if conn.topic not in out["first"]:
                m = plain(msg)
                if "data" in m and isinstance(m["data"], list):
                    m["data_len"] = len(m["data"])
                    m["data_head"] = m["data"][:16]
                    del m["data"]
                out["first"][conn.topic] = m
    print(json.dumps(out))


def cmd_read_mcap_foxglove(path):
    """The file as Foxglove's Python packages read it: `mcap`'s reader, messages decoded by
    `mcap-ros2-support` from the schemas in the file."""
    from mcap.reader import make_reader
    from ruamel.yaml import YAML
    from mcap_ros2.decoder import DecoderFactory
    out = {"channels": {}, "profile": None, "decoded": 0}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        out["profile"] = reader.get_header().profile
        for schema, channel, _message, decoded in reader.iter_decoded_messages():
            c = out["channels"].setdefault(channel.topic, {
                "schema": schema.name, "schema_encoding": schema.encoding,
                "message_encoding": channel.message_encoding,
                "metadata": dict(channel.metadata),
                "qos": YAML(typ="safe").load(channel.metadata.get("offered_qos_profiles", "null")),
                "messages": 0})
            c["messages"] += 1
            out["decoded"] += 1
            if c["messages"] == 1 and hasattr(decoded, "header"):
                c["first_stamp"] = [decoded.header.stamp.sec, decoded.header.stamp.nanosec]
    print(json.dumps(out))


def cmd_record_order(path):
    from mcap.records import Channel, Message
    from mcap.stream_reader import StreamReader
    order, topics = [], {}
    with open(path, "rb") as f:
        for r in StreamReader(f).records:
            if isinstance(r, Channel):
                topics[r.id] = r.topic
                order.append(["channel", r.topic])
            elif isinstance(r, Message):
                order.append(["message", topics.get(r.channel_id)])
    print(json.dumps({"order": order}))


def main():
    cmd, args = sys.argv[1], sys.argv[2:]
    if cmd == "router":
        cmd_router(int(args[0]))
    elif cmd == "publish":
        cmd_publish(int(args[0]), int(args[1]))
    elif cmd == "listen":
        cmd_listen(int(args[0]), int(args[1]), float(args[2]), args[3])
    elif cmd == "stream":
        flags = args[5:]
        cmd_stream(int(args[0]), float(args[1]), float(args[2]), int(args[3]), int(args[4]),
                   "garbage" in flags, "attach" in flags, "skip" in flags, "tfonce" in flags,
                   "distorted" in flags)
    elif cmd == "liveliness":
        cmd_liveliness(int(args[0]), args[1])
    elif cmd == "reset":
        cmd_reset(int(args[0]), int(args[1]))
    elif cmd == "hashes":
        cmd_hashes(args[0])
    elif cmd == "write-bag":
        cmd_write_bag(args[0], int(args[1]))
    elif cmd == "read-mcap":
        cmd_read_mcap(args[0])
    elif cmd == "read-mcap-foxglove":
        cmd_read_mcap_foxglove(args[0])
    elif cmd == "record-order":
        cmd_record_order(args[0])
    else:
        sys.exit(f"unknown command {cmd}")


if __name__ == "__main__":
    main()
