//! A photo's metadata from its JPEG header: the image size (from the frame header, not from EXIF,
//! which keeps the original size after a resize), EXIF (GPS, focal length, make and model, through
//! `kamadak-exif`), DJI's maker note (gimbal and flight attitude, kept by tools that strip XMP) and
//! DJI's XMP packet (`drone-dji:` attributes, parsed by hand in [`super::xmp`]).
//!
//! Only the header is read: segments up to the start of the scan, never the compressed image.
//! Where both carry the gimbal attitude, XMP wins (it has two decimals; the maker note's floats
//! are the same values rounded to f32).

use std::fs::File;
use std::io::{BufReader, Read};
use std::path::Path;

use exif::{In, Tag, Value};

use super::orientation::Attitude;
use super::xmp::DjiXmp;
use super::{AttitudeSource, GpsPosition, PhotoMetadata, PriorsError};

const EXIF_HEADER: &[u8] = b"Exif\0\0";
const XMP_HEADER: &[u8] = b"http://ns.adobe.com/xap/1.0/\0";

/// The parts of a JPEG header the priors need.
#[derive(Debug, Default)]
pub struct JpegHeader {
    /// Width and height from the frame header (SOFn).
    pub size_px: Option<(u32, u32)>,
    /// The TIFF structure of the first EXIF APP1 segment (after `Exif\0\0`).
    pub exif_tiff: Option<Vec<u8>>,
    /// The first XMP APP1 packet (after its namespace header).
    pub xmp: Option<Vec<u8>>,
}

/// Reads the segments before the scan. Errors say what is wrong with the stream.
pub fn read_header<R: Read>(reader: &mut R) -> Result<JpegHeader, String> {
    let mut header = JpegHeader::default();
    let mut two = [0u8; 2];
    reader
        .read_exact(&mut two)
        .map_err(|_| "the file is shorter than a JPEG's start-of-image marker".to_string())?;
    if two != [0xFF, 0xD8] {
        return Err(format!(
            "not a JPEG: its start-of-image marker (bytes 0–1) is {:02X} {:02X}, a JPEG's is FF D8",
            two[0], two[1]
        ));
    }
    loop {
        let mut byte = [0u8; 1];
        reader
            .read_exact(&mut byte)
            .map_err(|_| "the header segments end before the image data (start-of-scan marker): a truncated file".to_string())?;
        if byte[0] != 0xFF {
            return Err(format!(
                "expected a segment marker (FF), found {:02X}",
                byte[0]
            ));
        }
        // Fill bytes: any number of FF before the marker code.
        let mut marker = 0xFF;
        while marker == 0xFF {
            reader
                .read_exact(&mut byte)
                .map_err(|_| "the header ends inside a marker (truncated file)".to_string())?;
            marker = byte[0];
        }
        match marker {
            0xD9 | 0xDA => return Ok(header), // end of image, start of scan
            0x01 | 0xD0..=0xD7 => continue,   // markers without a length
            _ => {}
        }
        reader
            .read_exact(&mut two)
            .map_err(|_| format!("segment FF{marker:02X} has no length (truncated file)"))?;
        let length = usize::from(u16::from_be_bytes(two));
        if length < 2 {
            return Err(format!("segment FF{marker:02X} has length {length} (< 2)"));
        }
        let mut payload = vec![0u8; length - 2];
        reader
            .read_exact(&mut payload)
            .map_err(|_| format!("segment FF{marker:02X} is cut short (truncated file)"))?;
        match marker {
            0xE1 if payload.starts_with(EXIF_HEADER) && header.exif_tiff.is_none() => {
                header.exif_tiff = Some(payload[EXIF_HEADER.len()..].to_vec());
            }
            0xE1 if payload.starts_with(XMP_HEADER) && header.xmp.is_none() => {
                header.xmp = Some(payload[XMP_HEADER.len()..].to_vec());
            }
            // SOF0–SOF15 except DHT (C4), JPG (C8) and DAC (CC).
            0xC0..=0xCF if !matches!(marker, 0xC4 | 0xC8 | 0xCC) => {
                if payload.len() < 5 {
                    return Err(format!("frame header FF{marker:02X} is too short"));
                }
                let height = u32::from(u16::from_be_bytes([payload[1], payload[2]]));
                let width = u32::from(u16::from_be_bytes([payload[3], payload[4]]));
                header.size_px = Some((width, height));
            }
            _ => {}
        }
    }
}

