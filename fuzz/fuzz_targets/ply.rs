//! AFL++ entry point of the `ply` target ([`hapcloud_fuzz::ply`]).

fn main() {
    afl::fuzz!(|data: &[u8]| hapcloud_fuzz::ply(data));
}
