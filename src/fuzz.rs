//! Entry points for fuzzing the input readers: case files (every oracle
//! stage) and dataset folders (D-NeRF and nerfies layouts, with their point
//! clouds). Both the `cargo fuzz` targets in `fuzz/` and the deterministic
//! mutation replay of `cargo test` (`tests/fuzz_replay.rs`) call these; see
//! `fuzz/README.md`.
//!
//! The property is the README's error promise: any input gives a result or
//! an [`Error`](crate::Error), never a panic, an abort or a hang. To keep one
//! execution short, a case file whose metadata asks for a large (but valid)
//! problem is parsed and checked but not run ([`CASE_BUDGET`]).

use crate::dataset::{self, LoadOptions};
use crate::io::TensorFile;
use std::path::{Path, PathBuf};

/// Largest sizes a fuzzed case file is run with (larger valid sizes are
/// only parsed): image pixels, field width, depth, backbone layers.
pub const CASE_BUDGET: CaseBudget = CaseBudget {
    pixels: 1 << 14,
    width: 256,
    depth: 16,
    backbone_layers: 4,
};

/// See [`CASE_BUDGET`].
#[derive(Clone, Copy, Debug)]
pub struct CaseBudget {
    /// Most image pixels (width × height).
    pub pixels: usize,
    /// Widest field (MLP width or CfC hidden size).
    pub width: usize,
    /// Deepest field (MLP layers or CfC cells).
    pub depth: usize,
    /// Most CfC backbone layers.
    pub backbone_layers: usize,
}

/// What happened to one input.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Outcome {
    /// Read and run without error.
    Accepted,
    /// Refused with an error.
    Refused,
    /// Valid as far as checked, but larger than the budget: not run.
    OverBudget,
}

fn meta_usize(case: &TensorFile, key: &str) -> Option<usize> {
    case.metadata.get(key)?.trim().parse().ok()
}

/// Parse `bytes` as a case file and run its stage.
pub fn case_file(bytes: &[u8]) -> Outcome {
    let path = Path::new("fuzz.safetensors");
    let Ok(case) = TensorFile::from_bytes(path, bytes) else {
        return Outcome::Refused;
    };
    let b = CASE_BUDGET;
    let over = |key: &str, max: usize| meta_usize(&case, key).is_some_and(|v| v > max);
    let pixels = meta_usize(&case, "image_width")
        .unwrap_or(0)
        .saturating_mul(meta_usize(&case, "image_height").unwrap_or(0));
    if pixels > b.pixels
        || over("width", b.width)
        || over("backbone_units", b.width)
        || over("depth", b.depth)
        || over("backbone_layers", b.backbone_layers)
    {
        return Outcome::OverBudget;
    }
    match crate::oracle::run_case(&case) {
        Ok(_) => Outcome::Accepted,
        Err(_) => Outcome::Refused,
    }
}

/// The separator between the files of a dataset fuzz input.
pub const FILE_SEPARATOR: &[u8] = b"\n#~next-file~#\n";

/// The files of a D-NeRF fuzz input, in order.
pub const DNERF_FILES: [&str; 4] = [
    "transforms_train.json",
    "transforms_test.json",
    "transforms_val.json",
    "points3d.ply",
];

/// The files of a nerfies fuzz input, in order (the cameras of the
/// fixture's 12 ids).
pub fn nerfies_files() -> Vec<String> {
    let mut v: Vec<String> = ["dataset.json", "metadata.json", "scene.json", "points.npy"]
        .map(String::from)
        .to_vec();
    v.extend((0..12).map(|i| format!("camera/{i:05}.json")));
    v
}

/// A dataset fuzz input: the layout byte (even: D-NeRF, odd: nerfies),
/// then the layout's files joined by [`FILE_SEPARATOR`] (fewer sections:
/// the rest are absent).
pub fn encode_dataset(nerfies: bool, files: &[Vec<u8>]) -> Vec<u8> {
    let mut out = vec![nerfies as u8];
    for (i, f) in files.iter().enumerate() {
        if i > 0 {
            out.extend_from_slice(FILE_SEPARATOR);
        }
        out.extend_from_slice(f);
    }
    out
}

