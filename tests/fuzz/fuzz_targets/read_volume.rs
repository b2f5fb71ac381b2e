//! `cargo fuzz run read_volume`: see `harness::read_volume` (each input is written to a file in a
//! scratch folder of the process: the readers read files).
#![no_main]

#[path = "../harness.rs"]
mod harness;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = harness::read_volume(&harness::scratch_dir(), data);
});
