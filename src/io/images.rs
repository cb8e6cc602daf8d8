//! Image files in and out of the pipeline: photos are loaded as grayscale floats (what shading
//! gradients and SIFT work on), renderings and diagnostics are saved as PNG, and a photo's size is
//! checked against its camera before anything uses the two together.
//!
//! PNG and JPEG are supported (the `image` crate's decoders; the format is recognised from the
//! file's content, not its extension). Grayscale is Rec. 601 luma, `0.299 R + 0.587 G + 0.114 B`,
//! in `0..=1`; alpha is ignored; 16-bit images keep their precision. Images are
//! [`crate::core::image::Image`]s: grey ones `Image<f32>` (row-major, top row first, `0..=1`),
//! colour ones `Image<[u8; 3]>`. Every error names the file.

use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};

use image::{DynamicImage, ImageFormat, ImageReader};

use crate::core::camera::Camera;
use crate::core::image::{Image, ImageView};

/// Errors of loading, saving and checking images; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum ImageIoError {
    #[error("cannot open image {}: {source}", path.display())]
    Open {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "cannot decode image {} (corrupt, truncated, or not a PNG/JPEG file): {source}",
        path.display()
    )]
    Decode {
        path: PathBuf,
        #[source]
        source: image::ImageError,
    },
    #[error("cannot write image {}: {source}", path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: image::ImageError,
    },
    #[error(
        "cannot write image {}: a {width_px}x{height_px} image is empty or too large for a PNG",
        path.display()
    )]
    EmptyOrTooLarge {
        path: PathBuf,
        width_px: usize,
        height_px: usize,
    },
    #[error(
        "image {} is {width_px}x{height_px} px but camera {camera_id} in cameras.txt is {camera_width_px}x{camera_height_px} px; resize the image to {camera_width_px}x{camera_height_px} px or fix camera {camera_id} in cameras.txt (its WIDTH, HEIGHT and intrinsics together)",
        path.display()
    )]
    CameraSizeMismatch {
        path: PathBuf,
        width_px: usize,
        height_px: usize,
        camera_id: u32,
        camera_width_px: u32,
        camera_height_px: u32,
    },
}

/// Rec. 601 luma of linear-in-file RGB values in `0..=1`.
fn rec601_luma(rgb: [f32; 3]) -> f32 {
    0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2]
}

/// Decoded bytes allowed per byte of a PNG file: more than any PNG can hold (deflate expands at
/// most 1032 times; 1-bit pixels become bytes: 8 × 1032), so only a header that lies about the
/// size is refused.
const PNG_DECODED_BYTES_PER_FILE_BYTE: u64 = 16_384;
/// The same for JPEG: a block of 64 pixels takes at least a bit per component (a DC code), so a
/// byte holds at most 512 pixels, 1536 bytes of RGB.
const JPEG_DECODED_BYTES_PER_FILE_BYTE: u64 = 2_048;
/// Decoded bytes allowed whatever the file's size.
const DECODED_BYTES_BASE: u64 = 16 << 20;

/// The decoder's memory limit for a file of `file_bytes`: a 600-byte PNG whose header claims
/// 20000×20000 pixels is refused before 400 MB are reserved for it.
fn decode_limits(file_bytes: u64, is_jpeg: bool) -> image::Limits {
    let per_byte = if is_jpeg {
        JPEG_DECODED_BYTES_PER_FILE_BYTE
    } else {
        PNG_DECODED_BYTES_PER_FILE_BYTE
    };
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(DECODED_BYTES_BASE.saturating_add(file_bytes.saturating_mul(per_byte)));
    limits
}

fn decode(path: &Path) -> Result<DynamicImage, ImageIoError> {
    let decode_error = |source| ImageIoError::Decode {
        path: path.to_path_buf(),
        source,
    };
    // Photos are a few MB: read once, check, decode from memory.
    let bytes = std::fs::read(path).map_err(|source| ImageIoError::Open {
        path: path.to_path_buf(),
        source,
    })?;
    let mut reader = ImageReader::new(std::io::Cursor::new(bytes.as_slice()))
        .with_guessed_format()
        .map_err(|source| decode_error(image::ImageError::IoError(source)))?;
    let is_jpeg = reader.format() == Some(ImageFormat::Jpeg);
    // The JPEG decoder fills a file that ends early with grey instead of failing: check the end
    // first (decoding a cut file's full size from a few hundred bytes took 0.8 s and 150 MiB).
    if is_jpeg && !jpeg_is_complete(&bytes) {
        return Err(decode_error(image::ImageError::Decoding(
            image::error::DecodingError::new(
                ImageFormat::Jpeg.into(),
                "the file ends before the JPEG end-of-image marker (truncated)",
            ),
        )));
    }
    reader.limits(decode_limits(bytes.len() as u64, is_jpeg));
    reader.decode().map_err(decode_error)
}

