//! Any bytes as a dataset folder (D-NeRF or nerfies layout, see
//! `liquid_splat::fuzz::DatasetFuzzer`). Never a panic, abort or hang.
#![no_main]

use std::path::Path;
use std::sync::OnceLock;

static FUZZER: OnceLock<liquid_splat::fuzz::DatasetFuzzer> = OnceLock::new();

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let fuzzer = FUZZER.get_or_init(|| {
        let dir = std::env::temp_dir().join(format!("liquid-splat-fuzz-{}", std::process::id()));
        let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures");
        liquid_splat::fuzz::DatasetFuzzer::new(&dir, &fixtures).expect("fixture images")
    });
    let _ = fuzzer.run(data);
});
