//! WGS84 → UTM (forward transverse Mercator) and the meridian convergence, and the local metric
//! frame the priors are written in (UTM minus an offset, the same one the mesh is shifted by).
//!
//! The projection is Krüger's series to the sixth order in the third flattening `n` (Karney 2011,
//! "Transverse Mercator with an accuracy of a few nanometers", eqs. 6–11, 35): within a UTM zone
//! (±3° from the central meridian, and far beyond) its error is below a micrometre, so the
//! millimetres come from the input, not from here. Zones follow the standard rule (6° bands from
//! 180° W), with the Norway and Svalbard exceptions; a zone may also be forced (`--utm-zone`), which
//! is how photos on both sides of a zone boundary stay in one frame.

use std::f64::consts::PI;
use std::fmt;
use std::path::Path;

use super::PriorsError;

/// WGS84 semi-major axis.
const WGS84_A_M: f64 = 6_378_137.0;
/// WGS84 flattening.
const WGS84_F: f64 = 1.0 / 298.257_223_563;
/// UTM scale on the central meridian.
const UTM_K0: f64 = 0.9996;
/// UTM false easting.
const UTM_FALSE_EASTING_M: f64 = 500_000.0;
/// UTM false northing in the southern hemisphere.
const UTM_FALSE_NORTHING_SOUTH_M: f64 = 10_000_000.0;

/// A UTM zone: its number (1–60) and hemisphere (which false northing applies).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct UtmZone {
    pub number: u8,
    pub north: bool,
}

impl UtmZone {
    /// The zone a point lies in by the standard rule, with the Norway (32V) and Svalbard (31X–37X)
    /// exceptions.
    pub fn of(latitude_deg: f64, longitude_deg: f64) -> Self {
        let lon = (longitude_deg + 180.0).rem_euclid(360.0) - 180.0;
        let mut number = ((lon + 180.0) / 6.0).floor() as i32 + 1;
        if (56.0..64.0).contains(&latitude_deg) && (3.0..12.0).contains(&lon) {
            number = 32;
        }
        if (72.0..=84.0).contains(&latitude_deg) && (0.0..42.0).contains(&lon) {
            number = if lon < 9.0 {
                31
            } else if lon < 21.0 {
                33
            } else if lon < 33.0 {
                35
            } else {
                37
            };
        }
        Self {
            number: number.clamp(1, 60) as u8,
            north: latitude_deg >= 0.0,
        }
    }

    /// Longitude of the zone's central meridian.
    pub fn central_meridian_deg(self) -> f64 {
        f64::from(self.number) * 6.0 - 183.0
    }

    /// Parses `15N`, `15n`, `33S` (number 1–60, then N or S).
    pub fn parse(text: &str) -> Option<Self> {
        let text = text.trim();
        // Split before the last character, not the last byte: `15é` must be refused, not panic.
        let (last_start, _) = text.char_indices().next_back()?;
        let (number, hemisphere) = text.split_at(last_start);
        let number: u8 = number.parse().ok()?;
        if !(1..=60).contains(&number) {
            return None;
        }
        let north = match hemisphere {
            "N" | "n" => true,
            "S" | "s" => false,
            _ => return None,
        };
        Some(Self { number, north })
    }
}

impl fmt::Display for UtmZone {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}{}", self.number, if self.north { 'N' } else { 'S' })
    }
}

/// A point in UTM, with the local properties of the projection there.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct UtmPoint {
    pub easting_m: f64,
    pub northing_m: f64,
    /// Meridian convergence γ: the bearing of grid north measured clockwise from true north
    /// (positive east of the central meridian in the northern hemisphere). A direction with true
    /// bearing α has grid bearing α − γ.
    pub convergence_deg: f64,
    /// Point scale factor k (1 + distortion of lengths).
    pub scale: f64,
}

