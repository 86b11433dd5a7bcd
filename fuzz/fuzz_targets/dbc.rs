//! AFL++ entry point of the `dbc` target ([`hapcloud_fuzz::dbc`]).

fn main() {
    afl::fuzz!(|data: &[u8]| hapcloud_fuzz::dbc(data));
}
