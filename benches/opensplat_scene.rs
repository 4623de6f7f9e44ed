//! The liquid-splat half of `benches/compare_opensplat.sh`: writes one
//! D-NeRF scene's rasterizer inputs in one of two states, its first
//! training cameras and one output gradient per camera as raw little-endian
//! f32 files for the OpenSplat harness (`benches/opensplat_harness.cpp`),
//! times liquid-splat's forward and backward on them at 1 and 2 threads, and
//! writes its outputs for the numerical comparison.
//!
//! The state: with `STEPS = 0`, the initial Gaussians of a run as the
//! rasterizer receives them during warm-up (the same at every camera); with
//! `STEPS > 0`, the Gaussians after `STEPS` training iterations of
//! `liquid-splat train --iterations STEPS --seed SEED` with the paper's CfC
//! field (D6 W128): the library's [`Trainer`](liquid_splat::train::Trainer)
//! with the scene's training configuration (every schedule scaled to
//! `STEPS`, densification and opacity reset included), then at each camera
//! the Gaussians deformed by the field at that camera's time, with the
//! model's SH (bands above its active degree zeroed, so evaluating degree 3
//! renders what the model renders).
//!
//! ```text
//! cargo bench --bench opensplat_scene -- DATA_DIR OUT_DIR [DOWNSCALE=2] [POINTS=20000] [CAMERAS=10] [REPS=3] [STEPS=0] [SEED=0]
//! ```
//!
//! Files in `OUT_DIR`: `meta.txt` (`n width height cameras sh_degree`),
//! per camera `k`: `gaussians{k}.f32` (means `[N,3]`, activated scales
//! `[N,3]`, unit quaternions `[N,4]` (w, x, y, z), activated opacities
//! `[N]`, SH `[N,16,3]`), `camera{k}.f32` (world-to-camera `[4,4]` and full
//! projection `[4,4]`, both row-major for column vectors, then `tanfovx,
//! tanfovy, campos[3], background[3]`), `grad{k}.f32` (`dL/dcolor` `[3,H,W]`),
//! `ls_color{k}.f32` (`[3,H,W]`) and `ls_grads{k}.f32` (gradients of the
//! means, scales, quaternions, opacities and SH, same layouts as the inputs).
//! With the environment variable `PIN_THREADS=1` the pools' workers are
//! pinned one per CPU (`--pin-threads` of the command-line tool).
//!
//! Prints `liquid-splat threads=T fwd_ms=F bwd_ms=B fwd_cpu_ms=FC bwd_cpu_ms=BC`:
//! wall milliseconds, each the sum over the cameras of the minimum over
//! `REPS` runs, and CPU milliseconds of all threads (Linux), each the sum
//! over the cameras of the mean over the runs. On a shared machine the CPU
//! time divided by the thread count estimates the wall time the same work
//! takes with the cores to itself. Before each such line, a `stages` line:
//! the rasterizer's stages (`render::stages`) of one more run per camera,
//! wall (CPU) milliseconds summed over the cameras. The two-thread line
//! ends with `xcpu_before_ns=A xcpu_after_ns=B`: one cache line's round
//! trip between the pool's workers 0 and 1 just before and just after its
//! timed runs (the median of 5 batches of 2,000), which tells a shared
//! machine's slow periods from its quiet minutes (benches/README.md, "The
//! machine's slow periods").

use liquid_splat::dataset::{self, LoadOptions, Splits};
use liquid_splat::deform::{CfcConfig, FieldConfig};
use liquid_splat::gaussians::init::initial_gaussians;
use liquid_splat::render::{rasterize, rasterize_vjp, stages, Colors, Covariances, GradientMode};
use liquid_splat::train::deformed::deform_gaussians;
use liquid_splat::train::{run, TrainConfig};
use std::io::Write;
use std::path::Path;
use std::time::Instant;

/// SH degree the comparison evaluates (OpenSplat's default and the bench's).
const SH_DEGREE: usize = 3;
const SH_COEFFS: usize = 16;

fn write_f32(path: &Path, parts: &[&[f32]]) {
    let mut f = std::io::BufWriter::new(std::fs::File::create(path).expect("create output file"));
    for p in parts {
        for v in *p {
            f.write_all(&v.to_le_bytes()).expect("write output file");
        }
    }
}

/// CPU time of every thread of this process so far, in nanoseconds
/// (`CLOCK_PROCESS_CPUTIME_ID`, as the OpenSplat harness reads it: one
/// system call, so the wall times it sits between barely include it);
/// 0 where not available.
fn cpu_ns() -> u64 {
    liquid_splat::bench::harness::process_cpu_seconds().map_or(0, |s| (s * 1e9) as u64)
}

