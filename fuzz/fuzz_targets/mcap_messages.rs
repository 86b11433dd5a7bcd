//! AFL++ entry point of the `mcap_messages` target ([`hapcloud_fuzz::mcap_messages`]).

fn main() {
    afl::fuzz!(|data: &[u8]| hapcloud_fuzz::mcap_messages(data));
}
