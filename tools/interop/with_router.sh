# Sourced by tools/interop/node_latency.sh and tools/rt/soak.sh: a free loopback port, a
# temporary directory `$tmp` with `$tmp/node.toml` (two depth cameras, /cam0 and /cam1, on
# rmw_zenoh keys, the node connecting to the router), and interop.py's Zenoh router on
# 127.0.0.1:$port, which runs until this shell's fd 3 closes.
port=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')
tmp=$(mktemp -d)
cat > "$tmp/node.toml" <<TOML
hip_world_m = [0.0, 0.0, 1.55]
[zenoh]
connect = ["tcp/127.0.0.1:$port"]
[zenoh_source]
world_frame = "world"
[[zenoh_source.cameras]]
camera_id = 0
depth_image = "/cam0/depth/image_rect_raw"
[[zenoh_source.cameras]]
camera_id = 1
depth_image = "/cam1/depth/image_rect_raw"
TOML
exec 3> >(python3 "$(dirname "${BASH_SOURCE[0]}")/interop.py" router "$port" > "$tmp/router.out")
# Until the router listens (seconds on a loaded machine), at most 60 s.
for _ in $(seq 120); do
  python3 -c 'import socket, sys; socket.create_connection(("127.0.0.1", int(sys.argv[1])), 1)' "$port" 2>/dev/null && break
  sleep 0.5
done