/// Whether a JPEG byte stream reaches its end-of-image marker (`FF D9`) by walking its marker
/// segments and entropy-coded scans (so an embedded thumbnail's marker does not count; data
/// appended after the marker is allowed).
fn jpeg_is_complete(bytes: &[u8]) -> bool {
    const MARKER: u8 = 0xFF;
    const END_OF_IMAGE: u8 = 0xD9;
    const START_OF_SCAN: u8 = 0xDA;
    let is_standalone = |marker: u8| (0xD0..=0xD8).contains(&marker) || marker == 0x01;
    let mut index = 0;
    loop {
        if index + 1 >= bytes.len() || bytes[index] != MARKER {
            return false;
        }
        // Skip fill bytes before the marker code.
        while index + 1 < bytes.len() && bytes[index + 1] == MARKER {
            index += 1;
        }
        let Some(&marker) = bytes.get(index + 1) else {
            return false;
        };
        if marker == END_OF_IMAGE {
            return true;
        }
        if is_standalone(marker) {
            index += 2;
            continue;
        }
        let Some(length) = bytes
            .get(index + 2..index + 4)
            .map(|len| usize::from(u16::from_be_bytes([len[0], len[1]])))
        else {
            return false;
        };
        index += 2 + length;
        if index > bytes.len() {
            return false;
        }
        if marker == START_OF_SCAN {
            // Entropy-coded data: 0xFF is followed by 0x00 (stuffing) or a restart marker.
            loop {
                if index + 1 >= bytes.len() {
                    return false;
                }
                let next = bytes[index + 1];
                if bytes[index] == MARKER && next != 0x00 && !(0xD0..=0xD7).contains(&next) {
                    break;
                }
                index += 1;
            }
        }
    }
}

/// The size of an image file in pixels `(width, height)`, read from its header only.
pub fn read_image_size(path: &Path) -> Result<(usize, usize), ImageIoError> {
    let file = File::open(path).map_err(|source| ImageIoError::Open {
        path: path.to_path_buf(),
        source,
    })?;
    let decode_error = |source| ImageIoError::Decode {
        path: path.to_path_buf(),
        source,
    };
    let (width_px, height_px) = ImageReader::new(BufReader::new(file))
        .with_guessed_format()
        .map_err(|source| decode_error(image::ImageError::IoError(source)))?
        .into_dimensions()
        .map_err(decode_error)?;
    Ok((width_px as usize, height_px as usize))
}

/// Loads an image as Rec. 601 luma in `0..=1` (grayscale files are taken as they are).
pub fn load_gray(path: &Path) -> Result<Image<f32>, ImageIoError> {
    let image = decode(path)?;
    let (width_px, height_px) = (image.width() as usize, image.height() as usize);
    let pixels = match &image {
        // Most photos: straight from the bytes, without an RGB f32 copy (12 bytes a pixel).
        DynamicImage::ImageRgb8(rgb) => rgb
            .pixels()
            .map(|pixel| rec601_luma(pixel.0.map(|channel| f32::from(channel) / 255.0)))
            .collect(),
        _ if image.color().has_color() => image
            .to_rgb32f()
            .pixels()
            .map(|pixel| rec601_luma(pixel.0))
            .collect(),
        _ => image.to_luma32f().into_raw(),
    };
    Image::new(width_px, height_px, pixels).map_err(|error| decoded_size_error(path, error))
}

/// Loads an image as 8-bit RGB.
pub fn load_rgb(path: &Path) -> Result<Image<[u8; 3]>, ImageIoError> {
    let image = decode(path)?.to_rgb8();
    let (width_px, height_px) = (image.width() as usize, image.height() as usize);
    let pixels = image.pixels().map(|pixel| pixel.0).collect();
    Image::new(width_px, height_px, pixels).map_err(|error| decoded_size_error(path, error))
}

/// A decoder that returned a buffer of another size than it announced (never seen; reported as
/// a decoding error of the file rather than a panic).
fn decoded_size_error(path: &Path, error: crate::core::image::ImageError) -> ImageIoError {
    ImageIoError::Decode {
        path: path.to_path_buf(),
        source: image::ImageError::Decoding(image::error::DecodingError::new(
            image::error::ImageFormatHint::Unknown,
            error.to_string(),
        )),
    }
}

