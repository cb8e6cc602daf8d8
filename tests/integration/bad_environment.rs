//! A bad environment (issue #15 item 5): an output folder that cannot be written, a disk that is
//! full, a mesh larger than the memory given. Each gives a one-line error naming the path and a
//! non-zero exit, before the work where it can be known before (folder, mesh size).

use std::path::{Path, PathBuf};
use std::process::Output;

use crate::util::*;

fn register(dir: &Path, mesh: &Path, out: &Path, extra: &[&str]) -> Output {
    let (_, cameras, poses, _) = write_inputs(dir);
    let mut args = vec![
        "register",
        "--mesh",
        path_str(mesh),
        "--images",
        path_str(dir),
        "--cameras",
        path_str(&cameras),
        "--poses",
        path_str(&poses),
        "--coarse-poses",
        "3",
        "--no-overlays",
        "--out",
        path_str(out),
    ];
    args.extend_from_slice(extra);
    asgreg(&args)
}

/// The run fails with exactly one line on stderr (the error) that names every needle.
fn assert_one_line_error(output: &Output, needles: &[&str]) {
    assert_fails_naming(output, needles);
    let message = stderr(output);
    let lines: Vec<&str> = message.trim_end().lines().collect();
    assert_eq!(lines.len(), 1, "expected a one-line error:\n{message}");
    assert!(lines[0].starts_with("error: "), "{message}");
}

#[test]
fn an_output_folder_that_cannot_be_created_is_named_before_the_work() {
    let dir = tempfile::tempdir().unwrap();
    let (mesh, ..) = write_inputs(dir.path());
    let blocker = dir.path().join("a-file");
    std::fs::write(&blocker, "not a folder").unwrap();
    let out = blocker.join("out");
    let output = register(dir.path(), &mesh, &out, &[]);
    assert_one_line_error(&output, &[path_str(&out), "cannot be created"]);
}

/// A disk that fills while the results are written: the first output file is `/dev/full`, whose
/// writes fail with ENOSPC, as on a full disk.
#[test]
fn a_full_disk_while_writing_the_results_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let (mesh, ..) = write_inputs(dir.path());
    let out = dir.path().join("out");
    std::fs::create_dir(&out).unwrap();
    let opk = out.join("poses_opk.csv");
    std::os::unix::fs::symlink("/dev/full", &opk).unwrap();
    let output = register(dir.path(), &mesh, &out, &[]);
    assert_one_line_error(&output, &[path_str(&opk), "No space left on device"]);
}

#[test]
fn a_mesh_above_the_memory_limit_is_refused_from_its_header() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = huge_mesh_header(dir.path());
    let out = dir.path().join("out");
    let output = register(dir.path(), &mesh, &out, &["--max-mesh-mib", "512"]);
    assert_one_line_error(
        &output,
        &[path_str(&mesh), "needs about 8011 MiB", "limit of 512 MiB"],
    );
    // Under the limit, the same command goes on to read the mesh (and finds its data missing).
    let output = register(dir.path(), &mesh, &out, &["--max-mesh-mib", "9000"]);
    assert_fails_naming(&output, &[path_str(&mesh), "element 'vertex' 0"]);
}

/// A tmpfs mounted for the test, unmounted when dropped.
struct Tmpfs(PathBuf);

impl Tmpfs {
    fn mount(dir: &Path, options: &str) -> Self {
        let point = dir.join("mnt");
        std::fs::create_dir(&point).unwrap();
        let status = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", options, "tmpfs", path_str(&point)])
            .status()
            .expect("the mount command runs");
        assert!(
            status.success(),
            "could not mount a tmpfs at {} (this test needs root)",
            point.display()
        );
        Self(point)
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount").arg(&self.0).status();
    }
}

#[test]
#[ignore = "needs root: mounts a read-only tmpfs (cargo test --test integration bad_environment -- --ignored)"]
fn root_an_output_folder_on_a_read_only_file_system_is_named_before_the_work() {
    let dir = tempfile::tempdir().unwrap();
    let (mesh, ..) = write_inputs(dir.path());
    let mount = Tmpfs::mount(dir.path(), "size=1m,ro");
    let output = register(dir.path(), &mesh, &mount.0, &[]);
    assert_one_line_error(
        &output,
        &[
            path_str(&mount.0),
            "cannot be written",
            "Read-only file system",
        ],
    );
}

