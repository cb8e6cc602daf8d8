//! Middlebury `.flo` optical-flow files: the format of the ground-truth flows we score SIFT flow
//! (Liu, Yuen, Torralba, TPAMI 2011) against, and a way to save our own flows for inspection.
//!
//! Layout (little endian): the magic float `202021.25` (bytes "PIEH"), width and height as `i32`,
//! then `u, v` as `f32` per pixel, row major. Convention of the flows we write:
//! `source(x, y) ≈ target(x + u, y + v)`, pixel coordinates 0-based.
//! Preconditions: none; every error names the file.

use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use crate::core::sift_flow::FlowField;

/// The magic number at the start of every `.flo` file (its bytes spell "PIEH").
const FLO_MAGIC: f32 = 202_021.25;
/// Refuse absurd headers before allocating: 2^28 pixels is far beyond any image we handle.
const MAX_FLO_PIXELS: usize = 1 << 28;

/// Everything that can go wrong reading or writing a `.flo` file.
#[derive(Debug, thiserror::Error)]
pub enum FloError {
    #[error("{path}: cannot read or write .flo file: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: not a .flo file (the header's tag is {found} instead of 202021.25)")]
    BadMagic { path: PathBuf, found: f32 },
    #[error("{path}: the header's size {width_px} x {height_px} needs {expected_bytes} bytes, the file has {file_bytes}: the file is cut short or its width/height fields are damaged")]
    Truncated {
        path: PathBuf,
        width_px: usize,
        height_px: usize,
        expected_bytes: u64,
        file_bytes: u64,
    },
    #[error(
        "{path}: the file ends within its 12-byte header (tag, width, height): a truncated file"
    )]
    ShortHeader { path: PathBuf },
    #[error("{path}: bad .flo size in the header: width {width} x height {height}")]
    BadSize {
        path: PathBuf,
        width: i64,
        height: i64,
    },
}

/// Reads a Middlebury `.flo` file.
pub fn read_flo(path: &Path) -> Result<FlowField, FloError> {
    let io_error = |source| FloError::Io {
        path: path.to_path_buf(),
        source,
    };
    let file = File::open(path).map_err(io_error)?;
    let mut reader = BufReader::new(file);
    let mut header = [0u8; 12];
    reader.read_exact(&mut header).map_err(|source| {
        if source.kind() == std::io::ErrorKind::UnexpectedEof {
            FloError::ShortHeader {
                path: path.to_path_buf(),
            }
        } else {
            io_error(source)
        }
    })?;
    let magic = f32::from_le_bytes([header[0], header[1], header[2], header[3]]);
    if magic != FLO_MAGIC {
        return Err(FloError::BadMagic {
            path: path.to_path_buf(),
            found: magic,
        });
    }
    let width = i32::from_le_bytes([header[4], header[5], header[6], header[7]]);
    let height = i32::from_le_bytes([header[8], header[9], header[10], header[11]]);
    let bad_size = || FloError::BadSize {
        path: path.to_path_buf(),
        width: width.into(),
        height: height.into(),
    };
    let (Ok(width_px), Ok(height_px)) = (usize::try_from(width), usize::try_from(height)) else {
        return Err(bad_size());
    };
    let pixel_count = width_px.checked_mul(height_px).ok_or_else(bad_size)?;
    if pixel_count == 0 || pixel_count > MAX_FLO_PIXELS {
        return Err(bad_size());
    }
    // The header's size must match the file's before anything is allocated for it: a 12-byte
    // file claiming 2^28 pixels would otherwise reserve 2 GiB.
    let file_bytes = reader.get_ref().metadata().map_err(io_error)?.len();
    let expected_bytes = 12 + pixel_count as u64 * 8;
    if file_bytes < expected_bytes {
        return Err(FloError::Truncated {
            path: path.to_path_buf(),
            width_px,
            height_px,
            expected_bytes,
            file_bytes,
        });
    }
    let mut bytes = vec![0u8; pixel_count * 8];
    reader.read_exact(&mut bytes).map_err(io_error)?;
    let mut field = FlowField::zeros(width_px, height_px);
    let (u_px, v_px) = field.planes_mut();
    for ((u, v), chunk) in u_px.iter_mut().zip(v_px).zip(bytes.chunks_exact(8)) {
        *u = f32::from_le_bytes([chunk[0], chunk[1], chunk[2], chunk[3]]);
        *v = f32::from_le_bytes([chunk[4], chunk[5], chunk[6], chunk[7]]);
    }
    Ok(field)
}

