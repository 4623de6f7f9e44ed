//! LPIPS (VGG, v0.1) against the `lpips` package, and the weight files.
//!
//! `fixtures/lpips/golden.json` was computed by `python/reference_lpips.py` with the package
//! itself (`lpips.LPIPS(net='vgg')`): a VGG16 backbone with weights from a counter-based
//! formula (rebuilt here bit for bit by [`formula_weights`]), the package's shipped linear
//! weights (`fixtures/lpips/vgg.pth`, a copy of its `weights/v0.1/vgg.pth`) or formula ones,
//! both input conventions, f32 and f64.

mod support;

use liquid_splat::io::pth::{Container, PthFile};
use liquid_splat::lpips::weights::{self, LPIPS_VGG_SHA256};
use liquid_splat::lpips::{Convention, Lpips, LpipsWeights, Verify, WeightFile};
use liquid_splat::math::Real;
use std::path::{Path, PathBuf};
use support::{cli, read_json as json, text, tmp};

fn fixtures() -> PathBuf {
    support::fixture("lpips")
}

const CONVS: [(usize, usize); 13] = liquid_splat::lpips::VGG16_CONVS;
const LINS: [usize; 5] = liquid_splat::lpips::LAYER_CHANNELS;

/// `python/reference_lpips.py`'s `hash_u64`: splitmix64's finaliser of
/// `seed·G + i·H + C` (mod 2^64).
fn hash_u64(seed: u64, i: u64) -> u64 {
    let mut z = seed
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add(i.wrapping_mul(0xD1B5_4A32_D192_ED03))
        .wrapping_add(0x632B_E59B_D9B4_E019);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

fn uniform(seed: u64, n: usize) -> Vec<f64> {
    (0..n as u64)
        .map(|i| (hash_u64(seed, i) >> 40) as f64 / (1u64 << 24) as f64)
        .collect()
}

/// The 13 convolutions' (weight, bias) and the 5 linear layers' weights.
type Formula = (Vec<(Vec<f32>, Vec<f32>)>, Vec<Vec<f32>>);

/// `python/reference_lpips.py`'s `formula_weights` (exact f32 values).
fn formula_weights(base: u64) -> Formula {
    let convs = CONVS
        .iter()
        .enumerate()
        .map(|(l, &(cin, cout))| {
            let e = (24.0 / (9 * cin) as f64).sqrt().log2().round() as i32;
            let s = 2f64.powi(e);
            let w = uniform(base * 1000 + 2 * l as u64, cout * cin * 9)
                .iter()
                .map(|u| ((u - 0.5) * s) as f32)
                .collect();
            let b = uniform(base * 1000 + 2 * l as u64 + 1, cout)
                .iter()
                .map(|u| ((u - 0.5) / 16.0) as f32)
                .collect();
            (w, b)
        })
        .collect();
    let lins = LINS
        .iter()
        .enumerate()
        .map(|(k, &c)| {
            uniform(base * 1000 + 100 + k as u64, c)
                .iter()
                .map(|u| (u / 16.0) as f32)
                .collect()
        })
        .collect();
    (convs, lins)
}

fn memory(name: &str) -> WeightFile {
    WeightFile {
        path: PathBuf::from(name),
        sha256: String::new(),
        official: false,
    }
}

fn shipped_lins() -> (Vec<Vec<f32>>, WeightFile) {
    LpipsWeights::read_lins(&fixtures().join("vgg.pth"), Verify::Official).unwrap()
}

struct Golden {
    images: serde_json::Value,
    cases: Vec<serde_json::Value>,
}

fn golden() -> Golden {
    let text = std::fs::read_to_string(fixtures().join("golden.json")).unwrap();
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    Golden {
        images: v["images"].clone(),
        cases: v["cases"].as_array().unwrap().clone(),
    }
}

fn image<T: Real>(g: &Golden, name: &str, which: &str) -> (Vec<T>, usize, usize) {
    let im = &g.images[name];
    let (h, w) = (
        im["h"].as_u64().unwrap() as usize,
        im["w"].as_u64().unwrap() as usize,
    );
    let v = im[which]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| T::from_f64(x.as_u64().unwrap() as f64 / 255.0))
        .collect();
    (v, h, w)
}

