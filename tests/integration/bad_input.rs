//! Bad input: every broken file gives one clear error that names the file (and the line or field
//! where there is one) and a non-zero exit.

use crate::util::*;

fn overlay_with(
    dir: &std::path::Path,
    mesh: &std::path::Path,
    cameras: &std::path::Path,
    poses: &std::path::Path,
    photo: &std::path::Path,
) -> std::process::Output {
    let out = dir.join("out.png");
    asgreg(&[
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
    ])
}

#[test]
fn missing_mesh_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let (_, cameras, poses, photo) = write_inputs(dir.path());
    let missing = dir.path().join("no_such_mesh.ply");
    let output = overlay_with(dir.path(), &missing, &cameras, &poses, &photo);
    assert_fails_naming(&output, &["no_such_mesh.ply"]);
}

#[test]
fn truncated_binary_mesh_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let (_, cameras, poses, photo) = write_inputs(dir.path());
    let mesh = dir.path().join("truncated.ply");
    let mut bytes = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n".to_vec();
    bytes.extend_from_slice(&[0u8; 20]); // 3 vertices need 36 bytes
    std::fs::write(&mesh, bytes).unwrap();
    let output = overlay_with(dir.path(), &mesh, &cameras, &poses, &photo);
    assert_fails_naming(&output, &["truncated.ply", "vertex"]);
}

#[test]
fn malformed_and_unsupported_meshes_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let (_, cameras, poses, photo) = write_inputs(dir.path());
    let garbage = dir.path().join("garbage.ply");
    std::fs::write(&garbage, "this is not a mesh\n").unwrap();
    assert_fails_naming(
        &overlay_with(dir.path(), &garbage, &cameras, &poses, &photo),
        &["garbage.ply"],
    );

    let unsupported = dir.path().join("list_x.ply");
    std::fs::write(
        &unsupported,
        SQUARE_PLY.replace("property float x", "property list uchar float x"),
    )
    .unwrap();
    assert_fails_naming(
        &overlay_with(dir.path(), &unsupported, &cameras, &poses, &photo),
        &["list_x.ply", "x"],
    );

    let no_faces = dir.path().join("points.ply");
    std::fs::write(
        &no_faces,
        "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n",
    )
    .unwrap();
    assert_fails_naming(
        &overlay_with(dir.path(), &no_faces, &cameras, &poses, &photo),
        &["points.ply", "no faces"],
    );

    let odd = dir.path().join("mesh.stl");
    std::fs::write(&odd, "solid x\n").unwrap();
    assert_fails_naming(
        &overlay_with(dir.path(), &odd, &cameras, &poses, &photo),
        &["mesh.stl"],
    );
}

#[test]
fn colmap_bad_lines_are_named_with_line_numbers() {
    let dir = tempfile::tempdir().unwrap();
    let (mesh, cameras, poses, photo) = write_inputs(dir.path());

    let bad_cameras = dir.path().join("bad_cameras.txt");
    std::fs::write(
        &bad_cameras,
        CAMERAS_TXT.replace("60 60 32 24", "60 sixty 32 24"),
    )
    .unwrap();
    assert_fails_naming(
        &overlay_with(dir.path(), &mesh, &bad_cameras, &poses, &photo),
        &["bad_cameras.txt", "4"],
    );

    let bad_poses = dir.path().join("bad_images.txt");
    std::fs::write(
        &bad_poses,
        IMAGES_TXT.replace("1 1 0 0 0 0 0 0 1", "1 1 0 0 0 nan 0 0 1"),
    )
    .unwrap();
    assert_fails_naming(
        &overlay_with(dir.path(), &mesh, &cameras, &bad_poses, &photo),
        &["bad_images.txt", "5", "TX"],
    );

    let short_line = dir.path().join("short_images.txt");
    std::fs::write(
        &short_line,
        IMAGES_TXT.replace("1 1 0 0 0 0 0 0 1 photo.png", "1 1 0 0 0"),
    )
    .unwrap();
    assert_fails_naming(
        &overlay_with(dir.path(), &mesh, &cameras, &short_line, &photo),
        &["short_images.txt", "5"],
    );
}

#[test]
fn image_not_matching_its_camera_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let (mesh, cameras, poses, _) = write_inputs(dir.path());
    let photo = dir.path().join("photo.png");
    write_png(&photo, 80, 48);
    let output = overlay_with(dir.path(), &mesh, &cameras, &poses, &photo);
    assert_fails_naming(&output, &["photo.png", "80", "64"]);
}

#[test]
fn image_not_in_the_poses_file_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let (mesh, cameras, poses, _) = write_inputs(dir.path());
    let other = dir.path().join("other.png");
    write_png(&other, 64, 48);
    let output = overlay_with(dir.path(), &mesh, &cameras, &poses, &other);
    assert_fails_naming(&output, &["other.png", "images.txt"]);
}

#[test]
fn corrupt_image_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let (mesh, cameras, poses, photo) = write_inputs(dir.path());
    let bytes = std::fs::read(&photo).unwrap();
    std::fs::write(&photo, &bytes[..bytes.len() / 2]).unwrap();
    let output = overlay_with(dir.path(), &mesh, &cameras, &poses, &photo);
    assert_fails_naming(&output, &["photo.png"]);
}
