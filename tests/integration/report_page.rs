//! `OUT/report.html` opened in a real browser (Debian's `chromium`, headless): `register` on a
//! tiny synthetic scene writes the page, the browser renders it (the screenshot is not blank) and
//! its script runs (the frame count it writes matches report.json). Fails, never skips, when
//! chromium is missing: install it with `apt-get install -y chromium` (.ci/run does).

use std::path::Path;
use std::process::Command;

use crate::util::*;

/// The browser: `$ASGREG_CHROMIUM` or `chromium` on the PATH.
fn chromium() -> String {
    let program = std::env::var("ASGREG_CHROMIUM").unwrap_or_else(|_| "chromium".to_string());
    let found = Command::new(&program).arg("--version").output();
    assert!(
        found.as_ref().is_ok_and(|o| o.status.success()),
        "the report test needs a headless browser: `{program} --version` failed ({:?}); install Debian's chromium \
         (`apt-get install -y chromium`, as .ci/run does) or set ASGREG_CHROMIUM to its path",
        found.map(|o| o.status)
    );
    program
}

/// Runs chromium headless on `page` with `args` (a fresh profile in `profile`), returns stdout.
fn run_chromium(program: &str, profile: &Path, page: &Path, args: &[&str]) -> String {
    let output = Command::new(program)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--hide-scrollbars",
            "--no-first-run",
            &format!("--user-data-dir={}", profile.display()),
        ])
        .args(args)
        .arg(format!("file://{}", page.display()))
        .output()
        .expect("chromium runs");
    assert!(
        output.status.success(),
        "chromium {args:?} failed: {}",
        stderr(&output)
    );
    stdout(&output)
}

/// The text of the element with `id` in a dumped DOM.
fn element_text<'a>(dom: &'a str, id: &str) -> &'a str {
    let start = dom
        .find(&format!("id=\"{id}\""))
        .unwrap_or_else(|| panic!("no element #{id} in the page"));
    let open_end = start + dom[start..].find('>').expect("the tag closes") + 1;
    let close = open_end + dom[open_end..].find('<').expect("the element closes");
    &dom[open_end..close]
}

#[test]
fn register_report_renders_in_a_headless_browser_with_every_frame() {
    let browser = chromium();
    let dir = tempfile::tempdir().unwrap();
    let scene = synth_scene(dir.path(), 160, 90, 3);
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
    assert!(output.status.success(), "{}", stderr(&output));
    let page = out.join("report.html");
    let html = std::fs::read_to_string(&page).unwrap();
    assert!(
        !html.contains("src=\"http") && !html.contains("href=\"http"),
        "the page loads nothing from the network"
    );
    assert!(
        html.matches("data:image/jpeg;base64,").count() >= 3,
        "every frame's overlays are embedded"
    );
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    let frames = report["frames"].as_array().unwrap();
    let accepted = frames.iter().filter(|f| f["accepted"] == true).count();

    let profile = dir.path().join("chromium-profile");
    let dom = run_chromium(&browser, &profile, &page, &["--dump-dom"]);
    assert_eq!(
        element_text(&dom, "frame-count"),
        frames.len().to_string(),
        "the count the page's script wrote"
    );
    assert_eq!(element_text(&dom, "accepted-count"), accepted.to_string());
    assert!(
        dom.contains("data-ready=\"1\""),
        "the script ran to its end"
    );

    let shot = dir.path().join("shot.png");
    run_chromium(
        &browser,
        &profile,
        &page,
        &[
            &format!("--screenshot={}", shot.display()),
            "--window-size=1280,900",
        ],
    );
    let picture = image::open(&shot)
        .expect("chromium wrote the screenshot")
        .to_rgb8();
    assert_eq!(picture.dimensions(), (1280, 900));
    let pixels = picture.pixels().count() as f64;
    let not_white = picture
        .pixels()
        .filter(|p| p.0.iter().any(|&c| c < 230))
        .count() as f64;
    let colourful = picture
        .pixels()
        .filter(|p| {
            let (max, min) = (p.0.iter().max().unwrap(), p.0.iter().min().unwrap());
            max - min > 40
        })
        .count() as f64;
    // Text, tables and the embedded overlays (photo colours, the model's normal colours).
    assert!(
        not_white / pixels > 0.05,
        "the screenshot is nearly blank: {:.1} % not white",
        100.0 * not_white / pixels
    );
    assert!(
        colourful / pixels > 0.02,
        "no pictures in the screenshot: {:.1} % colourful",
        100.0 * colourful / pixels
    );
}
