//! The gsplat oracle stages through the CLI: `case new` for every stage and
//! option, `case run`, and typed errors (exit 2) for bad settings.

mod support;

use liquid_splat::io::TensorFile;
use std::path::Path;

#[test]
fn case_new_and_run_every_gsplat_stage() {
    let tmp = support::tmp("stages");
    let run = |args: &[&str]| support::cli(args);
    let p = |n: &str| tmp.join(n).display().to_string();
    for stage in liquid_splat::oracle::gsplat::STAGES {
        for (i, extra) in [
            vec!["--gsplat-version", "1.5.3"],
            vec![
                "--gsplat-version",
                "1.6",
                "--antialiased",
                "--gradient",
                "gsplat",
            ],
            vec!["--dense", "--width", "20", "--count", "3"],
        ]
        .into_iter()
        .enumerate()
        {
            // Options a stage does not use are refused, and left out below.
            let imaged = !stage.contains("covar") && !stage.contains("harmonics");
            let packs = stage.contains("projection") || stage.ends_with("rasterization");
            let unused = |o: &str| match o {
                "--antialiased" | "--width" => !imaged,
                "--dense" => !packs,
                _ => false,
            };
            let case = p(&format!("{stage}_{i}.safetensors"));
            let base = vec!["case", "new", stage, &case, "--dtype", "f32", "--seed", "5"];
            let mut used = Vec::new();
            let mut k = 0;
            while k < extra.len() {
                let takes_value = extra[k] != "--antialiased" && extra[k] != "--dense";
                let n = if takes_value { 2 } else { 1 };
                let opt = &extra[k..k + n];
                if unused(extra[k]) {
                    let o = run(&[&base[..], opt].concat());
                    assert_eq!(o.status.code(), Some(2), "{stage} {opt:?}");
                    assert!(String::from_utf8_lossy(&o.stderr).contains("not used by stage"));
                } else {
                    used.extend_from_slice(opt);
                }
                k += n;
            }
            let mut args = base.clone();
            args.extend(used.iter().copied());
            let o = run(&args);
            assert!(
                o.status.success(),
                "{stage} {extra:?}: {}",
                String::from_utf8_lossy(&o.stderr)
            );
            let f = TensorFile::load(Path::new(&case)).unwrap();
            assert_eq!(f.meta("stage").unwrap(), stage);
            let out = p("out.safetensors");
            let o = run(&["case", "run", &case, &out]);
            assert!(
                o.status.success(),
                "{stage} {extra:?}: {}",
                String::from_utf8_lossy(&o.stderr)
            );
            let r = TensorFile::load(Path::new(&out)).unwrap();
            // isect_tiles is piecewise constant: integer outputs only.
            let want = if stage == "gsplat_isect_tiles" {
                "flatten_ids"
            } else {
                "v_"
            };
            assert!(
                r.tensors.keys().any(|k| k.starts_with(want)),
                "{stage}: no {want}"
            );
        }
    }
    // Dense projection outputs are [C, N, ...].
    let f = TensorFile::load(&tmp.join("gsplat_fully_fused_projection_2.safetensors")).unwrap();
    assert_eq!(f.shape("v_means2d").unwrap(), &[2, 5, 2]);
    // A bad version, mode or layout flag is unusable input.
    let case = p("gsplat_rasterization_0.safetensors");
    let mut f = TensorFile::load(Path::new(&case)).unwrap();
    for (key, value) in [
        ("version", "1.4"),
        ("gradient", "inria"),
        ("rasterize_mode", "aa"),
    ] {
        let mut g = f.clone();
        g.set_meta(key, value);
        let bad = p("bad.safetensors");
        g.save(Path::new(&bad)).unwrap();
        let o = run(&["case", "run", &bad, &p("x.safetensors")]);
        assert_eq!(o.status.code(), Some(2), "{key}={value}");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains(key), "{err}");
    }
    f.tensors.remove("Ks");
    f.save(&tmp.join("bad.safetensors")).unwrap();
    let o = run(&["case", "run", &p("bad.safetensors"), &p("x.safetensors")]);
    assert_eq!(o.status.code(), Some(2));
    for bad in [
        vec![
            "case",
            "new",
            "gsplat_rasterization",
            "x",
            "--gsplat-version",
            "2.0",
        ],
        vec![
            "case",
            "new",
            "gsplat_rasterization",
            "x",
            "--gradient",
            "inria",
        ],
        vec!["case", "new", "rasterize", "x", "--antialiased"],
    ] {
        let o = run(&bad);
        assert_eq!(o.status.code(), Some(2), "{bad:?}");
    }
    std::fs::remove_dir_all(&tmp).unwrap();
}
