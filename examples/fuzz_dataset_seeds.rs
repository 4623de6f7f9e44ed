//! Write the dataset fuzz target's seed inputs (the committed fixture
//! scenes, see `liquid_splat::fuzz::dataset_seeds`) into a folder.
//!
//!     cargo run --release --example fuzz_dataset_seeds -- fuzz/corpus/dataset

use std::path::{Path, PathBuf};

fn main() -> std::io::Result<()> {
    let out = PathBuf::from(
        std::env::args()
            .nth(1)
            .unwrap_or_else(|| "fuzz/corpus/dataset".into()),
    );
    std::fs::create_dir_all(&out)?;
    let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures");
    for (k, seed) in liquid_splat::fuzz::dataset_seeds(&fixtures)?
        .iter()
        .enumerate()
    {
        std::fs::write(out.join(format!("seed{k}")), seed)?;
    }
    Ok(())
}
