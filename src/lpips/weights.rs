//! LPIPS weights from the files users already have:
//!
//! - the VGG16 backbone: torchvision's ImageNet weights `vgg16-397923af.pth`
//!   (`VGG16_Weights.IMAGENET1K_V1`, downloaded by torchvision into the torch
//!   hub cache, usually `~/.cache/torch/hub/checkpoints/`); only
//!   `features.{0,2,5,…,28}.weight` / `.bias` are read;
//! - the linear layers: the `lpips` package's `weights/v0.1/vgg.pth`
//!   (inside its wheel: `python -c "import lpips, os;
//!   print(os.path.dirname(lpips.__file__))"`), keys `lin{0..4}.model.1.weight`.
//!
//! Both are read directly ([`crate::io::pth`]); no Python is needed at run
//! time. With [`Verify::Official`] each file must have the size and SHA-256 of
//! the published file (recorded below); [`Verify::Any`] accepts other weights
//! of the right shapes (tests, retrained linear layers) and reports them as
//! such. Either way the SHA-256 of both files is recorded in
//! [`WeightFile`], so a result always says which weights produced it.

use super::{LAYER_CHANNELS, VGG16_CONVS, VGG16_CONV_INDEX};
use crate::error::{Error, Result};
use crate::io::pth::PthFile;
use sha2::{Digest, Sha256};
use std::io::Read;
use std::path::{Path, PathBuf};

/// torchvision's file name for the VGG16 ImageNet weights.
pub const VGG16_FILE_NAME: &str = "vgg16-397923af.pth";
/// SHA-256 of `vgg16-397923af.pth`. torchvision itself checks only the
/// first 8 hex digits (the file name's `397923af`); the full digest is the
/// one recorded, with the size below, by several independent public projects
/// that verify this file; it begins with those 8 digits.
pub const VGG16_SHA256: &str = "397923af8e79cdbb6a7127f12361acd7a2f83e06b05044ddf496e83de57a5bf0";
/// Size in bytes of `vgg16-397923af.pth` (the whole VGG16, classifier included).
pub const VGG16_BYTES: u64 = 553_433_881;
/// SHA-256 of the `lpips` package's `weights/v0.1/vgg.pth` (lpips 0.1.4, the
/// last release; computed from the installed wheel).
pub const LPIPS_VGG_SHA256: &str =
    "a78928a0af1e5f0fcb1f3b9e8f8c3a2a5a3de244d830ad5c1feddc79b8432868";
/// Size in bytes of the `lpips` package's `weights/v0.1/vgg.pth`.
pub const LPIPS_VGG_BYTES: u64 = 7_289;

/// Whether the weight files must be the published ones.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Verify {
    /// Size and SHA-256 must match the published files.
    Official,
    /// Any file with the right tensors and shapes.
    Any,
}

/// A weight file that was read: where, its SHA-256, and whether it is the
/// published file.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct WeightFile {
    /// Where it was read from.
    pub path: PathBuf,
    /// SHA-256 of its bytes, lowercase hex.
    pub sha256: String,
    /// True when the SHA-256 is the published file's.
    pub official: bool,
}

/// The LPIPS VGG weights, as stored in the files (f32).
#[derive(Clone, Debug)]
pub struct LpipsWeights {
    /// The 13 convolutions: weight `[out, in, 3, 3]` and bias `[out]`.
    pub convs: Vec<(Vec<f32>, Vec<f32>)>,
    /// The five linear layers' weights (`[1, C, 1, 1]` flattened to `C`).
    pub lins: Vec<Vec<f32>>,
    /// The file the convolutions came from.
    pub vgg: WeightFile,
    /// The file the linear layers came from.
    pub lin: WeightFile,
}

/// SHA-256 of a file, hexadecimal, read in 1 MiB pieces.
pub fn sha256_file(path: &Path) -> Result<String> {
    let mut f = crate::io::open(path)?;
    let mut h = Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = f.read(&mut buf).map_err(|e| Error::io(path, e))?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
    }
    Ok(h.finalize().iter().map(|b| format!("{b:02x}")).collect())
}

/// Check a file against a published size and digest (with `Official`) and
/// return its record.
fn identify(path: &Path, what: &str, bytes: u64, sha: &str, verify: Verify) -> Result<WeightFile> {
    let len = std::fs::metadata(path)
        .map_err(|e| Error::io(path, e))?
        .len();
    if verify == Verify::Official && len != bytes {
        return Err(Error::format(
            path,
            format!(
                "{len} bytes, but the published {what} has {bytes} bytes ({}); \
                 pass a complete copy of the published file",
                if len < bytes {
                    "truncated?"
                } else {
                    "a different file?"
                }
            ),
        ));
    }
    let got = sha256_file(path)?;
    let official = got == sha;
    if verify == Verify::Official && !official {
        return Err(Error::format(
            path,
            format!("SHA-256 {got}, but the published {what} has {sha}"),
        ));
    }
    Ok(WeightFile {
        path: path.to_path_buf(),
        sha256: got,
        official,
    })
}

