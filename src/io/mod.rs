//! File formats: COLMAP text models, meshes (PLY, OBJ), depth maps (PFM) and images. Every reader
//! names the file, and where it can the line or field, in its errors.

pub mod colmap;
pub mod colmap_bin;
pub mod colmap_model;
pub mod flo;
pub mod images;
pub mod mesh_file;
pub mod obj;
pub mod opk;
pub mod output;
pub mod pfm;
pub mod ply;
pub mod text;
