//! Network transport between hosts (zenoh): being written on branch wt-zen; the settings type is
//! here so the runtime's configuration compiles meanwhile.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ZenohSettings {
    pub mode: String,
    pub listen: Vec<String>,
    pub connect: Vec<String>,
    pub config_file: Option<PathBuf>,
}
