//! `liquid-splat case ...`: work with oracle case files.

use crate::deform::{FieldKind, Variant};
use crate::error::Outcome;
use crate::io::TensorFile;
use crate::math::Precision;
use crate::oracle::new::{golden_files, new_case, CaseSpec};
use crate::oracle::{compare, Tolerances};
use crate::render::GradientMode;
use crate::Error;
use clap::{Args, Subcommand};
use std::path::{Path, PathBuf};

/// The most pixels `case new --width × --height` writes.
pub use crate::oracle::new::MAX_CASE_PIXELS as MAX_PIXELS;

/// The most Gaussians or points `case new --count` writes.
pub use crate::oracle::new::MAX_CASE_COUNT as MAX_COUNT;

/// Subcommands of `case`.
#[derive(Subcommand)]
pub enum CaseCommand {
    /// Run the stage a case file names (metadata `stage`) and write its outputs.
    Run {
        /// The case file (safetensors).
        input: PathBuf,
        /// Where to write the outputs (safetensors).
        output: PathBuf,
    },
    /// Write a seeded random, well-formed case file (inputs only) for a stage.
    New(NewArgs),
    /// Rewrite the golden fixtures (inputs and expected outputs) into DIR.
    RegenGolden {
        /// Directory to write into (created if missing), normally fixtures/cases.
        dir: PathBuf,
    },
    /// Compare an expected output file with an actual one, tensor by tensor.
    /// Exit 0 when every tensor is within tolerance, 1 when one is not, 2 on
    /// unusable input.
    Compare(CompareArgs),
}

/// Arguments of `case new`.
#[derive(Args)]
pub struct NewArgs {
    /// Stage: rasterize, deform, loss, step, or a gsplat stage
    /// (gsplat_quat_scale_to_covar_preci, gsplat_spherical_harmonics,
    /// gsplat_fully_fused_projection, gsplat_isect_tiles,
    /// gsplat_rasterize_to_pixels, gsplat_rasterization).
    pub stage: String,
    /// Where to write the case (safetensors).
    pub output: PathBuf,
    /// Precision of every floating-point tensor: f32 or f64.
    #[arg(long, default_value = "f64")]
    pub dtype: String,
    /// Seed of every random draw.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Image width (rasterize, loss, step and the gsplat stages with a camera: all but
    /// gsplat_quat_scale_to_covar_preci and gsplat_spherical_harmonics).
    #[arg(long)]
    pub width: Option<usize>,
    /// Image height (the stages of --width).
    #[arg(long)]
    pub height: Option<usize>,
    /// Number of Gaussians (rasterize: in view, plus one beside it; the gsplat stages: in
    /// view, plus one beside it and one tiny one; step) or points (deform).
    #[arg(long)]
    pub count: Option<usize>,
    /// Rasterize: gradient mode, exact or inria; gsplat stages: exact or gsplat.
    #[arg(long)]
    pub gradient: Option<String>,
    /// Deform, step: field kind, mlp or cfc.
    #[arg(long)]
    pub field: Option<String>,
    /// Deform, step: depth (MLP layers or CfC cells); default small.
    #[arg(long)]
    pub depth: Option<usize>,
    /// Deform, step: width (MLP trunk or CfC hidden size); default small.
    #[arg(long)]
    pub hidden: Option<usize>,
    /// Deform, step: the field's time input, synthetic (timenet) or real
    /// (default: synthetic for deform, real for step).
    #[arg(long)]
    pub variant: Option<String>,
    /// Deform, step: the MLP field's 6-DoF (SE(3)) variant.
    #[arg(long = "6dof")]
    pub six_dof: bool,
    /// gsplat stages: the gsplat version whose conventions apply, 1.5.3 or 1.6.
    #[arg(long = "gsplat-version")]
    pub gsplat_version: Option<String>,
    /// gsplat stages with a camera: antialiased rasterization (compensated opacities).
    #[arg(long)]
    pub antialiased: bool,
    /// gsplat_fully_fused_projection, gsplat_rasterization: the dense layout instead of
    /// gsplat's default packed one.
    #[arg(long)]
    pub dense: bool,
}

