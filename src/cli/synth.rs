//! `asgreg synth`: writes an honest synthetic scene (docs/design.md §4) to a directory.

use std::path::PathBuf;

use asgreg::synth::city::{generate_city_scene, CityConfig, CitySceneSummary};
use asgreg::synth::{generate_scene, SceneKind, SceneSummary, SynthConfig};

#[derive(clap::Args, Debug)]
pub struct SynthArgs {
    /// Output directory (created; existing files with the same names are replaced).
    #[arg(long)]
    pub out: PathBuf,
    /// Random seed: the same seed writes the same scene, byte for byte.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Image width in pixels.
    #[arg(long, default_value_t = 505)]
    pub width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 275)]
    pub height: u32,
    /// Number of photos.
    #[arg(long, default_value_t = 48)]
    pub images: usize,
    /// A free-standing house seen from 2, 8 and 15 m, a block of buildings seen from 30–60 m, or
    /// a city of `--triangles` triangles (georeferenced, binary PLY) seen from 120–180 m up.
    #[arg(long, value_enum, default_value_t = SceneArg::House)]
    pub scene: SceneArg,
    /// Mean initial-pose errors to calibrate, in pixels, comma separated.
    #[arg(long, value_delimiter = ',', default_values_t = [30.0, 57.0, 80.0, 104.0])]
    pub levels: Vec<f64>,
    /// Make the model and the photographed world differ by known objects (new buildings and
    /// extensions in the photos only, demolished buildings in the model only) and write the true
    /// change masks (changes_gt/*.png) and objects (changes.json).
    #[arg(long)]
    pub changes: bool,
    /// Do not write the drone-like `initial/heading/` level (heading 10–40° off, 180° for every
    /// fourth photo, pitch/roll within 1°, GPS-like centre noise).
    #[arg(long)]
    pub no_heading_level: bool,
    /// The `heading` level's heading error range, degrees: ±U(min, max) (e.g. 60 and 180 for
    /// priors outside the pose search's ±45° around the heading and its flip).
    #[arg(long, default_value_t = asgreg::synth::initial::HeadingNoise::default().heading_min_deg)]
    pub heading_min_deg: f64,
    #[arg(long, default_value_t = asgreg::synth::initial::HeadingNoise::default().heading_max_deg)]
    pub heading_max_deg: f64,
    /// The `heading` level: every this many photos the heading is 180° off instead (0: never).
    #[arg(long, default_value_t = asgreg::synth::initial::HeadingNoise::default().flip_every)]
    pub heading_flip_every: usize,
    /// `--scene city`: triangles of the city mesh (10^7 for a district).
    #[arg(long, default_value_t = 1_000_000)]
    pub triangles: u64,
    /// Take the photos in flight order along a continuous path, consecutive ones a few metres
    /// apart, as a drone shooting every second or two: house, nine passes (front, left gable,
    /// back at 2, 8 and 15 m, 12–25 m away) flown around the house, 2.5–3.5 m between photos;
    /// block, arcs of an orbit of up to 16 photos each at 30–60 m height and 40–70 m out, 3–5 m
    /// apart, starting all around the block. Recorded as `flight_path` in `scene.json`. Without
    /// it each photo is placed on its own: consecutive ones are tens of metres apart (house s1:
    /// 17–52 m, block s1: 5–137 m). Not for `--scene city`.
    #[arg(long)]
    pub flight_path: bool,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum SceneArg {
    House,
    Block,
    City,
}

impl SynthArgs {
    pub fn config(&self) -> SynthConfig {
        SynthConfig {
            seed: self.seed,
            width_px: self.width,
            height_px: self.height,
            image_count: self.images,
            scene: match self.scene {
                // `--scene city` is made by `generate_city_scene` from `city_config`, not from
                // this config.
                SceneArg::House | SceneArg::City => SceneKind::House,
                SceneArg::Block => SceneKind::Block,
            },
            initial_levels_px: self.levels.clone(),
            changes: self.changes,
            flight_path: self.flight_path,
            heading_level: !self.no_heading_level,
            heading_noise: asgreg::synth::initial::HeadingNoise {
                heading_min_deg: self.heading_min_deg,
                heading_max_deg: self.heading_max_deg,
                flip_every: self.heading_flip_every,
                ..asgreg::synth::initial::HeadingNoise::default()
            },
            ..SynthConfig::default()
        }
    }
}

