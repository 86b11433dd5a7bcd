//! AFL++ entry point of the `pcd` target ([`hapcloud_fuzz::pcd`]).

fn main() {
    afl::fuzz!(|data: &[u8]| hapcloud_fuzz::pcd(data));
}