/// Arguments of `case compare`.
#[derive(Args)]
pub struct CompareArgs {
    /// The reference output (safetensors).
    pub expected: PathBuf,
    /// The output under test (safetensors).
    pub actual: PathBuf,
    /// Absolute tolerance for floating-point tensors (replaces the file's default).
    #[arg(long, allow_negative_numbers = true)]
    pub atol: Option<f64>,
    /// Relative tolerance for floating-point tensors (replaces the file's default).
    #[arg(long, allow_negative_numbers = true)]
    pub rtol: Option<f64>,
    /// Per-tensor tolerances (JSON; format in docs/ORACLE.md, `case compare`).
    #[arg(long, value_name = "FILE.json")]
    pub tolerances: Option<PathBuf>,
    /// Fraction of elements per tensor allowed to mismatch (replaces the file's default).
    #[arg(long, allow_negative_numbers = true)]
    pub max_mismatch_fraction: Option<f64>,
    /// Count NaN == NaN as a match.
    #[arg(long)]
    pub equal_nan: bool,
    /// Also write the full report as JSON.
    #[arg(long, value_name = "OUT.json")]
    pub report: Option<PathBuf>,
}

/// Run a `case` subcommand (`compare`: [`Outcome::CheckFailed`] when a
/// tensor is out of tolerance).
pub fn run(cmd: CaseCommand) -> crate::Result<Outcome> {
    match cmd {
        CaseCommand::Run { input, output } => run_case(&input, &output),
        CaseCommand::New(args) => run_new(args),
        CaseCommand::RegenGolden { dir } => regen_golden(&dir),
        CaseCommand::Compare(args) => run_compare(args),
    }
}