/// Krüger's α coefficients (Karney 2011, eq. 35), to n⁶.
fn alpha(n: f64) -> [f64; 6] {
    let n2 = n * n;
    let n3 = n2 * n;
    let n4 = n3 * n;
    let n5 = n4 * n;
    let n6 = n5 * n;
    [
        n / 2.0 - 2.0 * n2 / 3.0 + 5.0 * n3 / 16.0 + 41.0 * n4 / 180.0 - 127.0 * n5 / 288.0
            + 7891.0 * n6 / 37800.0,
        13.0 * n2 / 48.0 - 3.0 * n3 / 5.0 + 557.0 * n4 / 1440.0 + 281.0 * n5 / 630.0
            - 1_983_433.0 * n6 / 1_935_360.0,
        61.0 * n3 / 240.0 - 103.0 * n4 / 140.0
            + 15061.0 * n5 / 26880.0
            + 167_603.0 * n6 / 181_440.0,
        49561.0 * n4 / 161_280.0 - 179.0 * n5 / 168.0 + 6_601_661.0 * n6 / 7_257_600.0,
        34729.0 * n5 / 80640.0 - 3_418_889.0 * n6 / 1_995_840.0,
        212_378_941.0 * n6 / 319_334_400.0,
    ]
}

/// Projects a WGS84 point into the given UTM zone. Errors when the latitude is outside ±90° or
/// the longitude is more than 60° from the zone's central meridian (the series diverges long
/// before; 60° is generous: UTM itself stays within a few degrees).
pub fn to_utm(latitude_deg: f64, longitude_deg: f64, zone: UtmZone) -> Result<UtmPoint, String> {
    if !(latitude_deg.is_finite() && latitude_deg.abs() <= 90.0) {
        return Err(format!("latitude {latitude_deg}° is not within ±90°"));
    }
    let dlon_deg = (longitude_deg - zone.central_meridian_deg() + 180.0).rem_euclid(360.0) - 180.0;
    if !(dlon_deg.is_finite() && dlon_deg.abs() <= 60.0) {
        return Err(format!(
            "longitude {longitude_deg}° is {dlon_deg:.1}° from the central meridian of zone {zone}; \
             give a zone that holds the photos (--utm-zone)"
        ));
    }
    let f = WGS84_F;
    let n = f / (2.0 - f);
    let e = (f * (2.0 - f)).sqrt();
    let a_rect = WGS84_A_M / (1.0 + n) * (1.0 + n * n / 4.0 + n.powi(4) / 64.0 + n.powi(6) / 256.0);
    let phi = latitude_deg.to_radians();
    let lambda = dlon_deg.to_radians();

    // Conformal latitude (as its tangent τ') and the Gauss–Schreiber coordinates ξ', η'.
    let tau = phi.tan();
    let sigma = (e * (e * tau / (1.0 + tau * tau).sqrt()).atanh()).sinh();
    let tau_prime = tau * (1.0 + sigma * sigma).sqrt() - sigma * (1.0 + tau * tau).sqrt();
    let (xi_p, eta_p) = if latitude_deg.abs() == 90.0 {
        (phi, 0.0)
    } else {
        (
            tau_prime.atan2(lambda.cos()),
            (lambda.sin() / (tau_prime * tau_prime + lambda.cos().powi(2)).sqrt()).asinh(),
        )
    };

    let alpha = alpha(n);
    let mut xi = xi_p;
    let mut eta = eta_p;
    let mut p = 1.0; // σ of Karney's eq. 11 (the derivative's real part)
    let mut q = 0.0; // τ of eq. 11 (its imaginary part)
    for (j, a) in alpha.iter().enumerate() {
        let k = 2.0 * (j as f64 + 1.0);
        xi += a * (k * xi_p).sin() * (k * eta_p).cosh();
        eta += a * (k * xi_p).cos() * (k * eta_p).sinh();
        p += k * a * (k * xi_p).cos() * (k * eta_p).cosh();
        q += k * a * (k * xi_p).sin() * (k * eta_p).sinh();
    }

    let easting_m = UTM_FALSE_EASTING_M + UTM_K0 * a_rect * eta;
    let northing_m = UTM_K0 * a_rect * xi
        + if zone.north {
            0.0
        } else {
            UTM_FALSE_NORTHING_SOUTH_M
        };

    // Convergence and scale (Karney 2011, eqs. 12–13).
    let gamma_prime = (tau_prime * lambda.tan()).atan2((1.0 + tau_prime * tau_prime).sqrt());
    let gamma_pp = q.atan2(p);
    let convergence_deg = (gamma_prime + gamma_pp) * 180.0 / PI;
    let scale = UTM_K0
        * ((1.0 - (e * phi.sin()).powi(2)).sqrt() * (1.0 + tau * tau).sqrt()
            / (tau_prime * tau_prime + lambda.cos().powi(2)).sqrt())
        * a_rect
        / WGS84_A_M
        * (p * p + q * q).sqrt();
    Ok(UtmPoint {
        easting_m,
        northing_m,
        convergence_deg,
        scale,
    })
}

