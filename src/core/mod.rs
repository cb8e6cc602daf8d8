//! The algorithm core: camera geometry, meshes, rendering and (later) correspondence, pose solving
//! and verification. Pure: no transport, no async runtime, no message types, no global state;
//! randomness is passed in; hot paths write into caller-provided buffers.

pub mod camera;
pub mod icp;
pub mod mesh;
pub mod raster;
pub mod reprojection;
pub mod rigid;
pub mod shading;
