//! The process's heap kept instead of handed back to the kernel: a frame allocates and frees
//! many buffers of hundreds of kilobytes to megabytes (renderings, flow pyramids and cost
//! volumes, descriptors), and glibc's defaults serve each from fresh `mmap`ed pages (above its
//! adaptive mmap threshold) or trim the heap's top after each free, so the next frame's buffers
//! page-fault again and the kernel zeroes them (measured: 12 % of a registration's CPU in the
//! kernel, mostly `clear_page`). Called once at the start of `asgreg`; results do not change,
//! only where the memory comes from.

/// Largest mmap threshold glibc accepts on 64-bit targets (`DEFAULT_MMAP_THRESHOLD_MAX`).
pub const MMAP_THRESHOLD_BYTES: usize = 32 << 20;

/// Serve allocations up to [`MMAP_THRESHOLD_BYTES`] from the heap and never trim it: freed
/// memory is reused by the next allocation without page faults. Returns whether the allocator
/// took both settings (always false outside glibc, where it does nothing).
pub fn keep_freed_memory() -> bool {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: mallopt only changes glibc's allocator parameters; it may be called at any
        // time, from any thread.
        let mmap = unsafe { libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES as i32) };
        // SAFETY: as above.
        let trim = unsafe { libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX) };
        mmap == 1 && trim == 1
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    {
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Fails when glibc rejects a setting (a threshold above its maximum, say).
    #[test]
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    fn the_allocator_takes_the_settings() {
        assert!(keep_freed_memory());
    }
}