/// Prints what a generated scene holds and where.
pub fn print_summary(summary: &SceneSummary, out: &std::path::Path, seconds: f64) {
    println!(
        "wrote {} in {seconds:.1} s: {} photos at {}x{} px (f = {:.1} px), model {} faces ({} holes, mean deviation {:.3} m from the truth)",
        out.display(),
        summary.images.len(),
        summary.config.width_px,
        summary.config.height_px,
        summary.camera_fx_px,
        summary.model_faces,
        summary.model_holes,
        summary.model_mean_deviation_m
    );
    if summary.config.flight_path {
        let mut sorted_m: Vec<f64> = summary
            .images
            .windows(2)
            .map(|pair| {
                let [a, b] = [pair[0].camera_centre_m, pair[1].camera_centre_m];
                ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
            })
            .collect();
        sorted_m.sort_by(f64::total_cmp);
        if let (Some(first), Some(last)) = (sorted_m.first(), sorted_m.last()) {
            println!(
                "    along a flight path: consecutive photos {:.1} m apart (median), {first:.1}..{last:.1} m",
                sorted_m[sorted_m.len() / 2]
            );
        }
    }
    println!("    initial poses, mean δ to ground truth (target → achieved, range):");
    for level in &summary.initial_levels {
        println!(
            "    {:>6.1} px → {:>6.1} px ({:+.1} %), {:.1}..{:.1} px",
            level.target_px,
            level.mean_px,
            (level.mean_px / level.target_px - 1.0) * 100.0,
            level.min_px,
            level.max_px
        );
    }
    if let Some([min_px, mean_px, max_px]) = summary.heading_level_px {
        println!("    heading → {mean_px:>6.1} px, {min_px:.1}..{max_px:.1} px (δ over the frames it can measure)");
    }
}

/// The `--scene city` settings the command line selects.
fn city_config(args: &SynthArgs) -> CityConfig {
    CityConfig {
        seed: args.seed,
        triangles: args.triangles,
        width_px: args.width,
        height_px: args.height,
        image_count: args.images,
        initial_levels_px: args.levels.clone(),
        heading_level: !args.no_heading_level,
        ..CityConfig::default()
    }
}

fn print_city_summary(summary: &CitySceneSummary, out: &std::path::Path) {
    let t = &summary.timings;
    println!(
        "wrote {} in {:.1} s: city of {} x {} lots ({:.0} m), model {} faces, {} vertices (write {:.1} s, load {:.1} s); {} photos at {}x{} px (f = {:.1} px) in {:.1} s",
        out.display(),
        t.total_s,
        summary.lots_per_side,
        summary.lots_per_side,
        summary.side_m,
        summary.model_faces,
        summary.model_vertices,
        t.mesh_write_s,
        t.mesh_load_s,
        summary.images.len(),
        summary.config.width_px,
        summary.config.height_px,
        summary.camera_fx_px,
        t.photos_s
    );
    for level in &summary.initial_levels {
        println!(
            "    initial level {:>6.1} px → {:>6.1} px, {:.1}..{:.1} px",
            level.target_px, level.mean_px, level.min_px, level.max_px
        );
    }
    if let Some([min_px, mean_px, max_px]) = summary.heading_level_px {
        println!("    heading → {mean_px:>6.1} px, {min_px:.1}..{max_px:.1} px");
    }
    let (_, peak_mib) = super::bench_mesh::rss_mib();
    println!("    peak RSS {peak_mib:.0} MiB");
}

pub fn run(args: &SynthArgs) -> anyhow::Result<()> {
    if !(args.heading_min_deg.is_finite()
        && args.heading_max_deg.is_finite()
        && 0.0 <= args.heading_min_deg
        && args.heading_min_deg <= args.heading_max_deg
        && args.heading_max_deg <= 180.0)
    {
        anyhow::bail!(
            "--heading-min-deg {} / --heading-max-deg {}: need 0 ≤ min ≤ max ≤ 180",
            args.heading_min_deg,
            args.heading_max_deg
        );
    }
    if args.scene == SceneArg::City {
        if args.flight_path {
            anyhow::bail!("--flight-path is for --scene house and block, not city");
        }
        let summary = generate_city_scene(&city_config(args), &args.out)?;
        print_city_summary(&summary, &args.out);
        return Ok(());
    }
    let started = std::time::Instant::now();
    let summary = generate_scene(&args.config(), &args.out)?;
    print_summary(&summary, &args.out, started.elapsed().as_secs_f64());
    Ok(())
}
