//! `asgreg synth --changes` then `asgreg changes` on a tiny house scene: the change map finds the
//! objects the scene was built with (changes.json), as confirmed objects of the right kind in
//! changes.geojson, and writes a mask and an overlay per photo and report.html; without `--depth`
//! the depth comes from plane-sweep stereo of each photo with its nearest posed photos.

use crate::util::*;

#[test]
fn changes_finds_the_new_and_the_demolished_buildings_of_a_synth_changes_scene() {
    let dir = tempfile::tempdir().unwrap();
    let scene = small_changes_scene(dir.path(), 9, 30, 2, &[]);
    let truth: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(scene.join("changes.json")).unwrap())
            .unwrap();
    let objects = truth["objects"].as_array().unwrap();
    assert_eq!(objects.len(), 3, "{truth}");

    let out = dir.path().join("changes");
    let output = asgreg(&[
        "changes",
        "--mesh",
        path_str(&scene.join("model.ply")),
        "--images",
        path_str(&scene.join("images")),
        "--cameras",
        path_str(&scene.join("gt/cameras.txt")),
        "--poses",
        path_str(&scene.join("gt/images.txt")),
        // The exact depth: since synth's depth/ became MVS-like (a third of the pixels, none
        // on grass), the demolished building, which stood on grass, is not found with it (the
        // ground behind has no depth); that is change detection's limit, not this CLI's.
        "--depth",
        path_str(&scene.join("depth_exact")),
        "--out",
        path_str(&out),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    assert!(stdout(&output).contains("confirmed"), "{}", stdout(&output));
    for k in 0..9 {
        assert!(out.join(format!("masks/view_{k:03}.png")).is_file());
        assert!(out.join(format!("overlays/view_{k:03}.png")).is_file());
        // report.html: a row per photo with the model and the change classes embedded.
        let html = std::fs::read_to_string(out.join("report.html")).unwrap();
        assert!(
            html.contains(&format!("view_{k:03}.jpg</td>")),
            "no row for view_{k:03}"
        );
    }
    let geojson: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("changes.geojson")).unwrap())
            .unwrap();
    assert_eq!(geojson["type"], "FeatureCollection");
    let features = geojson["features"].as_array().unwrap();
    // Every true object seen by two or more photos is a confirmed feature of its kind whose
    // footprint contains (or lies within 1 m of) the true footprint's centre.
    let mut checked = 0;
    for object in objects {
        let seen = object["pixels_per_image"]
            .as_object()
            .unwrap()
            .values()
            .filter(|v| v.as_u64().unwrap() >= 25)
            .count();
        if seen < 2 {
            continue;
        }
        checked += 1;
        let kind = object["kind"].as_str().unwrap();
        let corners = object["footprint_m"].as_array().unwrap();
        let centre = corners.iter().fold([0.0, 0.0], |acc, c| {
            [
                acc[0] + c[0].as_f64().unwrap() / corners.len() as f64,
                acc[1] + c[1].as_f64().unwrap() / corners.len() as f64,
            ]
        });
        let found = features.iter().any(|f| {
            let ring = f["geometry"]["coordinates"][0].as_array().unwrap();
            let (mut min, mut max) = ([f64::MAX; 2], [f64::MIN; 2]);
            for p in ring {
                for axis in 0..2 {
                    let v = p[axis].as_f64().unwrap();
                    min[axis] = min[axis].min(v);
                    max[axis] = max[axis].max(v);
                }
            }
            f["properties"]["kind"] == kind
                && f["properties"]["confirmed"] == true
                && (0..2).all(|a| centre[a] >= min[a] - 1.5 && centre[a] <= max[a] + 1.5)
        });
        assert!(found, "{object} not among {geojson}");
    }
    assert!(
        checked >= 2,
        "only {checked} objects seen by two photos: {truth}"
    );

    // Without --depth: stereo depth from the neighbouring photos, written beside the masks.
    let out = dir.path().join("changes_stereo");
    let output = asgreg(&[
        "changes",
        "--mesh",
        path_str(&scene.join("model.ply")),
        "--images",
        path_str(&scene.join("images")),
        "--cameras",
        path_str(&scene.join("gt/cameras.txt")),
        "--poses",
        path_str(&scene.join("gt/images.txt")),
        "--out",
        path_str(&out),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    assert!(
        stdout(&output).contains("plane-sweep stereo"),
        "{}",
        stdout(&output)
    );
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    assert_eq!(report["depth_source"], "stereo");
    let with_depth: Vec<&serde_json::Value> = report["frames"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|f| f["stereo"].is_object())
        .collect();
    assert!(with_depth.len() >= 3, "{report}");
    for frame in with_depth {
        let name = frame["name"].as_str().unwrap().replace(".jpg", ".pfm");
        assert!(out.join("depth").join(&name).is_file(), "{name}");
        assert!(
            frame["stereo"]["valid_fraction"].as_f64().unwrap() > 0.05,
            "{frame}"
        );
        assert!(!frame["stereo"]["neighbours"].as_array().unwrap().is_empty());
    }
}

#[test]
fn eval_changes_under_other_poses_measures_each_frames_pose_term_against_its_true_error() {
    let dir = tempfile::tempdir().unwrap();
    let scene = small_changes_scene(dir.path(), 6, 30, 3, &["--no-heading-level"]);
    // The initial poses (30 px off on average) as the poses to detect under, with no
    // registration report beside them: each frame allows for no pose error (u = 0), and the
    // table says how far each pose really was.
    let out = dir.path().join("eval");
    let output = asgreg(&[
        "eval",
        "--changes",
        "--scene",
        path_str(&scene),
        "--changes-poses",
        path_str(&scene.join("initial/30/images.txt")),
        "--out",
        path_str(&out),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    assert!(stdout(&output).contains("pose term"), "{}", stdout(&output));
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("changes_eval.json")).unwrap())
            .unwrap();
    let rows = json["pose_term"].as_array().unwrap();
    assert_eq!(
        rows.len() as u64,
        json["frames"].as_u64().unwrap(),
        "{json}"
    );
    assert!(!rows.is_empty());
    let mut deltas: Vec<f64> = rows
        .iter()
        .map(|r| {
            assert_eq!(r["u_px"].as_f64().unwrap(), 0.0, "{r}");
            r["true_delta_px"].as_f64().unwrap()
        })
        .collect();
    deltas.sort_by(f64::total_cmp);
    assert!(deltas[0] > 1.0, "{deltas:?}");
    assert!(deltas[deltas.len() / 2] > 10.0, "{deltas:?}");
}
