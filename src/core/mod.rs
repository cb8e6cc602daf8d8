//! The algorithm core: camera geometry, meshes, rendering, dense matching, pose solving and
//! verification. Pure: no transport, no async runtime, no message types, no global state;
//! randomness is passed in; hot paths write into caller-provided buffers.

pub mod camera;
pub mod change;
pub mod confidence;
pub mod correlation;
pub mod dense_sift;
pub mod edge_align;
pub mod edge_consensus;
pub mod feature_align;
pub mod flow_consistency;
pub mod frame;
pub mod image;
pub mod mesh;
pub mod pose;
pub mod pose_search;
pub mod raster;
pub mod region_contrast;
pub mod reprojection;
pub mod rigid;
pub mod shading;
pub mod sift_flow;
pub mod undistort;
pub mod verify;
