//! AFL++ entry point of the `playback` target ([`hapcloud_fuzz::playback`]).

fn main() {
    afl::fuzz!(|data: &[u8]| hapcloud_fuzz::playback(data));
}
