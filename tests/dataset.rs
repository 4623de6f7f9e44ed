//! Dataset loading, the scene generator, the committed fixtures, bad input, and the real
//! D-NeRF scenes when the shared data folder is present.

mod support;

use liquid_splat::dataset::synth::{self, Layout, SynthOptions};
use liquid_splat::dataset::{self, Background, Dataset, DatasetKind, LoadOptions, NerfiesSplit};
use liquid_splat::gaussians::{init, Gaussians};
use liquid_splat::io::png::{decode as decode_png, encode as encode_png};
use std::path::{Path, PathBuf};
use support::tmp;

fn small() -> SynthOptions {
    SynthOptions {
        resolution: 16,
        frames: 4,
        eval_frames: 2,
        init_points: 1000,
        ..Default::default()
    }
}

/// Every file under `dir`, relative path → bytes, in sorted order.
fn tree(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    fn walk(root: &Path, d: &Path, out: &mut Vec<(PathBuf, Vec<u8>)>) {
        let mut entries: Vec<_> = std::fs::read_dir(d)
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        entries.sort();
        for p in entries {
            if p.is_dir() {
                walk(root, &p, out);
            } else {
                out.push((
                    p.strip_prefix(root).unwrap().to_path_buf(),
                    std::fs::read(&p).unwrap(),
                ));
            }
        }
    }
    let mut out = vec![];
    walk(dir, dir, &mut out);
    out
}

