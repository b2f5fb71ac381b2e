//! `cargo fuzz run parse_config`: see `harness::parse_config`.
#![no_main]

#[path = "../harness.rs"]
mod harness;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = harness::parse_config(data);
});
