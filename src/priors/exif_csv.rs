//! The photos' metadata from an exiftool CSV (`exiftool -csv -n DIR > exif.csv`), for photos whose
//! files lost it (resized or undistorted copies) or to take exiftool's word over ours.
//!
//! Columns are found by their header name, in any order; unknown columns are ignored. Required:
//! a name (`FileName`, else the base name of `SourceFile`), `GPSLatitude`, `GPSLongitude`,
//! `GPSAltitude` and the gimbal's yaw, pitch and roll (`GimbalYawDegree` … from XMP, or the DJI
//! maker note's `CameraYaw` …). Optional: `RelativeAltitude`, `FlightYawDegree` … (or the maker
//! note's `Yaw`, `Pitch`, `Roll`), `FocalLength`, `FocalLengthIn35mmFormat`, `Make`, `Model`,
//! `GPSLatitudeRef`, `GPSLongitudeRef`. Numbers may be plain (`-n`) or exiftool's printed form
//! (`46 deg 50' 33.39" N`, `198.3 m Above Sea Level`, `3.6 mm`, `+45.00`). Quoted fields follow
//! RFC 4180 (exiftool quotes those with commas or quotes).

use std::collections::HashMap;
use std::path::Path;

use super::orientation::Attitude;
use super::{AttitudeSource, GpsPosition, PhotoMetadata, PriorsError};

/// Parses one CSV line into fields (RFC 4180 quoting, no line breaks inside fields).
fn split_csv_line(line: &str) -> Result<Vec<String>, String> {
    let mut fields = Vec::new();
    let mut field = String::new();
    let mut chars = line.chars().peekable();
    let mut quoted = false;
    let mut at_start = true;
    while let Some(c) = chars.next() {
        if quoted {
            if c == '"' {
                if chars.peek() == Some(&'"') {
                    chars.next();
                    field.push('"');
                } else {
                    quoted = false;
                }
            } else {
                field.push(c);
            }
        } else if c == '"' && at_start {
            quoted = true;
            at_start = false;
        } else if c == ',' {
            fields.push(std::mem::take(&mut field));
            at_start = true;
        } else {
            field.push(c);
            at_start = false;
        }
    }
    if quoted {
        return Err("a quoted field is not closed on its line".to_string());
    }
    fields.push(field);
    Ok(fields)
}

/// A number with an optional unit (`198.3 m Above Sea Level`, `3.6 mm`, `+45.00`).
fn parse_number_with_unit(text: &str) -> Option<f64> {
    let mut words = text.split_whitespace();
    let value: f64 = words.next()?.parse().ok().filter(|v: &f64| v.is_finite())?;
    let rest: Vec<&str> = words.collect();
    let rest = rest.join(" ").to_ascii_lowercase();
    match rest.as_str() {
        "" | "m" | "mm" | "m above sea level" => Some(value),
        "m below sea level" => Some(-value.abs()),
        _ => None,
    }
}

/// An angle: a plain signed number, or exiftool's `D deg M' S" H` (H one of N, S, E, W).
fn parse_angle_deg(text: &str) -> Option<f64> {
    let text = text.trim();
    if let Ok(value) = text.parse::<f64>() {
        return value.is_finite().then_some(value);
    }
    let (body, sign) = match text.chars().next_back()? {
        'N' | 'E' => (&text[..text.len() - 1], 1.0),
        'S' | 'W' => (&text[..text.len() - 1], -1.0),
        _ => (text, 1.0),
    };
    let cleaned = body.replace("deg", " ").replace(['\'', '"', '°'], " ");
    let parts: Vec<f64> = cleaned
        .split_whitespace()
        .map(|p| p.parse::<f64>().ok().filter(|v| v.is_finite()))
        .collect::<Option<_>>()?;
    if parts.is_empty() || parts.len() > 3 {
        return None;
    }
    let value = parts
        .iter()
        .zip([1.0, 60.0, 3600.0])
        .map(|(v, d)| v / d)
        .sum::<f64>();
    Some(sign * value)
}