#[test]
fn written_scene_loads_as_the_builtin() {
    for bg in [Background::Black, Background::White] {
        let dir = tmp(&format!("builtin-{bg:?}"));
        let opts = SynthOptions {
            background: bg,
            ..small()
        };
        synth::write("swing", &dir, &opts, Layout::DNerf).unwrap();
        let lo = LoadOptions {
            background: bg,
            init_points: 1000,
            ..Default::default()
        };
        let loaded = dataset::load(&dir, &lo).unwrap();
        let built = synth::builtin("swing", &opts).unwrap();
        assert_eq!(loaded.kind, DatasetKind::DNerf);
        assert_eq!(
            Dataset {
                kind: DatasetKind::DNerf,
                ..built
            },
            loaded
        );
        assert_eq!(
            (loaded.train.len(), loaded.val.len(), loaded.test.len()),
            (4, 2, 2)
        );
        assert_eq!(loaded.train[3].time, 1.0);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}

#[test]
fn synthetic_scenes_are_deterministic_and_not_empty() {
    for name in ["bouncing", "swing", "blob"] {
        let (a, b) = (tmp(&format!("det-a-{name}")), tmp(&format!("det-b-{name}")));
        synth::write(name, &a, &small(), Layout::DNerf).unwrap();
        synth::write(name, &b, &small(), Layout::DNerf).unwrap();
        assert_eq!(tree(&a), tree(&b));
        let ds = dataset::load(&a, &LoadOptions::default()).unwrap();
        for f in ds.train.iter().chain(&ds.test) {
            let lit = f.image.iter().filter(|&&v| v > 0.0).count();
            assert!(
                lit > 10 && lit < f.image.len() * 9 / 10,
                "{name} {}: {lit} lit values",
                f.name
            );
        }
        // Motion: the first and last training frames differ... and so do scenes.
        assert_ne!(ds.train[0].image, ds.train[3].image);
        std::fs::remove_dir_all(&a).unwrap();
        std::fs::remove_dir_all(&b).unwrap();
    }
    assert!(synth::builtin("nope", &small()).is_err());
}

#[test]
fn nerfies_layout_loads() {
    let root = tmp("nerfies");
    let dir = root.join("scene");
    let opts = SynthOptions {
        frames: 6,
        ..small()
    };
    synth::write("bouncing", &dir, &opts, Layout::Nerfies).unwrap();
    let lo = LoadOptions {
        nerfies_split: NerfiesSplit::TrainVal,
        nerfies_ratio: Some(1.0),
        ..Default::default()
    };
    let ds = dataset::load(&dir, &lo).unwrap();
    assert_eq!(ds.kind, DatasetKind::Nerfies);
    assert_eq!(
        ds.train.iter().map(|f| f.name.as_str()).collect::<Vec<_>>(),
        ["00000", "00002", "00004"]
    );
    assert_eq!(ds.test.len(), 3);
    // fid = time_id / max(time_id) = i / 5.
    assert_eq!(ds.test[2].time, 5.0 / 5.0);
    assert_eq!(ds.train[1].time, 2.0 / 5.0);
    // The camera looks at the origin from distance 4.
    let c = ds.train[0].camera.centre();
    assert!(((c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt() - 4.0).abs() < 1e-9);
    assert!((ds.train[0].camera.fov_x - opts.fov).abs() < 1e-12);
    assert!(ds.warnings.is_empty());
    match &ds.init {
        dataset::InitialPoints::Cloud { xyz, rgb } => {
            assert_eq!(xyz.len(), 3 * 2000);
            assert!(rgb.is_none());
        }
        other => panic!("{other:?}"),
    }
    // Upstream's rule for a parent folder not named NeRF*/vrig*/interp*: every 4th id, ratio 0.5.
    let ds = dataset::load(&dir, &LoadOptions::default()).unwrap();
    assert_eq!(ds.train.len(), 2);
    assert_eq!((ds.train[0].width, ds.train[0].height), (8, 8));
    assert!(ds.test.is_empty());
    // An off-centre principal point is reported.
    let cam = dir.join("camera/00000.json");
    let text = std::fs::read_to_string(&cam).unwrap();
    std::fs::write(&cam, text.replacen("8.0,", "11.0,", 1)).unwrap();
    let ds = dataset::load(&dir, &lo).unwrap();
    assert_eq!(ds.warnings.len(), 1, "{:?}", ds.warnings);
    std::fs::remove_dir_all(dir.parent().unwrap()).unwrap();
}

#[test]
fn downscale_and_initial_gaussians() {
    let dir = tmp("down");
    synth::write("blob", &dir, &small(), Layout::DNerf).unwrap();
    let full = dataset::load(&dir, &LoadOptions::default()).unwrap();
    let lo = LoadOptions {
        downscale: 4,
        init_points: 300,
        ..Default::default()
    };
    let d4 = dataset::load(&dir, &lo).unwrap();
    let f = &d4.train[1];
    assert_eq!((f.width, f.height, f.camera.width), (4, 4, 4));
    assert_eq!(f.camera.fov_x, full.train[1].camera.fov_x);
    // Pixel (1, 2) of channel 0 is the rounded mean of its 4×4 block in bytes.
    let g = &full.train[1].image;
    let mut sum = 0u32;
    for y in 8..12 {
        for x in 4..8 {
            sum += (g[y * 16 + x] * 255.0).round() as u32;
        }
    }
    assert_eq!(f.image[2 * 4 + 1], ((sum + 8) / 16) as f32 / 255.0);
    let gs: Gaussians<f32> = init::initial_gaussians(&d4.init).unwrap();
    assert_eq!(gs.len(), 300);
    std::fs::remove_dir_all(&dir).unwrap();
}

fn fixtures() -> PathBuf {
    support::fixture("scenes")
}

#[test]
fn fixtures_regenerate_identically() {
    // The commands in fixtures/README.md.
    let cases = [
        (
            "bouncing",
            "bouncing",
            Layout::DNerf,
            SynthOptions::default(),
        ),
        ("swing", "swing", Layout::DNerf, SynthOptions::default()),
        ("blob", "blob", Layout::DNerf, SynthOptions::default()),
        (
            "blob-nerfies",
            "blob",
            Layout::Nerfies,
            SynthOptions {
                frames: 12,
                ..Default::default()
            },
        ),
    ];
    for (dir_name, scene, layout, opts) in cases {
        let committed = fixtures().join(dir_name);
        let out = tmp(&format!("fx-{dir_name}"));
        synth::write(scene, &out, &opts, layout).unwrap();
        let (a, b) = (tree(&committed), tree(&out));
        assert_eq!(
            a.iter().map(|x| &x.0).collect::<Vec<_>>(),
            b.iter().map(|x| &x.0).collect::<Vec<_>>()
        );
        let total: usize = a.iter().map(|x| x.1.len()).sum();
        assert!(total < 1 << 20, "{dir_name}: {total} bytes");
        for ((p, x), (_, y)) in a.iter().zip(&b) {
            if p.extension().is_some_and(|e| e == "png") {
                let (ix, iy) = (decode_png(p, x).unwrap(), decode_png(p, y).unwrap());
                assert_eq!(ix, iy, "{dir_name}/{}: decoded pixels differ", p.display());
            }
            assert!(x == y, "{dir_name}/{}: bytes differ", p.display());
        }
        std::fs::remove_dir_all(&out).unwrap();
    }
}

/// Copy a fresh small D-NeRF scene, apply `edit`, load, and return the error message.
fn broken(name: &str, edit: impl FnOnce(&Path)) -> String {
    let dir = tmp(&format!("bad-{name}"));
    synth::write("bouncing", &dir, &small(), Layout::DNerf).unwrap();
    edit(&dir);
    let e = dataset::load(&dir, &LoadOptions::default())
        .expect_err(name)
        .to_string();
    std::fs::remove_dir_all(&dir).unwrap();
    e
}

fn edit_json(dir: &Path, file: &str, f: impl FnOnce(&mut serde_json::Value)) {
    let p = dir.join(file);
    let mut v: serde_json::Value = serde_json::from_slice(&std::fs::read(&p).unwrap()).unwrap();
    f(&mut v);
    std::fs::write(&p, serde_json::to_string(&v).unwrap()).unwrap();
}

#[test]
fn bad_input_is_a_named_error() {
    let e = broken("missing-image", |d| {
        std::fs::remove_file(d.join("test/r_001.png")).unwrap()
    });
    assert!(e.contains("r_001.png"), "{e}");
    let e = broken("missing-test", |d| {
        std::fs::remove_file(d.join("transforms_test.json")).unwrap()
    });
    assert!(e.contains("transforms_test.json"), "{e}");
    let e = broken("time-type", |d| {
        edit_json(d, "transforms_train.json", |v| {
            v["frames"][2]["time"] = "soon".into()
        })
    });
    assert!(
        e.contains("transforms_train.json") && e.contains("frames[2].time") && e.contains("string"),
        "{e}"
    );
    let e = broken("fov-type", |d| {
        edit_json(d, "transforms_val.json", |v| {
            v["camera_angle_x"] = serde_json::json!([1])
        })
    });
    assert!(
        e.contains("transforms_val.json") && e.contains("camera_angle_x"),
        "{e}"
    );
    let e = broken("fov-tiny", |d| {
        edit_json(d, "transforms_train.json", |v| {
            v["camera_angle_x"] = serde_json::json!(1e-300)
        })
    });
    assert!(
        e.contains("transforms_train.json") && e.contains("camera_angle_x") && e.contains("1e-300"),
        "{e}"
    );
    // A folder where the point cloud goes was passed over (random points).
    let e = broken("ply-folder", |d| {
        let p = d.join("points3d.ply");
        let _ = std::fs::remove_file(&p);
        std::fs::create_dir(p).unwrap();
    });
    assert!(e.contains("points3d.ply"), "{e}");
    let e = broken("far-cameras", |d| {
        edit_json(d, "transforms_train.json", |v| {
            v["frames"][0]["transform_matrix"][0][3] = serde_json::json!(1e308);
            v["frames"][1]["transform_matrix"][0][3] = serde_json::json!(-1e308);
        })
    });
    assert!(
        e.contains("transforms_train.json")
            && e.contains("too far apart")
            && e.contains("training camera ")
            && e.contains("e308"),
        "{e}"
    );
    let e = broken("matrix-shape", |d| {
        edit_json(d, "transforms_train.json", |v| {
            v["frames"][0]["transform_matrix"][1] = serde_json::json!([1, 2])
        })
    });
    assert!(e.contains("frames[0].transform_matrix[1]"), "{e}");
    let e = broken("nan", |d| {
        let p = d.join("transforms_test.json");
        let mut v: serde_json::Value = serde_json::from_slice(&std::fs::read(&p).unwrap()).unwrap();
        v["frames"][1]["transform_matrix"][2][3] = "PLACEHOLDER".into();
        let s = serde_json::to_string(&v)
            .unwrap()
            .replace("\"PLACEHOLDER\"", "NaN");
        std::fs::write(&p, s).unwrap();
    });
    assert!(
        e.contains("transforms_test.json")
            && e.contains("frames[1].transform_matrix[2][3]")
            && e.contains("NaN"),
        "{e}"
    );
    let e = broken("empty", |d| {
        edit_json(d, "transforms_val.json", |v| {
            v["frames"] = serde_json::json!([])
        })
    });
    assert!(
        e.contains("transforms_val.json") && e.contains("frames") && e.contains("empty"),
        "{e}"
    );
    let e = broken("size", |d| {
        let png = encode_png(8, 8, 4, &[255u8; 8 * 8 * 4]).unwrap();
        std::fs::write(d.join("val/r_000.png"), png).unwrap();
    });
    assert!(e.contains("val/r_000.png") && e.contains("8x8"), "{e}");
    let e = broken("mode", |d| {
        let mut png = Vec::new();
        use image::{codecs::png::PngEncoder, ExtendedColorType, ImageEncoder};
        PngEncoder::new(&mut png)
            .write_image(&vec![0u8; 16 * 16 * 8], 16, 16, ExtendedColorType::Rgba16)
            .unwrap();
        std::fs::write(d.join("train/r_002.png"), png).unwrap();
    });
    assert!(e.contains("train/r_002.png") && e.contains("Rgba16"), "{e}");
    let e = broken("garbage-png", |d| {
        std::fs::write(d.join("train/r_000.png"), b"xx").unwrap()
    });
    assert!(e.contains("train/r_000.png"), "{e}");
    let e = broken("bad-json", |d| {
        std::fs::write(d.join("transforms_train.json"), b"{").unwrap()
    });
    assert!(
        e.contains("transforms_train.json") && e.contains("invalid JSON"),
        "{e}"
    );
}

#[test]
fn bad_nerfies_input_is_a_named_error() {
    let root = tmp("bad-nerfies");
    let dir = root.join("scene");
    synth::write("blob", &dir, &small(), Layout::Nerfies).unwrap();
    let lo = LoadOptions {
        nerfies_split: NerfiesSplit::TrainVal,
        ..Default::default()
    };
    // Each value is named by its own field.
    for (field, value) in [
        ("focal_length", serde_json::json!(1e-300)),
        ("focal_length", serde_json::json!(0.0)),
        ("focal_length", serde_json::json!(-5.0)),
        ("image_size", serde_json::json!([1e300, 16])),
        ("image_size", serde_json::json!([0, 16])),
    ] {
        let keep = std::fs::read(dir.join("camera/00002.json")).unwrap();
        edit_json(&dir, "camera/00002.json", |v| v[field] = value.clone());
        let e = dataset::load(&dir, &lo).unwrap_err().to_string();
        assert!(
            e.contains("00002.json") && e.contains(&format!("`{field}`")),
            "{field} {value}: {e}"
        );
        std::fs::write(dir.join("camera/00002.json"), keep).unwrap();
    }
    edit_json(&dir, "camera/00002.json", |v| {
        v["focal_length"] = serde_json::Value::Null
    });
    let e = dataset::load(&dir, &lo).unwrap_err().to_string();
    assert!(
        e.contains("00002.json") && e.contains("focal_length") && e.contains("null"),
        "{e}"
    );
    std::fs::remove_file(dir.join("camera/00002.json")).unwrap();
    let e = dataset::load(&dir, &lo).unwrap_err().to_string();
    assert!(e.contains("00002.json"), "{e}");
    edit_json(&dir, "dataset.json", |v| {
        v["train_ids"] = serde_json::json!([])
    });
    let e = dataset::load(&dir, &lo).unwrap_err().to_string();
    assert!(e.contains("dataset.json") && e.contains("empty"), "{e}");
    std::fs::remove_dir_all(dir.parent().unwrap()).unwrap();
}

#[test]
fn cli_exits_2_on_bad_input() {
    let dir = tmp("cli");
    let run = |args: &[&str]| support::cli(args);
    let out = run(&["inspect", dir.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).starts_with("error: "));
    assert_eq!(
        run(&["synth", "nope", dir.join("x").to_str().unwrap()])
            .status
            .code(),
        Some(2)
    );
    let scene = dir.join("s");
    let out = run(&[
        "synth",
        "blob",
        scene.to_str().unwrap(),
        "--resolution",
        "16",
        "--frames",
        "3",
    ]);
    assert_eq!(out.status.code(), Some(0));
    let out = run(&["inspect", scene.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(0));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["kind"], "dnerf");
    assert_eq!(v["frames"]["train"], 3);
    assert_eq!(v["image_size"], serde_json::json!([16, 16]));
    // The initial points `train` would start from: its default, and its option.
    assert_eq!(v["initial_points"]["count"], 2000);
    let out = run(&["inspect", scene.to_str().unwrap(), "--init-points", "50"]);
    assert_eq!(out.status.code(), Some(0));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["initial_points"]["count"], 50);
    std::fs::remove_dir_all(&dir).unwrap();
}

fn shared_data(scene: &str) -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/data/dnerf")
        .join(scene);
    if p.is_dir() {
        Some(p)
    } else {
        eprintln!("SKIPPED: {} is absent", p.display());
        None
    }
}

