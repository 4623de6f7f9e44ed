//! Training: bit-exact reproduction across thread counts and against a
//! recorded hash, checkpoint/resume, and damaged checkpoints.

mod support;

use liquid_splat::dataset::Dataset;
use liquid_splat::deform::{Activation, CfcConfig, FieldConfig, MlpConfig};
use liquid_splat::train::{self, checkpoint, Event, RunOptions, TrainConfig, Trainer};
use std::path::Path;
use support::{copy_dir, tmp};

use support::swing as scene;

/// The small CfC field of the short runs.
fn cfc_field() -> FieldConfig {
    FieldConfig::Cfc(CfcConfig {
        depth: 2,
        width: 8,
        backbone_units: 8,
        backbone_layers: 1,
        activation: Activation::Gelu,
        ..CfcConfig::paper()
    })
}

/// A small 6-DoF (SE(3)) MLP field: its warp sends a gradient of its own to
/// the canonical means (`Rᵀ·g`), which the recorded state includes.
fn mlp_6dof_field() -> FieldConfig {
    FieldConfig::Mlp(MlpConfig {
        depth: 4,
        width: 16,
        is_6dof: true,
        ..MlpConfig::paper()
    })
}

/// The small CfC field and a schedule compressed so that a short run passes
/// through warm-up, SH degree increases, densification (clone, split, prune)
/// and opacity resets.
fn config(iterations: u64) -> TrainConfig {
    config_with(iterations, cfc_field())
}

fn config_with(iterations: u64, field: FieldConfig) -> TrainConfig {
    let mut c = TrainConfig::new(iterations, 7, field);
    c.schedule.warm_up = 20;
    c.schedule.sh_degree_interval = 15;
    c.schedule.densify_from = 10;
    c.schedule.densify_until = 100;
    c.schedule.densification_interval = 15;
    c.schedule.opacity_reset_interval = 50;
    c.densify.screen_size_after = 50;
    c
}

fn train_in_pool<T: liquid_splat::math::Real>(
    threads: usize,
    data: &Dataset,
    iterations: u64,
    field: FieldConfig,
) -> Trainer<T> {
    support::with_threads(threads, || {
        let views = train::run::views::<T>(&data.train);
        let g = liquid_splat::gaussians::init::initial_gaussians::<T>(&data.init).unwrap();
        let mut t = Trainer::new(
            config_with(iterations, field),
            g,
            views.len(),
            data.scene_extent,
            [0.0; 3],
        )
        .unwrap();
        let (mut densified, mut resets) = (0, 0);
        while t.iteration() < iterations {
            let r = t.step(&views).unwrap();
            assert!(
                r.loss.is_finite(),
                "iteration {}: loss {}",
                r.iteration,
                r.loss
            );
            densified += r.densify.is_some() as u32;
            resets += r.opacity_reset as u32;
        }
        assert!(
            densified >= 5 && resets >= 1,
            "{densified} densifications, {resets} resets"
        );
        assert!(t.optimizer().field.step > 0);
        t
    })
}

/// The record the training hashes are compared with
/// (fixtures/training/record.json): the CfC run and the 6-DoF MLP run.
#[derive(serde::Deserialize, serde::Serialize, Debug, PartialEq, Clone)]
struct Record {
    crate_version: String,
    math_library: String,
    scene: String,
    iterations: u64,
    state_hash_f32: String,
    state_hash_f64: String,
    #[serde(default)]
    scene_6dof: String,
    #[serde(default)]
    state_hash_f32_6dof: String,
    #[serde(default)]
    state_hash_f64_6dof: String,
}

const ITERATIONS: u64 = 120;

/// Serialises the read-modify-write of the record between the tests below.
static RECORD: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Compare the fields `set` fills (and the versions) with the record; with
/// `LIQUID_SPLAT_RECORD=1`, write them first.
fn check_record(set: impl Fn(&mut Record)) {
    let _guard = RECORD.lock().unwrap_or_else(|e| e.into_inner());
    let path = support::fixture("training/record.json");
    let load = || -> Record { serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap() };
    let mut got = load();
    got.crate_version = env!("CARGO_PKG_VERSION").into();
    got.math_library = "libm 0.2.11; matrix products: fused multiply-add; f32 field activations and rasterizer exp: liquid_splat::deform::fastmath".into();
    got.iterations = ITERATIONS;
    set(&mut got);
    if std::env::var_os("LIQUID_SPLAT_RECORD").is_some() {
        std::fs::write(&path, serde_json::to_string_pretty(&got).unwrap() + "\n").unwrap();
    }
    assert_eq!(
        got,
        load(),
        "the training run no longer reproduces the recorded state; if the change is intended, \
         rerun with LIQUID_SPLAT_RECORD=1 and commit fixtures/training/record.json"
    );
}