#[test]
#[ignore = "needs root: mounts a 1 MiB tmpfs and fills it (cargo test --test integration bad_environment -- --ignored)"]
fn root_an_output_folder_on_a_full_tmpfs_is_named_before_the_work() {
    let dir = tempfile::tempdir().unwrap();
    let (mesh, ..) = write_inputs(dir.path());
    let mount = Tmpfs::mount(dir.path(), "size=1m");
    // Fill it: write until the disk refuses.
    {
        use std::io::Write as _;
        let mut filler = std::fs::File::create(mount.0.join("filler")).unwrap();
        while filler.write_all(&[0u8; 4096]).is_ok() {}
    }
    let out = mount.0.join("out");
    let output = register(dir.path(), &mesh, &out, &[]);
    assert_one_line_error(&output, &[path_str(&out), "No space left on device"]);
}

// The pipeline (`asgreg run`, `asgreg launch`): the same environment checked before any stage
// starts. A stage started into it would crash-loop (a mesh it cannot hold) or find out at the
// first result (a state folder it cannot write), and the output would be lost at the end.

/// A pipeline config over a mesh that is not there (these runs must stop before reading it),
/// `extra` lines added.
fn pipeline_config(dir: &Path, backend: &str, mesh: &Path, extra: &str) -> PathBuf {
    let (_, cameras, poses, _) = write_inputs(dir);
    let path = dir.join(format!("{backend}.toml"));
    std::fs::write(
        &path,
        format!(
            "mesh = \"{}\"\nbackend = \"{backend}\"\n{extra}\n[source]\nimages = \"{}\"\ncameras = \"{}\"\nposes = \"{}\"\n\n[transport]\npipeline = \"it-badenv-{backend}-{}\"\n",
            mesh.display(),
            dir.display(),
            cameras.display(),
            poses.display(),
            std::process::id()
        ),
    )
    .unwrap();
    path
}

/// `asgreg run` (threads) and `asgreg launch` (iceoryx2 processes) with `config_extra` in the
/// config and `args` after it; each must fail with one line naming every needle, and `launch`
/// before starting any stage (it prints a line per stage it starts).
fn assert_run_and_launch_refuse(
    dir: &Path,
    mesh: &Path,
    config_extra: &str,
    args: &[&str],
    needles: &[&str],
) {
    for (command, backend) in [("run", "crossbeam"), ("launch", "iceoryx2")] {
        let config = pipeline_config(dir, backend, mesh, config_extra);
        let mut full = vec![command];
        if command == "run" {
            full.push("--config");
        }
        full.push(path_str(&config));
        full.extend_from_slice(args);
        let output = asgreg(&full);
        assert_one_line_error(&output, needles);
    }
}

fn a_file_in_the_way(dir: &Path) -> PathBuf {
    let blocker = dir.join("a-file");
    std::fs::write(&blocker, "not a folder").unwrap();
    blocker
}

#[test]
fn the_pipeline_refuses_an_output_folder_that_cannot_be_created_before_any_stage() {
    let dir = tempfile::tempdir().unwrap();
    let out = a_file_in_the_way(dir.path()).join("out");
    assert_run_and_launch_refuse(
        dir.path(),
        &dir.path().join("missing.ply"),
        "",
        &["--out", path_str(&out)],
        &[path_str(&out), "output folder cannot be created"],
    );
}

#[test]
fn the_pipeline_refuses_a_state_folder_that_cannot_be_created_before_any_stage() {
    let dir = tempfile::tempdir().unwrap();
    let state = a_file_in_the_way(dir.path()).join("state");
    let out = dir.path().join("out");
    assert_run_and_launch_refuse(
        dir.path(),
        &dir.path().join("missing.ply"),
        &format!("state_dir = \"{}\"", state.display()),
        &["--out", path_str(&out)],
        &[
            path_str(&state),
            "state folder",
            "cannot be created",
            "state_dir",
        ],
    );
}

#[test]
fn the_pipeline_refuses_a_mesh_above_the_memory_limit_before_any_stage() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = huge_mesh_header(dir.path());
    let out = dir.path().join("out");
    let needles = [path_str(&mesh), "needs about 8011 MiB", "limit of 512 MiB"];
    // On the command line, and in the config.
    assert_run_and_launch_refuse(
        dir.path(),
        &mesh,
        "",
        &["--out", path_str(&out), "--max-mesh-mib", "512"],
        &needles,
    );
    assert_run_and_launch_refuse(
        dir.path(),
        &mesh,
        "max_mesh_mib = 512",
        &["--out", path_str(&out)],
        &needles,
    );
}