/// Largest absolute and relative differences from the golden values, over
/// the cases of one precision.
fn check_golden<T: Real>(dtype: &str) -> (f64, f64) {
    let g = golden();
    let (shipped, shipped_id) = shipped_lins();
    let (mut worst_abs, mut worst_rel) = (0.0f64, 0.0f64);
    let mut n = 0;
    for vgg in [1u64, 2] {
        let (convs, _) = formula_weights(vgg);
        for lin in ["shipped", "formula:3"] {
            let lins = if lin == "shipped" {
                shipped.clone()
            } else {
                formula_weights(3).1
            };
            let w = LpipsWeights::from_parts(
                convs.clone(),
                lins,
                memory("formula"),
                shipped_id.clone(),
            )
            .unwrap();
            let net = Lpips::<T>::new(&w);
            for c in &g.cases {
                if c["vgg_formula"] != vgg || c["lin"] != lin || c["dtype"] != dtype {
                    continue;
                }
                let conv = match c["convention"].as_str().unwrap() {
                    "d3dgs" => Convention::D3dgs,
                    _ => Convention::Normalize,
                };
                let name = c["image"].as_str().unwrap();
                let (a, h, wd) = image::<T>(&g, name, "a");
                let (b, _, _) = image::<T>(&g, name, "b");
                let got = net.distance(&a, &b, h, wd, conv).unwrap();
                let want = c["value"].as_f64().unwrap();
                let layers: Vec<f64> = c["per_layer"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|x| x.as_f64().unwrap())
                    .collect();
                for (g, w) in std::iter::once((got.value.to_f64(), want)).chain(
                    got.per_layer
                        .iter()
                        .map(|v| v.to_f64())
                        .zip(layers.iter().copied()),
                ) {
                    worst_abs = worst_abs.max((g - w).abs());
                    worst_rel = worst_rel.max((g - w).abs() / w.abs());
                }
                n += 1;
            }
        }
    }
    assert_eq!(n, 8, "golden cases of {dtype}");
    (worst_abs, worst_rel)
}

/// f64 against the package in f64 (`.double()`): the same arithmetic up to
/// summation order. Measured: worst relative difference 1.3e-14 (total and
/// per-layer values, 8 cases); the bound leaves a factor of about 80.
#[test]
fn lpips_f64_matches_the_lpips_package() {
    let (abs, rel) = check_golden::<f64>("f64");
    eprintln!("f64: worst abs {abs:.3e}, worst rel {rel:.3e}");
    assert!(rel < 1e-12, "worst relative difference {rel:e}");
}

/// f32 against the package in f32: both sum convolutions of up to 4,608
/// terms in f32, in different orders. Measured: worst absolute difference
/// 3.7e-9 (values 1e-3 to 5e-2), worst relative 4.1e-6 (a small per-layer
/// term); the bounds leave a factor of about 10.
#[test]
fn lpips_f32_matches_the_lpips_package() {
    let (abs, rel) = check_golden::<f32>("f32");
    eprintln!("f32: worst abs {abs:.3e}, worst rel {rel:.3e}");
    assert!(abs < 4e-8 && rel < 4e-5, "worst abs {abs:e}, rel {rel:e}");
}

/// The D-3DGS convention feeds [0,1] images as they are; `normalize`
/// feeds `2x − 1`. So `normalize` on `x` equals the D-3DGS convention on
/// `2x − 1` (exactly, in f64: `2x − 1` is computed the same way), and the two
/// conventions differ on the same images (the golden values too).
#[test]
fn the_two_conventions_are_the_d3dgs_quirk_both_ways() {
    let g = golden();
    let (convs, lins) = formula_weights(2);
    let w = LpipsWeights::from_parts(convs, lins, memory("a"), memory("b")).unwrap();
    let net = Lpips::<f64>::new(&w);
    let (a, h, wd) = image::<f64>(&g, "random_37x45", "a");
    let (b, _, _) = image::<f64>(&g, "random_37x45", "b");
    let n = net.distance(&a, &b, h, wd, Convention::Normalize).unwrap();
    let map = |v: &[f64]| v.iter().map(|x| 2.0 * x - 1.0).collect::<Vec<_>>();
    let d = net
        .distance(&map(&a), &map(&b), h, wd, Convention::D3dgs)
        .unwrap();
    assert_eq!(n.value.to_bits(), d.value.to_bits());
    let q = net.distance(&a, &b, h, wd, Convention::D3dgs).unwrap();
    assert!((q.value - n.value).abs() > 1e-3 * n.value.abs());
    // Identical images: exactly 0.
    assert_eq!(
        net.distance(&a, &a, h, wd, Convention::D3dgs)
            .unwrap()
            .value,
        0.0
    );
}

