//! `asgreg priors`: an initial pose per photo from the photo itself (GPS and DJI gimbal attitude
//! in EXIF/XMP, or an exiftool CSV), in the mesh's local UTM frame, written as a COLMAP model with
//! the frame's offset beside it (`priors` module).

use std::collections::HashMap;
use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use asgreg::io::colmap::ColmapModel;
use asgreg::io::colmap_model::{read_cameras_at, write_model_dir};
use asgreg::priors::exif_csv::read_exif_csv;
use asgreg::priors::jpeg::{read_header, read_photo};
use asgreg::priors::utm::{LocalFrame, UtmZone};
use asgreg::priors::{build_priors, PhotoMetadata, PriorsOptions};

/// The offset file written next to the model.
pub const OFFSET_FILE: &str = "utm_offset.txt";

#[derive(clap::Args, Debug)]
pub struct PriorsArgs {
    /// Folder of the photos (JPEG): their size, and their EXIF/XMP unless --exif-csv is given.
    #[arg(long)]
    pub images: PathBuf,
    /// exiftool CSV (`exiftool -csv -n DIR > F`) to take GPS and gimbal angles from instead of the
    /// photos (for copies that lost their EXIF). One row per photo, matched by file name.
    #[arg(long)]
    pub exif_csv: Option<PathBuf>,
    /// Output folder: COLMAP model (cameras, images, empty points3D; text and binary) and
    /// utm_offset.txt (the local frame: shift the mesh by the same offset).
    #[arg(long)]
    pub out: PathBuf,
    /// Local frame's easting offset (m): X = easting − this. With --offset-n; default: the photos'
    /// minimum easting rounded down to 100 m.
    #[arg(long, requires = "offset_n", conflicts_with = "offset_file")]
    pub offset_e: Option<f64>,
    /// Local frame's northing offset (m): Y = northing − this.
    #[arg(long, requires = "offset_e", conflicts_with = "offset_file")]
    pub offset_n: Option<f64>,
    /// Local frame's altitude offset (m): Z = GPS altitude − this.
    #[arg(long, default_value_t = 0.0, conflicts_with = "offset_file")]
    pub offset_z: f64,
    /// The offset as a file: a utm_offset.txt written by an earlier run (or by hand:
    /// `zone 15N`, `easting_m E`, `northing_m N`, `altitude_m Z` lines), so that several batches
    /// and the mesh share one frame.
    #[arg(long)]
    pub offset_file: Option<PathBuf>,
    /// UTM zone, e.g. 15N or 33S; default: the offset file's, else the photos' mean position's.
    #[arg(long)]
    pub utm_zone: Option<String>,
    /// Keep the gimbal yaw as bearing from true north instead of turning it to grid north (the
    /// meridian convergence, 0.73° at Brighton Beach). Off by default: the frame is UTM's grid.
    #[arg(long)]
    pub no_meridian_convergence: bool,
    /// A calibration to use instead of EXIF's focal length: COLMAP cameras.txt/.bin or a model
    /// folder; one camera, or one per image size.
    #[arg(long)]
    pub cameras: Option<PathBuf>,
}

/// The JPEG files of a folder, sorted by name.
fn list_jpegs(dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(dir).with_context(|| {
        format!(
            "{}: cannot list the photos folder (--images)",
            dir.display()
        )
    })?;
    let mut paths = Vec::new();
    for entry in entries {
        let path = entry
            .with_context(|| format!("{}: cannot list the photos folder", dir.display()))?
            .path();
        let is_jpeg = path
            .extension()
            .map(|e| e.to_string_lossy().to_ascii_lowercase())
            .is_some_and(|e| e == "jpg" || e == "jpeg");
        if is_jpeg && path.is_file() {
            paths.push(path);
        }
    }
    paths.sort();
    if paths.is_empty() {
        bail!(
            "{}: no .jpg/.jpeg files; give the folder of the photos with --images",
            dir.display()
        );
    }
    Ok(paths)
}

/// Each photo's metadata from the CSV, with its size (and, where the CSV lacks them, focal length,
/// make and model) from the JPEG.
fn photos_from_csv(csv: &Path, paths: &[PathBuf]) -> anyhow::Result<Vec<PhotoMetadata>> {
    let rows = read_exif_csv(csv)?;
    let by_name: HashMap<String, &PhotoMetadata> = rows
        .iter()
        .map(|row| (row.name.to_lowercase(), row))
        .collect();
    let mut photos = Vec::with_capacity(paths.len());
    for path in paths {
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let Some(row) = by_name.get(&name.to_lowercase()) else {
            bail!(
                "{}: no row for this photo in {} (matched by FileName, or SourceFile's file name); \
                 add it (exiftool -csv -n) or move the photo out of --images",
                path.display(),
                csv.display()
            );
        };
        let mut photo = (*row).clone();
        photo.name = name;
        // The JPEG's own metadata only fills gaps; a broken EXIF there does not matter.
        match read_photo(path) {
            Ok(own) => {
                photo.image_size_px = own.image_size_px;
                photo.focal_length_mm = photo.focal_length_mm.or(own.focal_length_mm);
                photo.focal_length_35mm = photo.focal_length_35mm.or(own.focal_length_35mm);
                photo.make = photo.make.or(own.make);
                photo.model = photo.model.or(own.model);
            }
            Err(error) => {
                tracing::warn!("{error}; only the image size is read from it");
                let file =
                    File::open(path).with_context(|| format!("{}: cannot open", path.display()))?;
                let header = read_header(&mut BufReader::new(file))
                    .map_err(|why| anyhow::anyhow!("{}: {why}", path.display()))?;
                photo.image_size_px = header.size_px;
            }
        }
        photos.push(photo);
    }
    let unused = rows.len().saturating_sub(photos.len());
    if unused > 0 {
        tracing::info!(
            "{unused} row(s) of {} have no photo in {}",
            csv.display(),
            paths[0].parent().unwrap_or(Path::new(".")).display()
        );
    }
    Ok(photos)
}

