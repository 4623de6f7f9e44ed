//! `liquid-splat case compare` as a CI job sees it: exit codes and outputs.

mod support;

use liquid_splat::io::TensorFile;
use std::path::{Path, PathBuf};
use support::tmp as scratch;

fn write(dir: &Path, name: &str, color: &[f32], radii: Vec<i32>) -> PathBuf {
    let mut f = TensorFile::new(dir.join(name));
    f.set_meta("stage", "rasterize");
    f.insert_real::<f32>("color", vec![color.len()], color);
    f.insert_i32("radii", vec![radii.len()], radii);
    let p = dir.join(name);
    f.save(&p).unwrap();
    p
}

fn run(args: &[&std::ffi::OsStr]) -> (i32, String, String) {
    let args: Vec<&std::ffi::OsStr> = ["case".as_ref(), "compare".as_ref()]
        .into_iter()
        .chain(args.iter().copied())
        .collect();
    let out = support::cli(&args);
    (
        support::code(&out),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn exit_codes_pass_fail_and_unusable() {
    let d = scratch("codes");
    let e = write(&d, "e.safetensors", &[1.0, 2.0, 3.0], vec![1, 2]);
    let near = write(&d, "near.safetensors", &[1.0, 2.0 + 1e-6, 3.0], vec![1, 2]);
    let far = write(&d, "far.safetensors", &[1.0, 2.1, 3.0], vec![1, 2]);

    let (code, out, _) = run(&[e.as_os_str(), near.as_os_str()]);
    assert_eq!(code, 0, "{out}");
    assert!(out.contains("PASS"), "{out}");

    let report = d.join("report.json");
    let (code, out, _) = run(&[
        e.as_os_str(),
        far.as_os_str(),
        "--report".as_ref(),
        report.as_os_str(),
    ]);
    assert_eq!(code, 1, "{out}");
    assert!(out.contains("FAIL") && out.contains("color"), "{out}");
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    assert_eq!(json["passed"], false);

    // A loose enough flag makes it pass.
    let (code, out, _) = run(&[
        e.as_os_str(),
        far.as_os_str(),
        "--atol".as_ref(),
        "0.2".as_ref(),
    ]);
    assert_eq!(code, 0, "{out}");

    // A tolerance file naming the tensor.
    let tol = d.join("tol.json");
    std::fs::write(
        &tol,
        r#"{"tensors": {"col*": {"max_mismatch_fraction": 0.34}}}"#,
    )
    .unwrap();
    let (code, out, _) = run(&[
        e.as_os_str(),
        far.as_os_str(),
        "--tolerances".as_ref(),
        tol.as_os_str(),
    ]);
    assert_eq!(code, 0, "{out}");

    // Bad tolerance file, missing file, bad flag value: unusable input.
    std::fs::write(&tol, r#"{"default": {"atol": -1}}"#).unwrap();
    let (code, _, err) = run(&[
        e.as_os_str(),
        near.as_os_str(),
        "--tolerances".as_ref(),
        tol.as_os_str(),
    ]);
    assert_eq!(code, 2);
    assert!(err.contains("atol"), "{err}");
    let (code, _, err) = run(&[e.as_os_str(), d.join("nope.safetensors").as_os_str()]);
    assert_eq!(code, 2);
    assert!(err.starts_with("error:"), "{err}");
    let (code, _, _) = run(&[
        e.as_os_str(),
        near.as_os_str(),
        "--rtol".as_ref(),
        "abc".as_ref(),
    ]);
    assert_eq!(code, 2);
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn integer_mismatch_and_missing_tensor_fail() {
    let d = scratch("ints");
    let e = write(&d, "e.safetensors", &[1.0], vec![1, 2]);
    let a = write(&d, "a.safetensors", &[1.0], vec![1, 3]);
    let (code, out, _) = run(&[e.as_os_str(), a.as_os_str()]);
    assert_eq!(code, 1, "{out}");
    assert!(out.contains("radii"), "{out}");

    let mut f = TensorFile::new(d.join("only_color.safetensors"));
    f.insert_real::<f32>("color", vec![1], &[1.0]);
    let p = d.join("only_color.safetensors");
    f.save(&p).unwrap();
    let (code, out, _) = run(&[e.as_os_str(), p.as_os_str()]);
    assert_eq!(code, 1, "{out}");
    assert!(out.contains("missing"), "{out}");
    // Extra tensors in actual do not fail.
    let (code, out, _) = run(&[p.as_os_str(), e.as_os_str()]);
    assert_eq!(code, 0, "{out}");
    assert!(out.contains("extra"), "{out}");
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn corrupted_and_truncated_files_exit_2() {
    let d = scratch("corrupt");
    let e = write(&d, "e.safetensors", &[1.0, 2.0, 3.0, 4.0], vec![1, 2]);
    let bytes = std::fs::read(&e).unwrap();
    let cases: Vec<(&str, Vec<u8>)> = vec![
        ("empty", vec![]),
        ("truncated_header", bytes[..6].to_vec()),
        ("truncated_data", bytes[..bytes.len() - 3].to_vec()),
        ("text", b"this is not a safetensors file at all".to_vec()),
        ("huge_header_len", {
            let mut b = bytes.clone();
            b[..8].copy_from_slice(&u64::MAX.to_le_bytes());
            b
        }),
        ("garbage_header", {
            let mut b = bytes.clone();
            for x in b[8..20].iter_mut() {
                *x = b'#';
            }
            b
        }),
    ];
    for (name, content) in cases {
        let p = d.join(format!("{name}.safetensors"));
        std::fs::write(&p, content).unwrap();
        let (code, out, err) = run(&[e.as_os_str(), p.as_os_str()]);
        assert_eq!(code, 2, "{name}: {out} {err}");
        assert!(err.starts_with("error:"), "{name}: {err}");
        let (code, _, _) = run(&[p.as_os_str(), e.as_os_str()]);
        assert_eq!(code, 2, "{name} as expected");
    }
    std::fs::remove_dir_all(&d).unwrap();
}

/// A `--report` path that cannot be written is refused before the
/// comparison: the table and "PASS" were printed, then exit 2.
#[test]
fn an_unwritable_report_path_is_refused_before_the_verdict() {
    let d = scratch("report-path");
    let e = write(&d, "e.safetensors", &[1.0, 2.0, 3.0], vec![1, 2]);
    let missing_folder = std::path::PathBuf::from(format!("{}/", d.join("new").display()));
    for report in [
        d.join("missing").join("r.json"),
        d.to_path_buf(),
        missing_folder,
    ] {
        let (code, out, err) = run(&[
            e.as_os_str(),
            e.as_os_str(),
            "--report".as_ref(),
            report.as_os_str(),
        ]);
        assert_eq!(code, 2, "{out}{err}");
        assert!(err.contains("--report"), "{err}");
        assert!(!out.contains("PASS"), "{out}");
    }
}
