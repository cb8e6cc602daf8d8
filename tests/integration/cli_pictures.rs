//! The picture commands on a tiny hand-made scene: what they write is checked pixel by pixel.

use crate::util::*;

#[test]
fn overlay_draws_the_square_where_the_pose_puts_it() {
    let dir = tempfile::tempdir().unwrap();
    let (mesh, cameras, poses, photo) = write_inputs(dir.path());
    let out = dir.path().join("overlay.png");
    let output = asgreg(&[
        "overlay",
        "--mesh",
        path_str(&mesh),
        "--image",
        path_str(&photo),
        "--cameras",
        path_str(&cameras),
        "--poses",
        path_str(&poses),
        "--out",
        path_str(&out),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    assert!(stdout(&output).contains("overlay.png"));
    let picture = image::open(&out).unwrap().to_rgb8();
    // The square spans ±2 m at 10 m with f = 60 px: columns 20..=43, rows 12..=35.
    let photo_pixel = image::Rgb([(2 * 4) as u8, (2 * 5) as u8, 90]);
    assert_eq!(
        picture.get_pixel(2, 2),
        &photo_pixel,
        "outside the model the photo is untouched"
    );
    assert_ne!(
        picture.get_pixel(32, 24)[2],
        90,
        "inside, the normal colour is blended in"
    );
    assert_eq!(
        picture.get_pixel(20, 24),
        &image::Rgb([255, 40, 40]),
        "the left silhouette is an edge"
    );
}

/// A gable 4 m wide: two planes meeting at a ridge along x, 1 m closer to the camera (z = 9 m) than
/// the eaves (z = 10 m). The ridge projects to image row 24 (pixel rows 23 and 24 meet there).
const GABLE_PLY: &str = "ply
format ascii 1.0
element vertex 6
property float x
property float y
property float z
element face 4
property list uchar int vertex_indices
end_header
-2 -2 10
2 -2 10
2 0 9
-2 0 9
2 2 10
-2 2 10
3 0 2 1
3 0 3 2
3 3 4 2
3 3 5 4
";

#[test]
fn render_writes_an_asg_image_with_the_ridge_and_flat_roof_planes() {
    let dir = tempfile::tempdir().unwrap();
    let (_, cameras, poses, _) = write_inputs(dir.path());
    let mesh = dir.path().join("gable.ply");
    std::fs::write(&mesh, GABLE_PLY).unwrap();
    let out = dir.path().join("asg.png");
    let output = asgreg(&[
        "render",
        "--mesh",
        path_str(&mesh),
        "--cameras",
        path_str(&cameras),
        "--poses",
        path_str(&poses),
        "--image",
        "photo.png",
        "--out",
        path_str(&out),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    assert!(stdout(&output).contains("asg.png"));
    let asg = image::open(&out).unwrap().to_luma8();
    assert_eq!(asg.dimensions(), (64, 48));
    assert_eq!(
        asg.get_pixel(32, 15)[0],
        0,
        "a flat roof plane has no shading gradient"
    );
    assert_eq!(asg.get_pixel(32, 33)[0], 0, "nor has the other one");
    let ridge = asg.get_pixel(32, 23)[0].max(asg.get_pixel(32, 24)[0]);
    assert!(ridge > 200, "the ridge is the strongest gradient: {ridge}");
}
