//! `cargo fuzz run decode_message`: see `harness::decode_message`.
#![no_main]

#[path = "../harness.rs"]
mod harness;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = harness::decode_message(data);
});
