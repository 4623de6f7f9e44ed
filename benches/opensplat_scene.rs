//! The liquid-splat half of `benches/compare_opensplat.sh`: writes one
//! D-NeRF scene's rasterizer inputs (the initial Gaussians of a run, as the
//! rasterizer receives them during warm-up), its first training cameras and
//! one output gradient per camera as raw little-endian f32 files for the
//! OpenSplat harness (`benches/opensplat_harness.cpp`), times liquid-splat's
//! forward and backward on them at 1 and 2 threads, and writes its outputs
//! for the numerical comparison.
//!
//! ```text
//! cargo bench --bench opensplat_scene -- DATA_DIR OUT_DIR [DOWNSCALE=2] [POINTS=20000] [CAMERAS=10] [REPS=3]
//! ```
//!
//! Files in `OUT_DIR`: `meta.txt` (`n width height cameras sh_degree`),
//! `gaussians.f32` (means `[N,3]`, activated scales `[N,3]`, unit
//! quaternions `[N,4]` (w, x, y, z), activated opacities `[N]`, SH `[N,16,3]`),
//! per camera `k`: `camera{k}.f32` (world-to-camera `[4,4]` and full
//! projection `[4,4]`, both row-major for column vectors, then `tanfovx,
//! tanfovy, campos[3], background[3]`), `grad{k}.f32` (`dL/dcolor` `[3,H,W]`),
//! `ls_color{k}.f32` (`[3,H,W]`) and `ls_grads{k}.f32` (gradients of the
//! means, scales, quaternions, opacities and SH, same layouts as the inputs).
//! Prints `liquid-splat threads=T fwd_ms=F bwd_ms=B fwd_cpu_ms=FC bwd_cpu_ms=BC`:
//! wall milliseconds, each the sum over the cameras of the minimum over
//! `REPS` runs, and CPU milliseconds of all threads (Linux), each the sum
//! over the cameras of the mean over the runs. On a shared machine the CPU
//! time divided by the thread count estimates the wall time the same work
//! takes with the cores to itself.

use liquid_splat::dataset::{self, LoadOptions, Splits};
use liquid_splat::gaussians::init::initial_gaussians;
use liquid_splat::render::{rasterize, rasterize_vjp, Colors, Covariances, GradientMode};
use liquid_splat::train::deformed::deform_gaussians;
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

/// CPU time of every thread of this process so far, in nanoseconds (the
/// first field of each thread's `schedstat`); 0 where not available.
fn cpu_ns() -> u64 {
    let Ok(dir) = std::fs::read_dir("/proc/self/task") else {
        return 0;
    };
    dir.filter_map(|e| {
        let s = std::fs::read_to_string(e.ok()?.path().join("schedstat")).ok()?;
        s.split_whitespace().next()?.parse::<u64>().ok()
    })
    .sum()
}

fn main() {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .collect();
    if args.len() < 2 {
        eprintln!(
            "usage: opensplat_scene DATA_DIR OUT_DIR [DOWNSCALE=2] [POINTS=20000] [CAMERAS=10] [REPS=3]"
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
    let g = initial_gaussians::<f32>(&data.init).expect("initial Gaussians");
    let d = deform_gaussians(&g, None);
    let n = g.len();
    // SH padded to degree 3 (the initial Gaussians may store fewer bands).
    let k_in = g.coeffs();
    let mut sh = vec![0f32; n * SH_COEFFS * 3];
    for i in 0..n {
        for c in 0..k_in.min(SH_COEFFS) * 3 {
            sh[i * SH_COEFFS * 3 + c] = g.sh[i * k_in * 3 + c];
        }
    }
    let bg = [if data.white_background { 1f32 } else { 0f32 }; 3];
    let frames = &data.train[..cameras.min(data.train.len())];
    let (w, h) = (frames[0].width, frames[0].height);
    std::fs::write(
        out.join("meta.txt"),
        format!("{n} {w} {h} {} {SH_DEGREE}\n", frames.len()),
    )
    .expect("write meta.txt");
    write_f32(
        &out.join("gaussians.f32"),
        &[&d.means, &d.scales, &d.rotations, &d.opacities, &sh],
    );
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
        means3d: &d.means,
        colors: Colors::Sh {
            coeffs: &sh,
            stride: SH_COEFFS,
            degree: SH_DEGREE,
        },
        opacities: &d.opacities,
        covariances: Covariances::ScaleRotation {
            scales: &d.scales,
            rotations: &d.rotations,
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
        "liquid-splat: {n} Gaussians, {w}x{h}, {} cameras, f32, SH degree {SH_DEGREE}, instruction set {:?}",
        cams.len(),
        liquid_splat::kernels::fastmath::isa()
    );
    for threads in [1usize, 2] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("thread pool");
        let (mut fwd, mut bwd, mut fwd_cpu, mut bwd_cpu) = (0.0, 0.0, 0u64, 0u64);
        let reps = reps.max(1);
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
        println!(
            "liquid-splat threads={threads} fwd_ms={:.1} bwd_ms={:.1} fwd_cpu_ms={:.1} bwd_cpu_ms={:.1}",
            fwd * 1e3,
            bwd * 1e3,
            fwd_cpu as f64 / reps as f64 * 1e-6,
            bwd_cpu as f64 / reps as f64 * 1e-6
        );
    }
}