/// Checks that the size fits a PNG (not empty, each side a `u32`); returns it as `u32`s.
fn checked_size(
    path: &Path,
    width_px: usize,
    height_px: usize,
) -> Result<(u32, u32), ImageIoError> {
    let size_error = || ImageIoError::EmptyOrTooLarge {
        path: path.to_path_buf(),
        width_px,
        height_px,
    };
    if width_px == 0 || height_px == 0 {
        return Err(size_error());
    }
    match (u32::try_from(width_px), u32::try_from(height_px)) {
        (Ok(width), Ok(height)) => Ok((width, height)),
        _ => Err(size_error()),
    }
}

fn save_png<P: image::Pixel + image::PixelWithColorType>(
    path: &Path,
    buffer: image::ImageBuffer<P, Vec<P::Subpixel>>,
) -> Result<(), ImageIoError>
where
    [P::Subpixel]: image::EncodableLayout,
{
    buffer
        .save_with_format(path, ImageFormat::Png)
        .map_err(|source| ImageIoError::Write {
            path: path.to_path_buf(),
            source,
        })
}

/// Saves a grayscale image as an 8-bit PNG; values are clamped to `0..=1` (NaN becomes 0).
pub fn save_gray_png(path: &Path, image: ImageView<'_, f32>) -> Result<(), ImageIoError> {
    let (width, height) = checked_size(path, image.width_px(), image.height_px())?;
    let bytes: Vec<u8> = image
        .data()
        .iter()
        .map(|value| (value.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    // The image's size is checked at construction: the buffer always fits.
    let buffer = image::GrayImage::from_raw(width, height, bytes)
        .ok_or_else(|| unexpected_length(path, image.width_px(), image.height_px()))?;
    save_png(path, buffer)
}

/// Saves an 8-bit RGB image as a PNG.
pub fn save_rgb_png(path: &Path, image: ImageView<'_, [u8; 3]>) -> Result<(), ImageIoError> {
    let (width, height) = checked_size(path, image.width_px(), image.height_px())?;
    let bytes: Vec<u8> = image.data().iter().flatten().copied().collect();
    let buffer = image::RgbImage::from_raw(width, height, bytes)
        .ok_or_else(|| unexpected_length(path, image.width_px(), image.height_px()))?;
    save_png(path, buffer)
}

/// An 8-bit RGB image encoded as a JPEG in memory (`quality` 1..=100), for pages that embed
/// their pictures.
pub fn encode_rgb_jpeg(
    image: ImageView<'_, [u8; 3]>,
    quality: u8,
) -> Result<Vec<u8>, ImageIoError> {
    let path = Path::new("<in-memory JPEG>");
    let (width, height) = checked_size(path, image.width_px(), image.height_px())?;
    let bytes: Vec<u8> = image.data().iter().flatten().copied().collect();
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, quality.clamp(1, 100))
        .encode(&bytes, width, height, image::ExtendedColorType::Rgb8)
        .map_err(|source| ImageIoError::Write {
            path: path.to_path_buf(),
            source,
        })?;
    Ok(out)
}

/// The `image` crate refused a buffer of the right length (cannot happen; an error, not a panic).
fn unexpected_length(path: &Path, width_px: usize, height_px: usize) -> ImageIoError {
    ImageIoError::EmptyOrTooLarge {
        path: path.to_path_buf(),
        width_px,
        height_px,
    }
}

/// Checks that an image of `width_px` × `height_px` (the size of the file at `image_path`) is the
/// size its camera `camera_id` says; the error says which file, both sizes and what to do.
pub fn check_image_matches_camera(
    image_path: &Path,
    width_px: usize,
    height_px: usize,
    camera_id: u32,
    camera: &Camera,
) -> Result<(), ImageIoError> {
    if width_px == camera.width_px as usize && height_px == camera.height_px as usize {
        Ok(())
    } else {
        Err(ImageIoError::CameraSizeMismatch {
            path: image_path.to_path_buf(),
            width_px,
            height_px,
            camera_id,
            camera_width_px: camera.width_px,
            camera_height_px: camera.height_px,
        })
    }
}

/// [`check_image_matches_camera`] for an image file, whose size is read from its header.
pub fn check_image_file_matches_camera(
    image_path: &Path,
    camera_id: u32,
    camera: &Camera,
) -> Result<(), ImageIoError> {
    let (width_px, height_px) = read_image_size(image_path)?;
    check_image_matches_camera(image_path, width_px, height_px, camera_id, camera)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::camera::PinholeIntrinsics;

    #[test]
    fn gray_png_round_trips_to_8_bit_precision_and_clamps() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("gray.png");
        let image = Image::new(3, 2, vec![0.0, 0.25, 1.0, -0.5, 1.7, 100.0 / 255.0]).unwrap();
        save_gray_png(&path, image.view()).unwrap();
        let loaded = load_gray(&path).unwrap();
        assert_eq!(loaded.size(), (3, 2));
        let expected = [0.0, 64.0 / 255.0, 1.0, 0.0, 1.0, 100.0 / 255.0];
        for (got, want) in loaded.data().iter().zip(expected) {
            assert!((got - want).abs() < 1e-6, "{got} vs {want}");
        }
        assert_eq!(loaded.get(2, 1), Some(&loaded.data()[5]));
        assert_eq!(loaded.get(3, 0), None);
        assert_eq!(read_image_size(&path).unwrap(), (3, 2));
    }

    #[test]
    fn rgb_round_trips_and_gray_is_rec601_luma() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("rgb.png");
        let rgb = [[255, 0, 0], [0, 255, 0], [0, 0, 255], [10, 200, 30]];
        let image = Image::new(2, 2, rgb.to_vec()).unwrap();
        save_rgb_png(&path, image.view()).unwrap();
        assert_eq!(load_rgb(&path).unwrap(), image);

        let gray = load_gray(&path).unwrap();
        let expected = [
            0.299,
            0.587,
            0.114,
            (0.299 * 10.0 + 0.587 * 200.0 + 0.114 * 30.0) / 255.0,
        ];
        for (got, want) in gray.data().iter().zip(expected) {
            assert!((got - want).abs() < 1e-6, "{got} vs {want}");
        }
    }

    #[test]
    fn jpeg_loads_by_content_whatever_the_extension() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("photo.png");
        let buffer = image::RgbImage::from_fn(16, 8, |x, _| image::Rgb([(x * 16) as u8, 128, 64]));
        buffer.save_with_format(&path, ImageFormat::Jpeg).unwrap();
        let gray = load_gray(&path).unwrap();
        assert_eq!(gray.size(), (16, 8));
        // Brightness rises left to right.
        assert!(gray.get(15, 4).unwrap() > &(gray.get(0, 4).unwrap() + 0.2));
    }

    #[test]
    fn missing_truncated_and_foreign_files_are_errors_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("missing.png");
        let error = load_gray(&missing).unwrap_err();
        assert!(matches!(error, ImageIoError::Open { .. }));
        assert!(error.to_string().contains("missing.png"), "{error}");

        let good = dir.path().join("good.png");
        let noise: Vec<[u8; 3]> = (0..64 * 64)
            .map(|i: u32| {
                [
                    (i * 7 % 251) as u8,
                    (i * 13 % 253) as u8,
                    (i * 31 % 255) as u8,
                ]
            })
            .collect();
        save_rgb_png(&good, Image::new(64, 64, noise).unwrap().view()).unwrap();
        let bytes = std::fs::read(&good).unwrap();
        let truncated = dir.path().join("truncated.png");
        std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
        for result in [
            load_gray(&truncated).map(|_| ()),
            load_rgb(&truncated).map(|_| ()),
        ] {
            let error = result.unwrap_err();
            assert!(matches!(error, ImageIoError::Decode { .. }), "{error}");
            assert!(error.to_string().contains("truncated.png"), "{error}");
        }

        let jpeg = dir.path().join("good.jpg");
        image::RgbImage::from_fn(64, 64, |x, y| image::Rgb([(x * 4) as u8, (y * 4) as u8, 7]))
            .save_with_format(&jpeg, ImageFormat::Jpeg)
            .unwrap();
        let bytes = std::fs::read(&jpeg).unwrap();
        assert!(jpeg_is_complete(&bytes));
        let half_jpeg = dir.path().join("half.jpg");
        std::fs::write(&half_jpeg, &bytes[..bytes.len() / 2]).unwrap();
        let error = load_gray(&half_jpeg).unwrap_err();
        assert!(matches!(error, ImageIoError::Decode { .. }), "{error}");
        assert!(error.to_string().contains("half.jpg"), "{error}");
        assert!(!jpeg_is_complete(&bytes[..bytes.len() - 1]));
        let mut appended = bytes.clone();
        appended.extend_from_slice(b"trailing data after the image");
        assert!(jpeg_is_complete(&appended));

        let text = dir.path().join("notes.png");
        std::fs::write(&text, "not an image").unwrap();
        let error = load_rgb(&text).unwrap_err();
        assert!(error.to_string().contains("notes.png"), "{error}");
        let error = read_image_size(&text).unwrap_err();
        assert!(error.to_string().contains("notes.png"), "{error}");
    }

    #[test]
    fn saving_checks_the_size_and_names_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("empty.png");
        let error = save_gray_png(&path, Image::filled(0, 5, 0.0).view()).unwrap_err();
        assert!(matches!(
            error,
            ImageIoError::EmptyOrTooLarge {
                width_px: 0,
                height_px: 5,
                ..
            }
        ));
        assert!(error.to_string().contains("empty.png"), "{error}");
        let error = save_rgb_png(&path, Image::filled(3, 0, [0; 3]).view()).unwrap_err();
        assert!(matches!(error, ImageIoError::EmptyOrTooLarge { .. }));
        assert!(!path.exists());

        let unwritable = dir.path().join("no_such_dir").join("out.png");
        let error = save_gray_png(&unwritable, Image::filled(2, 2, 0.0).view()).unwrap_err();
        assert!(matches!(error, ImageIoError::Write { .. }));
        assert!(error.to_string().contains("out.png"), "{error}");
    }

    #[test]
    fn image_size_is_checked_against_its_camera() {
        let camera = Camera::pinhole(995, 558, PinholeIntrinsics::centered(585.0, 995, 558));
        let path = Path::new("images/DJI_0025.JPG");
        assert!(check_image_matches_camera(path, 995, 558, 1, &camera).is_ok());
        let error = check_image_matches_camera(path, 1000, 562, 1, &camera).unwrap_err();
        let message = error.to_string();
        for part in [
            "DJI_0025.JPG",
            "1000x562",
            "camera 1",
            "995x558",
            "resize",
            "cameras.txt",
        ] {
            assert!(message.contains(part), "no '{part}' in: {message}");
        }
        assert!(check_image_matches_camera(path, 558, 995, 1, &camera).is_err());

        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("small.png");
        save_gray_png(&file, Image::filled(4, 3, 0.0).view()).unwrap();
        let small = Camera::pinhole(4, 3, PinholeIntrinsics::centered(5.0, 4, 3));
        assert!(check_image_file_matches_camera(&file, 2, &small).is_ok());
        let message = check_image_file_matches_camera(&file, 2, &camera)
            .unwrap_err()
            .to_string();
        assert!(
            message.contains("small.png") && message.contains("4x3"),
            "{message}"
        );
    }

    /// Loads a real photo: its size, a plausible brightness, complete; a copy cut to two thirds is
    /// rejected, naming the file.
    fn check_real_photo(path: &Path, width_px: usize, height_px: usize) {
        let gray = load_gray(path).unwrap();
        assert_eq!(gray.size(), (width_px, height_px));
        assert_eq!(read_image_size(path).unwrap(), (width_px, height_px));
        let mean = gray.data().iter().sum::<f32>() / gray.pixel_count() as f32;
        assert!(mean > 0.05 && mean < 0.95, "mean {mean}");
        let bytes = std::fs::read(path).unwrap();
        assert!(jpeg_is_complete(&bytes), "{}", path.display());
        let dir = tempfile::tempdir().unwrap();
        let truncated = dir.path().join("photo_cut.jpg");
        std::fs::write(&truncated, &bytes[..bytes.len() * 2 / 3]).unwrap();
        let error = load_rgb(&truncated).unwrap_err();
        assert!(error.to_string().contains("photo_cut.jpg"), "{error}");
    }

    /// A crop of a Brighton Beach photo that keeps the photo's EXIF segment, a JPEG thumbnail
    /// inside it (`tests/data/brighton_beach/README.md`).
    #[test]
    fn real_photo_loads_and_a_truncated_copy_is_rejected() {
        let path = crate::test_data::repo_data("brighton_beach/DJI_0025_crop.jpg");
        check_real_photo(&path, 240, 136);
    }

    #[test]
    #[ignore = "needs ../shared/data/brighton_beach (the shared data set beside the repo)"]
    fn shared_data_brighton_beach_photos_load_and_are_complete() {
        let data = crate::test_data::shared_data("brighton_beach");
        check_real_photo(&data.join("images_undistorted/DJI_0025.JPG"), 995, 558);
        // No false alarms on any of the real photos (EXIF thumbnails, XMP, etc.).
        for folder in ["images_undistorted", "images_distorted"] {
            let folder = crate::test_data::shared_data(&format!("brighton_beach/{folder}"));
            let mut photos = 0;
            for entry in std::fs::read_dir(&folder).unwrap() {
                let photo = entry.unwrap().path();
                let bytes = std::fs::read(&photo).unwrap();
                assert!(jpeg_is_complete(&bytes), "{}", photo.display());
                photos += 1;
            }
            assert_eq!(photos, 18, "{}", folder.display());
        }
    }
}
