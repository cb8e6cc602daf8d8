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
    let mesh = dir.path().join("huge.ply");
    // The header of a 10^8-vertex mesh; the data is never read.
    std::fs::write(
        &mesh,
        "ply\nformat binary_little_endian 1.0\nelement vertex 100000000\nproperty float x\n\
         property float y\nproperty float z\nelement face 200000000\n\
         property list uchar int vertex_indices\nend_header\n",
    )
    .unwrap();
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