// ---- the .pth reader ----

fn expected() -> serde_json::Value {
    let text = std::fs::read_to_string(fixtures().join("pth/expected.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

fn check_tensor(f: &PthFile, name: &str, want: &serde_json::Value) {
    let shape: Vec<usize> = want["shape"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap() as usize)
        .collect();
    assert_eq!(f.shape(name).unwrap(), shape.as_slice(), "{name}");
    let values: Vec<f64> = want["values"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    assert_eq!(f.read_f64(name).unwrap(), values, "{name}");
}

#[test]
fn pth_reader_reads_torch_save_files_of_both_containers() {
    let exp = expected();
    for (tag, container) in [("zip", Container::Zip), ("legacy", Container::Legacy)] {
        let f = PthFile::open(&fixtures().join(format!("pth/tensors_{tag}.pth"))).unwrap();
        assert_eq!(f.container(), container);
        for name in [
            "f32",
            "f64",
            "f16",
            "bf16",
            "transposed",
            "base",
            "offset",
            "scalar",
        ] {
            check_tensor(&f, name, &exp[name]);
        }
        let m = PthFile::open(&fixtures().join(format!("pth/module_{tag}.pth"))).unwrap();
        assert_eq!(m.names().collect::<Vec<_>>(), ["0.weight", "0.bias"]);
        check_tensor(&m, "0.weight", &exp["module:0.weight"]);
        check_tensor(&m, "0.bias", &exp["module:0.bias"]);
        assert!(m.read_f64("1.weight").is_err());
    }
}

#[test]
fn the_shipped_linear_weights_are_read_from_the_package_file() {
    let path = fixtures().join("vgg.pth");
    assert_eq!(weights::sha256_file(&path).unwrap(), LPIPS_VGG_SHA256);
    let f = PthFile::open(&path).unwrap();
    assert_eq!(f.container(), Container::Legacy);
    let (lins, id) = shipped_lins();
    assert!(id.official);
    for (l, &c) in lins.iter().zip(&LINS) {
        assert_eq!(l.len(), c);
        // Trained LPIPS layers are non-negative and not all zero.
        assert!(l.iter().all(|&v| v >= 0.0) && l.iter().any(|&v| v > 0.0));
    }
}

// ---- a full backbone file, and bad weight files ----

/// A legacy-format `.pth` (as `torch.save(..., _use_new_zipfile_serialization=False)`
/// writes it) holding an OrderedDict of f32 tensors.
fn write_legacy_pth(path: &Path, tensors: &[(String, Vec<usize>, Vec<f32>)]) {
    fn s(out: &mut Vec<u8>, v: &str) {
        out.push(b'X');
        out.extend((v.len() as u32).to_le_bytes());
        out.extend(v.as_bytes());
    }
    fn int(out: &mut Vec<u8>, v: usize) {
        out.push(b'J');
        out.extend((v as i32).to_le_bytes());
    }
    let mut o = Vec::new();
    // Magic number, protocol version, system info.
    o.extend(b"\x80\x02\x8a\x0a\x6c\xfc\x9c\x46\xf9\x20\x6a\xa8\x50\x19.");
    o.extend(b"\x80\x02M\xe9\x03.");
    o.extend(b"\x80\x02}(");
    s(&mut o, "protocol_version");
    o.extend(b"M\xe9\x03");
    s(&mut o, "little_endian");
    o.push(0x88);
    o.extend(b"u.");
    // The object.
    o.extend(b"\x80\x02ccollections\nOrderedDict\n)R(");
    for (k, (name, shape, _)) in tensors.iter().enumerate() {
        s(&mut o, name);
        o.extend(b"ctorch._utils\n_rebuild_tensor_v2\n((");
        s(&mut o, "storage");
        o.extend(b"ctorch\nFloatStorage\n");
        s(&mut o, &k.to_string());
        s(&mut o, "cpu");
        int(&mut o, shape.iter().product());
        o.extend(b"tQK\x00(");
        for &d in shape {
            int(&mut o, d);
        }
        o.extend(b"t(");
        let mut stride = vec![1usize; shape.len()];
        for d in (0..shape.len().saturating_sub(1)).rev() {
            stride[d] = stride[d + 1] * shape[d + 1];
        }
        for st in stride {
            int(&mut o, st);
        }
        o.extend(b"t\x89NtR");
    }
    o.extend(b"u.");
    // Storage keys, then the storages.
    o.extend(b"\x80\x02](");
    for k in 0..tensors.len() {
        s(&mut o, &k.to_string());
    }
    o.extend(b"e.");
    for (_, _, data) in tensors {
        o.extend((data.len() as u64).to_le_bytes());
        for v in data {
            o.extend(v.to_le_bytes());
        }
    }
    std::fs::write(path, o).unwrap();
}

fn write_formula_vgg(path: &Path, base: u64) {
    let (convs, _) = formula_weights(base);
    let idx = liquid_splat::lpips::VGG16_CONV_INDEX;
    let mut t = Vec::new();
    for ((w, b), (&(cin, cout), i)) in convs.into_iter().zip(CONVS.iter().zip(idx)) {
        t.push((format!("features.{i}.weight"), vec![cout, cin, 3, 3], w));
        t.push((format!("features.{i}.bias"), vec![cout], b));
    }
    write_legacy_pth(path, &t);
}

#[test]
fn weights_load_from_files_and_bad_files_are_named_errors() {
    let d = tmp("files");
    let vgg = d.join("vgg16.pth");
    write_formula_vgg(&vgg, 1);
    let lin = fixtures().join("vgg.pth");

    // A complete file of the right shapes loads (as unofficial weights).
    let w = LpipsWeights::load(&vgg, &lin, Verify::Any).unwrap();
    assert!(!w.vgg.official && w.lin.official);
    assert_eq!(w.convs, formula_weights(1).0);
    assert_eq!(w.vgg.sha256, weights::sha256_file(&vgg).unwrap());
    // ... but is not the published backbone.
    let e = LpipsWeights::load(&vgg, &lin, Verify::Official).unwrap_err();
    assert!(
        e.to_string().contains("vgg16.pth") && e.to_string().contains("553433881"),
        "{e}"
    );

    let msg = |vgg: &Path, lin: &Path, v: Verify| {
        LpipsWeights::load(vgg, lin, v).unwrap_err().to_string()
    };
    // Missing files.
    let e = msg(&d.join("none.pth"), &lin, Verify::Any);
    assert!(e.contains("none.pth"), "{e}");
    let e = msg(&vgg, &d.join("nolin.pth"), Verify::Any);
    assert!(e.contains("nolin.pth"), "{e}");
    // Truncated backbone.
    let bytes = std::fs::read(&vgg).unwrap();
    let cut = d.join("cut.pth");
    for at in [10, 3000, bytes.len() / 2, bytes.len() - 1] {
        std::fs::write(&cut, &bytes[..at]).unwrap();
        let e = msg(&cut, &lin, Verify::Any);
        assert!(e.contains("cut.pth"), "{e}");
    }
    // Truncated linear weights: wrong size for the published file; unreadable otherwise.
    let lin_bytes = std::fs::read(&lin).unwrap();
    let lcut = d.join("lincut.pth");
    std::fs::write(&lcut, &lin_bytes[..lin_bytes.len() - 100]).unwrap();
    let e = LpipsWeights::read_lins(&lcut, Verify::Official)
        .unwrap_err()
        .to_string();
    assert!(e.contains("lincut.pth") && e.contains("truncated"), "{e}");
    let e = msg(&vgg, &lcut, Verify::Any);
    assert!(e.contains("lincut.pth"), "{e}");
    // Same size, one byte changed in the data: the SHA-256 names it.
    let mut changed = lin_bytes.clone();
    let n = changed.len();
    changed[n - 5] ^= 1;
    let lbad = d.join("linhash.pth");
    std::fs::write(&lbad, &changed).unwrap();
    let e = LpipsWeights::read_lins(&lbad, Verify::Official)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("linhash.pth") && e.contains("SHA-256") && e.contains(LPIPS_VGG_SHA256),
        "{e}"
    );
    let (_, id) = LpipsWeights::read_lins(&lbad, Verify::Any).unwrap();
    assert!(!id.official);
    // Wrong shapes and missing tensors.
    let p = fixtures().join("pth");
    let e = msg(&vgg, &p.join("lin_wrong_shape.pth"), Verify::Any);
    assert!(
        e.contains("lin2.model.1.weight") && e.contains("255"),
        "{e}"
    );
    let e = msg(&p.join("vgg_wrong_shape.pth"), &lin, Verify::Any);
    assert!(
        e.contains("features.0.weight") && e.contains("[64, 3, 5, 5]"),
        "{e}"
    );
    let e = msg(&p.join("vgg_missing.pth"), &lin, Verify::Any);
    assert!(e.contains("missing tensor `features.2.weight`"), "{e}");
    // Not a PyTorch file at all.
    let junk = d.join("junk.pth");
    std::fs::write(&junk, b"hello").unwrap();
    let e = msg(&junk, &lin, Verify::Any);
    assert!(
        e.contains("junk.pth") && e.contains("not a PyTorch file"),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(&d);
}

// ---- the commands ----

/// `train` and `eval` report LPIPS per view and mean when weights are given
/// (labelled with the convention and the weight files), and never without.
#[test]
fn train_and_eval_report_lpips_only_with_weights() {
    let d = tmp("cli");
    let vgg = d.join("vgg16-formula.pth");
    write_formula_vgg(&vgg, 1);
    let lin = fixtures().join("vgg.pth");
    let (vs, ls) = (vgg.to_str().unwrap(), lin.to_str().unwrap());
    let out = d.join("run");
    let o = out.to_str().unwrap();
    let base = [
        "train",
        "--scene",
        "swing",
        "--resolution",
        "24",
        "--iterations",
        "6",
        "--init-points",
        "100",
        "--depth",
        "2",
        "--width",
        "8",
        "--eval-every",
        "3",
        "--quiet",
        "--out",
        o,
    ];
    // Not the published backbone: refused unless --lpips-unverified.
    let mut args = base.to_vec();
    args.extend(["--lpips-vgg", vs, "--lpips-lin", ls]);
    let r = cli(&args);
    assert_eq!(r.status.code(), Some(2), "{}", text(&r));
    assert!(text(&r).contains("vgg16-formula.pth"), "{}", text(&r));
    args.push("--lpips-unverified");
    let r = cli(&args);
    assert!(r.status.success(), "{}", text(&r));
    assert!(text(&r).contains("LPIPS"), "{}", text(&r));
    let results = json(&out.join("results.json"));
    let per_view = json(&out.join("per_view.json"));
    let mean = results["lpips"].as_f64().unwrap();
    assert!(mean > 0.0 && mean < 1.0, "{mean}");
    assert_eq!(results["lpips_info"]["convention"], "d3dgs");
    assert_eq!(results["lpips_info"]["vgg"]["official"], false);
    assert_eq!(results["lpips_info"]["lin"]["official"], true);
    let views = per_view["lpips"].as_object().unwrap();
    assert_eq!(views.len(), 8);
    let avg = views.values().map(|v| v.as_f64().unwrap()).sum::<f64>() / 8.0;
    assert!((avg - mean).abs() < 1e-12);
    let curve = json(&out.join("checkpoints/iteration_000006/curve.json"));
    let evals: Vec<&serde_json::Value> = curve
        .as_array()
        .unwrap()
        .iter()
        .filter(|p| p["test_lpips"].is_number())
        .collect();
    assert_eq!(evals.len(), 2, "{curve}");
    assert_eq!(evals[1]["test_lpips"].as_f64().unwrap(), mean);

    // eval from the saved PNGs: the same numbers.
    let r = cli(&[
        "eval",
        o,
        "--lpips-vgg",
        vs,
        "--lpips-lin",
        ls,
        "--lpips-unverified",
    ]);
    assert!(r.status.success(), "{}", text(&r));
    assert_eq!(json(&out.join("results.json")), results);
    assert_eq!(json(&out.join("per_view.json")), per_view);
    // The other convention: another number, labelled as such.
    let r = cli(&[
        "eval",
        o,
        "--lpips-vgg",
        vs,
        "--lpips-lin",
        ls,
        "--lpips-unverified",
        "--lpips-normalize",
    ]);
    assert!(r.status.success(), "{}", text(&r));
    let n = json(&out.join("results.json"));
    assert_eq!(n["lpips_info"]["convention"], "normalize");
    assert_ne!(n["lpips"], results["lpips"]);
    // Without weights: no LPIPS key anywhere, and the output says so.
    let r = cli(&["eval", o]);
    assert!(r.status.success(), "{}", text(&r));
    assert!(text(&r).contains("LPIPS not computed"), "{}", text(&r));
    let plain = json(&out.join("results.json"));
    assert!(plain.get("lpips").is_none() && plain.get("lpips_info").is_none());
    assert!(json(&out.join("per_view.json")).get("lpips").is_none());
    assert_eq!(plain["psnr"], results["psnr"]);
    // A missing weight file: exit 2, named.
    let r = cli(&["eval", o, "--lpips-vgg", "nowhere.pth", "--lpips-lin", ls]);
    assert_eq!(r.status.code(), Some(2), "{}", text(&r));
    assert!(text(&r).contains("nowhere.pth"), "{}", text(&r));
    let _ = std::fs::remove_dir_all(&d);
}

/// The experiment report gives, for every run, the final metrics and the
/// best of the periodic evaluations with their iterations, labelled.
#[test]
fn experiment_reports_final_and_best_of_evaluations_with_lpips() {
    let d = tmp("exp");
    let vgg = d.join("vgg16-formula.pth");
    write_formula_vgg(&vgg, 1);
    let lin = fixtures().join("vgg.pth");
    let out = d.join("exp");
    let r = cli(&[
        "experiment",
        "--scenes",
        "swing",
        "--iterations",
        "6",
        "--resolution",
        "16",
        "--init-points",
        "100",
        "--evals",
        "3",
        "--sweep-times",
        "5",
        "--out",
        out.to_str().unwrap(),
        "--lpips-vgg",
        vgg.to_str().unwrap(),
        "--lpips-lin",
        lin.to_str().unwrap(),
        "--lpips-unverified",
    ]);
    assert!(r.status.success(), "{}", text(&r));
    let rec = json(&out.join("runs/swing__cfc-d6-w128-gelu__seed0.json"));
    let best = &rec["best"];
    assert_eq!(best["evaluations"], 3);
    // The best is the best of the curve's evaluations, at the iteration recorded.
    let curve = rec["curves"].as_array().unwrap();
    let evals: Vec<(u64, f64, f64)> = curve
        .iter()
        .filter(|p| p["test_psnr"].is_number())
        .map(|p| {
            (
                p["iteration"].as_u64().unwrap(),
                p["test_psnr"].as_f64().unwrap(),
                p["test_lpips"].as_f64().unwrap(),
            )
        })
        .collect();
    assert_eq!(evals.iter().map(|e| e.0).collect::<Vec<_>>(), [2, 4, 6]);
    let bp = evals
        .iter()
        .fold(evals[0], |b, e| if e.1 > b.1 { *e } else { b });
    let bl = evals
        .iter()
        .fold(evals[0], |b, e| if e.2 < b.2 { *e } else { b });
    assert_eq!(best["psnr"]["value"].as_f64().unwrap(), bp.1);
    assert_eq!(best["psnr"]["iteration"].as_u64().unwrap(), bp.0);
    assert_eq!(best["lpips"]["value"].as_f64().unwrap(), bl.2);
    assert_eq!(best["lpips"]["iteration"].as_u64().unwrap(), bl.0);
    // The final metrics are the last evaluation's.
    assert_eq!(rec["test_psnr"].as_f64().unwrap(), evals[2].1);
    assert_eq!(rec["test_lpips"].as_f64().unwrap(), evals[2].2);
    let md = std::fs::read_to_string(out.join("report.md")).unwrap();
    for needle in [
        "Best of the periodic test evaluations",
        "best PSNR (iteration)",
        "best LPIPS (iteration)",
        "final LPIPS",
        "D-3DGS convention",
        "not the published file",
    ] {
        assert!(md.contains(needle), "report.md lacks {needle:?}:\n{md}");
    }
    let csv = std::fs::read_to_string(out.join("runs.csv")).unwrap();
    assert!(csv.lines().next().unwrap().contains("best_lpips_iteration"));
    let _ = std::fs::remove_dir_all(&d);
}
