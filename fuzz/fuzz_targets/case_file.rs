//! Any bytes as an oracle case file: read, checked, run (see
//! `liquid_splat::fuzz::case_file`). Never a panic, abort or hang.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = liquid_splat::fuzz::case_file(data);
});
