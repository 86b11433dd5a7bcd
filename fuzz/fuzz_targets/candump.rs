//! AFL++ entry point of the `candump` target ([`hapcloud_fuzz::candump`]).

fn main() {
    afl::fuzz!(|data: &[u8]| hapcloud_fuzz::candump(data));
}
