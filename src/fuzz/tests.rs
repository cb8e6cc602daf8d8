//! The short form of the fuzz run (every `cargo test`), the full form (`#[ignore]`d; also
//! `asgreg fuzz`), and the guard's own checks.

use std::path::Path;

use super::*;

fn repo() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn run_all(inputs_per_target: usize) {
    let work = tempfile::tempdir_in(default_work_root()).unwrap();
    let targets = all_targets(repo(), &work.path().join("seeds")).unwrap();
    let options = FuzzOptions::new(inputs_per_target, 1, work.path().join("run"));
    let mut failures = Vec::new();
    println!("{MARKDOWN_HEADER}");
    for target in &targets {
        let report = run_target(target, &options).unwrap();
        println!("{}", markdown_row(&report));
        assert_eq!(
            report.inputs, inputs_per_target,
            "{}: inputs run",
            target.name
        );
        for finding in &report.findings {
            failures.push(format!(
                "{} input {:?}: {:?}: {} ({} bytes: {:?})",
                target.name,
                finding.input_index,
                finding.kind,
                finding.detail,
                finding.input.len(),
                String::from_utf8_lossy(&finding.input[..finding.input.len().min(200)])
            ));
        }
    }
    assert!(
        failures.is_empty(),
        "fuzz findings:\n{}",
        failures.join("\n")
    );
}

#[test]
fn short_fuzz_of_every_reader_and_decoder_finds_nothing() {
    run_all(300);
}

#[test]
#[ignore = "the full form: 10^4 inputs per target, minutes; also `asgreg fuzz`"]
fn full_fuzz_of_every_reader_and_decoder_finds_nothing() {
    run_all(10_000);
}

#[test]
fn every_reader_of_user_files_and_every_message_kind_is_a_target() {
    let work = tempfile::tempdir_in(default_work_root()).unwrap();
    let targets = all_targets(repo(), work.path()).unwrap();
    let names: Vec<&str> = targets.iter().map(|t| t.name.as_str()).collect();
    for expected in [
        "ply-binary",
        "ply-ascii",
        "obj",
        "colmap-cameras-txt",
        "colmap-images-txt",
        "colmap-cameras-bin",
        "colmap-images-bin",
        "colmap-points3d-bin",
        "pfm",
        "flo",
        "image-png",
        "image-jpeg",
        "priors-jpeg",
        "priors-exif-csv",
        "priors-offset",
        "pipeline-config",
        "msg-Frame",
        "msg-FlowJob",
        "msg-Correspondences",
        "msg-Hypothesis",
        "msg-FrameFailed",
        "msg-PoseResult",
        "msg-Credit",
        "msg-Metrics",
        "msg-StreamEnd",
        "msg-FrameQuery",
    ] {
        assert!(
            names.contains(&expected),
            "no fuzz target {expected}: {names:?}"
        );
    }
    // Every message kind on the wire, those added after this list included (the change
    // messages of v5 were missing until the list came from the wire).
    let mut value = 1u16;
    while let Some(kind) = crate::msg::MessageKind::from_wire(value) {
        let expected = format!("msg-{kind:?}");
        assert!(
            names.contains(&expected.as_str()),
            "no fuzz target {expected}: {names:?}"
        );
        value += 1;
    }
    assert!(value > 13, "the wire has {} kinds", value - 1);
}

/// The guard is this test binary's allocator and counts: a parser that allocates for a count
/// read from the file is reported as a blow-up.
#[test]
fn a_parser_that_allocates_for_a_count_it_read_is_a_blowup() {
    let work = tempfile::tempdir_in(default_work_root()).unwrap();
    let target = Target {
        name: "naive-counts".to_string(),
        file_name: "counts.bin",
        seeds: vec![vec![0, 0, 0, 1]],
        text: false,
        names_file: true,
        names_place: &["line"],
        allocation_per_input_byte: 64,
        fixup: None,
        parse: |path, bytes| {
            if bytes.len() < 4 {
                return Err(format!("{}: too short", path.display()));
            }
            // Trusts the count: up to 4 GiB, far above the budget of a 4-byte input.
            let count = u32::from_be_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]) as usize;
            let values = std::hint::black_box(vec![0u8; count.min(1 << 30)]);
            drop(values);
            Ok(())
        },
    };
    let options = FuzzOptions::new(200, 3, work.path().to_path_buf());
    let report = run_target(&target, &options).unwrap();
    assert!(report.count(FindingKind::Blowup) > 0, "{report:?}");
}