/// The local metric frame: `X = easting − easting_m`, `Y = northing − northing_m`,
/// `Z = altitude − altitude_m`, in one UTM zone. The mesh must be in the same frame (shifted by
/// the same offset) for the priors to fit it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LocalFrame {
    pub zone: UtmZone,
    pub easting_m: f64,
    pub northing_m: f64,
    pub altitude_m: f64,
}

impl LocalFrame {
    /// The frame whose origin is the south-west corner of the points' UTM bounding box rounded
    /// down to whole hundreds of metres (altitude offset 0: Z stays the GPS altitude), so that
    /// every local coordinate is small and positive and the offset is a round number to type.
    pub fn rounded_minimum(zone: UtmZone, points: &[UtmPoint]) -> Self {
        let min_e = points
            .iter()
            .map(|p| p.easting_m)
            .fold(f64::INFINITY, f64::min);
        let min_n = points
            .iter()
            .map(|p| p.northing_m)
            .fold(f64::INFINITY, f64::min);
        let round = |v: f64| {
            if v.is_finite() {
                (v / 100.0).floor() * 100.0
            } else {
                0.0
            }
        };
        Self {
            zone,
            easting_m: round(min_e),
            northing_m: round(min_n),
            altitude_m: 0.0,
        }
    }

    /// The local coordinates of a UTM point at an altitude.
    pub fn local(&self, point: &UtmPoint, altitude_m: f64) -> [f64; 3] {
        [
            point.easting_m - self.easting_m,
            point.northing_m - self.northing_m,
            altitude_m - self.altitude_m,
        ]
    }

    /// The offset file (`utm_offset.txt`): comment lines, then `key value` lines.
    pub fn to_file_text(&self) -> String {
        format!(
            "# asgreg priors: local frame = UTM - offset: X = easting - easting_m, \
             Y = northing - northing_m, Z = altitude - altitude_m (WGS84, metres).\n\
             # Shift the mesh by the same offset (or give this file to `asgreg priors --offset-file`).\n\
             zone {}\neasting_m {}\nnorthing_m {}\naltitude_m {}\n",
            self.zone, self.easting_m, self.northing_m, self.altitude_m
        )
    }

