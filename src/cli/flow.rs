//! `asgreg flow`: SIFT flow between two images (convention `A(x, y) ≈ B(x + u, y + v)`), written as
//! a Middlebury `.flo` that any optical-flow tool reads; prints the time of each step and, given the
//! true flow, the end-point error.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context};
use asgreg::core::dense_sift::{
    compute_dense_sift, DenseSiftConfig, DenseSiftImage, DenseSiftWorkspace,
};
use asgreg::core::image::Image;
use asgreg::core::sift_flow::{compute_sift_flow, FlowField, SiftFlowConfig, SiftFlowWorkspace};
use asgreg::io::flo::{read_flo, write_flo};
use asgreg::io::images::load_gray;

#[derive(clap::Args, Debug)]
pub struct FlowArgs {
    /// Source image A.
    pub image_a: PathBuf,
    /// Target image B (same size as A).
    pub image_b: PathBuf,
    /// Output `.flo` (the flow from A to B, A's size).
    #[arg(long)]
    pub out: PathBuf,
    /// Mask of A: pixels that are black (0) in this image take no part.
    #[arg(long)]
    pub mask_a: Option<PathBuf>,
    /// Halve both images first (as Ce Liu's demo does): about 4× faster, less accurate.
    #[arg(long)]
    pub half: bool,
    /// Parameter set: Ce Liu's reference defaults, or far fewer BP iterations (same accuracy on
    /// the shared pairs, a third of the time).
    #[arg(long, value_enum, default_value_t = Preset::Reference)]
    pub preset: Preset,
    /// The true flow (`.flo`): print the end-point error on pixels at least 20 px from the border.
    #[arg(long)]
    pub truth: Option<PathBuf>,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum Preset {
    Reference,
    Fast,
}

/// Halves an image by 2×2 box averaging (odd last rows/columns are dropped).
fn halve(image: &Image<f32>) -> Image<f32> {
    let at = |c: usize, r: usize| image.data()[r * image.width_px() + c];
    Image::from_fn(image.width_px() / 2, image.height_px() / 2, |col, row| {
        (at(2 * col, 2 * row)
            + at(2 * col + 1, 2 * row)
            + at(2 * col, 2 * row + 1)
            + at(2 * col + 1, 2 * row + 1))
            / 4.0
    })
}

/// A half-resolution flow brought to `width_px × height_px`: bilinear sampling at the matching
/// half-resolution position, vectors doubled.
fn upsample_flow(half: &FlowField, width_px: usize, height_px: usize) -> FlowField {
    let mut out = FlowField::zeros(width_px, height_px);
    let (half_width, half_height) = half.size();
    let sample = |values: &[f32], x: f32, y: f32| {
        let x = x.clamp(0.0, (half_width - 1) as f32);
        let y = y.clamp(0.0, (half_height - 1) as f32);
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(half_width - 1), (y0 + 1).min(half_height - 1));
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let at = |c: usize, r: usize| values[r * half_width + c];
        (at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx) * (1.0 - fy)
            + (at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx) * fy
    };
    let (out_u, out_v) = out.planes_mut();
    for row in 0..height_px {
        for col in 0..width_px {
            let (x, y) = (
                (col as f32 + 0.5) / 2.0 - 0.5,
                (row as f32 + 0.5) / 2.0 - 0.5,
            );
            out_u[row * width_px + col] = 2.0 * sample(half.u_px().data(), x, y);
            out_v[row * width_px + col] = 2.0 * sample(half.v_px().data(), x, y);
        }
    }
    out
}

