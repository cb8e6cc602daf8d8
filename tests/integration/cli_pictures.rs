//! The picture commands on a tiny hand-made scene: what they write is checked pixel by pixel.

use crate::util::*;

#[test]
fn overlay_draws_the_square_where_the_pose_puts_it() {
    let dir = tempfile::tempdir().unwrap();
    let (mesh, cameras, poses, photo) = write_inputs(dir.path());
    let out = dir.path().join("overlay.png");
    let output = asgreg(&[
        "overlay", "--mesh", path_str(&mesh), "--image", path_str(&photo), "--cameras", path_str(&cameras),
        "--poses", path_str(&poses), "--out", path_str(&out),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    assert!(stdout(&output).contains("overlay.png"));
    let picture = image::open(&out).unwrap().to_rgb8();
    // The square spans ±2 m at 10 m with f = 60 px: columns 20..=43, rows 12..=35.
    let photo_pixel = image::Rgb([(2 * 4) as u8, (2 * 5) as u8, 90]);
    assert_eq!(picture.get_pixel(2, 2), &photo_pixel, "outside the model the photo is untouched");
    assert_ne!(picture.get_pixel(32, 24)[2], 90, "inside, the normal colour is blended in");
    assert_eq!(picture.get_pixel(20, 24), &image::Rgb([255, 40, 40]), "the left silhouette is an edge");
}

#[test]
fn render_writes_an_asg_image_with_edges_at_the_silhouette() {
    let dir = tempfile::tempdir().unwrap();
    let (mesh, cameras, poses, _) = write_inputs(dir.path());
    let out = dir.path().join("asg.png");
    let output = asgreg(&[
        "render", "--mesh", path_str(&mesh), "--cameras", path_str(&cameras), "--poses", path_str(&poses),
        "--image", "photo.png", "--out", path_str(&out),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let asg = image::open(&out).unwrap().to_luma8();
    assert_eq!(asg.dimensions(), (64, 48));
    assert_eq!(asg.get_pixel(32, 24)[0], 0, "a flat square has no shading gradient inside");
    let silhouette_max = (18..=21).map(|col| asg.get_pixel(col, 24)[0]).max().unwrap();
    assert!(silhouette_max > 100, "the silhouette must show: {silhouette_max}");
}