fn main() {
    // As the command-line tool: freed memory is reused, not returned.
    liquid_splat::memory::keep_freed_memory();
    liquid_splat::threads::set_pinning(std::env::var("PIN_THREADS").is_ok_and(|v| v == "1"));
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .collect();
    if args.len() < 2 {
        eprintln!(
            "usage: opensplat_scene DATA_DIR OUT_DIR [DOWNSCALE=2] [POINTS=20000] [CAMERAS=10] [REPS=3] [STEPS=0] [SEED=0]"
        );
        std::process::exit(2);
    }
    let num = |i: usize, d: usize| -> usize {
        args.get(i)
            .map(|s| s.parse().expect("a positive integer argument"))
            .unwrap_or(d)
    };
    let (data_dir, out) = (Path::new(&args[0]), Path::new(&args[1]));
    let (downscale, points, cameras, reps) = (num(2, 2), num(3, 20_000), num(4, 10), num(5, 3));
    let (steps, seed) = (num(6, 0) as u64, num(7, 0) as u64);
    std::fs::create_dir_all(out).expect("create OUT_DIR");
    let opts = LoadOptions {
        downscale,
        init_points: points,
        splits: Splits {
            train: true,
            val: false,
            test: false,
        },
        ..LoadOptions::default()
    };
    let data = dataset::load(data_dir, &opts).expect("load the dataset");
    let bg = [if data.white_background { 1f32 } else { 0f32 }; 3];
    let frames = &data.train[..cameras.min(data.train.len())];
    let (w, h) = (frames[0].width, frames[0].height);
    // The Gaussians the rasterizer receives at each camera, and their SH
    // (`stride` coefficients per Gaussian, `degree` bands evaluated).
    let (deformed, g_sh, stride, degree) = if steps == 0 {
        let g = initial_gaussians::<f32>(&data.init).expect("initial Gaussians");
        let d = deform_gaussians(&g, None);
        let (k, deg) = (g.coeffs(), g.max_sh_degree);
        (vec![d; frames.len()], g.sh, k, deg)
    } else {
        let config = TrainConfig::new(steps, seed, FieldConfig::Cfc(CfcConfig::paper()));
        let views = run::views::<f32>(&data.train);
        let mut trainer = run::new_trainer::<f32>(&config, &data).expect("a trainer");
        let t0 = Instant::now();
        let mut last = None;
        while trainer.iteration() < steps {
            last = Some(trainer.step(&views).expect("a training step"));
        }
        let r = last.expect("at least one step");
        println!(
            "trained {steps} iterations ({}, seed {seed}, {} train views) in {:.0} s: last loss {:.4}, {} Gaussians, SH degree {}, field {}",
            liquid_splat::report::field_label(&config.field),
            views.len(),
            t0.elapsed().as_secs_f64(),
            r.loss,
            r.gaussians,
            trainer.model().active_sh_degree,
            if trainer.field_active(steps) { "on" } else { "off (warm-up)" }
        );
        let d: Vec<_> = frames
            .iter()
            .map(|f| trainer.deformed(f.time).expect("deformed Gaussians"))
            .collect();
        let m = trainer.model();
        (
            d,
            m.gaussians.sh.clone(),
            m.gaussians.coeffs(),
            m.active_sh_degree,
        )
    };
    let n = deformed[0].opacities.len();
    // SH padded to degree 3, bands above `degree` zeroed: evaluated at
    // degree 3 they give the colours the model's degree gives.
    let used = (degree + 1) * (degree + 1);
    let mut sh = vec![0f32; n * SH_COEFFS * 3];
    for i in 0..n {
        for c in 0..used.min(stride).min(SH_COEFFS) * 3 {
            sh[i * SH_COEFFS * 3 + c] = g_sh[i * stride * 3 + c];
        }
    }
    std::fs::write(
        out.join("meta.txt"),
        format!("{n} {w} {h} {} {SH_DEGREE}\n", frames.len()),
    )
    .expect("write meta.txt");
    for (k, d) in deformed.iter().enumerate() {
        write_f32(
            &out.join(format!("gaussians{k}.f32")),
            &[&d.means, &d.scales, &d.rotations, &d.opacities, &sh],
        );
    }
    let cams: Vec<_> = frames.iter().map(|f| f.camera.raster::<f32>()).collect();
    let grads: Vec<Vec<f32>> = (0..cams.len())
        .map(|k| {
            liquid_splat::math::gradcheck::cotangent(k as u64 + 1, 3 * w * h)
                .into_iter()
                .map(|v| v as f32)
                .collect()
        })
        .collect();
    let input = |k: usize| liquid_splat::render::RasterInput {
        means3d: &deformed[k].means,
        colors: Colors::Sh {
            coeffs: &sh,
            stride: SH_COEFFS,
            degree: SH_DEGREE,
        },
        opacities: &deformed[k].opacities,
        covariances: Covariances::ScaleRotation {
            scales: &deformed[k].scales,
            rotations: &deformed[k].rotations,
            scale_modifier: 1.0,
        },
        camera: &cams[k],
        background: bg,
    };
    for (k, cam) in cams.iter().enumerate() {
        // The rasterizer's matrices are transposed (row vectors); write them
        // for column vectors.
        let t = |m: &[f32; 16]| -> Vec<f32> { (0..16).map(|i| m[4 * (i % 4) + i / 4]).collect() };
        let mut rest = vec![cam.tanfovx, cam.tanfovy];
        rest.extend_from_slice(&cam.campos);
        rest.extend_from_slice(&bg);
        write_f32(
            &out.join(format!("camera{k}.f32")),
            &[&t(&cam.viewmatrix), &t(&cam.projmatrix), &rest],
        );
        write_f32(&out.join(format!("grad{k}.f32")), &[&grads[k]]);
        let (o, saved) = rasterize(&input(k)).expect("rasterize");
        let gr = rasterize_vjp(&input(k), &saved, &grads[k], None, GradientMode::Exact)
            .expect("rasterize_vjp");
        write_f32(&out.join(format!("ls_color{k}.f32")), &[&o.color]);
        write_f32(
            &out.join(format!("ls_grads{k}.f32")),
            &[
                &gr.means3d,
                &gr.scales_or_cov,
                &gr.rotations,
                &gr.opacities,
                &gr.colors,
            ],
        );
    }
    println!(
        "liquid-splat: {}, {n} Gaussians, {w}x{h}, {} cameras, f32, SH degree {SH_DEGREE}, instruction set {:?}",
        if steps == 0 { "initial state".to_string() } else { format!("after {steps} training steps") },
        cams.len(),
        liquid_splat::kernels::fastmath::isa()
    );
    for threads in [1usize, 2] {
        let pool = liquid_splat::threads::pool(threads).expect("thread pool");
        let (mut fwd, mut bwd, mut fwd_cpu, mut bwd_cpu) = (0.0, 0.0, 0u64, 0u64);
        let reps = reps.max(1);
        let before = liquid_splat::bench::harness::round_trip_median_ns(&pool);
        pool.install(|| {
            for (k, grad) in grads.iter().enumerate() {
                let (mut f, mut b) = (f64::INFINITY, f64::INFINITY);
                for _ in 0..reps {
                    let (c0, t0) = (cpu_ns(), Instant::now());
                    let (_, saved) = rasterize(&input(k)).expect("rasterize");
                    let (c1, t1) = (cpu_ns(), Instant::now());
                    rasterize_vjp(&input(k), &saved, grad, None, GradientMode::Exact)
                        .expect("rasterize_vjp");
                    let (c2, t2) = (cpu_ns(), Instant::now());
                    f = f.min((t1 - t0).as_secs_f64());
                    b = b.min((t2 - t1).as_secs_f64());
                    fwd_cpu += c1.saturating_sub(c0);
                    bwd_cpu += c2.saturating_sub(c1);
                }
                fwd += f;
                bwd += b;
            }
        });
        let after = liquid_splat::bench::harness::round_trip_median_ns(&pool);
        // One more run per camera with the stage clock on: each stage's wall
        // (CPU) milliseconds summed over the cameras.
        let mut sums: Vec<(&'static str, f64, f64)> = Vec::new();
        pool.install(|| {
            for (k, grad) in grads.iter().enumerate() {
                let ((_, saved), fs) = stages::record(|| rasterize(&input(k)).expect("rasterize"));
                let (_, bs) = stages::record(|| {
                    rasterize_vjp(&input(k), &saved, grad, None, GradientMode::Exact)
                        .expect("rasterize_vjp")
                });
                for (i, st) in fs.iter().chain(&bs).enumerate() {
                    if sums.len() <= i {
                        sums.push((st.name, 0.0, 0.0));
                    }
                    sums[i].1 += st.wall * 1e3;
                    sums[i].2 += st.cpu.unwrap_or(f64::NAN) * 1e3;
                }
            }
        });
        let list: Vec<String> = sums
            .iter()
            .map(|(name, wall, cpu)| format!("{name} {wall:.1} ({cpu:.1})"))
            .collect();
        println!(
            "stages threads={threads}, ms wall (CPU), one run, sum over the cameras: {}",
            list.join(", ")
        );
        let trips = match (before, after) {
            (Some(b), Some(a)) => format!(" xcpu_before_ns={b:.0} xcpu_after_ns={a:.0}"),
            _ => String::new(),
        };
        println!(
            "liquid-splat threads={threads} fwd_ms={:.1} bwd_ms={:.1} fwd_cpu_ms={:.1} bwd_cpu_ms={:.1}{trips}",
            fwd * 1e3,
            bwd * 1e3,
            fwd_cpu as f64 / reps as f64 * 1e-6,
            bwd_cpu as f64 / reps as f64 * 1e-6
        );
    }
}
