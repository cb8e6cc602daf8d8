//! `asgreg flow` on the real flow pair of `tests/data/flow-pairs`: the written `.flo` is read back
//! and scored against the true flow (Ce Liu's reference reaches 0.44 px end-point error at full
//! resolution).

use crate::util::*;

#[test]
fn flow_on_the_real_pair_beats_the_reference_end_point_error() {
    let pairs = repo_data("flow-pairs");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("flow.flo");
    let output = asgreg(&[
        "flow",
        path_str(&pairs.join("dji0024_505x275_im1.png")),
        path_str(&pairs.join("dji0024_505x275_im2.png")),
        "--out",
        path_str(&out),
        "--truth",
        path_str(&pairs.join("dji0024_505x275_gt.flo")),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let printed = stdout(&output);
    assert!(printed.contains("belief propagation"), "{printed}");
    let flow = asgreg::io::flo::read_flo(&out).unwrap();
    let truth = asgreg::io::flo::read_flo(&pairs.join("dji0024_505x275_gt.flo")).unwrap();
    let (mut sum, mut count) = (0.0f64, 0usize);
    for row in 20..flow.height_px() - 20 {
        for col in 20..flow.width_px() - 20 {
            let u =
                |field: &asgreg::core::sift_flow::FlowField| field.u_px().get(col, row).copied();
            let v =
                |field: &asgreg::core::sift_flow::FlowField| field.v_px().get(col, row).copied();
            let (Some(u_px), Some(v_px), Some(true_u_px), Some(true_v_px)) =
                (u(&flow), v(&flow), u(&truth), v(&truth))
            else {
                panic!("the true flow is smaller than the flow");
            };
            sum += f64::from(u_px - true_u_px).hypot(f64::from(v_px - true_v_px));
            count += 1;
        }
    }
    let end_point_error_px = sum / count as f64;
    println!("asgreg flow end-point error: {end_point_error_px:.3} px");
    assert!(end_point_error_px <= 0.44, "{end_point_error_px}");
}

#[test]
fn flow_of_images_of_different_sizes_is_refused_with_both_names() {
    let dir = tempfile::tempdir().unwrap();
    let a = dir.path().join("a.png");
    let b = dir.path().join("b.png");
    write_png(&a, 40, 30);
    write_png(&b, 41, 30);
    let out = dir.path().join("f.flo");
    let output = asgreg(&["flow", path_str(&a), path_str(&b), "--out", path_str(&out)]);
    assert_fails_naming(&output, &["a.png", "b.png", "40x30", "41x30"]);
}