    /// Reads an offset file written by [`LocalFrame::to_file_text`]. `zone` is optional (the caller
    /// then chooses it); `altitude_m` defaults to 0.
    pub fn parse_file(path: &Path, text: &str) -> Result<(Option<UtmZone>, [f64; 3]), PriorsError> {
        let mut zone = None;
        let mut values: [Option<f64>; 3] = [None, None, Some(0.0)];
        for (index, raw) in text.lines().enumerate() {
            let line = raw.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let bad = |field: &str, expected: &str| PriorsError::Field {
                path: path.to_path_buf(),
                field: format!("line {}: {field}", index + 1),
                found: raw.to_string(),
                expected: expected.to_string(),
            };
            let mut words = line.split_whitespace();
            let key = words.next().unwrap_or_default();
            let value = words.next().ok_or_else(|| bad(key, "`key value`"))?;
            if words.next().is_some() {
                return Err(bad(key, "`key value` and nothing more"));
            }
            let slot = match key {
                "zone" => {
                    zone = Some(
                        UtmZone::parse(value)
                            .ok_or_else(|| bad("zone", "a UTM zone such as 15N or 33S"))?,
                    );
                    continue;
                }
                "easting_m" => 0,
                "northing_m" => 1,
                "altitude_m" => 2,
                _ => {
                    return Err(bad(
                        key,
                        "one of the keys zone, easting_m, northing_m, altitude_m",
                    ))
                }
            };
            let number: f64 = value
                .parse()
                .ok()
                .filter(|v: &f64| v.is_finite())
                .ok_or_else(|| bad(key, "a finite number of metres"))?;
            values[slot] = Some(number);
        }
        let missing = |field: &str| PriorsError::MissingField {
            path: path.to_path_buf(),
            field: field.to_string(),
            hint: "the offset file needs `easting_m E` and `northing_m N` lines".to_string(),
        };
        Ok((
            zone,
            [
                values[0].ok_or_else(|| missing("easting_m"))?,
                values[1].ok_or_else(|| missing("northing_m"))?,
                values[2].unwrap_or(0.0),
            ],
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn zone(text: &str) -> UtmZone {
        UtmZone::parse(text).unwrap()
    }

    /// Reference conversions from PROJ 9.5.1 (pyproj 3.7.2, `EPSG:4326 → EPSG:326zz/327zz`, and
    /// `Proj.get_factors` for convergence and scale), printed to 0.1 mm. Two are textbook values:
    /// the false origin, and 45° N on a central meridian, where the northing is k0 × the WGS84
    /// meridian arc 4 984 944.378 m. One (Guayaquil-ish, 17S) is 3.1° off its central meridian.
    #[test]
    fn known_points_match_proj_to_a_millimetre() {
        // (lat, lon, zone, easting, northing, convergence °, scale)
        let cases = [
            (
                46.8426070833333,
                -91.9945598888889,
                "15N",
                576663.0979,
                5188164.5561,
                0.733481475,
                0.9996722355,
            ),
            (0.0, -93.0, "15N", 500000.0000, 0.0000, 0.0, 0.9996000001),
            (
                45.0,
                9.0,
                "32N",
                500000.0000,
                4982950.4002,
                0.0,
                0.9996000000,
            ),
            (
                -33.85678,
                151.2153,
                "56S",
                334900.5312,
                6252290.9708,
                0.994514915,
                0.9999360326,
            ),
            (
                51.4778,
                -0.0015,
                "30N",
                708213.9506,
                5707224.5426,
                2.346764502,
                1.0001323062,
            ),
            (
                64.1466,
                -21.9426,
                "27N",
                454138.3765,
                7113689.8690,
                -0.848272359,
                0.9996257544,
            ),
            (
                -0.5,
                -77.9,
                "17S",
                845108.8668,
                9944653.4305,
                -0.027079224,
                1.0010746692,
            ),
            (
                70.0,
                -88.5,
                "16N",
                442748.1100,
                7766577.4147,
                -1.409576687,
                0.9996400964,
            ),
            (
                35.0,
                -103.0,
                "13N",
                682516.0936,
                3874870.6347,
                1.147469846,
                1.0000105718,
            ),
            (
                46.8426,
                -89.0,
                "15N",
                804978.4704,
                5195445.0425,
                2.920149373,
                1.0007433745,
            ),
        ];
        for (lat, lon, z, e, n, gamma, k) in cases {
            let p = to_utm(lat, lon, zone(z)).unwrap();
            assert!(
                (p.easting_m - e).abs() < 1e-3,
                "{lat} {lon}: E {} vs {e}",
                p.easting_m
            );
            assert!(
                (p.northing_m - n).abs() < 1e-3,
                "{lat} {lon}: N {} vs {n}",
                p.northing_m
            );
            assert!(
                (p.convergence_deg - gamma).abs() < 1e-8,
                "{lat} {lon}: γ {} vs {gamma}",
                p.convergence_deg
            );
            assert!(
                (p.scale - k).abs() < 1e-9,
                "{lat} {lon}: k {} vs {k}",
                p.scale
            );
        }
    }

    #[test]
    fn projection_is_symmetric_about_the_central_meridian_and_the_equator() {
        let z = zone("15N");
        let east = to_utm(46.8, -91.0, z).unwrap();
        let west = to_utm(46.8, -95.0, z).unwrap();
        assert!((east.easting_m - 500_000.0 + (west.easting_m - 500_000.0)).abs() < 1e-6);
        assert!((east.northing_m - west.northing_m).abs() < 1e-6);
        assert!((east.convergence_deg + west.convergence_deg).abs() < 1e-12);
        let south = to_utm(-46.8, -91.0, zone("15S")).unwrap();
        assert!((south.northing_m - (10_000_000.0 - east.northing_m)).abs() < 1e-6);
    }

    /// The convergence is the grid bearing of true north, negated: a small step north along the
    /// meridian moves in the grid by (dE, dN) with atan2(dE, dN) = −γ. Likewise the scale is the
    /// grid length of a small step over its length on the ellipsoid (checked east–west, where the
    /// ellipsoid's length is the parallel's radius × dλ).
    #[test]
    fn convergence_and_scale_match_finite_differences() {
        let z = zone("15N");
        for (lat, lon) in [
            (46.8426, -91.99456),
            (10.0, -95.5),
            (70.0, -90.1),
            (46.8, -93.0),
        ] {
            let p = to_utm(lat, lon, z).unwrap();
            let step = 1e-6;
            let north = to_utm(lat + step, lon, z).unwrap();
            let bearing = (north.easting_m - p.easting_m).atan2(north.northing_m - p.northing_m);
            assert!(
                (bearing.to_degrees() + p.convergence_deg).abs() < 1e-6,
                "{lat} {lon}: γ {} vs finite difference {}",
                p.convergence_deg,
                -bearing.to_degrees()
            );
            let east = to_utm(lat, lon + step, z).unwrap();
            let grid = ((east.easting_m - p.easting_m).powi(2)
                + (east.northing_m - p.northing_m).powi(2))
            .sqrt();
            let e2 = WGS84_F * (2.0 - WGS84_F);
            let phi = lat.to_radians();
            let parallel_radius = WGS84_A_M * phi.cos() / (1.0 - e2 * phi.sin().powi(2)).sqrt();
            let ground = parallel_radius * step.to_radians();
            assert!(
                (grid / ground - p.scale).abs() < 1e-7,
                "scale {} vs {}",
                p.scale,
                grid / ground
            );
        }
        // γ ≈ Δλ·sin φ near the central meridian (the textbook first-order formula).
        let p = to_utm(46.8426, -91.99456, z).unwrap();
        let first_order = 1.00544_f64 * 46.8426_f64.to_radians().sin();
        assert!(
            (p.convergence_deg - first_order).abs() < 0.01,
            "{}",
            p.convergence_deg
        );
    }

    #[test]
    fn zones_follow_the_standard_rule_and_its_exceptions() {
        assert_eq!(UtmZone::of(46.84, -91.99), zone("15N"));
        assert_eq!(UtmZone::of(-33.9, 18.4), zone("34S"));
        assert_eq!(UtmZone::of(60.0, 5.0), zone("32N")); // Norway
        assert_eq!(UtmZone::of(78.0, 15.0), zone("33N")); // Svalbard
        assert_eq!(UtmZone::of(10.0, 180.0), zone("1N"));
        assert_eq!(UtmZone::of(10.0, 179.9), zone("60N"));
        assert_eq!(zone("15N").to_string(), "15N");
        for bad in ["", "N", "0N", "61S", "15X", "15.5N"] {
            assert_eq!(UtmZone::parse(bad), None, "{bad}");
        }
    }

    #[test]
    fn bad_coordinates_are_errors() {
        assert!(to_utm(91.0, 0.0, zone("31N")).is_err());
        assert!(to_utm(f64::NAN, 0.0, zone("31N")).is_err());
        let far = to_utm(10.0, 100.0, zone("15N")).unwrap_err();
        assert!(far.contains("--utm-zone"), "{far}");
    }

    #[test]
    fn offset_file_round_trips_and_names_bad_lines() {
        let frame = LocalFrame {
            zone: zone("15N"),
            easting_m: 576_700.0,
            northing_m: 5_188_100.0,
            altitude_m: 0.0,
        };
        let path = Path::new("utm_offset.txt");
        let (z, offset) = LocalFrame::parse_file(path, &frame.to_file_text()).unwrap();
        assert_eq!(z, Some(frame.zone));
        assert_eq!(offset, [576_700.0, 5_188_100.0, 0.0]);
        let error = LocalFrame::parse_file(path, "easting_m 1\nnorthing_m x\n")
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("utm_offset.txt") && error.contains("northing_m"),
            "{error}"
        );
        let error = LocalFrame::parse_file(path, "easting_m 1\n")
            .unwrap_err()
            .to_string();
        assert!(error.contains("northing_m"), "{error}");
    }
}