/// A state folder on a disk that fills while the pipeline runs: a 1 MiB tmpfs, filled to the
/// last byte once the run's results journal is there (the start's check has passed). The
/// journal's first page still takes a few lines (a full disk refuses new pages only); 16 frames'
/// lines need more. Every frame gets exactly one result, the run goes on to the end, and the
/// frames whose result could not be recorded are failed naming the journal and "No space left
/// on device".
#[test]
#[ignore = "needs root: mounts a 1 MiB tmpfs and fills it (cargo test --test integration bad_environment -- --ignored)"]
fn root_a_state_folder_that_fills_while_running_fails_those_frames_with_the_reason() {
    let dir = tempfile::tempdir().unwrap();
    let scene = synth_scene(dir.path(), 240, 132, 16);
    let mount = Tmpfs::mount(dir.path(), "size=1m");
    let config = dir.path().join("run.toml");
    std::fs::write(
        &config,
        format!(
            "synthetic_scene = \"{}\"\nstate_dir = \"{}\"\n\n[workers]\nchange = 0\n\n[registration]\ncoarse_pose_count = 3\n\n[transport]\npipeline = \"it-badenv-full-{}\"\n",
            scene.display(),
            mount.0.display(),
            std::process::id()
        ),
    )
    .unwrap();
    let out = dir.path().join("out");
    let child = std::process::Command::new(env!("CARGO_BIN_EXE_asgreg"))
        .args([
            "run",
            "--config",
            path_str(&config),
            "--out",
            path_str(&out),
        ])
        .env("RUST_LOG", "warn")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // The run's own state folder (asgreg-run-*) with its results journal, made when verify starts.
    let journal_is_there = || {
        std::fs::read_dir(&mount.0).unwrap().flatten().any(|run| {
            std::fs::read_dir(run.path()).is_ok_and(|files| {
                files.flatten().any(|f| {
                    f.file_name()
                        .to_string_lossy()
                        .ends_with(".results-journal")
                })
            })
        })
    };
    let started = std::time::Instant::now();
    while !journal_is_there() {
        assert!(
            started.elapsed() < std::time::Duration::from_secs(120),
            "no results journal appeared under {}",
            mount.0.display()
        );
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    {
        use std::io::Write as _;
        let mut filler = std::fs::File::create(mount.0.join("filler")).unwrap();
        while filler.write_all(&[0u8; 4096]).is_ok() {}
        while filler.write_all(&[0u8; 1]).is_ok() {}
    }
    let output = child.wait_with_output().unwrap();
    assert!(output.status.success(), "{}", stderr(&output));
    let text = std::fs::read_to_string(out.join("results.jsonl")).unwrap();
    let results: Vec<serde_json::Value> = text
        .lines()
        .map(|line| serde_json::from_str(line).unwrap())
        .collect();
    let ids: Vec<u64> = results
        .iter()
        .map(|r| r["frame_id"].as_u64().unwrap())
        .collect();
    assert_eq!(ids, (0..16).collect::<Vec<u64>>());
    let full: Vec<&str> = results
        .iter()
        .filter_map(|r| r["failure"].as_str())
        .filter(|f| f.contains("No space left on device"))
        .collect();
    assert!(!full.is_empty(), "no frame met the full disk:\n{text}");
    for failure in full {
        assert!(
            failure.starts_with(&format!("verify: {}", mount.0.display()))
                && failure.contains(".results-journal"),
            "{failure}"
        );
    }
}

/// `dir/huge.ply`: the header of a 10^8-vertex mesh (about 8011 MiB loaded) and no data; a limit
/// must refuse it from the header alone.
fn huge_mesh_header(dir: &Path) -> PathBuf {
    let mesh = dir.join("huge.ply");
    std::fs::write(
        &mesh,
        "ply\nformat binary_little_endian 1.0\nelement vertex 100000000\nproperty float x\n\
         property float y\nproperty float z\nelement face 200000000\n\
         property list uchar int vertex_indices\nend_header\n",
    )
    .unwrap();
    mesh
}
