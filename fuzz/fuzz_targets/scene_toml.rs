//! AFL++ entry point of the `scene_toml` target ([`hapcloud_fuzz::scene_toml`]).

fn main() {
    afl::fuzz!(|data: &[u8]| hapcloud_fuzz::scene_toml(data));
}
