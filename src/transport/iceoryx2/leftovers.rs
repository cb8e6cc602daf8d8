//! What iceoryx2 0.10's own dead-node cleanup cannot remove, removed by file. Two shapes were
//! left in `/tmp/iceoryx2/nodes` by the iceoryx2 soak (a SIGKILL every second, CI of
//! 2026-12-04: 25 files more after the run than before, and every later cleanup warned about
//! the same dead nodes):
//! - **half-removed**: a dead node whose `.details` file is gone but whose directory still holds
//!   an (empty) tag file. iceoryx2 removes the details only in its last step, after it detached
//!   the node from every service and port it found; the tag it did not find keeps the directory,
//!   so that last step and every later try fail (`NotEmptyOrHardLinksPointingToTheDirectory`,
//!   reported as `InternalError`; upstream iceoryx2 #1967 is this for port tags).
//! - **unborn**: a node directory with only its `.details` and no monitor token:
//!   `NodeBuilder::create` writes the details first and the token next, and the process was
//!   killed in between. `Node::list` finds nodes by their token, so iceoryx2 never sees it.
//!
//! Only files of these two shapes are removed, with names taken from iceoryx2's [`Config`]; a
//! service tag whose service still exists is kept (that service may still count the node).

use std::collections::HashSet;
use std::io;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

use ::iceoryx2::config::Config;

/// Where and under which names iceoryx2 keeps its node files (from its configuration).
#[derive(Clone, Debug)]
pub(super) struct Layout {
    node_dir: PathBuf,
    service_dir: PathBuf,
    prefix: String,
    monitor_suffix: String,
    details_suffix: String,
    service_tag_suffix: String,
    port_tag_suffix: String,
}

/// What [`remove_unborn_nodes`] did.
#[derive(Debug, Default, PartialEq)]
pub(super) struct Unborn {
    /// Unborn node directories removed.
    pub removed: usize,
    /// How long until the youngest unborn node left in place is old enough; `None` when none
    /// was left.
    pub next_in: Option<Duration>,
}

impl Layout {
    pub(super) fn of(config: &Config) -> Self {
        let global = &config.global;
        Self {
            node_dir: PathBuf::from(global.node_dir().to_string()),
            service_dir: PathBuf::from(global.service_dir().to_string()),
            prefix: global.prefix.to_string(),
            monitor_suffix: global.node.monitor_suffix.to_string(),
            details_suffix: global.node.static_config_suffix.to_string(),
            service_tag_suffix: global.node.service_tag_suffix.to_string(),
            port_tag_suffix: global.node.port_tag_suffix.to_string(),
        }
    }

    /// The directory of node `id` (its details and tags).
    fn node_files(&self, id: u128) -> PathBuf {
        self.node_dir.join(id.to_string())
    }

    /// The ids of the nodes with a monitor token (or one of its companion files), under any
    /// file prefix (node directories are named by id alone, whatever the prefix): one listing.
    fn monitored_ids(&self) -> io::Result<HashSet<u128>> {
        Ok(names_in(&self.node_dir)?
            .iter()
            .filter_map(|name| {
                let (before, _) = name.split_once(self.monitor_suffix.as_str())?;
                // The id is the run of digits ending where the suffix begins (a prefix may hold
                // digits of its own).
                let start = before.trim_end_matches(|c: char| c.is_ascii_digit()).len();
                before[start..].parse().ok()
            })
            .collect())
    }

    /// Whether `name` (in a node's directory) is a tag of this prefix.
    fn is_tag(&self, name: &str) -> bool {
        name.starts_with(&self.prefix)
            && (name.ends_with(&self.service_tag_suffix) || name.ends_with(&self.port_tag_suffix))
    }

    /// Whether a service whose hash a service tag names still has files.
    fn service_exists(&self, tag_name: &str) -> bool {
        let hash = tag_name
            .strip_suffix(&self.service_tag_suffix)
            .unwrap_or(tag_name);
        std::fs::read_dir(&self.service_dir)
            .map(|entries| {
                entries
                    .filter_map(Result::ok)
                    .any(|e| e.file_name().to_string_lossy().starts_with(hash))
            })
            .unwrap_or(false)
    }
}

fn names_in(dir: &Path) -> io::Result<Vec<String>> {
    Ok(std::fs::read_dir(dir)?
        .filter_map(Result::ok)
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect())
}

/// Removes the tag files left in the directory of the dead node `id` when its details are
/// already gone (a half-removed node: iceoryx2's cleanup can finish it afterwards). Returns how
/// many files it removed; 0 when the node still has its details or holds anything but tags.
pub(super) fn remove_tags_of_half_removed(layout: &Layout, id: u128) -> io::Result<usize> {
    let dir = layout.node_files(id);
    let names = match names_in(&dir) {
        Ok(names) => names,
        Err(error) if error.kind() == io::ErrorKind::NotFound => return Ok(0),
        Err(error) => return Err(error),
    };
    if names.iter().any(|name| !layout.is_tag(name)) {
        return Ok(0);
    }
    let mut removed = 0;
    for name in &names {
        if name.ends_with(&layout.service_tag_suffix) && layout.service_exists(name) {
            continue;
        }
        std::fs::remove_file(dir.join(name))?;
        removed += 1;
    }
    Ok(removed)
}

