//! Network transport between hosts (zenoh): to be written.
