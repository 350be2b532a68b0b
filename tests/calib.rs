//! `flownav calib import|show` on the binary: OpenCV (YAML, XML) and ROS calibration files in,
//! flownav TOML out, with the numbers exact; the built-in calibration from outside the repository.

use flownav::calib_import::{self, SourceFormat};
use hal::Calibration;
use hal::calib::Mount;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn flownav(dir: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_flownav"))
        .args(args)
        .current_dir(dir)
        .env("NO_COLOR", "1")
        .output()
        .expect("the flownav binary runs")
}

fn example(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("calib/examples").join(name)
}

fn text(out: &[u8]) -> String {
    String::from_utf8_lossy(out).into_owned()
}

/// The numbers OpenCV wrote into the example files (`%.16e`), digit for digit: the import must
/// read them to the same doubles as Rust reads these literals.
#[allow(clippy::excessive_precision)]
const OPENCV_K: [f64; 4] =
    [1.2683147259306331e+03, 1.2691608713912416e+03, 6.4217384615027162e+02, 3.5538152306231474e+02];
#[allow(clippy::excessive_precision)]
const OPENCV_D: [f64; 5] = [
    -7.1243609865213456e-02,
    1.2541876530127718e-01,
    -4.3081287329148261e-04,
    3.1147302915580911e-04,
    -5.3820951843300102e-02,
];

#[test]
fn opencv_yaml_and_xml_import_to_the_same_exact_numbers_with_the_given_mount() {
    let dir = tempfile::tempdir().unwrap();
    for (file, format) in [("opencv-c310.yaml", SourceFormat::OpenCvYaml), ("opencv-c310.xml", SourceFormat::OpenCvXml)]
    {
        let source = std::fs::read_to_string(example(file)).unwrap();
        assert_eq!(calib_import::import(&source, file).unwrap().format, format);
        let out = dir.path().join(file.replace('.', "-")).with_extension("toml");
        let run = flownav(
            dir.path(),
            &[
                "calib",
                "import",
                example(file).to_str().unwrap(),
                "--mount",
                "0.12,-0.01,0.35,0.05",
                "-o",
                out.to_str().unwrap(),
            ],
        );
        assert!(run.status.success(), "{}", text(&run.stderr));
        let c = Calibration::load(&out).unwrap();
        let i = c.camera;
        assert_eq!((i.width, i.height), (1280, 720));
        assert_eq!([i.fx, i.fy, i.cx, i.cy], OPENCV_K, "{file}");
        assert_eq!(i.distortion, OPENCV_D, "{file}");
        assert_eq!(c.mount, Mount { x_m: 0.12, y_m: -0.01, z_m: 0.35, pitch_rad: 0.05 });
        // Not overwritten without --force.
        let again =
            flownav(dir.path(), &["calib", "import", example(file).to_str().unwrap(), "-o", out.to_str().unwrap()]);
        assert!(!again.status.success() && text(&again.stderr).contains("--force"), "{}", text(&again.stderr));
    }
}

#[test]
fn ros_camera_info_imports_to_stdout_with_the_nominal_mount_and_a_warning() {
    let dir = tempfile::tempdir().unwrap();
    let run = flownav(dir.path(), &["calib", "import", example("ros-c310.yaml").to_str().unwrap()]);
    assert!(run.status.success(), "{}", text(&run.stderr));
    let c = Calibration::from_toml(&text(&run.stdout), "stdout").unwrap();
    let i = c.camera;
    // ROS writes shortest round-trip decimals: these literals are the file's.
    assert_eq!([i.fx, i.fy, i.cx, i.cy], [1268.314725930633, 1269.160871391242, 642.1738461502716, 355.3815230623147]);
    assert_eq!(
        i.distortion,
        [-0.07124360986521346, 0.1254187653012772, -0.0004308128732914826, 0.0003114730291558091, -0.0538209518433001]
    );
    assert!(c.model.starts_with("c310 (imported from the ROS camera_info YAML"), "{}", c.model);
    assert_eq!(c.mount, Calibration::nominal_c310().mount);
    assert!(text(&run.stdout).contains("measure it"), "the file says its mount is not measured");
    assert!(text(&run.stderr).contains("--mount"), "{}", text(&run.stderr));
}