/// The f32 hash with 1, 2 and 3 threads and the f64 hash with `f64_threads`,
/// each required equal across thread counts.
fn hashes(data: &Dataset, field: FieldConfig, f64_threads: &[usize]) -> (u64, u64) {
    let h32: Vec<u64> = [1, 2, 3]
        .iter()
        .map(|&n| train_in_pool::<f32>(n, data, ITERATIONS, field).state_hash())
        .collect();
    assert!(
        h32.iter().all(|&h| h == h32[0]),
        "{field:?}: f32 hashes differ by thread count: {h32:x?}"
    );
    let h64: Vec<u64> = f64_threads
        .iter()
        .map(|&n| train_in_pool::<f64>(n, data, ITERATIONS, field).state_hash())
        .collect();
    assert!(
        h64.iter().all(|&h| h == h64[0]),
        "{field:?}: f64 hashes differ by thread count: {h64:x?}"
    );
    (h32[0], h64[0])
}

#[test]
fn training_is_bit_identical_for_1_2_and_3_threads_and_matches_the_record() {
    let (h32, h64) = hashes(&scene(), cfc_field(), &[2, 1]);
    check_record(|r| {
        r.scene = "fixtures/scenes/swing, 300 random initial points (seed 0), CfC D2 W8 gelu backbone 8x1, seed 7, tests/train.rs config()".into();
        r.state_hash_f32 = format!("{h32:016x}");
        r.state_hash_f64 = format!("{h64:016x}");
    });
}

#[test]
fn training_6dof_is_bit_identical_for_1_2_and_3_threads_and_matches_the_record() {
    let (h32, h64) = hashes(&scene(), mlp_6dof_field(), &[1, 2, 3]);
    check_record(|r| {
        r.scene_6dof = "fixtures/scenes/swing, 300 random initial points (seed 0), MLP D4 W16 6-DoF (SE(3)) synthetic, seed 7, tests/train.rs config_with(mlp_6dof_field())".into();
        r.state_hash_f32_6dof = format!("{h32:016x}");
        r.state_hash_f64_6dof = format!("{h64:016x}");
    });
}

fn run(
    config: &TrainConfig,
    data: &Dataset,
    out: &Path,
    every: u64,
    resume: bool,
) -> train::RunSummary {
    let opts = RunOptions {
        out: out.to_path_buf(),
        checkpoint_every: every,
        eval_every: 0,
        resume,
        data_name: "fixtures/scenes/swing".into(),
        lpips: None,
    };
    train::run::<f32>(config, data, &opts, &mut |_: Event| {}).unwrap()
}

fn binding(data: &Dataset) -> checkpoint::DataBinding {
    checkpoint::DataBinding::of(data, "fixtures/scenes/swing")
}

#[test]
fn resumed_run_ends_bit_identical_to_the_uninterrupted_run() {
    let data = scene();
    let cfg = config(90);
    let a = tmp("full");
    let full = run(&cfg, &data, &a, 30, false);
    assert_eq!(full.iterations_run, 90);
    for it in [30, 60] {
        // "Interrupted" after the checkpoint at `it`, with a half-written
        // later checkpoint left behind.
        let b = tmp(&format!("resumed{it}"));
        let name = checkpoint::checkpoint_name(it);
        copy_dir(
            &a.join("checkpoints").join(&name),
            &b.join("checkpoints").join(&name),
        );
        let partial = b
            .join("checkpoints")
            .join(format!("{}.partial", checkpoint::checkpoint_name(it + 30)));
        std::fs::create_dir_all(&partial).unwrap();
        std::fs::write(partial.join(checkpoint::STATE_FILE), b"half").unwrap();
        let resumed = run(&cfg, &data, &b, 30, true);
        assert_eq!(resumed.iterations_run, 90 - it);
        assert_eq!(resumed.state_hash, full.state_hash);
        assert_eq!(resumed.psnr.to_bits(), full.psnr.to_bits());
        assert_eq!(resumed.curve, full.curve);
        for f in ["results.json", "per_view.json"] {
            assert_eq!(
                std::fs::read(a.join(f)).unwrap(),
                std::fs::read(b.join(f)).unwrap(),
                "{f}"
            );
        }
    }
    // The final checkpoint loads and its PLY is a valid Inria file of the same Gaussians.
    let last = checkpoint::latest(&a.join("checkpoints")).unwrap().unwrap();
    let t = checkpoint::load::<f32>(&last, &cfg, &binding(&data)).unwrap();
    assert_eq!(format!("{:016x}", t.state_hash()), full.state_hash);
    // Renamed as an earlier checkpoint, it is refused (a resumed run would
    // name its next checkpoints from the state's iteration).
    let renamed = tmp("renamed").join("checkpoints").join("iteration_000030");
    copy_dir(&last, &renamed);
    let err = checkpoint::load::<f32>(&renamed, &cfg, &binding(&data))
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("__metadata__.iteration")
            && err.contains("90, but the checkpoint's folder is named for iteration 30 (a folder renamed or copied over another)"),
        "{err}"
    );
    let ply = liquid_splat::gaussians::ply::read_gaussians::<f32>(&last.join(checkpoint::PLY_FILE))
        .unwrap();
    assert_eq!(ply.xyz, t.model().gaussians.xyz);
    assert_eq!(ply.opacity, t.model().gaussians.opacity);
}

