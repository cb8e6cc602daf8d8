//! A photo evidence for a pose that reads regions, not edges (issue #11 item 4, #12): how much of
//! the photo's brightness near the model's outlines the model's own surfaces explain. An
//! untextured model cannot predict a facade's texture, but it does predict where the photo's
//! brightness changes as a whole: surfaces facing different ways are lit differently (sun side,
//! shade side, roof against wall, building against ground). At the true pose the model's faces,
//! grouped by the direction they face, split the photo near their borders into groups of
//! similar brightness; at a pose a few pixels off, strips of one surface fall into another's
//! group. The edge support ([`crate::core::edge_align`]) asks for a photo gradient at each model
//! edge and is fooled by texture edges (windows, bricks, tiles) a few pixels away; this figure
//! weighs whole strips on both sides of each outline instead.

use super::flow_consistency::near_model_edge_mask;
use super::image::{Image, ImageView};
use super::mesh::Mesh;
use super::raster::NO_FACE;

/// Number of groups faces fall into by the direction they face (see [`facing_group`]), besides
/// the background (no model surface).
const FACING_GROUPS: u8 = 18;
/// The group of pixels without a model surface.
const BACKGROUND_GROUP: u8 = 0;

/// The group of a face by the direction its world normal `normal` faces (z up): 1 for near
/// horizontal surfaces facing up (flat roofs, ground), 2 facing down, then 8 compass sectors
/// (45° each) for steep surfaces (walls) and 8 for the ones between (sloped roofs).
fn facing_group(normal: [f32; 3]) -> u8 {
    let [x, y, z] = normal;
    if z > 0.9 {
        return 1;
    }
    if z < -0.9 {
        return 2;
    }
    let azimuth = y.atan2(x); // -π..π
    let sector = (((azimuth + std::f32::consts::PI) / (std::f32::consts::FRAC_PI_4)).floor() as i32)
        .rem_euclid(8) as u8;
    if z.abs() < 0.35 {
        3 + sector
    } else {
        11 + sector
    }
}

/// Buffers of [`region_contrast`], reused across calls.
#[derive(Default)]
pub struct RegionContrastWorkspace {
    /// Each face's facing group, filled as faces are seen ([`u8::MAX`]: not yet).
    facing: Vec<u8>,
    groups: Vec<u8>,
    /// 1 at the pixels on a border between two groups, 0 elsewhere.
    borders: Image<f32>,
    row_counts: Vec<u32>,
    band: Image<bool>,
}

/// The share of the photo's brightness variance, over the pixels within `band_px` of a border
/// between two facing groups of the rendering `face_index` (model faces of `mesh`), that the
/// groups explain (the correlation ratio η², 0..1): 1 − Σ within-group squares / total squares.
/// `None` when the sizes differ, no border is in view or the photo is constant there.
pub fn region_contrast(
    photo: ImageView<'_, f32>,
    face_index: ImageView<'_, u32>,
    mesh: &Mesh,
    band_px: usize,
    workspace: &mut RegionContrastWorkspace,
) -> Option<f64> {
    let [contrast] = region_contrasts(photo, face_index, mesh, [band_px], workspace);
    contrast
}

