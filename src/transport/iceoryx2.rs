//! Shared-memory transport between processes on one host (iceoryx2): to be written.