/// Removes every unborn node directory (only a details file of this prefix, no monitor token
/// of any prefix) whose details are at least `min_age` old; a younger one may belong to a node
/// being created right now.
pub(super) fn remove_unborn_nodes(layout: &Layout, min_age: Duration) -> io::Result<Unborn> {
    let mut unborn = Unborn::default();
    let entries = match std::fs::read_dir(&layout.node_dir) {
        Ok(entries) => entries,
        Err(error) if error.kind() == io::ErrorKind::NotFound => return Ok(unborn),
        Err(error) => return Err(error),
    };
    let monitored = layout.monitored_ids()?;
    for entry in entries.filter_map(Result::ok) {
        let Ok(id) = entry.file_name().to_string_lossy().parse::<u128>() else {
            continue;
        };
        if !entry.file_type().is_ok_and(|t| t.is_dir()) || monitored.contains(&id) {
            continue;
        }
        let dir = entry.path();
        let names = names_in(&dir)?;
        let [details] = names.as_slice() else {
            continue;
        };
        if !(details.starts_with(&layout.prefix) && details.ends_with(&layout.details_suffix)) {
            continue;
        }
        let age = std::fs::metadata(dir.join(details))?
            .modified()
            .ok()
            .and_then(|modified| SystemTime::now().duration_since(modified).ok())
            .unwrap_or(Duration::ZERO);
        if age < min_age {
            let wait = min_age - age;
            unborn.next_in = Some(unborn.next_in.map_or(wait, |next| next.max(wait)));
            continue;
        }
        std::fs::remove_file(dir.join(details))?;
        std::fs::remove_dir(&dir)?;
        unborn.removed += 1;
    }
    Ok(unborn)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ::iceoryx2::prelude::{ipc, NodeBuilder, SemanticString as _};

    /// An iceoryx2 configuration whose files all live under `root`.
    fn config_in(root: &Path) -> Config {
        let mut config = Config::default();
        let root = format!("{}/", root.display());
        config.global.set_root_path(
            &::iceoryx2::prelude::Path::new(root.as_bytes()).expect("a valid iceoryx2 path"),
        );
        config
    }

    fn touch(path: &Path) {
        std::fs::create_dir_all(path.parent().expect("a parent")).expect("dirs");
        std::fs::write(path, b"").expect("a file");
    }

    #[test]
    fn the_layout_names_the_files_a_live_node_has() {
        let root = tempfile::tempdir().expect("tempdir");
        let config = config_in(root.path());
        let node = NodeBuilder::new()
            .config(&config)
            .create::<ipc::Service>()
            .expect("a node");
        let layout = Layout::of(&config);
        let id = node.id().value();
        assert!(
            layout.monitored_ids().expect("io").contains(&id),
            "no monitor token for {id}"
        );
        let names = names_in(&layout.node_files(id)).expect("the node's directory");
        assert!(
            names.iter().any(|n| n.ends_with(&layout.details_suffix)),
            "{names:?}"
        );
        // A live node is neither shape.
        assert_eq!(remove_tags_of_half_removed(&layout, id).expect("io"), 0);
        assert_eq!(
            remove_unborn_nodes(&layout, Duration::ZERO).expect("io"),
            Unborn::default()
        );
        assert!(layout.node_files(id).is_dir());
    }

    #[test]
    fn only_the_tags_of_a_node_without_details_are_removed() {
        let root = tempfile::tempdir().expect("tempdir");
        let layout = Layout::of(&config_in(root.path()));
        let (half, whole) = (11_u128, 22_u128);
        let port_tag = layout.node_files(half).join("iox2_123.port_tag");
        let gone_service = layout.node_files(half).join("iox2_aaaa.service_tag");
        let live_service = layout.node_files(half).join("iox2_bbbb.service_tag");
        for tag in [&port_tag, &gone_service, &live_service] {
            touch(tag);
        }
        touch(&layout.service_dir.join("iox2_bbbb.service"));
        touch(&layout.node_files(whole).join("iox2_node.details"));
        touch(&layout.node_files(whole).join("iox2_456.port_tag"));

        assert_eq!(remove_tags_of_half_removed(&layout, half).expect("io"), 2);
        assert!(!port_tag.exists() && !gone_service.exists());
        assert!(live_service.exists(), "its service still exists");
        assert_eq!(remove_tags_of_half_removed(&layout, whole).expect("io"), 0);
        assert_eq!(names_in(&layout.node_files(whole)).expect("io").len(), 2);
        assert_eq!(remove_tags_of_half_removed(&layout, 33).expect("io"), 0);
    }

    #[test]
    fn an_unborn_node_is_removed_once_old_enough_and_a_monitored_one_never() {
        let root = tempfile::tempdir().expect("tempdir");
        let layout = Layout::of(&config_in(root.path()));
        let (unborn, monitored) = (11_u128, 22_u128);
        touch(&layout.node_files(unborn).join("iox2_node.details"));
        touch(&layout.node_files(monitored).join("iox2_node.details"));
        touch(
            &layout
                .node_dir
                .join(format!("other_{monitored}.node_monitor")),
        );
        // A prefix ending in digits does not hide the id before the suffix.
        let digit_prefixed = 44_u128;
        touch(&layout.node_files(digit_prefixed).join("iox2_node.details"));
        touch(
            &layout
                .node_dir
                .join(format!("asgt_7_{digit_prefixed}.node_monitor")),
        );
        let other_prefix = 33_u128;
        touch(&layout.node_files(other_prefix).join("other_node.details"));

        let young = remove_unborn_nodes(&layout, Duration::from_secs(3600)).expect("io");
        assert_eq!(young.removed, 0);
        assert!(young
            .next_in
            .is_some_and(|wait| wait > Duration::from_secs(3000)));
        assert!(layout.node_files(unborn).is_dir());

        let old = remove_unborn_nodes(&layout, Duration::ZERO).expect("io");
        assert_eq!(
            old,
            Unborn {
                removed: 1,
                next_in: None
            }
        );
        assert!(!layout.node_files(unborn).exists());
        assert!(layout.node_files(monitored).is_dir());
        assert!(layout.node_files(other_prefix).is_dir(), "another prefix's");
        assert!(layout.node_files(digit_prefixed).is_dir(), "monitored");
    }
}