pub fn run(args: &FlowArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    let image_a = load_gray(&args.image_a)?;
    let image_b = load_gray(&args.image_b)?;
    if image_a.size() != image_b.size() {
        bail!(
            "{} is {}x{} px but {} is {}x{} px: SIFT flow needs two images of the same size",
            args.image_a.display(),
            image_a.width_px(),
            image_a.height_px(),
            args.image_b.display(),
            image_b.width_px(),
            image_b.height_px()
        );
    }
    let mask = match &args.mask_a {
        Some(path) => {
            let mask = load_gray(path)?;
            if mask.size() != image_a.size() {
                bail!(
                    "the mask {} is {}x{} px, image A is {}x{} px",
                    path.display(),
                    mask.width_px(),
                    mask.height_px(),
                    image_a.width_px(),
                    image_a.height_px()
                );
            }
            Some(mask)
        }
        None => None,
    };
    let load_ms = started.elapsed().as_secs_f64() * 1e3;
    let (full_width, full_height) = image_a.size();
    let (a, b, mask) = if args.half {
        (halve(&image_a), halve(&image_b), mask.as_ref().map(halve))
    } else {
        (image_a, image_b, mask)
    };
    let participates: Option<Image<bool>> = mask.map(|m| m.map(|v| *v > 0.0));

    let sift_config = DenseSiftConfig::default();
    let flow_config = match args.preset {
        Preset::Reference => SiftFlowConfig::default(),
        Preset::Fast => SiftFlowConfig::fast(),
    };
    let sift_started = Instant::now();
    let (mut sift_a, mut sift_b) = (DenseSiftImage::default(), DenseSiftImage::default());
    let (result_a, result_b) = rayon::join(
        || {
            compute_dense_sift(
                a.view(),
                &sift_config,
                &mut DenseSiftWorkspace::default(),
                &mut sift_a,
            )
        },
        || {
            compute_dense_sift(
                b.view(),
                &sift_config,
                &mut DenseSiftWorkspace::default(),
                &mut sift_b,
            )
        },
    );
    result_a?;
    result_b?;
    let sift_ms = sift_started.elapsed().as_secs_f64() * 1e3;
    let mut flow = FlowField::zeros(a.width_px(), a.height_px());
    let mut matching_cost = Image::default();
    let timings = compute_sift_flow(
        &sift_a,
        participates.as_ref().map(Image::view),
        &sift_b,
        None,
        &flow_config,
        &mut SiftFlowWorkspace::default(),
        &mut flow,
        &mut matching_cost,
    )?;
    if args.half {
        flow = upsample_flow(&flow, full_width, full_height);
    }
    write_flo(&args.out, &flow).with_context(|| format!("writing {}", args.out.display()))?;
    let ms = |d: std::time::Duration| d.as_secs_f64() * 1e3;
    println!(
        "flow {} -> {} ({}x{} px{}): load {load_ms:.0} ms, dense SIFT {sift_ms:.0} ms, pyramid {:.0} ms, data cost {:.0} ms, belief propagation {:.0} ms, total {:.0} ms -> {}",
        args.image_a.display(),
        args.image_b.display(),
        a.width_px(),
        a.height_px(),
        if args.half { ", halved" } else { "" },
        ms(timings.pyramid),
        ms(timings.data_cost),
        ms(timings.belief_propagation),
        started.elapsed().as_secs_f64() * 1e3,
        args.out.display()
    );
    if let Some(truth_path) = &args.truth {
        let truth = read_flo(truth_path)?;
        if truth.size() != flow.size() {
            bail!(
                "the true flow {} is {}x{} px, the flow {}x{} px",
                truth_path.display(),
                truth.width_px(),
                truth.height_px(),
                flow.width_px(),
                flow.height_px()
            );
        }
        const BORDER_PX: usize = 20;
        let (mut sum, mut below_1px, mut count) = (0.0f64, 0usize, 0usize);
        let (u_px, v_px) = (flow.u_px().data(), flow.v_px().data());
        let (true_u_px, true_v_px) = (truth.u_px().data(), truth.v_px().data());
        for row in BORDER_PX..flow.height_px().saturating_sub(BORDER_PX) {
            for col in BORDER_PX..flow.width_px().saturating_sub(BORDER_PX) {
                let i = row * flow.width_px() + col;
                let error =
                    f64::from(u_px[i] - true_u_px[i]).hypot(f64::from(v_px[i] - true_v_px[i]));
                sum += error;
                below_1px += usize::from(error < 1.0);
                count += 1;
            }
        }
        let count_f = count.max(1) as f64;
        println!(
            "end-point error against {} (pixels ≥ {BORDER_PX} px from the border): {:.3} px, {:.1} % under 1 px",
            truth_path.display(),
            sum / count_f,
            100.0 * below_1px as f64 / count_f
        );
    }
    Ok(())
}
