//! AFL++ entry point of the `recording` target ([`hapcloud_fuzz::recording`]).

fn main() {
    afl::fuzz!(|data: &[u8]| hapcloud_fuzz::recording(data));
}