fn split<'a>(mut data: &'a [u8], sep: &[u8]) -> Vec<&'a [u8]> {
    let mut parts = Vec::new();
    while let Some(i) = data.windows(sep.len()).position(|w| w == sep) {
        parts.push(&data[..i]);
        data = &data[i + sep.len()..];
    }
    parts.push(data);
    parts
}

/// A folder where dataset inputs are written and loaded: the fixture
/// scenes' images are copied in once (`swing` for D-NeRF, `blob-nerfies`
/// for nerfies); each input then replaces the JSON, PLY and npy files.
pub struct DatasetFuzzer {
    dir: PathBuf,
}

fn copy_tree(from: &Path, to: &Path) -> std::io::Result<()> {
    std::fs::create_dir_all(to)?;
    for e in std::fs::read_dir(from)? {
        let e = e?;
        if e.file_type()?.is_dir() {
            copy_tree(&e.path(), &to.join(e.file_name()))?;
        } else {
            std::fs::copy(e.path(), to.join(e.file_name()))?;
        }
    }
    Ok(())
}

impl DatasetFuzzer {
    /// Prepare `dir` (created, emptied) with the images of
    /// `fixtures/scenes` under `fixtures`.
    pub fn new(dir: &Path, fixtures: &Path) -> std::io::Result<Self> {
        let _ = std::fs::remove_dir_all(dir);
        let scenes = fixtures.join("scenes");
        for split in ["train", "test", "val"] {
            copy_tree(
                &scenes.join("swing").join(split),
                &dir.join("dnerf").join(split),
            )?;
        }
        copy_tree(
            &scenes.join("blob-nerfies").join("rgb"),
            &dir.join("nerfies").join("rgb"),
        )?;
        std::fs::create_dir_all(dir.join("nerfies").join("camera"))?;
        Ok(DatasetFuzzer {
            dir: dir.to_path_buf(),
        })
    }

    /// Write the input's files and load the dataset (few random initial
    /// points).
    pub fn run(&self, data: &[u8]) -> Outcome {
        let Some((&layout, rest)) = data.split_first() else {
            return Outcome::Refused;
        };
        let nerfies = layout % 2 == 1;
        let (root, names) = if nerfies {
            (self.dir.join("nerfies"), nerfies_files())
        } else {
            (
                self.dir.join("dnerf"),
                DNERF_FILES.map(String::from).to_vec(),
            )
        };
        let parts = split(rest, FILE_SEPARATOR);
        for (i, name) in names.iter().enumerate() {
            let p = root.join(name);
            let written = match parts.get(i) {
                Some(bytes) => std::fs::write(&p, bytes),
                None => match std::fs::remove_file(&p) {
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
                    r => r,
                },
            };
            if written.is_err() {
                return Outcome::Refused;
            }
        }
        let opts = LoadOptions {
            init_points: 64,
            ..Default::default()
        };
        match dataset::load(&root, &opts) {
            Ok(_) => Outcome::Accepted,
            Err(_) => Outcome::Refused,
        }
    }
}

/// The seed inputs from the committed fixtures: `swing` (D-NeRF, with a
/// small point cloud added) and `blob-nerfies`.
pub fn dataset_seeds(fixtures: &Path) -> std::io::Result<Vec<Vec<u8>>> {
    let scenes = fixtures.join("scenes");
    let swing = scenes.join("swing");
    let mut files: Vec<Vec<u8>> = DNERF_FILES[..3]
        .iter()
        .map(|f| std::fs::read(swing.join(f)))
        .collect::<std::io::Result<_>>()?;
    let mut ply = b"ply\nformat ascii 1.0\nelement vertex 6\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n".to_vec();
    for k in 0..6 {
        let x = k as f32 * 0.1;
        ply.extend_from_slice(format!("{x} {} {} 10 200 30\n", -x, 0.5 * x).as_bytes());
    }
    files.push(ply);
    let dnerf = encode_dataset(false, &files);
    let nf = scenes.join("blob-nerfies");
    let files: Vec<Vec<u8>> = nerfies_files()
        .iter()
        .map(|f| std::fs::read(nf.join(f)))
        .collect::<std::io::Result<_>>()?;
    Ok(vec![dnerf, encode_dataset(true, &files)])
}