/// Reads the CSV. Every error names the file, and the line and column where there is one.
pub fn read_exif_csv(path: &Path) -> Result<Vec<PhotoMetadata>, PriorsError> {
    let text = crate::io::text::read_utf8(path).map_err(|source| PriorsError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    parse_exif_csv(path, &text)
}

/// [`read_exif_csv`] on text already read (`path` names it in errors).
pub fn parse_exif_csv(path: &Path, text: &str) -> Result<Vec<PhotoMetadata>, PriorsError> {
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, line)| !line.trim().is_empty());
    let csv_error = |line: usize, field: &str, found: &str, expected: &str| PriorsError::Field {
        path: path.to_path_buf(),
        field: format!("line {line}, column {field}"),
        found: format!("\"{found}\""),
        expected: expected.to_string(),
    };
    let Some((header_index, header_line)) = lines.next() else {
        return Err(PriorsError::MissingField {
            path: path.to_path_buf(),
            field: "header line".to_string(),
            hint: "the file is empty; write it with `exiftool -csv -n DIR > FILE`".to_string(),
        });
    };
    let header = split_csv_line(header_line.trim_start_matches('\u{feff}'))
        .map_err(|why| csv_error(header_index + 1, "header", header_line, &why))?;
    let columns: HashMap<&str, usize> = header
        .iter()
        .enumerate()
        .map(|(i, name)| (name.trim(), i))
        .collect();
    let find = |names: &[&str]| names.iter().find_map(|n| columns.get(n).copied());
    let require = |names: &[&str]| {
        find(names).ok_or_else(|| PriorsError::MissingColumn {
            path: path.to_path_buf(),
            column: names.join(" or "),
        })
    };
    let name_column = require(&["FileName", "SourceFile"])?;
    let latitude_column = require(&["GPSLatitude"])?;
    let longitude_column = require(&["GPSLongitude"])?;
    let altitude_column = require(&["GPSAltitude"])?;
    let gimbal_columns = [
        require(&["GimbalYawDegree", "CameraYaw"])?,
        require(&["GimbalPitchDegree", "CameraPitch"])?,
        require(&["GimbalRollDegree", "CameraRoll"])?,
    ];
    let flight_columns = [
        find(&["FlightYawDegree", "Yaw"]),
        find(&["FlightPitchDegree", "Pitch"]),
        find(&["FlightRollDegree", "Roll"]),
    ];
    let relative_column = find(&["RelativeAltitude"]);
    let focal_column = find(&["FocalLength"]);
    let focal35_column = find(&["FocalLengthIn35mmFormat", "FocalLengthIn35mmFilm"]);
    let make_column = find(&["Make"]);
    let model_column = find(&["Model"]);
    let latitude_ref_column = find(&["GPSLatitudeRef"]);
    let longitude_ref_column = find(&["GPSLongitudeRef"]);

    let mut photos = Vec::new();
    for (index, line) in lines {
        let number = index + 1;
        let fields = split_csv_line(line).map_err(|why| csv_error(number, "-", line, &why))?;
        let cell = |column: usize| fields.get(column).map(|s| s.trim()).unwrap_or("");
        let header_name = |column: usize| header.get(column).map(String::as_str).unwrap_or("?");
        let optional = |column: Option<usize>, parse: fn(&str) -> Option<f64>| match column {
            Some(c) if !cell(c).is_empty() && cell(c) != "-" => parse(cell(c))
                .map(Some)
                .ok_or_else(|| csv_error(number, header_name(c), cell(c), "a number")),
            _ => Ok(None),
        };
        let required = |column: usize, parse: fn(&str) -> Option<f64>, expected: &str| {
            parse(cell(column))
                .ok_or_else(|| csv_error(number, header_name(column), cell(column), expected))
        };
        let raw_name = cell(name_column);
        let name = Path::new(raw_name)
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        if name.is_empty() {
            return Err(csv_error(
                number,
                header_name(name_column),
                raw_name,
                "a file name",
            ));
        }
        let mut latitude_deg = required(latitude_column, parse_angle_deg, "a latitude in degrees")?;
        let mut longitude_deg =
            required(longitude_column, parse_angle_deg, "a longitude in degrees")?;
        let hemisphere = |column: Option<usize>| {
            column
                .map(|c| cell(c).to_ascii_lowercase())
                .unwrap_or_default()
        };
        if latitude_deg > 0.0 && matches!(hemisphere(latitude_ref_column).as_str(), "s" | "south") {
            latitude_deg = -latitude_deg;
        }
        if longitude_deg > 0.0 && matches!(hemisphere(longitude_ref_column).as_str(), "w" | "west")
        {
            longitude_deg = -longitude_deg;
        }
        let altitude_m = required(
            altitude_column,
            parse_number_with_unit,
            "an altitude in metres",
        )?;
        let angle = |column: usize| required(column, parse_angle_deg, "an angle in degrees");
        let gimbal = Attitude {
            yaw_deg: angle(gimbal_columns[0])?,
            pitch_deg: angle(gimbal_columns[1])?,
            roll_deg: angle(gimbal_columns[2])?,
        };
        let flight = match [
            optional(flight_columns[0], parse_angle_deg)?,
            optional(flight_columns[1], parse_angle_deg)?,
            optional(flight_columns[2], parse_angle_deg)?,
        ] {
            [Some(yaw_deg), Some(pitch_deg), Some(roll_deg)] => Some(Attitude {
                yaw_deg,
                pitch_deg,
                roll_deg,
            }),
            _ => None,
        };
        let text = |column: Option<usize>| {
            column
                .map(|c| cell(c).to_string())
                .filter(|s| !s.is_empty() && s != "-")
        };
        photos.push(PhotoMetadata {
            name,
            gps: Some(GpsPosition {
                latitude_deg,
                longitude_deg,
                altitude_m,
            }),
            relative_altitude_m: optional(relative_column, parse_number_with_unit)?,
            gimbal: Some(gimbal),
            flight,
            attitude_source: Some(AttitudeSource::Csv),
            focal_length_mm: optional(focal_column, parse_number_with_unit)?,
            focal_length_35mm: optional(focal35_column, parse_number_with_unit)?
                .filter(|f| *f > 0.0),
            make: text(make_column),
            model: text(model_column),
            image_size_px: None,
        });
    }
    Ok(photos)
}