#[test]
fn a_panic_and_an_error_without_the_file_are_found_and_the_panic_minimised() {
    let work = tempfile::tempdir_in(default_work_root()).unwrap();
    let target = Target {
        name: "fragile".to_string(),
        file_name: "fragile.txt",
        seeds: vec![b"count 3\nabc\n".to_vec()],
        text: true,
        names_file: true,
        names_place: &["line"],
        allocation_per_input_byte: 64,
        fixup: None,
        parse: |_, bytes| {
            let text = std::str::from_utf8(bytes).map_err(|_| "not text".to_string())?;
            let count: usize = text
                .split_whitespace()
                .nth(1)
                .and_then(|word| word.parse().ok())
                .ok_or("no count")?;
            // Indexes with the count it read.
            let _byte = text.as_bytes()[count];
            Ok(())
        },
    };
    let options = FuzzOptions::new(300, 5, work.path().to_path_buf());
    let report = run_target(&target, &options).unwrap();
    assert!(report.count(FindingKind::Panic) > 0, "{report:?}");
    assert!(
        report.count(FindingKind::ErrorWithoutFile) > 0,
        "{report:?}"
    );
    assert!(
        report.count(FindingKind::ErrorWithoutPlace) > 0,
        "{report:?}"
    );
    let panic = report
        .findings
        .iter()
        .find(|finding| finding.kind == FindingKind::Panic)
        .unwrap();
    assert!(
        panic.detail.contains("src/fuzz/tests.rs"),
        "{}",
        panic.detail
    );
    let minimised = minimise_panic(&target, &work.path().join("min.txt"), &panic.input, 2000);
    assert!(minimised.len() <= panic.input.len());
    assert!(
        minimised.len() <= 10,
        "{:?}",
        String::from_utf8_lossy(&minimised)
    );
}

#[test]
fn the_same_seed_gives_the_same_inputs() {
    let work = tempfile::tempdir_in(default_work_root()).unwrap();
    let targets = all_targets(repo(), work.path()).unwrap();
    for target in targets.iter().take(3) {
        assert_eq!(input_for(target, 9, 17), input_for(target, 9, 17));
        assert_ne!(input_for(target, 9, 17), input_for(target, 10, 17));
    }
}

#[test]
fn an_error_must_say_where_in_the_file_by_its_format_rule() {
    let work = tempfile::tempdir_in(default_work_root()).unwrap();
    let targets = all_targets(repo(), work.path()).unwrap();
    for target in &targets {
        // Image decoders report no position: their errors are not checked for a place.
        let unplaced = !target.names_file || target.name.starts_with("image-");
        assert_eq!(
            unplaced,
            target.names_place.is_empty(),
            "{}: every file reader but the image decoders has a rule for where its errors point",
            target.name
        );
    }
    let text = targets
        .iter()
        .find(|t| t.name == "colmap-images-txt")
        .unwrap();
    // The message as the check sees it: the file's path taken out.
    assert!(names_place(text, ": line 3: `x` is not a number"));
    assert!(names_place(text, ":12: field QW: found x; a number"));
    assert!(!names_place(text, ": not a number"));
    assert!(!names_place(text, ": 12 fields"));
    let ply = targets.iter().find(|t| t.name == "ply-binary").unwrap();
    assert!(names_place(
        ply,
        ": element face, record 3, property vertex_indices: cut short"
    ));
    assert!(!names_place(ply, ": unexpected end of file"));
    let message = targets.iter().find(|t| t.name == "msg-Frame").unwrap();
    assert!(names_place(message, "anything"));
}