fn run_new(a: NewArgs) -> crate::Result<Outcome> {
    let mut spec = CaseSpec::new(&a.stage);
    spec.precision = match a.dtype.as_str() {
        "f32" => Precision::F32,
        "f64" => Precision::F64,
        other => return Err(Error::invalid("--dtype", format!("`{other}` (f32 or f64)"))),
    };
    spec.seed = a.seed;
    let uses = |flag: &str, given: bool, stages: &[&str]| -> crate::Result<()> {
        if given && !stages.contains(&a.stage.as_str()) {
            return Err(Error::invalid(
                flag,
                format!(
                    "not used by stage `{}` (only {})",
                    a.stage,
                    stages.join(", ")
                ),
            ));
        }
        Ok(())
    };
    use crate::oracle::gsplat::{ISECT, PROJECTION, RASTERIZATION, RASTERIZE};
    let gs = crate::oracle::gsplat::STAGES;
    let with_gs =
        |base: &[&'static str]| -> Vec<&'static str> { base.iter().copied().chain(gs).collect() };
    // (The gsplat stages without a camera or image, the covariance and SH
    // stages, use none of the image options.)
    let imaged = [PROJECTION, ISECT, RASTERIZE, RASTERIZATION];
    let sized = [
        "rasterize",
        "loss",
        "step",
        PROJECTION,
        ISECT,
        RASTERIZE,
        RASTERIZATION,
    ];
    uses("--width", a.width.is_some(), &sized)?;
    uses("--height", a.height.is_some(), &sized)?;
    uses(
        "--count",
        a.count.is_some(),
        &with_gs(&["rasterize", "deform", "step"]),
    )?;
    uses("--gradient", a.gradient.is_some(), &with_gs(&["rasterize"]))?;
    uses("--gsplat-version", a.gsplat_version.is_some(), &gs)?;
    uses("--antialiased", a.antialiased, &imaged)?;
    uses("--dense", a.dense, &[PROJECTION, RASTERIZATION])?;
    uses("--field", a.field.is_some(), &["deform", "step"])?;
    uses("--depth", a.depth.is_some(), &["deform", "step"])?;
    uses("--hidden", a.hidden.is_some(), &["deform", "step"])?;
    uses("--variant", a.variant.is_some(), &["deform", "step"])?;
    uses("--6dof", a.six_dof, &["deform", "step"])?;
    spec.width = a.width.unwrap_or(spec.width);
    spec.height = a.height.unwrap_or(spec.height);
    spec.count = a.count.unwrap_or(spec.count);
    if spec.width == 0 || spec.height == 0 || spec.width.saturating_mul(spec.height) > MAX_PIXELS {
        return Err(Error::invalid(
            "--width/--height",
            format!(
                "{}x{} pixels (each side at least 1, at most {MAX_PIXELS} pixels)",
                spec.width, spec.height,
            ),
        ));
    }
    if spec.count > MAX_COUNT {
        return Err(Error::invalid(
            "--count",
            format!("{} is above the limit {MAX_COUNT}", spec.count),
        ));
    }
    if let Some(g) = &a.gradient {
        if gs.contains(&a.stage.as_str()) {
            spec.gsplat.gradient = crate::gsplat::GradientMode::from_name(g)?;
        } else {
            spec.gradient = GradientMode::from_name(g)?;
        }
    }
    if let Some(v) = &a.gsplat_version {
        spec.gsplat.version = crate::gsplat::Version::from_name(v)?;
    }
    spec.gsplat.antialiased = a.antialiased;
    spec.gsplat.packed = !a.dense;
    if let Some(f) = &a.field {
        spec.field = FieldKind::parse(f)?;
    }
    spec.depth = a.depth;
    spec.hidden = a.hidden;
    if let Some(v) = &a.variant {
        spec.variant = Some(Variant::parse(v)?);
    }
    spec.is_6dof = a.six_dof;
    let mut case = new_case(&spec)?;
    case.path = a.output.clone();
    case.save(&a.output)?;
    Ok(Outcome::Success)
}

fn regen_golden(dir: &Path) -> crate::Result<Outcome> {
    crate::io::create_dir_all(dir)?;
    for (name, bytes) in golden_files()? {
        let path = dir.join(&name);
        crate::io::write_atomic(&path, &bytes)?;
        outln!("{} ({} bytes)", path.display(), bytes.len());
    }
    Ok(Outcome::Success)
}

fn run_case(input: &Path, output: &Path) -> crate::Result<Outcome> {
    let case = TensorFile::load(input)?;
    // (The outputs would replace the case.)
    if std::fs::canonicalize(output)
        .is_ok_and(|o| std::fs::canonicalize(input).is_ok_and(|i| i == o))
    {
        return Err(Error::invalid(
            "OUTPUT",
            format!("{} is the input case", output.display()),
        ));
    }
    let mut out = crate::oracle::run_case(&case)?;
    out.path = output.to_path_buf();
    out.save(output)?;
    Ok(Outcome::Success)
}

/// Refuses a `--report` path that cannot be written (a folder, or in a
/// folder that does not exist) before the comparison prints its verdict.
fn check_report_path(p: &std::path::Path) -> crate::Result<()> {
    // (A name ending in a separator is a folder's, existing or not.)
    let why = if p.is_dir()
        || p.as_os_str()
            .to_string_lossy()
            .ends_with(std::path::is_separator)
    {
        Some("is a folder")
    } else {
        match p.parent() {
            Some(d) if !d.as_os_str().is_empty() && !d.is_dir() => {
                Some("is in no folder that exists")
            }
            _ => None,
        }
    };
    match why {
        Some(why) => Err(crate::Error::invalid(
            "--report",
            format!("{} {why}", p.display()),
        )),
        None => Ok(()),
    }
}

fn run_compare(args: CompareArgs) -> crate::Result<Outcome> {
    if let Some(p) = &args.report {
        check_report_path(p)?;
    }
    let mut tol = match &args.tolerances {
        Some(p) => Tolerances::load(p)?,
        None => Tolerances::default(),
    };
    if args.atol.is_some() {
        tol.default.atol = args.atol;
    }
    if args.rtol.is_some() {
        tol.default.rtol = args.rtol;
    }
    if args.max_mismatch_fraction.is_some() {
        tol.default.max_mismatch_fraction = args.max_mismatch_fraction;
    }
    if args.equal_nan {
        tol.default.equal_nan = Some(true);
    }
    let expected = TensorFile::load(&args.expected)?;
    let actual = TensorFile::load(&args.actual)?;
    let report = compare(&expected, &actual, &tol)?;
    outln!("{report}");
    if let Some(p) = &args.report {
        crate::io::write_atomic(p, report.to_json().as_bytes())?;
    }
    Ok(Outcome::of_check(report.passed))
}