#[cfg(test)]
mod tests {
    use super::*;

    const BRIGHTON_HEAD: &str = "SourceFile,FileName,GPSLatitude,GPSLongitude,GPSAltitude,RelativeAltitude,GimbalYawDegree,GimbalPitchDegree,GimbalRollDegree,FlightYawDegree,FlightPitchDegree,FlightRollDegree\n\
DJI_0018.JPG,DJI_0018.JPG,46.8426070833333,-91.9945598888889,198.309,+39.80,+45.00,-89.90,+0.00,+46.00,+1.80,+3.00\n\
DJI_0019.JPG,DJI_0019.JPG,46.8426906666667,-91.9944272777778,198.609,+40.10,+42.80,-89.90,+0.00,+40.10,+1.20,+0.40\n";

    #[test]
    fn brighton_columns() {
        let photos = parse_exif_csv(Path::new("exif.csv"), BRIGHTON_HEAD).unwrap();
        assert_eq!(photos.len(), 2);
        let p = &photos[1];
        assert_eq!(p.name, "DJI_0019.JPG");
        assert_eq!(
            p.gps,
            Some(GpsPosition {
                latitude_deg: 46.8426906666667,
                longitude_deg: -91.9944272777778,
                altitude_m: 198.609
            })
        );
        assert_eq!(p.relative_altitude_m, Some(40.1));
        assert_eq!(
            p.gimbal,
            Some(Attitude {
                yaw_deg: 42.8,
                pitch_deg: -89.9,
                roll_deg: 0.0
            })
        );
        assert_eq!(p.flight.map(|f| f.roll_deg), Some(0.4));
        assert_eq!(p.attitude_source, Some(AttitudeSource::Csv));
        assert_eq!(p.focal_length_mm, None);
    }