/// Read tensor `name` with the expected `shape` from `f`.
fn tensor(f: &PthFile, path: &Path, name: &str, shape: &[usize]) -> Result<Vec<f32>> {
    let found = f.shape(name).ok_or_else(|| Error::MissingTensor {
        context: path.display().to_string(),
        name: name.to_string(),
    })?;
    if found != shape {
        return Err(Error::Tensor {
            context: path.display().to_string(),
            name: name.to_string(),
            expected: format!("shape {shape:?}"),
            found: format!("shape {found:?}"),
        });
    }
    f.read_f32(name)
}

impl LpipsWeights {
    /// Read the backbone from `vgg` (torchvision's VGG16 state_dict) and the
    /// linear layers from `lin` (the `lpips` package's `vgg.pth`).
    pub fn load(vgg: &Path, lin: &Path, verify: Verify) -> Result<LpipsWeights> {
        let vgg_id = identify(vgg, VGG16_FILE_NAME, VGG16_BYTES, VGG16_SHA256, verify)?;
        let (lins, lin_id) = Self::read_lins(lin, verify)?;
        let vf = PthFile::open(vgg)?;
        let mut convs = Vec::with_capacity(13);
        for (&(cin, cout), &i) in VGG16_CONVS.iter().zip(&VGG16_CONV_INDEX) {
            let w = tensor(
                &vf,
                vgg,
                &format!("features.{i}.weight"),
                &[cout, cin, 3, 3],
            )?;
            let b = tensor(&vf, vgg, &format!("features.{i}.bias"), &[cout])?;
            convs.push((w, b));
        }
        let w = LpipsWeights {
            convs,
            lins,
            vgg: vgg_id,
            lin: lin_id,
        };
        w.check_finite()?;
        Ok(w)
    }

    /// Weights from memory (shapes as in the files); errors name the tensor.
    pub fn from_parts(
        convs: Vec<(Vec<f32>, Vec<f32>)>,
        lins: Vec<Vec<f32>>,
        vgg: WeightFile,
        lin: WeightFile,
    ) -> Result<LpipsWeights> {
        let ctx = "LPIPS weights";
        if convs.len() != 13 || lins.len() != 5 {
            return Err(Error::invalid(
                ctx,
                format!(
                    "{} convolutions and {} linear layers, expected 13 and 5",
                    convs.len(),
                    lins.len()
                ),
            ));
        }
        for (((w, b), &(cin, cout)), &i) in convs.iter().zip(&VGG16_CONVS).zip(&VGG16_CONV_INDEX) {
            for (name, len, want) in [
                (format!("features.{i}.weight"), w.len(), cout * cin * 9),
                (format!("features.{i}.bias"), b.len(), cout),
            ] {
                if len != want {
                    return Err(Error::Tensor {
                        context: ctx.into(),
                        name,
                        expected: format!("{want} values"),
                        found: format!("{len}"),
                    });
                }
            }
        }
        for (k, (l, &c)) in lins.iter().zip(&LAYER_CHANNELS).enumerate() {
            if l.len() != c {
                return Err(Error::Tensor {
                    context: ctx.into(),
                    name: format!("lin{k}.model.1.weight"),
                    expected: format!("{c} values"),
                    found: format!("{}", l.len()),
                });
            }
        }
        let w = LpipsWeights {
            convs,
            lins,
            vgg,
            lin,
        };
        w.check_finite()?;
        Ok(w)
    }

    fn check_finite(&self) -> Result<()> {
        let bad = |v: &[f32]| v.iter().position(|x| !x.is_finite());
        for ((w, b), &i) in self.convs.iter().zip(&VGG16_CONV_INDEX) {
            for (name, v) in [("weight", w), ("bias", b)] {
                if let Some(j) = bad(v) {
                    return Err(Error::format(
                        &self.vgg.path,
                        format!("features.{i}.{name}[{j}] is {}", v[j]),
                    ));
                }
            }
        }
        for (k, l) in self.lins.iter().enumerate() {
            if let Some(j) = bad(l) {
                return Err(Error::format(
                    &self.lin.path,
                    format!("lin{k}.model.1.weight[{j}] is {}", l[j]),
                ));
            }
        }
        Ok(())
    }

    /// Read only the linear layers from `lin` (the package's `vgg.pth`).
    pub fn read_lins(lin: &Path, verify: Verify) -> Result<(Vec<Vec<f32>>, WeightFile)> {
        let id = identify(
            lin,
            "lpips weights/v0.1/vgg.pth",
            LPIPS_VGG_BYTES,
            LPIPS_VGG_SHA256,
            verify,
        )?;
        let lf = PthFile::open(lin)?;
        let mut lins = Vec::with_capacity(5);
        for (k, &c) in LAYER_CHANNELS.iter().enumerate() {
            lins.push(tensor(
                &lf,
                lin,
                &format!("lin{k}.model.1.weight"),
                &[1, c, 1, 1],
            )?);
        }
        Ok((lins, id))
    }
}