#[test]
fn missing_fields_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let ros = std::fs::read_to_string(example("ros-c310.yaml")).unwrap();
    for (field, broken) in [
        ("image_width", ros.replace("image_width: 1280\n", "")),
        ("camera_matrix", ros.replace("camera_matrix:", "camera_matrices:")),
        ("distortion_coefficients", ros.replace("distortion_coefficients:", "distortion:")),
    ] {
        let path = dir.path().join("broken.yaml");
        std::fs::write(&path, broken).unwrap();
        let run = flownav(dir.path(), &["calib", "import", path.to_str().unwrap()]);
        assert!(!run.status.success());
        let err = text(&run.stderr);
        assert!(err.contains(&format!("missing field `{field}`")) && err.contains("broken.yaml"), "{err}");
    }
}

#[test]
fn show_prints_the_field_of_view_of_the_closed_form() {
    let dir = tempfile::tempdir().unwrap();
    let run = flownav(dir.path(), &["calib", "show", example("opencv-c310.xml").to_str().unwrap()]);
    assert!(run.status.success(), "{}", text(&run.stderr));
    let out = text(&run.stdout);
    assert!(out.contains("OpenCV FileStorage XML") && out.contains("fx 1268.3147259306331 px"), "{out}");
    assert!(out.contains("bottom-right") && out.contains("mount         (not in this file"), "{out}");

    // A pinhole: the closed form 2·atan(w / 2f) (principal point at the centre).
    let pinhole = "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   \
                   cols: 3\n   dt: d\n   data: [ 500., 0., 319.5, 0., 500., 239.5, 0., 0., 1. ]\n\
                   distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ 0., 0., 0., 0., 0. ]\n";
    let path = dir.path().join("pinhole.yml");
    std::fs::write(&path, pinhole).unwrap();
    let run = flownav(dir.path(), &["calib", "show", path.to_str().unwrap()]);
    assert!(run.status.success(), "{}", text(&run.stderr));
    let (h, v, d) = (
        2.0 * (320.0f64 / 500.0).atan().to_degrees(),
        2.0 * (240.0f64 / 500.0).atan().to_degrees(),
        2.0 * (400.0f64 / 500.0).atan().to_degrees(),
    );
    let expected = format!("field of view {h:.2}° horizontal, {v:.2}° vertical, {d:.2}° diagonal");
    assert!(text(&run.stdout).contains(&expected), "{expected}\n{}", text(&run.stdout));
    assert!(text(&run.stdout).contains("top-left        0.00 px"), "{}", text(&run.stdout));
}

#[test]
fn the_built_in_calibration_works_outside_the_repository() {
    let dir = tempfile::tempdir().unwrap();
    assert!(!dir.path().join("calib").exists());
    let run = flownav(dir.path(), &["calib", "show"]);
    assert!(run.status.success(), "{}", text(&run.stderr));
    let out = text(&run.stdout);
    assert!(out.contains("calibration   built-in") && out.contains("fx 1272 px"), "{out}");
    let (h, v) = (2.0 * (640.0f64 / 1272.0).atan(), 2.0 * (360.0f64 / 1272.0).atan());
    let expected = format!("field of view {:.2}° horizontal, {:.2}° vertical", h.to_degrees(), v.to_degrees());
    assert!(out.contains(&expected), "{expected}\n{out}");
    // --calib overrides it.
    let wide = Path::new(env!("CARGO_MANIFEST_DIR")).join("calib/wide90.toml");
    let run = flownav(dir.path(), &["--calib", wide.to_str().unwrap(), "calib", "show"]);
    assert!(text(&run.stdout).contains("90.00° horizontal"), "{}", text(&run.stdout));
    // A missing --calib file is an error that names it.
    let run = flownav(dir.path(), &["--calib", "nowhere.toml", "calib", "show"]);
    assert!(!run.status.success() && text(&run.stderr).contains("nowhere.toml"), "{}", text(&run.stderr));
}
