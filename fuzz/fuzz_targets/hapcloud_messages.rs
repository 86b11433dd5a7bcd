//! AFL++ entry point of the `hapcloud_messages` target ([`hapcloud_fuzz::hapcloud_messages`]).

fn main() {
    afl::fuzz!(|data: &[u8]| hapcloud_fuzz::hapcloud_messages(data));
}
