//! Depth maps as grayscale PFM files (`Pf`, 32-bit floats): the format COLMAP-adjacent tools and
//! renderers exchange depth in, used here to save rendered depth and to read reference depth.
//!
//! Conventions of a depth map (an [`Image<f32>`]):
//! - values are **metres along the optical axis** (the camera-frame z), not along the ray;
//! - **holes are `0.0`**. Files from other tools mark holes with NaN, infinity or negative values:
//!   [`read_pfm`] turns all of those into `0.0`, [`write_pfm`] writes every hole as `0.0`, and
//!   [`is_hole_value`] (with [`depth_at`], [`valid_depth_count`]) treats them all as holes for
//!   depth maps built in memory;
//! - memory is row-major with the **top row first** (image convention); the file stores rows
//!   bottom-to-top as the PFM format prescribes, and the reader and writer flip them.
//!
//! The header is `Pf`, then `width height`, then a scale whose sign gives the byte order
//! (negative: little endian, positive: big endian), each followed by whitespace; the data follow
//! the single whitespace character after the scale. Files are written little endian with scale
//! `-1`. Colour files (`PF`) are rejected.

use std::fs;
use std::path::{Path, PathBuf};

use crate::core::image::{Image, ImageView};

/// Errors of reading and writing PFM depth maps; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum PfmError {
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: not a grayscale PFM depth map: {why}", path.display())]
    BadHeader { path: PathBuf, why: String },
    #[error(
        "{}: colour PFM ('PF', three floats per pixel) is not supported; depth maps must be grayscale 'Pf'",
        path.display()
    )]
    ColourUnsupported { path: PathBuf },
    #[error(
        "{}: truncated: a {width_px}x{height_px} depth map needs {expected_bytes} data bytes, the file has {found_bytes}",
        path.display()
    )]
    Truncated {
        path: PathBuf,
        width_px: usize,
        height_px: usize,
        expected_bytes: usize,
        found_bytes: usize,
    },
    #[error(
        "{}: size mismatch: {what} ({width_px}x{height_px} px needs {expected_values} values, found {found_values})",
        path.display()
    )]
    SizeMismatch {
        path: PathBuf,
        what: &'static str,
        width_px: usize,
        height_px: usize,
        expected_values: usize,
        found_values: usize,
    },
}

/// Whether a depth value marks a hole: zero, negative or not finite.
pub fn is_hole_value(depth_m: f32) -> bool {
    !(depth_m.is_finite() && depth_m > 0.0)
}

/// The depth at `(col, row)` of a depth map, `None` for a hole or a position outside the image.
pub fn depth_at(depth_m: ImageView<'_, f32>, col: usize, row: usize) -> Option<f32> {
    depth_m
        .get(col, row)
        .copied()
        .filter(|depth| !is_hole_value(*depth))
}

/// Number of pixels of a depth map that hold a valid depth.
pub fn valid_depth_count(depth_m: ImageView<'_, f32>) -> usize {
    depth_m
        .data()
        .iter()
        .filter(|d| !is_hole_value(**d))
        .count()
}