#[test]
fn damaged_or_foreign_checkpoints_are_errors() {
    let data = scene();
    let cfg = config(25);
    let a = tmp("damaged");
    run(&cfg, &data, &a, 0, false);
    let ckpt = checkpoint::latest(&a.join("checkpoints")).unwrap().unwrap();
    assert!(checkpoint::load::<f32>(&ckpt, &cfg, &binding(&data)).is_ok());

    let state = ckpt.join(checkpoint::STATE_FILE);
    let field = ckpt.join(checkpoint::FIELD_FILE);
    let original = std::fs::read(&state).unwrap();
    let original_field = std::fs::read(&field).unwrap();
    let expect_err = |what: &str, needle: &str| {
        let e = checkpoint::load::<f32>(&ckpt, &cfg, &binding(&data))
            .err()
            .unwrap_or_else(|| panic!("{what}: loaded"));
        assert!(e.to_string().contains(needle), "{what}: {e}");
    };

    // One flipped bit in the tensor data (the last byte belongs to a tensor).
    let mut bad = original.clone();
    *bad.last_mut().unwrap() ^= 1;
    std::fs::write(&state, &bad).unwrap();
    expect_err("flipped bit", "corrupt");

    std::fs::write(&state, &original[..original.len() / 2]).unwrap();
    expect_err("truncated", "state.safetensors");
    std::fs::write(&state, &original).unwrap();

    let mut bad = original_field.clone();
    *bad.last_mut().unwrap() ^= 0x40;
    std::fs::write(&field, &bad).unwrap();
    expect_err("flipped bit in the field", "corrupt");
    std::fs::write(&field, &original_field[..100]).unwrap();
    expect_err("truncated field", "deform.safetensors");
    std::fs::write(&field, &original_field).unwrap();

    let mut other = cfg.clone();
    other.seed += 1;
    let e = checkpoint::load::<f32>(&ckpt, &other, &binding(&data))
        .err()
        .unwrap();
    assert!(e.to_string().contains("different run configuration"), "{e}");
    // Only the field that differs is shown, not the whole configuration.
    assert!(
        e.to_string().contains(&format!("seed: {}", cfg.seed)),
        "{e}"
    );
    assert!(e.to_string().len() < 600, "{e}");
    let e = checkpoint::load::<f64>(&ckpt, &cfg, &binding(&data))
        .err()
        .unwrap();
    assert!(e.to_string().contains("dtype"), "{e}");
    assert!(checkpoint::load::<f32>(&ckpt, &cfg, &binding(&data)).is_ok());
}

/// Gaussians that are not finite are refused when the trainer is made, and a
/// step whose loss is not finite stops the run before its update.
#[test]
fn non_finite_gaussians_and_losses_stop_the_run() {
    let data = scene();
    let views = train::run::views::<f32>(&data.train);
    let make = |edit: &dyn Fn(&mut liquid_splat::gaussians::Gaussians<f32>)| {
        let mut g = liquid_splat::gaussians::init::initial_gaussians::<f32>(&data.init).unwrap();
        edit(&mut g);
        Trainer::new(config(40), g, views.len(), data.scene_extent, [0.0; 3])
    };
    let err = make(&|g| g.scaling[4] = f32::INFINITY)
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("scaling of Gaussian 1 is inf"), "{err}");
    // Colours of 1e30 are finite, but the SSIM's squares overflow f32.
    let mut t = make(&|g| g.sh.iter_mut().for_each(|v| *v = 1e30)).unwrap();
    let before = t.model().gaussians.clone();
    let err = t.step(&views).unwrap_err().to_string();
    assert!(err.contains("iteration 1: the loss is NaN"), "{err}");
    let after = &t.model().gaussians;
    assert!(after.sh == before.sh && after.xyz == before.xyz && after.scaling == before.scaling);
    assert_eq!(t.iteration(), 0);
}