    /// exiftool without `-n`: printed angles, units, quoted fields, maker-note column names,
    /// columns in another order, a path in SourceFile only.
    #[test]
    fn printed_values_and_maker_note_names() {
        let text = "Model,SourceFile,CameraRoll,CameraYaw,CameraPitch,GPSAltitude,GPSLongitude,GPSLatitude,FocalLength,FocalLengthIn35mmFormat\n\
FC300S,\"photos/DJI, 1.JPG\",0,-132,-89.9,198.5 m Above Sea Level,\"91 deg 59' 37.77\"\" W\",\"46 deg 50' 33.99\"\" N\",3.6 mm,20 mm\n";
        let photos = parse_exif_csv(Path::new("exif.csv"), text).unwrap();
        let p = &photos[0];
        assert_eq!(p.name, "DJI, 1.JPG");
        let gps = p.gps.unwrap();
        assert!((gps.latitude_deg - (46.0 + 50.0 / 60.0 + 33.99 / 3600.0)).abs() < 1e-12);
        assert!((gps.longitude_deg + (91.0 + 59.0 / 60.0 + 37.77 / 3600.0)).abs() < 1e-12);
        assert_eq!(gps.altitude_m, 198.5);
        assert_eq!(p.gimbal.map(|g| g.yaw_deg), Some(-132.0));
        assert_eq!(p.focal_length_mm, Some(3.6));
        assert_eq!(p.focal_length_35mm, Some(20.0));
        assert_eq!(p.model.as_deref(), Some("FC300S"));
        assert_eq!(parse_number_with_unit("12 m Below Sea Level"), Some(-12.0));
        assert_eq!(
            parse_angle_deg("33 deg 51' 24.41\" S").map(|v| v < 0.0),
            Some(true)
        );
    }

    #[test]
    fn missing_columns_and_bad_values_are_named() {
        let no_yaw =
            "FileName,GPSLatitude,GPSLongitude,GPSAltitude,GimbalPitchDegree,GimbalRollDegree\n";
        let error = parse_exif_csv(Path::new("e.csv"), no_yaw)
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("e.csv") && error.contains("GimbalYawDegree or CameraYaw"),
            "{error}"
        );

        let bad = BRIGHTON_HEAD.replace("-91.9944272777778", "west");
        let error = parse_exif_csv(Path::new("e.csv"), &bad)
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("line 3") && error.contains("GPSLongitude") && error.contains("west"),
            "{error}"
        );

        let short = BRIGHTON_HEAD.replace(",+40.10,+42.80,-89.90,+0.00,+40.10,+1.20,+0.40", "");
        let error = parse_exif_csv(Path::new("e.csv"), &short)
            .unwrap_err()
            .to_string();
        assert!(error.contains("line 3"), "{error}");

        let error = parse_exif_csv(Path::new("e.csv"), "")
            .unwrap_err()
            .to_string();
        assert!(error.contains("empty"), "{error}");
        let unclosed = format!("{}\"DJI_0020.JPG,1\n", BRIGHTON_HEAD);
        let error = parse_exif_csv(Path::new("e.csv"), &unclosed)
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("line 4") && error.contains("not closed"),
            "{error}"
        );
    }

    #[test]
    fn csv_lines_split_like_rfc_4180() {
        assert_eq!(
            split_csv_line("a,\"b,c\",\"d\"\"e\",").unwrap(),
            ["a", "b,c", "d\"e", ""]
        );
        assert!(split_csv_line("\"open").is_err());
    }
}
