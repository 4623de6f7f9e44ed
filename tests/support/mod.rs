//! Helpers shared by the integration tests: the command-line runner, a
//! local thread pool, scratch directories, fixture paths and the x86
//! subnormal-arithmetic flags.
//!
//! Each test file that needs them declares `mod support;` (Cargo builds
//! every `tests/*.rs` as its own crate, so a file uses only part of this).
#![allow(dead_code)]

use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The `liquid-splat` binary Cargo built for these tests.
pub const BIN: &str = env!("CARGO_BIN_EXE_liquid-splat");

/// Run the command-line tool with `args` (without the program name) and
/// capture its exit status, stdout and stderr.
pub fn cli<S: AsRef<OsStr>>(args: &[S]) -> Output {
    Command::new(BIN)
        .args(args)
        .output()
        .unwrap_or_else(|e| panic!("cannot run {BIN}: {e}"))
}

/// The exit code of a finished run (`-1` when a signal ended it).
pub fn code(o: &Output) -> i32 {
    o.status.code().unwrap_or(-1)
}

/// A run's stdout followed by its stderr, as text.
pub fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// Run `f` on a local rayon pool of `threads` workers (the library's
/// parallel loops use the pool they are called from).
pub fn with_threads<R: Send>(threads: usize, f: impl FnOnce() -> R + Send) -> R {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap_or_else(|e| panic!("cannot start {threads} threads: {e}"))
        .install(f)
}

/// A fresh, empty scratch directory for `name`, unique to this test crate
/// and process, removed with everything in it when the returned guard is
/// dropped; a failing test (one that is panicking) keeps it and prints its
/// path.
pub fn tmp(name: &str) -> Scratch {
    let d = std::env::temp_dir().join(format!(
        "ls-{}-{}-{name}",
        env!("CARGO_CRATE_NAME"),
        std::process::id()
    ));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap_or_else(|e| panic!("{}: {e}", d.display()));
    Scratch(d)
}

/// A scratch directory (see [`tmp`]); derefs to its path.
pub struct Scratch(PathBuf);

impl Scratch {
    /// The directory's path.
    pub fn as_path(&self) -> &Path {
        &self.0
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        if std::thread::panicking() {
            eprintln!("kept the failing test's files in {}", self.0.display());
        } else {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

impl std::ops::Deref for Scratch {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.0
    }
}

impl AsRef<Path> for Scratch {
    fn as_ref(&self) -> &Path {
        &self.0
    }
}

/// A path under the repository's `fixtures/` directory.
pub fn fixture(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("fixtures")
        .join(rel)
}

/// A path as `&str` (test paths are UTF-8).
pub fn s(p: &Path) -> &str {
    p.to_str().expect("a UTF-8 path")
}

/// A JSON file's contents.
pub fn read_json(p: &Path) -> serde_json::Value {
    let bytes = std::fs::read(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
    serde_json::from_slice(&bytes).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// The committed fixture scene `swing` with 300 random initial points.
pub fn swing() -> liquid_splat::dataset::Dataset {
    let options = liquid_splat::dataset::LoadOptions {
        init_points: 300,
        ..Default::default()
    };
    liquid_splat::dataset::load(&fixture("scenes/swing"), &options)
        .unwrap_or_else(|e| panic!("fixtures/scenes/swing: {e}"))
}

/// Copy directory `from` into `to`, recursively (`to` is created).
pub fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap_or_else(|e| panic!("{}: {e}", to.display()));
    for e in std::fs::read_dir(from).unwrap_or_else(|e| panic!("{}: {e}", from.display())) {
        let e = e.unwrap();
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &to.join(e.file_name()));
        } else {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}

/// The x86 status flags of subnormal arithmetic (MXCSR's denormal-operand
/// and underflow flags) that `f` raises on this thread: cleared before it,
/// read after it.
#[cfg(target_arch = "x86_64")]
pub fn subnormal_flags(f: impl FnOnce()) -> u32 {
    const DENORMAL: u32 = 1 << 1;
    const UNDERFLOW: u32 = 1 << 4;
    fn get() -> u32 {
        let mut x: u32 = 0;
        // SAFETY: stores MXCSR into `x`, a valid u32.
        unsafe {
            std::arch::asm!("stmxcsr [{}]", in(reg) &mut x, options(nostack, preserves_flags))
        };
        x
    }
    fn set(x: u32) {
        // SAFETY: loads MXCSR from `x`, the current value with status flags
        // cleared (only the sticky flags change).
        unsafe {
            std::arch::asm!("ldmxcsr [{}]", in(reg) &x, options(nostack, readonly, preserves_flags))
        };
    }
    set(get() & !(DENORMAL | UNDERFLOW));
    f();
    get() & (DENORMAL | UNDERFLOW)
}