pub fn run(args: &PriorsArgs) -> anyhow::Result<()> {
    let paths = list_jpegs(&args.images)?;
    let photos = match &args.exif_csv {
        Some(csv) => photos_from_csv(csv, &paths)?,
        None => paths
            .iter()
            .map(|path| read_photo(path))
            .collect::<Result<Vec<_>, _>>()
            .context("reading the photos' EXIF/XMP (or give --exif-csv)")?,
    };

    let mut zone = match &args.utm_zone {
        Some(text) => Some(UtmZone::parse(text).with_context(|| {
            format!("--utm-zone {text}: expected a zone number 1–60 and N or S, e.g. 15N")
        })?),
        None => None,
    };
    let offset_m = match (&args.offset_file, args.offset_e, args.offset_n) {
        (Some(file), _, _) => {
            let text = asgreg::io::text::read_utf8(file).with_context(|| {
                format!(
                    "{}: cannot read the offset file (--offset-file)",
                    file.display()
                )
            })?;
            let (file_zone, offset) = LocalFrame::parse_file(file, &text)?;
            match (zone, file_zone) {
                (Some(given), Some(in_file)) if given != in_file => bail!(
                    "--utm-zone {given} but {} says zone {in_file}; give one of them",
                    file.display()
                ),
                (None, in_file) => zone = in_file,
                _ => {}
            }
            Some(offset)
        }
        (None, Some(e), Some(n)) => Some([e, n, args.offset_z]),
        _ => None,
    };
    let cameras = match &args.cameras {
        Some(path) => {
            let (cameras, file) = read_cameras_at(path)?;
            Some((cameras, file))
        }
        None => None,
    };
    let options = PriorsOptions {
        zone,
        offset_m,
        correct_convergence: !args.no_meridian_convergence,
        cameras,
    };
    let priors = build_priors(&photos, &options)
        .with_context(|| format!("photos in {}", args.images.display()))?;

    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("{}: cannot create the output folder", args.out.display()))?;
    let model = ColmapModel {
        cameras: priors.cameras.clone(),
        images: priors.images.clone(),
    };
    write_model_dir(&args.out, &model)?;
    let offset_path = args.out.join(OFFSET_FILE);
    std::fs::write(&offset_path, priors.frame.to_file_text())
        .with_context(|| format!("{}: cannot write", offset_path.display()))?;

    println!(
        "{:<24} {:>10} {:>11} {:>11} {:>9} {:>8} {:>7} {:>6} {:>8} {:>3}",
        "image", "source", "X m", "Y m", "Z m", "yaw°", "pitch°", "roll°", "rel.alt", "cam"
    );
    for s in &priors.summary {
        println!(
            "{:<24} {:>10} {:>11.3} {:>11.3} {:>9.3} {:>8.2} {:>7.2} {:>6.2} {:>8} {:>3}",
            s.name,
            s.source.map(|s| s.label()).unwrap_or("-"),
            s.center_m[0],
            s.center_m[1],
            s.center_m[2],
            s.gimbal.yaw_deg,
            s.gimbal.pitch_deg,
            s.gimbal.roll_deg,
            s.relative_altitude_m
                .map(|r| format!("{r:.2}"))
                .unwrap_or_else(|| "-".to_string()),
            s.camera_id
        );
    }
    let frame = &priors.frame;
    let gamma = priors
        .summary
        .first()
        .map(|s| s.convergence_deg)
        .unwrap_or(0.0);
    println!(
        "frame: UTM {} minus (E {}, N {}, Z {}) m{}; meridian convergence {gamma:.3}° {}",
        frame.zone,
        frame.easting_m,
        frame.northing_m,
        frame.altitude_m,
        if offset_m.is_some() {
            ""
        } else {
            " (chosen: shift the mesh by the same offset)"
        },
        if options.correct_convergence {
            "subtracted from the yaw (grid north)"
        } else {
            "not corrected (yaw from true north)"
        }
    );
    for (id, camera) in &priors.cameras {
        println!(
            "camera {id}: {}×{} px, f = {:.3} px ({})",
            camera.width_px,
            camera.height_px,
            camera.intrinsics.fx_px,
            priors
                .camera_sources
                .get(id)
                .map(String::as_str)
                .unwrap_or("-")
        );
    }
    println!(
        "wrote {} priors -> {} (cameras, images, points3D; .txt and .bin) and {}",
        priors.images.len(),
        args.out.display(),
        offset_path.display()
    );
    Ok(())
}
