//! asgreg registers aerial photographs to an untextured 3D mesh: from a frame's rough GPS/IMU pose
//! to an accurate camera pose and a verdict on whether it succeeded (Average Shading Gradients +
//! SIFT flow + RANSAC + a plausibility check). See `ARCHITECTURE.md` for the module map.

pub mod baseline;
pub mod batch;
pub mod core;
pub mod diagnose;
pub mod eval;
pub mod frame_files;
pub mod fuzz;
pub mod io;
pub mod msg;
pub mod priors;
pub mod report_html;
pub mod runtime;
pub mod stage;
pub mod synth;
pub mod transport;
pub mod viz;

#[cfg(test)]
pub(crate) mod test_data;

/// The library's tests run the fuzz short form, which measures allocations (`fuzz::alloc_guard`).
#[cfg(test)]
#[global_allocator]
static TEST_ALLOCATOR: fuzz::alloc_guard::GuardedAllocator = fuzz::alloc_guard::GuardedAllocator;
