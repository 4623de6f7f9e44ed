//! The `train`, `render`, `eval` and `experiment` commands end to end, and
//! their exit codes on bad input.

mod support;

use std::path::Path;
use support::{cli, read_json as json, text, tmp};

const SMALL_FIELD: [&str; 8] = [
    "--depth",
    "2",
    "--width",
    "8",
    "--backbone-units",
    "8",
    "--backbone-layers",
    "1",
];

#[test]
fn train_render_eval_on_the_fixture_scene() {
    let out = tmp("run");
    let scene = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/scenes/swing");
    let o = out.to_str().unwrap();
    let mut args = vec![
        "train",
        scene,
        "--iterations",
        "40",
        "--init-points",
        "200",
        "--out",
        o,
    ];
    args.extend(SMALL_FIELD);
    let r = cli(&args);
    assert!(r.status.success(), "{}", text(&r));
    let stdout = String::from_utf8_lossy(&r.stdout);
    assert!(stdout.contains("test PSNR"), "{stdout}");
    // Not a terminal: a log line every 40 / 20 = 2 iterations, each
    // followed by the stages' milliseconds per iteration since the last.
    let stderr = String::from_utf8_lossy(&r.stderr);
    let lines: Vec<&str> = stderr.lines().collect();
    let logged: Vec<usize> = (0..lines.len())
        .filter(|&i| lines[i].starts_with("iteration "))
        .collect();
    assert_eq!(logged.len(), 20, "{stderr}");
    assert!(
        lines[logged[19]].starts_with("iteration     40/40 "),
        "{stderr}"
    );
    for &i in &logged {
        let next = lines.get(i + 1).copied().unwrap_or("");
        assert!(
            next.starts_with("  ms/iteration over the last 2: field forward ")
                && liquid_splat::train::StageTimes::NAMES
                    .iter()
                    .chain(&["all stages", "wall"])
                    .all(|s| next.contains(s)),
            "{stderr}"
        );
    }
    let results = json(&out.join("results.json"));
    let per_view = json(&out.join("per_view.json"));
    assert_eq!(results["views"], 8);
    assert_eq!(per_view["psnr"].as_object().unwrap().len(), 8);
    for sub in ["renders", "renders_exr", "gt"] {
        assert_eq!(
            std::fs::read_dir(out.join("test").join(sub))
                .unwrap()
                .count(),
            8,
            "{sub}"
        );
    }
    let ckpt = out.join("checkpoints/iteration_000040");
    for f in [
        "state.safetensors",
        "deform.safetensors",
        "point_cloud.ply",
        "curve.json",
    ] {
        assert!(ckpt.join(f).is_file(), "{f}");
    }

    // eval recomputes the metrics from the PNGs: the same numbers.
    let r = cli(&["eval", o]);
    assert!(r.status.success(), "{}", text(&r));
    assert_eq!(json(&out.join("results.json")), results);
    assert_eq!(json(&out.join("per_view.json")), per_view);

    let r = cli(&["render", o, "--sweep-frames", "5", "--sweep-view", "1"]);
    assert!(r.status.success(), "{}", text(&r));
    let r = cli(&["render", o, "--sweep-frames", "3", "--sweep-view", "1"]);
    assert!(r.status.success(), "{}", text(&r));
    for k in 0..3 {
        assert!(out.join(format!("sweep/{k:04}.png")).is_file());
        assert!(out.join(format!("sweep/{k:04}.exr")).is_file());
    }
    // The earlier sweep's frames 3 and 4 are gone.
    for k in 3..5 {
        assert!(!out.join(format!("sweep/{k:04}.png")).exists());
        assert!(!out.join(format!("sweep/{k:04}.exr")).exists());
    }
    assert_eq!(json(&out.join("results.json")), results);

    // Resuming a finished run with other arguments is refused.
    let mut args = vec![
        "train",
        scene,
        "--iterations",
        "50",
        "--init-points",
        "200",
        "--out",
        o,
        "--resume",
    ];
    args.extend(SMALL_FIELD);
    let r = cli(&args);
    assert_eq!(r.status.code(), Some(2), "{}", text(&r));
    assert!(text(&r).contains("iterations: recorded"), "{}", text(&r));
}

/// run.json records the dataset folder as an absolute path: a run trained
/// with a relative one renders from any folder, and resumes with the folder
/// written either way.
#[test]
fn a_relative_dataset_folder_is_found_from_anywhere() {
    let dir = tmp("relative");
    support::copy_dir(
        Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/fixtures/scenes/swing"
        )),
        &dir.join("swing"),
    );
    let out = dir.join("run");
    let mut args = vec![
        "train",
        "swing",
        "--iterations",
        "4",
        "--init-points",
        "50",
        "--quiet",
        "--out",
        "run",
    ];
    args.extend(SMALL_FIELD);
    let in_dir = |args: &[&str], cwd: &Path| {
        std::process::Command::new(env!("CARGO_BIN_EXE_liquid-splat"))
            .args(args)
            .current_dir(cwd)
            .output()
            .unwrap()
    };
    let r = in_dir(&args, &dir);
    assert!(r.status.success(), "{}", text(&r));
    let r = in_dir(
        &["render", out.to_str().unwrap(), "--sweep-frames", "0"],
        Path::new("/"),
    );
    assert!(r.status.success(), "{}", text(&r));
    let abs = dir.join("swing");
    args[1] = abs.to_str().unwrap();
    args.push("--resume");
    let r = in_dir(&args, &dir);
    assert!(r.status.success(), "{}", text(&r));
}

