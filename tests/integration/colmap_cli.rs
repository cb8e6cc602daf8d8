//! COLMAP models on the command line: `--cameras` and `--poses` take text or binary files or a
//! model folder (binary read first), and a broken or missing model is named.

use asgreg::io::colmap::read_model;
use asgreg::io::colmap_bin::write_model_bin;

use crate::util::*;

fn overlay(
    dir: &std::path::Path,
    mesh: &std::path::Path,
    cameras: &std::path::Path,
    poses: &std::path::Path,
    photo: &std::path::Path,
    out_name: &str,
) -> (std::process::Output, std::path::PathBuf) {
    let out = dir.join(out_name);
    let output = asgreg(&[
        "overlay",
        "--mesh",
        path_str(mesh),
        "--image",
        path_str(photo),
        "--cameras",
        path_str(cameras),
        "--poses",
        path_str(poses),
        "--out",
        path_str(&out),
    ]);
    (output, out)
}

#[test]
fn text_files_text_folders_binary_files_and_binary_folders_give_the_same_picture() {
    let dir = tempfile::tempdir().unwrap();
    let (mesh, cameras, poses, photo) = write_inputs(dir.path());
    let mut model = read_model(dir.path()).unwrap();
    // The photo's pose moved 0.5 m so that the square is not centred: any pose mix-up shows.
    model.images[0].cam_from_world.translation.x = 0.5;
    std::fs::write(
        &poses,
        "1 1 0 0 0 0.5 0 0 1 photo.png\n\n", // the same pose in text
    )
    .unwrap();
    let binary = dir.path().join("binary");
    std::fs::create_dir(&binary).unwrap();
    write_model_bin(&binary, &model).unwrap();

    let (output, reference) = overlay(dir.path(), &mesh, &cameras, &poses, &photo, "files.png");
    assert!(output.status.success(), "{}", stderr(&output));
    let reference = std::fs::read(reference).unwrap();
    for (cameras, poses, name) in [
        (
            dir.path().to_path_buf(),
            dir.path().to_path_buf(),
            "text_folder.png",
        ),
        (binary.clone(), binary.clone(), "binary_folder.png"),
        (
            binary.join("cameras.bin"),
            binary.join("images.bin"),
            "binary_files.png",
        ),
        (cameras.clone(), binary.clone(), "mixed.png"),
    ] {
        let (output, picture) = overlay(dir.path(), &mesh, &cameras, &poses, &photo, name);
        assert!(output.status.success(), "{name}: {}", stderr(&output));
        assert_eq!(std::fs::read(picture).unwrap(), reference, "{name}");
    }

    // A binary model beside the text one is read first: its pose (moved back) changes the picture.
    model.images[0].cam_from_world.translation.x = 0.0;
    write_model_bin(dir.path(), &model).unwrap();
    let (output, picture) = overlay(
        dir.path(),
        &mesh,
        dir.path(),
        dir.path(),
        &photo,
        "both.png",
    );
    assert!(output.status.success(), "{}", stderr(&output));
    assert_ne!(std::fs::read(picture).unwrap(), reference);
}

#[test]
fn broken_or_missing_models_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let (mesh, cameras, _, photo) = write_inputs(dir.path());
    let binary = dir.path().join("binary");
    std::fs::create_dir(&binary).unwrap();
    write_model_bin(&binary, &read_model(dir.path()).unwrap()).unwrap();

    // A cut images.bin: the file, the record and the field.
    let images_bin = binary.join("images.bin");
    let bytes = std::fs::read(&images_bin).unwrap();
    std::fs::write(&images_bin, &bytes[..bytes.len() - 3]).unwrap();
    let (output, _) = overlay(dir.path(), &mesh, &binary, &binary, &photo, "out.png");
    assert_fails_naming(
        &output,
        &["images.bin", "image record 1 of 1", "NUM_POINTS2D"],
    );

    // A folder with one binary file: the missing one is named.
    std::fs::remove_file(&images_bin).unwrap();
    let (output, _) = overlay(dir.path(), &mesh, &binary, &binary, &photo, "out.png");
    assert_fails_naming(&output, &["incomplete binary COLMAP model", "images.bin"]);

    // A folder without a model.
    let empty = dir.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    let (output, _) = overlay(dir.path(), &mesh, &cameras, &empty, &photo, "out.png");
    assert_fails_naming(&output, &["empty", "no COLMAP model here"]);
}
