//! AFL++ entry point of the `config_toml` target ([`hapcloud_fuzz::config_toml`]).

fn main() {
    afl::fuzz!(|data: &[u8]| hapcloud_fuzz::config_toml(data));
}