/// Writes a Middlebury `.flo` file.
pub fn write_flo(path: &Path, field: &FlowField) -> Result<(), FloError> {
    let (width_px, height_px) = field.size();
    let (Ok(width), Ok(height)) = (i32::try_from(width_px), i32::try_from(height_px)) else {
        return Err(FloError::BadSize {
            path: path.to_path_buf(),
            width: width_px as i64,
            height: height_px as i64,
        });
    };
    let io_error = |source| FloError::Io {
        path: path.to_path_buf(),
        source,
    };
    let file = File::create(path).map_err(io_error)?;
    let mut writer = BufWriter::new(file);
    let mut bytes = Vec::with_capacity(12 + field.u_px().pixel_count() * 8);
    bytes.extend_from_slice(&FLO_MAGIC.to_le_bytes());
    bytes.extend_from_slice(&width.to_le_bytes());
    bytes.extend_from_slice(&height.to_le_bytes());
    for (u, v) in field.u_px().data().iter().zip(field.v_px().data()) {
        bytes.extend_from_slice(&u.to_le_bytes());
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    writer.write_all(&bytes).map_err(io_error)?;
    writer.flush().map_err(io_error)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_keeps_every_value() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("field.flo");
        let mut field = FlowField::zeros(3, 2);
        let (u_px, v_px) = field.planes_mut();
        for pixel in 0..6 {
            u_px[pixel] = pixel as f32 * 0.5 - 1.0;
            v_px[pixel] = -(pixel as f32) * 1.25;
        }
        write_flo(&path, &field).unwrap();
        let read_back = read_flo(&path).unwrap();
        assert_eq!(read_back, field);
    }

    #[test]
    fn bad_magic_and_truncation_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bad.flo");
        std::fs::write(&path, b"NOPE\x01\x00\x00\x00\x01\x00\x00\x00").unwrap();
        let error = read_flo(&path).unwrap_err();
        assert!(matches!(error, FloError::BadMagic { .. }));
        assert!(error.to_string().contains("bad.flo"));

        let mut truncated = Vec::new();
        truncated.extend_from_slice(&FLO_MAGIC.to_le_bytes());
        truncated.extend_from_slice(&4i32.to_le_bytes());
        truncated.extend_from_slice(&4i32.to_le_bytes());
        truncated.extend_from_slice(&[0u8; 10]);
        std::fs::write(&path, &truncated).unwrap();
        let error = read_flo(&path).unwrap_err();
        assert!(matches!(error, FloError::Truncated { .. }), "{error}");
        assert!(error.to_string().contains("bad.flo"));

        let mut negative = Vec::new();
        negative.extend_from_slice(&FLO_MAGIC.to_le_bytes());
        negative.extend_from_slice(&(-4i32).to_le_bytes());
        negative.extend_from_slice(&4i32.to_le_bytes());
        std::fs::write(&path, &negative).unwrap();
        assert!(matches!(
            read_flo(&path).unwrap_err(),
            FloError::BadSize { .. }
        ));
    }

    #[test]
    fn real_pair_ground_truth_has_the_documented_size() {
        let path = crate::test_data::repo_data("flow-pairs/dji0024_505x275_gt.flo");
        let field = read_flo(&path).unwrap();
        assert_eq!(field.size(), (505, 275));
        // Translation (7, -4) plus at most 3 px of sinusoid.
        let u_px = field.u_px().data();
        let mean_u = u_px.iter().sum::<f32>() / u_px.len() as f32;
        assert!((mean_u - 7.0).abs() < 3.0, "mean u {mean_u}");
    }
}
