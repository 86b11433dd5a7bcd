//! AFL++ entry point of the `depth_tiff` target ([`hapcloud_fuzz::depth_tiff`]).

fn main() {
    afl::fuzz!(|data: &[u8]| hapcloud_fuzz::depth_tiff(data));
}