#[test]
fn shared_data_lego_loads() {
    let Some(dir) = shared_data("lego") else {
        return;
    };
    let lo = LoadOptions {
        downscale: 8,
        background: Background::White,
        ..Default::default()
    };
    let ds = dataset::load(&dir, &lo).unwrap();
    assert_eq!(ds.val.len(), 11);
    assert!(ds.val.iter().any(|f| f.name == "r_0"), "unpadded val names");
    assert!(ds.test.iter().any(|f| f.name == "r_000"));
    let f = &ds.train[0];
    assert_eq!((f.width, f.height), (100, 100));
    assert_eq!(f.camera.fov_y, 0.6911112070083618);
    assert!(ds.train.iter().all(|f| (0.0..=1.0).contains(&f.time)));
    assert!(ds.scene_extent > 3.0 && ds.scene_extent < 6.0);
    // D-NeRF cameras look at the origin: the upstream formula agrees. The stored matrices are
    // f32-rounded, so their rotation is orthonormal only to ~1e-7: upstream inverts it while
    // the correct conversion transposes it, hence tolerances at that level.
    let text = std::fs::read_to_string(dir.join("transforms_train.json")).unwrap();
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    let m = &v["frames"][0]["transform_matrix"];
    let c2w: [[f64; 4]; 4] =
        std::array::from_fn(|i| std::array::from_fn(|j| m[i][j].as_f64().unwrap()));
    let (r, t) = dataset::dnerf::upstream_w2c(c2w).unwrap();
    for i in 0..3 {
        assert!(
            (t[i] - f.camera.translation[i]).abs() < 1e-5,
            "{t:?} {:?}",
            f.camera.translation
        );
        for (a, b) in r[i].iter().zip(&f.camera.rotation[i]) {
            assert!((a - b).abs() < 1e-6);
        }
    }
}

#[test]
fn shared_data_hellwarrior_loads() {
    let Some(dir) = shared_data("hellwarrior") else {
        return;
    };
    let lo = LoadOptions {
        downscale: 8,
        splits: dataset::Splits {
            train: true,
            val: false,
            test: false,
        },
        ..Default::default()
    };
    let ds = dataset::load(&dir, &lo).unwrap();
    assert!(!ds.train.is_empty() && ds.test.is_empty());
    assert_eq!((ds.train[0].width, ds.train[0].height), (100, 100));
    assert!(ds
        .train
        .iter()
        .all(|f| f.image.iter().all(|v| (0.0..=1.0).contains(v))));
}
