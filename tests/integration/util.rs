//! Helpers shared by the integration tests: running the binary and writing small input files.

use std::path::{Path, PathBuf};
use std::process::Output;

pub fn asgreg(args: &[&str]) -> Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_asgreg"))
        .args(args)
        .env("RUST_LOG", "warn")
        .output()
        .expect("the asgreg binary runs")
}

/// `tests/data/<relative>` (part of the repository, see `tests/data/README.md`), which must exist.
pub fn repo_data(relative: &str) -> PathBuf {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(relative);
    assert!(
        path.exists(),
        "{} is missing; it is part of the repository (tests/data/README.md)",
        path.display()
    );
    path
}

pub fn stderr(output: &Output) -> String {
    String::from_utf8_lossy(&output.stderr).into_owned()
}

pub fn stdout(output: &Output) -> String {
    String::from_utf8_lossy(&output.stdout).into_owned()
}

/// Asserts a failed run whose error message contains every one of `needles`.
pub fn assert_fails_naming(output: &Output, needles: &[&str]) {
    let message = stderr(output);
    assert!(
        !output.status.success(),
        "expected failure, got success; stderr: {message}"
    );
    for needle in needles {
        assert!(
            message.contains(needle),
            "stderr does not name '{needle}':\n{message}"
        );
    }
}

/// A 4 m × 4 m square 10 m in front of the identity camera, as an ASCII PLY.
pub const SQUARE_PLY: &str = "ply
format ascii 1.0
element vertex 4
property float x
property float y
property float z
element face 2
property list uchar int vertex_indices
end_header
-2 -2 10
2 -2 10
2 2 10
-2 2 10
3 0 2 1
3 0 3 2
";

pub const CAMERAS_TXT: &str = "# Camera list with one line of data per camera:
#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]
# Number of cameras: 1
1 PINHOLE 64 48 60 60 32 24
";

pub const IMAGES_TXT: &str = "# Image list with two lines of data per image:
#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME
#   POINTS2D[] as (X, Y, POINT3D_ID)
# Number of images: 1, mean observations per image: 0
1 1 0 0 0 0 0 0 1 photo.png

";

/// Writes a complete small input set (mesh, cameras, poses, a 64×48 photo) into `dir`.
pub fn write_inputs(dir: &Path) -> (PathBuf, PathBuf, PathBuf, PathBuf) {
    let mesh = dir.join("square.ply");
    let cameras = dir.join("cameras.txt");
    let poses = dir.join("images.txt");
    let photo = dir.join("photo.png");
    std::fs::write(&mesh, SQUARE_PLY).unwrap();
    std::fs::write(&cameras, CAMERAS_TXT).unwrap();
    std::fs::write(&poses, IMAGES_TXT).unwrap();
    write_png(&photo, 64, 48);
    (mesh, cameras, poses, photo)
}

pub fn write_png(path: &Path, width: u32, height: u32) {
    let image = image::RgbImage::from_fn(width, height, |x, y| {
        image::Rgb([(x * 4) as u8, (y * 5) as u8, 90])
    });
    image.save(path).unwrap();
}

pub fn path_str(path: &Path) -> &str {
    path.to_str().unwrap()
}

/// Writes a synthetic scene (`asgreg synth`, 30 px initial poses) of `frames` photos at
/// `width`×`height` into `dir/scene` and returns that folder.
pub fn synth_scene(dir: &Path, width: u32, height: u32, frames: usize) -> PathBuf {
    synth_scene_with(
        dir,
        &[
            "--width",
            &width.to_string(),
            "--height",
            &height.to_string(),
            "--images",
            &frames.to_string(),
            "--levels",
            "30",
        ],
    )
}

/// The integration tests' small change scene: `asgreg synth --changes` at 240×132 with `images`
/// photos, initial poses at `levels` (px) and `seed`, plus `extra` arguments, into `dir/scene`.
pub fn small_changes_scene(
    dir: &Path,
    images: usize,
    levels: u32,
    seed: u64,
    extra: &[&str],
) -> PathBuf {
    let (images, levels, seed) = (images.to_string(), levels.to_string(), seed.to_string());
    let mut args = vec![
        "--width",
        "240",
        "--height",
        "132",
        "--images",
        &images,
        "--levels",
        &levels,
        "--seed",
        &seed,
        "--changes",
    ];
    args.extend_from_slice(extra);
    synth_scene_with(dir, &args)
}

/// Writes `asgreg synth <args>` into `dir/scene` and returns that folder.
pub fn synth_scene_with(dir: &Path, args: &[&str]) -> PathBuf {
    let scene = dir.join("scene");
    let mut all = vec!["synth", "--out", path_str(&scene)];
    all.extend_from_slice(args);
    let output = asgreg(&all);
    assert!(output.status.success(), "{}", stderr(&output));
    scene
}
