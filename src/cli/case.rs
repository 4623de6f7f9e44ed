//! `liquid-splat case ...`: work with oracle case files.

use clap::{Args, Subcommand};
use liquid_splat::io::TensorFile;
use liquid_splat::oracle::{compare, Tolerances};
use std::path::PathBuf;
use std::process::ExitCode;

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
    /// Compare an expected output file with an actual one, tensor by tensor.
    /// Exit 0 when every tensor is within tolerance, 1 when one is not, 2 on
    /// unusable input.
    Compare(CompareArgs),
}

/// Arguments of `case compare`.
#[derive(Args)]
pub struct CompareArgs {
    /// The reference output (safetensors).
    pub expected: PathBuf,
    /// The output under test (safetensors).
    pub actual: PathBuf,
    /// Absolute tolerance for floating-point tensors (replaces the file's default).
    #[arg(long)]
    pub atol: Option<f64>,
    /// Relative tolerance for floating-point tensors (replaces the file's default).
    #[arg(long)]
    pub rtol: Option<f64>,
    /// Per-tensor tolerances (JSON; format in the `oracle::compare` docs).
    #[arg(long, value_name = "FILE.json")]
    pub tolerances: Option<PathBuf>,
    /// Fraction of elements per tensor allowed to mismatch (replaces the file's default).
    #[arg(long)]
    pub max_mismatch_fraction: Option<f64>,
    /// Count NaN == NaN as a match.
    #[arg(long)]
    pub equal_nan: bool,
    /// Also write the full report as JSON.
    #[arg(long, value_name = "OUT.json")]
    pub report: Option<PathBuf>,
}

/// Run a `case` subcommand and return the process exit code.
pub fn run(cmd: CaseCommand) -> ExitCode {
    match cmd {
        CaseCommand::Run { input, output } => run_case(&input, &output),
        CaseCommand::Compare(args) => run_compare(args),
    }
}

fn run_case(input: &std::path::Path, output: &std::path::Path) -> ExitCode {
    let outcome = (|| -> liquid_splat::Result<()> {
        let case = TensorFile::load(input)?;
        let mut out = liquid_splat::oracle::run_case(&case)?;
        out.path = output.to_path_buf();
        out.save(output)
    })();
    match outcome {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(2)
        }
    }
}

fn run_compare(args: CompareArgs) -> ExitCode {
    let outcome = (|| -> liquid_splat::Result<bool> {
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
        println!("{report}");
        if let Some(p) = &args.report {
            liquid_splat::io::write_atomic(p, report.to_json().as_bytes())?;
        }
        Ok(report.passed)
    })();
    match outcome {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::from(1),
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(2)
        }
    }
}