/// Reads a JPEG's metadata. Missing fields are `None`; malformed ones are errors naming the file
/// and the field.
pub fn read_photo(path: &Path) -> Result<PhotoMetadata, PriorsError> {
    let file = File::open(path).map_err(|source| PriorsError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let header = read_header(&mut BufReader::new(file)).map_err(|why| PriorsError::Jpeg {
        path: path.to_path_buf(),
        why,
    })?;
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let mut meta = PhotoMetadata {
        name,
        image_size_px: header.size_px,
        ..PhotoMetadata::default()
    };
    if let Some(tiff) = header.exif_tiff {
        read_exif(path, tiff, &mut meta)?;
    }
    if let Some(xmp) = header.xmp {
        let xmp = DjiXmp::parse(&String::from_utf8_lossy(&xmp));
        apply_xmp(path, &xmp, &mut meta)?;
    }
    Ok(meta)
}

fn field_error(path: &Path, field: &str, found: impl Into<String>, expected: &str) -> PriorsError {
    PriorsError::Field {
        path: path.to_path_buf(),
        field: field.to_string(),
        found: found.into(),
        expected: expected.to_string(),
    }
}

/// EXIF fields into `meta`. The TIFF structure is parsed leniently (a broken IFD elsewhere, e.g. a
/// maker note that an editor moved, does not hide the GPS), the fields used strictly.
fn read_exif(path: &Path, tiff: Vec<u8>, meta: &mut PhotoMetadata) -> Result<(), PriorsError> {
    let exif = match exif::Reader::new().continue_on_error(true).read_raw(tiff) {
        Ok(exif) => exif,
        Err(exif::Error::PartialResult(partial)) => {
            let (exif, errors) = partial.into_inner();
            tracing::debug!("{}: EXIF partly unreadable: {errors:?}", path.display());
            exif
        }
        Err(source) => {
            return Err(PriorsError::Exif {
                path: path.to_path_buf(),
                source,
            })
        }
    };
    let field = |tag: Tag| exif.get_field(tag, In::PRIMARY).map(|f| &f.value);
    let ascii = |tag: Tag| -> Option<String> {
        match field(tag)? {
            Value::Ascii(parts) => parts.first().map(|bytes| {
                String::from_utf8_lossy(bytes)
                    .trim_matches(|c: char| c == '\0' || c.is_whitespace())
                    .to_string()
            }),
            _ => None,
        }
        .filter(|text| !text.is_empty())
    };
    meta.make = ascii(Tag::Make);
    meta.model = ascii(Tag::Model);

    let rationals = |tag: Tag, name: &str, count: usize| -> Result<Option<Vec<f64>>, PriorsError> {
        let Some(value) = field(tag) else {
            return Ok(None);
        };
        let numbers: Vec<f64> = match value {
            Value::Rational(values) => values
                .iter()
                .map(|r| (r.denom != 0).then(|| f64::from(r.num) / f64::from(r.denom)))
                .collect::<Option<_>>()
                .unwrap_or_default(),
            _ => Vec::new(),
        };
        if numbers.len() < count {
            return Err(field_error(
                path,
                name,
                format!("{value:?}"),
                &format!("{count} rational number(s) with non-zero denominators"),
            ));
        }
        Ok(Some(numbers))
    };
    let reference =
        |tag: Tag, name: &str, allowed: [&str; 2]| -> Result<Option<bool>, PriorsError> {
            let Some(text) = ascii(tag) else {
                return Ok(None);
            };
            if text.eq_ignore_ascii_case(allowed[0]) {
                Ok(Some(true))
            } else if text.eq_ignore_ascii_case(allowed[1]) {
                Ok(Some(false))
            } else {
                Err(field_error(
                    path,
                    name,
                    text,
                    &format!("{} or {}", allowed[0], allowed[1]),
                ))
            }
        };

    let latitude = rationals(Tag::GPSLatitude, "GPSLatitude", 3)?;
    let longitude = rationals(Tag::GPSLongitude, "GPSLongitude", 3)?;
    let altitude = rationals(Tag::GPSAltitude, "GPSAltitude", 1)?;
    if let (Some(lat), Some(lon), Some(alt)) = (latitude, longitude, altitude) {
        let north =
            reference(Tag::GPSLatitudeRef, "GPSLatitudeRef", ["N", "S"])?.ok_or_else(|| {
                field_error(
                    path,
                    "GPSLatitudeRef",
                    "nothing",
                    "N or S next to GPSLatitude",
                )
            })?;
        let east =
            reference(Tag::GPSLongitudeRef, "GPSLongitudeRef", ["E", "W"])?.ok_or_else(|| {
                field_error(
                    path,
                    "GPSLongitudeRef",
                    "nothing",
                    "E or W next to GPSLongitude",
                )
            })?;
        let below_sea_level = match field(Tag::GPSAltitudeRef) {
            None => false,
            Some(Value::Byte(bytes)) if bytes.first() == Some(&0) => false,
            Some(Value::Byte(bytes)) if bytes.first() == Some(&1) => true,
            Some(other) => {
                return Err(field_error(
                    path,
                    "GPSAltitudeRef",
                    format!("{other:?}"),
                    "0 (above sea level) or 1 (below)",
                ))
            }
        };
        let dms = |v: &[f64]| v[0] + v[1] / 60.0 + v[2] / 3600.0;
        let sign = |positive: bool| if positive { 1.0 } else { -1.0 };
        meta.gps = Some(GpsPosition {
            latitude_deg: sign(north) * dms(&lat),
            longitude_deg: sign(east) * dms(&lon),
            altitude_m: sign(!below_sea_level) * alt[0],
        });
    }
    meta.focal_length_mm = rationals(Tag::FocalLength, "FocalLength", 1)?.map(|v| v[0]);
    meta.focal_length_35mm = match field(Tag::FocalLengthIn35mmFilm) {
        None => None,
        Some(value) => match value.get_uint(0) {
            Some(0) | None => None, // 0 means unknown (EXIF 2.3)
            Some(f) => Some(f64::from(f)),
        },
    };
    if meta
        .make
        .as_deref()
        .is_some_and(|m| m.eq_ignore_ascii_case("DJI"))
    {
        if let Some(Value::Undefined(bytes, _)) = field(Tag::MakerNote) {
            if let Some(note) = dji_maker_note(bytes) {
                meta.gimbal = note.camera;
                meta.flight = note.flight;
                if meta.gimbal.is_some() {
                    meta.attitude_source = Some(AttitudeSource::MakerNote);
                }
            }
        }
    }
    Ok(())
}

/// The attitudes in a DJI maker note (exiftool's DJI tags 0x06–0x0B: Pitch, Yaw, Roll,
/// CameraPitch, CameraYaw, CameraRoll, each one f32).
#[derive(Debug, Default, PartialEq)]
pub struct DjiMakerNote {
    pub flight: Option<Attitude>,
    pub camera: Option<Attitude>,
}

/// Parses a DJI maker note: a bare IFD (no header), whose byte order is its own (little-endian on
/// the drones; an editor that rewrites the EXIF big-endian copies it unchanged), so both are tried
/// and the one whose first entry is `Make = "DJI"` kept. `None` when it is not one.
pub fn dji_maker_note(bytes: &[u8]) -> Option<DjiMakerNote> {
    [true, false]
        .into_iter()
        .find_map(|little| dji_maker_note_with(bytes, little))
}

fn dji_maker_note_with(bytes: &[u8], little: bool) -> Option<DjiMakerNote> {
    let u16_at = |at: usize| -> Option<u16> {
        let b: [u8; 2] = bytes.get(at..at + 2)?.try_into().ok()?;
        Some(if little {
            u16::from_le_bytes(b)
        } else {
            u16::from_be_bytes(b)
        })
    };
    let u32_at = |at: usize| -> Option<u32> {
        let b: [u8; 4] = bytes.get(at..at + 4)?.try_into().ok()?;
        Some(if little {
            u32::from_le_bytes(b)
        } else {
            u32::from_be_bytes(b)
        })
    };
    let count = usize::from(u16_at(0)?);
    if count == 0 || count > 64 || bytes.len() < 2 + 12 * count {
        return None;
    }
    let mut values = [None::<f64>; 12];
    let mut is_dji = false;
    for index in 0..count {
        let at = 2 + 12 * index;
        let (tag, kind, n) = (u16_at(at)?, u16_at(at + 2)?, u32_at(at + 4)?);
        let inline = bytes.get(at + 8..at + 12)?;
        if tag == 0x01 && kind == 2 && n == 4 && inline == b"DJI\0" {
            is_dji = true;
        }
        if (0x06..=0x0B).contains(&tag) && kind == 11 && n == 1 {
            let value = f32::from_bits(u32_at(at + 8)?);
            values[usize::from(tag)] = value.is_finite().then_some(f64::from(value));
        }
    }
    if !is_dji {
        return None;
    }
    let attitude = |pitch: usize, yaw: usize, roll: usize| -> Option<Attitude> {
        Some(Attitude {
            yaw_deg: values[yaw]?,
            pitch_deg: values[pitch]?,
            roll_deg: values[roll]?,
        })
    };
    Some(DjiMakerNote {
        flight: attitude(0x06, 0x07, 0x08),
        camera: attitude(0x09, 0x0A, 0x0B),
    })
}

/// XMP's DJI attributes into `meta` (they replace the maker note's attitudes).
fn apply_xmp(path: &Path, xmp: &DjiXmp, meta: &mut PhotoMetadata) -> Result<(), PriorsError> {
    let number = |name: &str| {
        xmp.number(name)
            .map_err(|found| field_error(path, name, found, "a decimal number"))
    };
    let attitude = |prefix: &str| -> Result<Option<Attitude>, PriorsError> {
        let names = [
            format!("{prefix}YawDegree"),
            format!("{prefix}PitchDegree"),
            format!("{prefix}RollDegree"),
        ];
        let values = [number(&names[0])?, number(&names[1])?, number(&names[2])?];
        match values {
            [Some(yaw_deg), Some(pitch_deg), Some(roll_deg)] => Ok(Some(Attitude {
                yaw_deg,
                pitch_deg,
                roll_deg,
            })),
            [None, None, None] => Ok(None),
            _ => {
                let missing = names
                    .iter()
                    .zip(values)
                    .find(|(_, v)| v.is_none())
                    .map(|(n, _)| n.clone())
                    .unwrap_or_default();
                Err(field_error(
                    path,
                    &format!("drone-dji:{missing}"),
                    "nothing",
                    &format!("all three of {prefix}Yaw/Pitch/RollDegree, or none"),
                ))
            }
        }
    };
    if let Some(gimbal) = attitude("Gimbal")? {
        meta.gimbal = Some(gimbal);
        meta.attitude_source = Some(AttitudeSource::Xmp);
    }
    if let Some(flight) = attitude("Flight")? {
        meta.flight = Some(flight);
    }
    if let Some(relative) = number("RelativeAltitude")? {
        meta.relative_altitude_m = Some(relative);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_data::repo_data;

    /// A JPEG header with the crop's segments and an XMP packet inserted after SOI.
    pub(crate) fn with_xmp(jpeg: &[u8], xmp: &str) -> Vec<u8> {
        let mut payload = XMP_HEADER.to_vec();
        payload.extend_from_slice(xmp.as_bytes());
        let length = u16::try_from(payload.len() + 2).unwrap();
        let mut out = jpeg[..2].to_vec();
        out.extend_from_slice(&[0xFF, 0xE1]);
        out.extend_from_slice(&length.to_be_bytes());
        out.extend_from_slice(&payload);
        out.extend_from_slice(&jpeg[2..]);
        out
    }

    /// The crop keeps the original photo's EXIF (rewritten big-endian by an editor, the DJI maker
    /// note copied unchanged, little-endian) but no XMP: GPS, camera and the maker note's gimbal
    /// must equal the shared set's `exif_gps_imu.csv` row of DJI_0025.
    #[test]
    fn crop_exif_gives_gps_camera_and_maker_note_attitude() {
        let meta = read_photo(&repo_data("brighton_beach/DJI_0025_crop.jpg")).unwrap();
        assert_eq!(meta.name, "DJI_0025_crop.jpg");
        assert_eq!(meta.image_size_px, Some((240, 136)));
        assert_eq!(meta.make.as_deref(), Some("DJI"));
        assert_eq!(meta.model.as_deref(), Some("FC300S"));
        let gps = meta.gps.unwrap();
        // exif_gps_imu.csv: 46.8427738611111, -91.9938259444444, 198.509
        assert!(
            (gps.latitude_deg - 46.842_773_861_111_1).abs() < 1e-12,
            "{gps:?}"
        );
        assert!(
            (gps.longitude_deg + 91.993_825_944_444_4).abs() < 1e-12,
            "{gps:?}"
        );
        assert!((gps.altitude_m - 198.509).abs() < 1e-9, "{gps:?}");
        assert_eq!(meta.focal_length_mm, Some(3.61));
        assert_eq!(meta.focal_length_35mm, Some(20.0));
        // exif_gps_imu.csv: gimbal -132.00, -89.90, +0.00; flight -129.90, -1.60, +0.90.
        assert_eq!(meta.attitude_source, Some(AttitudeSource::MakerNote));
        let gimbal = meta.gimbal.unwrap();
        assert!((gimbal.yaw_deg + 132.0).abs() < 1e-5, "{gimbal:?}");
        assert!((gimbal.pitch_deg + 89.9).abs() < 1e-5, "{gimbal:?}");
        assert!(gimbal.roll_deg.abs() < 1e-5, "{gimbal:?}");
        let flight = meta.flight.unwrap();
        assert!((flight.yaw_deg + 129.9).abs() < 1e-5, "{flight:?}");
        assert!((flight.pitch_deg + 1.6).abs() < 1e-5, "{flight:?}");
        assert!((flight.roll_deg - 0.9).abs() < 1e-5, "{flight:?}");
        assert_eq!(meta.relative_altitude_m, None);
    }

    #[test]
    fn xmp_attitude_replaces_the_maker_note() {
        let jpeg = std::fs::read(repo_data("brighton_beach/DJI_0025_crop.jpg")).unwrap();
        let xmp = r#"<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF><rdf:Description
            drone-dji:RelativeAltitude="+40.00" drone-dji:GimbalRollDegree="+0.10"
            drone-dji:GimbalYawDegree="-131.50" drone-dji:GimbalPitchDegree="-89.80"
            drone-dji:FlightYawDegree="-129.90" drone-dji:FlightPitchDegree="-1.60"
            drone-dji:FlightRollDegree="+0.90"/></rdf:RDF></x:xmpmeta>"#;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("with_xmp.jpg");
        std::fs::write(&path, with_xmp(&jpeg, xmp)).unwrap();
        let meta = read_photo(&path).unwrap();
        assert_eq!(meta.attitude_source, Some(AttitudeSource::Xmp));
        assert_eq!(
            meta.gimbal,
            Some(Attitude {
                yaw_deg: -131.5,
                pitch_deg: -89.8,
                roll_deg: 0.1
            })
        );
        assert_eq!(meta.relative_altitude_m, Some(40.0));
        assert!(meta.gps.is_some());

        // Malformed: the error names the file and the field.
        let broken = xmp.replace("-89.80", "minus ninety");
        std::fs::write(&path, with_xmp(&jpeg, &broken)).unwrap();
        let error = read_photo(&path).unwrap_err().to_string();
        assert!(
            error.contains("with_xmp.jpg") && error.contains("GimbalPitchDegree"),
            "{error}"
        );
        // Incomplete: one angle missing is an error too.
        let partial = xmp.replace("drone-dji:GimbalRollDegree=\"+0.10\"", "");
        std::fs::write(&path, with_xmp(&jpeg, &partial)).unwrap();
        let error = read_photo(&path).unwrap_err().to_string();
        assert!(error.contains("GimbalRollDegree"), "{error}");
    }

    #[test]
    fn headers_without_metadata_and_broken_files() {
        // SOI, SOF0 (8-bit, 3×2 px), SOS: no EXIF, no XMP.
        let minimal = [
            0xFF, 0xD8, 0xFF, 0xC0, 0x00, 0x0B, 0x08, 0x00, 0x02, 0x00, 0x03, 0x01, 0x01, 0x11,
            0x00, 0xFF, 0xDA,
        ];
        let header = read_header(&mut &minimal[..]).unwrap();
        assert_eq!(header.size_px, Some((3, 2)));
        assert!(header.exif_tiff.is_none() && header.xmp.is_none());
        assert!(read_header(&mut &b"\x89PNG\r\n"[..])
            .unwrap_err()
            .contains("not a JPEG"));
        assert!(read_header(&mut &minimal[..9])
            .unwrap_err()
            .contains("truncated"));

        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("fake.jpg");
        std::fs::write(&path, b"not a jpeg at all").unwrap();
        let error = read_photo(&path).unwrap_err().to_string();
        assert!(
            error.contains("fake.jpg") && error.contains("not a JPEG"),
            "{error}"
        );
    }

    #[test]
    fn maker_notes_are_read_in_either_byte_order_and_others_ignored() {
        fn note(little: bool) -> Vec<u8> {
            let u16b = |v: u16| {
                if little {
                    v.to_le_bytes()
                } else {
                    v.to_be_bytes()
                }
            };
            let u32b = |v: u32| {
                if little {
                    v.to_le_bytes()
                } else {
                    v.to_be_bytes()
                }
            };
            let mut out = u16b(7).to_vec();
            let mut entry = |tag: u16, kind: u16, inline: [u8; 4]| {
                out.extend_from_slice(&u16b(tag));
                out.extend_from_slice(&u16b(kind));
                out.extend_from_slice(&u32b(if kind == 2 { 4 } else { 1 }));
                out.extend_from_slice(&inline);
            };
            entry(1, 2, *b"DJI\0");
            for (tag, value) in [
                (6, 1.5f32),
                (7, 46.0),
                (8, 3.0),
                (9, -89.9),
                (10, 45.0),
                (11, 0.0),
            ] {
                entry(tag, 11, u32b(value.to_bits()));
            }
            out
        }
        for little in [true, false] {
            let parsed = dji_maker_note(&note(little)).unwrap();
            let camera = parsed.camera.unwrap();
            assert_eq!(camera.yaw_deg, 45.0);
            assert!((camera.pitch_deg + 89.9).abs() < 1e-5);
            assert_eq!(parsed.flight.unwrap().pitch_deg, 1.5);
        }
        let mut other = note(true);
        other[10..13].copy_from_slice(b"XYZ");
        assert_eq!(dji_maker_note(&other), None);
        assert_eq!(dji_maker_note(&[1, 2, 3]), None);
    }
}