/// [`region_contrast`] at each of `bands_px`, the groups and their borders found once.
pub fn region_contrasts<const N: usize>(
    photo: ImageView<'_, f32>,
    face_index: ImageView<'_, u32>,
    mesh: &Mesh,
    bands_px: [usize; N],
    workspace: &mut RegionContrastWorkspace,
) -> [Option<f64>; N] {
    let (width_px, height_px) = photo.size();
    if face_index.size() != (width_px, height_px) || width_px == 0 || height_px == 0 {
        return [None; N];
    }
    let RegionContrastWorkspace {
        facing,
        groups,
        borders,
        row_counts,
        band,
    } = workspace;
    facing.clear();
    facing.resize(mesh.face_count(), u8::MAX);
    groups.clear();
    groups.extend(face_index.data().iter().map(|&face| {
        if face == NO_FACE {
            return BACKGROUND_GROUP;
        }
        let slot = &mut facing[face as usize];
        if *slot == u8::MAX {
            *slot = facing_group(mesh.face_normal(face as usize).to_array());
        }
        *slot
    }));
    borders.reset(width_px, height_px, 0.0);
    let marks = borders.data_mut();
    for y in 0..height_px {
        for x in 0..width_px {
            let pixel = y * width_px + x;
            for other in [
                (x + 1 < width_px).then_some(pixel + 1),
                (y + 1 < height_px).then_some(pixel + width_px),
            ]
            .into_iter()
            .flatten()
            {
                if groups[pixel] != groups[other] {
                    marks[pixel] = 1.0;
                    marks[other] = 1.0;
                }
            }
        }
    }
    bands_px.map(|band_px| {
        near_model_edge_mask(borders.view(), 0.5, band_px, row_counts, band);
        let mut sums = [(0.0f64, 0.0f64, 0.0f64); FACING_GROUPS as usize + 1];
        for ((&inside, &group), &value) in band.data().iter().zip(groups.iter()).zip(photo.data()) {
            if inside {
                let value = f64::from(value);
                let entry = &mut sums[group as usize];
                entry.0 += 1.0;
                entry.1 += value;
                entry.2 += value * value;
            }
        }
        let (count, sum, squares) = sums
            .iter()
            .fold((0.0, 0.0, 0.0), |(n, s, q), &(gn, gs, gq)| {
                (n + gn, s + gs, q + gq)
            });
        if count < 2.0 {
            return None;
        }
        let total = squares - sum * sum / count;
        if total <= f64::EPSILON * count {
            return None;
        }
        let within: f64 = sums
            .iter()
            .filter(|(n, _, _)| *n > 0.0)
            .map(|&(n, s, q)| q - s * s / n)
            .sum();
        Some((1.0 - within / total).clamp(0.0, 1.0))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A photo made of the groups' own brightness plus texture is explained best by the
    /// rendering that lines up with it, and less the further the rendering is shifted.
    #[test]
    fn the_groups_explain_the_photo_best_where_they_line_up() {
        // Two triangles, a wall facing along x and one facing along y; the rendering (left part
        // the first, right part the second) is made by hand.
        let positions = [
            [0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [0.0, 0.0, 0.0],
            [0.0, 0.0, 1.0],
            [1.0, 0.0, 0.0],
        ];
        let mesh = Mesh::from_world(
            &positions
                .iter()
                .map(|p: &[f64; 3]| nalgebra::Vector3::new(p[0], p[1], p[2]))
                .collect::<Vec<_>>(),
            vec![[0, 1, 2], [3, 4, 5]],
            None,
        )
        .expect("mesh");
        assert_ne!(
            facing_group(mesh.face_normal(0).to_array()),
            facing_group(mesh.face_normal(1).to_array())
        );
        let (width, height) = (64usize, 32usize);
        let border = 32usize;
        let faces = |shift: isize| {
            let mut image =
                Image::new(width, height, vec![NO_FACE; width * height]).expect("image");
            for y in 4..28 {
                for x in 4..60 {
                    image.data_mut()[y * width + x] = if (x as isize) < border as isize + shift {
                        0
                    } else {
                        1
                    };
                }
            }
            image
        };
        let mut photo = Image::new(width, height, vec![0.1f32; width * height]).expect("image");
        for y in 0..height {
            for x in 0..width {
                let texture = ((x * 7 + y * 13) % 5) as f32 * 0.03;
                let base = if !(4..28).contains(&y) || !(4..60).contains(&x) {
                    0.1
                } else if x < border {
                    0.7
                } else {
                    0.4
                };
                photo.data_mut()[y * width + x] = base + texture;
            }
        }
        let mut workspace = RegionContrastWorkspace::default();
        let at = |shift: isize, workspace: &mut RegionContrastWorkspace| {
            region_contrast(photo.view(), faces(shift).view(), &mesh, 6, workspace)
                .expect("contrast")
        };
        let aligned = at(0, &mut workspace);
        let off_2 = at(2, &mut workspace);
        let off_5 = at(-5, &mut workspace);
        assert!(aligned > 0.8, "{aligned}");
        assert!(
            aligned > off_2 && off_2 > off_5,
            "{aligned} {off_2} {off_5}"
        );
    }
}
