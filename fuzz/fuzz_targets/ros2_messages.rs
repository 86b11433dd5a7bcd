//! AFL++ entry point of the `ros2_messages` target ([`hapcloud_fuzz::ros2_messages`]).

fn main() {
    afl::fuzz!(|data: &[u8]| hapcloud_fuzz::ros2_messages(data));
}
