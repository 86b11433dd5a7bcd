//! AFL++ entry point of the `depth_png` target ([`hapcloud_fuzz::depth_png`]).

fn main() {
    afl::fuzz!(|data: &[u8]| hapcloud_fuzz::depth_png(data));
}