#[test]
fn bad_input_exits_2_with_a_message() {
    let out = tmp("bad");
    let o = out.to_str().unwrap();
    let cases: Vec<(Vec<&str>, &str)> = vec![
        (
            vec!["train", "/nonexistent/scene", "--out", o],
            "/nonexistent/scene",
        ),
        (
            vec!["train", "--scene", "nosuchscene", "--out", o],
            "nosuchscene",
        ),
        (
            vec!["train", "--scene", "swing", "--iterations", "0", "--out", o],
            "iterations",
        ),
        (
            vec![
                "train",
                "--scene",
                "swing",
                "--activation",
                "softplus",
                "--out",
                o,
            ],
            "softplus",
        ),
        (vec!["train", "--out", o], "required"),
        (vec!["render", "/nonexistent/run"], "run.json"),
        (vec!["eval", "/nonexistent/run"], "renders"),
    ];
    for (args, needle) in cases {
        let r = cli(&args);
        assert_eq!(r.status.code(), Some(2), "{args:?}: {}", text(&r));
        assert!(text(&r).contains(needle), "{args:?}: {}", text(&r));
        // Nothing is written into the output folder.
        assert!(!out.join("run.json").exists(), "{args:?} wrote run.json");
    }
}

#[test]
fn experiment_writes_a_report_and_resumes_per_configuration() {
    let out = tmp("exp");
    let o = out.to_str().unwrap();
    let args = [
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
        "2",
        "--sweep-times",
        "9",
        "--out",
        o,
    ];
    let r = cli(&args);
    assert!(r.status.success(), "{}", text(&r));
    let md = std::fs::read_to_string(out.join("report.md")).unwrap();
    for needle in [
        "mlp-d8-w256-relu",
        "cfc-d6-w128-gelu",
        "522,280",
        "334,504",
        "threads",
        // (One sentence across source lines, without their indentation.)
        "made during each run (the last iteration included), each metric on its own",
    ] {
        assert!(md.contains(needle), "report.md lacks {needle}");
    }
    let runs = |d: &Path| {
        let mut v: Vec<String> = std::fs::read_dir(d.join("runs"))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
            .collect();
        v.sort();
        v
    };
    assert_eq!(runs(&out).len(), 2);
    let mlp = out.join("runs/swing__mlp-d8-w256-relu__seed0.json");
    let cfc = out.join("runs/swing__cfc-d6-w128-gelu__seed0.json");
    let cfc_before = std::fs::read(&cfc).unwrap();
    let rec = json(&mlp);
    assert!(rec["temporal_smoothness"].as_f64().unwrap().is_finite());
    assert_eq!(
        rec["curves"].as_array().unwrap().last().unwrap()["iteration"],
        6
    );

    // Rerun after removing one record: only that configuration trains again.
    std::fs::remove_file(&mlp).unwrap();
    let r = cli(&args);
    assert!(r.status.success(), "{}", text(&r));
    assert!(text(&r).contains("done earlier, kept"), "{}", text(&r));
    assert_eq!(std::fs::read(&cfc).unwrap(), cfc_before);
    let again = json(&mlp);
    assert_eq!(again["test_psnr"], rec["test_psnr"]);
    // Each training folder is a run that render opens.
    let work = out.join("training/swing__mlp-d8-w256-relu__seed0");
    let r = cli(&["render", work.to_str().unwrap(), "--sweep-frames", "0"]);
    assert!(r.status.success(), "{}", text(&r));
    assert_eq!(again["smoothness_sweep"], serde_json::json!([9, 1000]));

    // A kept record made with other settings is refused, not mixed into the
    // report.
    for (flag, value, needle) in [
        ("--iterations", "7", "6 iterations, not 7"),
        ("--resolution", "8", "16x16, not 8x8"),
        ("--sweep-times", "5", "[9, 1000]"),
    ] {
        let mut other = args.to_vec();
        let i = other.iter().position(|a| *a == flag).unwrap();
        other[i + 1] = value;
        let r = cli(&other);
        assert_eq!(r.status.code(), Some(2), "{flag}: {}", text(&r));
        assert!(text(&r).contains(needle), "{flag}: {}", text(&r));
        assert!(!text(&r).contains(": training"), "{flag}: {}", text(&r));
    }
    assert_eq!(std::fs::read(&cfc).unwrap(), cfc_before);
}
