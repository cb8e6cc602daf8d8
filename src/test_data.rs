//! Where the tests' data lives (compiled for tests only; see `tests/data/README.md`).
//!
//! `tests/data/` is part of the repository: a test that reads it fails when a file is missing.
//! `../shared/data/` is the large data set beside the repository (the whole Brighton Beach set,
//! the 1010×550 flow pair): the tests that read it are `#[ignore]`d, their names start with
//! `shared_data_`, and run without the data they fail, naming the missing path. No test skips.

use std::path::{Path, PathBuf};

/// `tests/data/<relative>`, which must exist.
pub(crate) fn repo_data(relative: &str) -> PathBuf {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(relative);
    assert!(
        path.exists(),
        "{} is missing; it is part of the repository (tests/data/README.md)",
        path.display()
    );
    path
}

/// `../shared/data/<relative>` (the shared data set beside the repository), which must exist.
pub(crate) fn shared_data(relative: &str) -> PathBuf {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/data")
        .join(relative);
    assert!(
        path.exists(),
        "{} is absent: this test needs the shared data set beside the repository \
         (../shared/data), which is why it is #[ignore]d; run it only where that data is",
        path.display()
    );
    path
}
