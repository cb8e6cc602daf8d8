//! `asgreg register` on a tiny synthetic scene: every input frame gets exactly one entry in
//! report.json, a frame whose photo is missing fails with a reason naming the file, and the run
//! still writes its COLMAP output (text and binary) and its omega-phi-kappa CSV.

use crate::util::*;

#[test]
fn every_frame_gets_exactly_one_result_even_when_its_photo_is_missing() {
    let dir = tempfile::tempdir().unwrap();
    let scene = synth_scene(dir.path(), 160, 90, 3);
    let missing = scene.join("images/view_001.jpg");
    std::fs::remove_file(&missing).unwrap();
    let out = dir.path().join("out");
    let output = asgreg(&[
        "register",
        "--mesh",
        path_str(&scene.join("model.ply")),
        "--images",
        path_str(&scene.join("images")),
        "--cameras",
        path_str(&scene.join("gt/cameras.txt")),
        "--poses",
        path_str(&scene.join("initial/30/images.txt")),
        "--depth",
        path_str(&scene.join("depth")),
        "--coarse-poses",
        "5",
        "--out",
        path_str(&out),
    ]);
    assert!(
        output.status.success(),
        "a failed frame must not fail the run: {}",
        stderr(&output)
    );
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    let frames = report["frames"].as_array().unwrap();
    let names: Vec<&str> = frames.iter().map(|f| f["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["view_000.jpg", "view_001.jpg", "view_002.jpg"]);
    let failed = &frames[1];
    assert_eq!(failed["accepted"], false);
    assert!(
        failed["reason"].as_str().unwrap().contains("view_001.jpg"),
        "{failed}"
    );
    for frame in frames {
        let accepted = frame["accepted"].as_bool().unwrap();
        assert_eq!(
            accepted,
            frame["reason"].is_null(),
            "accepted frames have no reason: {frame}"
        );
        assert_eq!(accepted, !frame["cam_from_world"].is_null());
        if accepted {
            assert!(frame["rejected_candidate"].is_null(), "{frame}");
        }
    }
    // A frame that never got as far as a pose has no candidate either.
    assert!(failed["rejected_candidate"].is_null(), "{failed}");
    // The COLMAP output lists exactly the accepted frames.
    let accepted = frames.iter().filter(|f| f["accepted"] == true).count();
    let poses = asgreg::io::colmap::read_images_txt(&out.join("images.txt")).unwrap();
    assert_eq!(poses.len(), accepted);
    // The same poses in COLMAP's binary format (read first), and one omega-phi-kappa row each.
    let (binary, format) = asgreg::io::colmap_model::read_model_dir(&out).unwrap();
    assert_eq!(format, asgreg::io::colmap_model::ModelFormat::Binary);
    let names = |images: &[asgreg::io::colmap::ImagePose]| -> Vec<String> {
        images.iter().map(|image| image.name.clone()).collect()
    };
    assert_eq!(names(&binary.images), names(&poses));
    let opk = std::fs::read_to_string(out.join("poses_opk.csv")).unwrap();
    assert!(
        opk.starts_with("name,X,Y,Z,omega_deg,phi_deg,kappa_deg\n"),
        "{opk}"
    );
    assert_eq!(opk.lines().count(), accepted + 1, "{opk}");
    assert!(out.join("overlays/view_000_before.png").is_file());
}

#[test]
fn register_with_a_missing_mesh_names_it_and_exits_non_zero() {
    let dir = tempfile::tempdir().unwrap();
    let (_, cameras, poses, _) = write_inputs(dir.path());
    let out = dir.path().join("out");
    let output = asgreg(&[
        "register",
        "--mesh",
        path_str(&dir.path().join("nope.ply")),
        "--images",
        path_str(dir.path()),
        "--cameras",
        path_str(&cameras),
        "--poses",
        path_str(&poses),
        "--out",
        path_str(&out),
    ]);
    assert_fails_naming(&output, &["nope.ply"]);
}

/// `synth --scene city` writes a scene `register` runs on, and `register --truth` puts each
/// frame's δ to the true poses in its output: the path of issue #16's city-size check, small.
#[test]
fn a_city_scene_registers_and_truth_gives_each_frame_its_delta() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("city");
    let output = asgreg(&[
        "synth",
        "--scene",
        "city",
        "--triangles",
        "30000",
        "--images",
        "2",
        "--levels",
        "30",
        "--no-heading-level",
        "--width",
        "240",
        "--height",
        "135",
        "--out",
        path_str(&scene),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    assert!(stdout(&output).contains("peak RSS"), "{}", stdout(&output));
    let out = dir.path().join("out");
    let output = asgreg(&[
        "register",
        "--mesh",
        path_str(&scene.join("model.ply")),
        "--images",
        path_str(&scene.join("images")),
        "--cameras",
        path_str(&scene.join("gt")),
        "--poses",
        path_str(&scene.join("initial/30")),
        "--truth",
        path_str(&scene.join("gt")),
        "--diagnose",
        "--coarse-poses",
        "5",
        "--no-overlays",
        "--out",
        path_str(&out),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    // --diagnose: each frame run step by step against its true pose, with the truth's own
    // evidence (the tables of `eval --diagnose`).
    let diagnosis: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("diagnosis.json")).unwrap())
            .unwrap();
    let frames = diagnosis["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 2, "{diagnosis}");
    for frame in frames {
        let truth = &frame["diagnosis"]["truth_correlation"];
        assert!(
            truth["at_pose"].as_f64().unwrap() > truth["far"].as_f64().unwrap(),
            "{frame}"
        );
        assert!(
            frame["diagnosis"]["truth_best_confidence"].is_f64(),
            "{frame}"
        );
    }
    assert!(std::fs::read_to_string(out.join("diagnosis.md"))
        .unwrap()
        .contains("correlation at truth"));
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    let deltas = report["truth"]["delta_px"].as_array().unwrap();
    assert_eq!(deltas.len(), 2, "{report}");
    for (frame, delta) in report["frames"].as_array().unwrap().iter().zip(deltas) {
        let initial_px = delta["delta"]["initial_px"].as_f64().unwrap();
        assert!((5.0..80.0).contains(&initial_px), "{delta}");
        // An accepted frame has its δ after; a refused one none.
        assert_eq!(
            frame["accepted"].as_bool().unwrap(),
            delta["delta"]["final_px"].is_f64(),
            "{frame} {delta}"
        );
    }
    assert!(report["peak_rss_mib"].as_f64().unwrap() > 0.0);
    assert!(
        stdout(&output).contains("δ to the truth"),
        "{}",
        stdout(&output)
    );
}