/// Reads a grayscale PFM. Holes (NaN, infinity, negative, zero) come back as `0.0`; rows are
/// returned top row first.
pub fn read_pfm(path: &Path) -> Result<Image<f32>, PfmError> {
    let bytes = fs::read(path).map_err(|source| PfmError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let bad_header = |why: String| PfmError::BadHeader {
        path: path.to_path_buf(),
        why,
    };

    let mut cursor = 0;
    let mut tokens = Vec::with_capacity(4);
    for name in ["identifier", "width", "height", "scale"] {
        while cursor < bytes.len() && bytes[cursor].is_ascii_whitespace() {
            cursor += 1;
        }
        let start = cursor;
        while cursor < bytes.len() && !bytes[cursor].is_ascii_whitespace() && cursor - start < 64 {
            cursor += 1;
        }
        if cursor >= bytes.len() || !bytes[cursor].is_ascii_whitespace() {
            return Err(bad_header(format!(
                "the header ends before its {name} (expected 'Pf', width, height, scale, each followed by whitespace)"
            )));
        }
        let token = String::from_utf8_lossy(&bytes[start..cursor]).into_owned();
        if name == "identifier" {
            match token.as_str() {
                "Pf" => {}
                "PF" => {
                    return Err(PfmError::ColourUnsupported {
                        path: path.to_path_buf(),
                    })
                }
                other => {
                    return Err(bad_header(format!(
                        "it starts with '{other}' instead of 'Pf'"
                    )))
                }
            }
        }
        tokens.push(token);
    }
    // Exactly one whitespace character separates the scale from the data.
    let data = &bytes[cursor + 1..];

    let parse_size = |token: &str, name: &str| match token.parse::<usize>() {
        Ok(value) if value > 0 => Ok(value),
        _ => Err(bad_header(format!(
            "{name} '{token}' is not a positive whole number"
        ))),
    };
    let width_px = parse_size(&tokens[1], "width")?;
    let height_px = parse_size(&tokens[2], "height")?;
    let scale = match tokens[3].parse::<f32>() {
        Ok(value) if value.is_finite() && value != 0.0 => value,
        _ => {
            return Err(bad_header(format!(
                "scale '{}' is not a non-zero number (its sign gives the byte order)",
                tokens[3]
            )))
        }
    };
    let little_endian = scale < 0.0;

    let expected_values = width_px
        .checked_mul(height_px)
        .filter(|values| values.checked_mul(4).is_some())
        .ok_or_else(|| bad_header(format!("size {width_px}x{height_px} is too large")))?;
    let expected_bytes = expected_values * 4;
    if data.len() < expected_bytes {
        return Err(PfmError::Truncated {
            path: path.to_path_buf(),
            width_px,
            height_px,
            expected_bytes,
            found_bytes: data.len(),
        });
    }
    if data.len() > expected_bytes {
        return Err(PfmError::SizeMismatch {
            path: path.to_path_buf(),
            what: "the file has more data than its header announces",
            width_px,
            height_px,
            expected_values,
            found_values: data.len() / 4,
        });
    }

    let mut depth_m = vec![0.0_f32; expected_values];
    let row_bytes = width_px * 4;
    for (file_row, chunk) in data.chunks_exact(row_bytes).enumerate() {
        let row = height_px - 1 - file_row;
        let out = &mut depth_m[row * width_px..(row + 1) * width_px];
        for (value, raw) in out.iter_mut().zip(chunk.chunks_exact(4)) {
            let raw = [raw[0], raw[1], raw[2], raw[3]];
            let depth = if little_endian {
                f32::from_le_bytes(raw)
            } else {
                f32::from_be_bytes(raw)
            };
            *value = if is_hole_value(depth) { 0.0 } else { depth };
        }
    }
    Image::new(width_px, height_px, depth_m).map_err(|_| PfmError::SizeMismatch {
        path: path.to_path_buf(),
        what: "the decoded values do not fill the image",
        width_px,
        height_px,
        expected_values,
        found_values: expected_values,
    })
}

/// Writes a grayscale little-endian PFM (scale `-1`); holes are written as `0.0`.
pub fn write_pfm(path: &Path, depth_m: ImageView<'_, f32>) -> Result<(), PfmError> {
    let (width_px, height_px) = depth_m.size();
    if width_px == 0 || height_px == 0 {
        return Err(PfmError::SizeMismatch {
            path: path.to_path_buf(),
            what: "the depth map is empty",
            width_px,
            height_px,
            expected_values: 0,
            found_values: 0,
        });
    }
    let header = format!("Pf\n{width_px} {height_px}\n-1\n");
    let mut bytes = Vec::with_capacity(header.len() + depth_m.pixel_count() * 4);
    bytes.extend_from_slice(header.as_bytes());
    for row in depth_m.data().chunks_exact(width_px).rev() {
        for &value in row {
            let value = if is_hole_value(value) { 0.0_f32 } else { value };
            bytes.extend_from_slice(&value.to_le_bytes());
        }
    }
    fs::write(path, bytes).map_err(|source| PfmError::Io {
        path: path.to_path_buf(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Image<f32> {
        // 3 wide, 2 high; top row 1 2 3, bottom row 4 (hole) 6.
        Image::new(3, 2, vec![1.0, 2.5, 3.0, 4.0, 0.0, 6.125]).unwrap()
    }

    #[test]
    fn round_trip_keeps_values_and_orientation() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("depth.pfm");
        let depth = sample();
        write_pfm(&path, depth.view()).unwrap();
        assert_eq!(read_pfm(&path).unwrap(), depth);

        let bytes = fs::read(&path).unwrap();
        let header = b"Pf\n3 2\n-1\n";
        assert_eq!(&bytes[..header.len()], header);
        // The file stores the bottom row first: 4, 0, 6.125.
        let first = f32::from_le_bytes(bytes[header.len()..header.len() + 4].try_into().unwrap());
        assert_eq!(first, 4.0);
        assert_eq!(bytes.len(), header.len() + 6 * 4);
    }

    #[test]
    fn hand_built_big_endian_file_reads_top_row_first_and_clears_holes() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("be.pfm");
        // Width and height on separate lines, as some writers do; positive scale = big endian.
        let mut bytes = b"Pf\n2\n2\n1.0\n".to_vec();
        for value in [10.0_f32, f32::NAN, -3.0, 40.0] {
            bytes.extend_from_slice(&value.to_be_bytes());
        }
        fs::write(&path, &bytes).unwrap();
        let depth = read_pfm(&path).unwrap();
        // File rows bottom-to-top: [10, NaN] is the bottom row, [-3, 40] the top row.
        assert_eq!(depth.data(), &[0.0, 40.0, 10.0, 0.0]);
        assert_eq!(depth_at(depth.view(), 1, 0), Some(40.0));
        assert_eq!(depth_at(depth.view(), 0, 1), Some(10.0));
        assert_eq!(depth_at(depth.view(), 0, 0), None);
        assert_eq!(depth_at(depth.view(), 2, 0), None);
        assert_eq!(valid_depth_count(depth.view()), 2);
    }

    #[test]
    fn holes_of_every_kind_are_holes() {
        let depth = Image::new(5, 1, vec![0.0, -1.0, f32::NAN, f32::INFINITY, 2.0]).unwrap();
        let holes: Vec<bool> = depth.data().iter().map(|d| is_hole_value(*d)).collect();
        assert_eq!(holes, vec![true, true, true, true, false]);
        assert_eq!(valid_depth_count(depth.view()), 1);
        assert_eq!(depth_at(depth.view(), 2, 0), None);

        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("holes.pfm");
        write_pfm(&path, depth.view()).unwrap();
        assert_eq!(read_pfm(&path).unwrap().data(), &[0.0, 0.0, 0.0, 0.0, 2.0]);
    }

    #[test]
    fn truncated_bad_and_colour_files_are_rejected_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let good = dir.path().join("good.pfm");
        write_pfm(&good, sample().view()).unwrap();
        let bytes = fs::read(&good).unwrap();

        let truncated = dir.path().join("truncated.pfm");
        fs::write(&truncated, &bytes[..bytes.len() - 5]).unwrap();
        let error = read_pfm(&truncated).unwrap_err();
        assert!(matches!(
            error,
            PfmError::Truncated {
                expected_bytes: 24,
                found_bytes: 19,
                ..
            }
        ));
        assert!(error.to_string().contains("truncated.pfm"), "{error}");

        let long = dir.path().join("long.pfm");
        let mut extra = bytes.clone();
        extra.extend_from_slice(&[0; 4]);
        fs::write(&long, &extra).unwrap();
        let error = read_pfm(&long).unwrap_err();
        assert!(matches!(error, PfmError::SizeMismatch { .. }));
        assert!(error.to_string().contains("long.pfm"), "{error}");

        let cases: &[(&str, &[u8])] = &[
            ("colour.pfm", b"PF\n1 1\n-1\n000000000000"),
            ("p6.pfm", b"P6\n1 1\n255\n000"),
            ("zero_width.pfm", b"Pf\n0 1\n-1\n"),
            ("zero_scale.pfm", b"Pf\n1 1\n0\n0000"),
            ("header_only.pfm", b"Pf\n1 1"),
            ("empty.pfm", b""),
        ];
        for (name, contents) in cases {
            let path = dir.path().join(name);
            fs::write(&path, contents).unwrap();
            let error = read_pfm(&path).unwrap_err();
            assert!(error.to_string().contains(name), "{error}");
            if *name == "colour.pfm" {
                assert!(
                    matches!(error, PfmError::ColourUnsupported { .. }),
                    "{error}"
                );
            } else {
                assert!(
                    matches!(error, PfmError::BadHeader { .. }),
                    "{name}: {error}"
                );
            }
        }

        let missing = dir.path().join("missing.pfm");
        let error = read_pfm(&missing).unwrap_err();
        assert!(matches!(error, PfmError::Io { .. }));
        assert!(error.to_string().contains("missing.pfm"), "{error}");
    }

    #[test]
    fn writing_an_empty_depth_map_fails() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("empty.pfm");
        let error = write_pfm(&path, Image::filled(0, 3, 0.0).view()).unwrap_err();
        assert!(matches!(
            error,
            PfmError::SizeMismatch {
                width_px: 0,
                height_px: 3,
                ..
            }
        ));
        assert!(error.to_string().contains("empty.pfm"), "{error}");
        assert!(!path.exists());
    }
}
