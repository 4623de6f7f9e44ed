//! Oracle stage `rasterize`: file round trip through the CLI and malformed inputs.

mod support;

use liquid_splat::io::TensorFile;
use liquid_splat::oracle::rasterize::run;
use liquid_splat::render::scene::{random_scene, ColorSource, CovSource, SceneSpec};
use liquid_splat::render::{rasterize, rasterize_vjp, Colors, GradientMode};
use std::path::PathBuf;
use support::{cli, s, text};

fn case_file(path: PathBuf) -> (TensorFile, Vec<f64>, Vec<f64>) {
    let s = random_scene(&SceneSpec::small(6, 3)).unwrap();
    let n = s.len();
    let rc = &s.raster_camera;
    let mut f = TensorFile::new(path);
    f.set_meta("stage", "rasterize");
    f.set_meta("image_height", rc.height);
    f.set_meta("image_width", rc.width);
    f.set_meta("tanfovx", format!("{:?}", rc.tanfovx));
    f.set_meta("tanfovy", format!("{:?}", rc.tanfovy));
    f.set_meta("scale_modifier", "1.0");
    f.set_meta("sh_degree", s.sh_degree);
    f.insert_real("means3D", vec![n, 3], &s.means3d);
    f.insert_real("shs", vec![n, 16, 3], &s.sh);
    f.insert_real("opacities", vec![n, 1], &s.opacities);
    f.insert_real("scales", vec![n, 3], &s.scales);
    f.insert_real("rotations", vec![n, 4], &s.rotations);
    f.insert_real("viewmatrix", vec![4, 4], &rc.viewmatrix);
    f.insert_real("projmatrix", vec![4, 4], &rc.projmatrix);
    f.insert_real("campos", vec![3], &rc.campos);
    f.insert_real("bg", vec![3], &s.background);
    let gc = liquid_splat::math::gradcheck::cotangent(1, 3 * rc.width * rc.height);
    let gd = liquid_splat::math::gradcheck::cotangent(2, rc.width * rc.height);
    f.insert_real("grad_out_color", vec![3, rc.height, rc.width], &gc);
    f.insert_real("grad_out_depth", vec![1, rc.height, rc.width], &gd);
    // Direct library results for comparison.
    let input = s.input(ColorSource::Sh, CovSource::ScaleRotation);
    let (out, state) = rasterize(&input).unwrap();
    let g = rasterize_vjp(&input, &state, &gc, Some(&gd), GradientMode::Exact).unwrap();
    assert!(matches!(input.colors, Colors::Sh { .. }));
    (f, out.color, g.means3d)
}

#[test]
fn round_trip_through_the_cli_matches_the_library() {
    let dir = support::tmp("round-trip");
    let (case, color, gmeans) = case_file(dir.join("in.safetensors"));
    case.save(&dir.join("in.safetensors")).unwrap();
    let (input, output) = (dir.join("in.safetensors"), dir.join("out.safetensors"));
    let st = cli(&["case", "run", s(&input), s(&output)]);
    assert!(st.status.success(), "{}", text(&st));
    let out = TensorFile::load(&dir.join("out.safetensors")).unwrap();
    assert_eq!(out.get_real::<f64>("color", &[3, 24, 32]).unwrap(), color);
    assert_eq!(
        out.get_real::<f64>("grad_means3D", &[6, 3]).unwrap(),
        gmeans
    );
    for name in [
        "depth",
        "final_T",
        "means2D",
        "grad_means2D",
        "grad_shs",
        "grad_opacities",
        "grad_scales",
        "grad_rotations",
    ] {
        assert!(out.contains(name), "{name}");
    }
    assert_eq!(out.shape("radii").unwrap(), &[6]);
    // Wrong stage: exit 2.
    let mut wrong = case.clone();
    wrong.set_meta("stage", "no-such-stage");
    wrong.save(&dir.join("wrong.safetensors")).unwrap();
    let (input, output) = (dir.join("wrong.safetensors"), dir.join("out2.safetensors"));
    let st = cli(&["case", "run", s(&input), s(&output)]);
    assert_eq!(st.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&st.stderr).contains("stage"));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn malformed_cases_name_the_problem() {
    let (case, _, _) = case_file(PathBuf::from("case.safetensors"));
    // Wrong shape.
    let mut c = case.clone();
    c.insert_real("opacities", vec![6], &[0.5f64; 6]);
    let e = run(&c).unwrap_err().to_string();
    assert!(
        e.contains("opacities") && e.contains("[6,1]") && e.contains("[6]"),
        "{e}"
    );
    // Missing tensor.
    let mut c = case.clone();
    c.tensors.remove("bg");
    let e = run(&c).unwrap_err().to_string();
    assert!(e.contains("bg"), "{e}");
    // Mixed dtype.
    let mut c = case.clone();
    c.insert_real("bg", vec![3], &[0.0f32; 3]);
    let e = run(&c).unwrap_err().to_string();
    assert!(e.contains("F64") || e.contains("F32"), "{e}");
    // Unknown tensor and bad metadata.
    let mut c = case.clone();
    c.insert_real("extra", vec![1], &[0.0f64]);
    assert!(run(&c).unwrap_err().to_string().contains("extra"));
    let mut c = case.clone();
    c.set_meta("sh_degree", "7");
    assert!(run(&c).unwrap_err().to_string().contains("degree"));
    let mut c = case;
    c.set_meta("gradient", "fancy");
    assert!(run(&c).unwrap_err().to_string().contains("fancy"));
}

#[test]
fn gradient_metadata_selects_the_mode_and_is_echoed() {
    let (case, _, gmeans) = case_file(PathBuf::from("case.safetensors"));
    let out = run(&case).unwrap();
    assert_eq!(out.meta("gradient").unwrap(), "exact");
    assert_eq!(
        out.get_real::<f64>("grad_means3D", &[6, 3]).unwrap(),
        gmeans
    );
    let mut c = case.clone();
    c.set_meta("gradient", "inria");
    let out_i = run(&c).unwrap();
    assert_eq!(out_i.meta("gradient").unwrap(), "inria");
    // The case has a depth gradient, which inria mode ignores.
    let s = random_scene(&SceneSpec::small(6, 3)).unwrap();
    let input = s.input(ColorSource::Sh, CovSource::ScaleRotation);
    let (_, state) = rasterize(&input).unwrap();
    let gc = case
        .get_real::<f64>("grad_out_color", &[3, 24, 32])
        .unwrap();
    let g = rasterize_vjp(&input, &state, &gc, None, GradientMode::Inria).unwrap();
    assert_eq!(
        out_i.get_real::<f64>("grad_means3D", &[6, 3]).unwrap(),
        g.means3d
    );
    // Forward outputs do not depend on the mode.
    assert_eq!(out_i.tensors["color"], out.tensors["color"]);
    assert_ne!(out_i.tensors["grad_means3D"], out.tensors["grad_means3D"]);
}
