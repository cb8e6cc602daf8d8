//! The degraded model handed to registration, made the way a Poisson reconstruction of MVS points
//! would look: the signed distance of the building solids (without small parts) and the ground
//! is sampled into a grid, blurred (rounded edges and corners, thin parts thinned or lost), turned back
//! into a mesh of voxel-sized triangles by surface nets, Taubin-smoothed, warped by low-frequency
//! noise and jittered per vertex; the ground is trimmed to an irregular patch around the
//! buildings and a few patches of faces are cut out as holes.

use glam::{Vec2, Vec3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use rayon::prelude::*;

use super::geometry::Scene;
use super::texture::{fbm, hash_unit};

/// How strongly the model is degraded.
#[derive(Clone, Copy, Debug)]
pub struct DegradeParams {
    /// Edge length of the distance-field voxels (≈ triangle size), metres.
    pub voxel_m: f32,
    /// Gaussian blur of the distance field (edge rounding radius), metres.
    pub smoothing_sigma_m: f32,
    /// Taubin smoothing iterations on the extracted mesh.
    pub taubin_iterations: u32,
    /// Standard deviation of the per-vertex noise, metres.
    pub vertex_noise_m: f32,
    /// Amplitude of the low-frequency warp along the normal, metres.
    pub warp_m: f32,
    /// Number of holes cut into the mesh.
    pub hole_count: u32,
    /// Largest hole radius, metres (radii are drawn from half of it to it).
    pub hole_radius_m: f32,
    /// Ground kept around the buildings, metres (the border is irregular by ±30 %).
    pub ground_margin_m: f32,
}

/// The result: world positions, faces, and figures for the summary.
#[derive(Clone, Debug)]
pub struct DegradedModel {
    pub positions_m: Vec<Vec3>,
    pub faces: Vec<[u32; 3]>,
    pub holes_cut: u32,
    pub faces_removed_by_holes: usize,
}

/// Dense scalar grid, x fastest.
struct Grid {
    origin_m: Vec3,
    voxel_m: f32,
    size: [usize; 3],
    values: Vec<f32>,
}

impl Grid {
    fn index(&self, i: usize, j: usize, k: usize) -> usize {
        (k * self.size[1] + j) * self.size[0] + i
    }

    fn centre(&self, i: usize, j: usize, k: usize) -> Vec3 {
        self.origin_m + (Vec3::new(i as f32, j as f32, k as f32) + 0.5) * self.voxel_m
    }

    /// Trilinear interpolation between voxel centres (clamped at the border).
    fn sample(&self, p: Vec3) -> f32 {
        let q = (p - self.origin_m) / self.voxel_m - 0.5;
        let max = Vec3::new(
            self.size[0] as f32 - 1.001,
            self.size[1] as f32 - 1.001,
            self.size[2] as f32 - 1.001,
        );
        let q = q.clamp(Vec3::ZERO, max);
        let base = q.floor();
        let f = q - base;
        let (i, j, k) = (base.x as usize, base.y as usize, base.z as usize);
        let v = |di: usize, dj: usize, dk: usize| self.values[self.index(i + di, j + dj, k + dk)];
        let x00 = v(0, 0, 0) + (v(1, 0, 0) - v(0, 0, 0)) * f.x;
        let x10 = v(0, 1, 0) + (v(1, 1, 0) - v(0, 1, 0)) * f.x;
        let x01 = v(0, 0, 1) + (v(1, 0, 1) - v(0, 0, 1)) * f.x;
        let x11 = v(0, 1, 1) + (v(1, 1, 1) - v(0, 1, 1)) * f.x;
        let y0 = x00 + (x10 - x00) * f.y;
        let y1 = x01 + (x11 - x01) * f.y;
        y0 + (y1 - y0) * f.z
    }
}

/// Builds the degraded model of `scene`.
pub fn degrade(scene: &Scene, params: &DegradeParams, rng: &mut ChaCha8Rng) -> DegradedModel {
    let noise_seed: u64 = rng.random();
    let grid = inside_field(scene, params);
    let grid = blur(grid, params.smoothing_sigma_m);
    let (mut positions, faces) = surface_nets(&grid, 0.0);
    // Surface-nets vertices terrace on planes that are not aligned with the grid (the ASG
    // shows the terraces as stripes, which a Poisson surface does not have): move each vertex
    // onto the smooth iso-surface of the trilinear field.
    project_to_iso_surface(&grid, &mut positions, 0.0);
    let neighbours = vertex_neighbours(positions.len(), &faces);
    taubin(&mut positions, &neighbours, params.taubin_iterations);

    // Trim the ground to an irregular patch around the buildings.
    let faces: Vec<[u32; 3]> = faces
        .into_iter()
        .filter(|f| {
            let c =
                (positions[f[0] as usize] + positions[f[1] as usize] + positions[f[2] as usize])
                    / 3.0;
            let distance = scene.distance_to_buildings_m(Vec2::new(c.x, c.y));
            let wobble = 1.0 + 0.6 * fbm(noise_seed ^ 1, Vec3::new(c.x, c.y, 0.0), 6.0, 3, 0.0);
            distance <= params.ground_margin_m * wobble
        })
        .collect();

    // Warp and jitter.
    let normals = vertex_normals(&positions, &faces);
    let normal = Normal::new(0.0f32, params.vertex_noise_m.max(0.0)).ok();
    for (p, n) in positions.iter_mut().zip(&normals) {
        let warp = params.warp_m * 2.0 * smooth_noise(noise_seed ^ 2, *p, 3.0);
        let jitter = match &normal {
            Some(normal) => Vec3::new(normal.sample(rng), normal.sample(rng), normal.sample(rng)),
            None => Vec3::ZERO,
        };
        *p += *n * warp + jitter;
    }

    // Holes: remove faces within a radius of random face centres.
    let mut faces = faces;
    let before = faces.len();
    let mut holes_cut = 0;
    for _ in 0..params.hole_count {
        if faces.is_empty() {
            break;
        }
        let seed_face = faces[rng.random_range(0..faces.len())];
        let centre = (positions[seed_face[0] as usize]
            + positions[seed_face[1] as usize]
            + positions[seed_face[2] as usize])
            / 3.0;
        let radius = rng.random_range(params.hole_radius_m * 0.5..=params.hole_radius_m.max(1e-3));
        faces.retain(|f| {
            let c =
                (positions[f[0] as usize] + positions[f[1] as usize] + positions[f[2] as usize])
                    / 3.0;
            (c - centre).length() > radius
        });
        holes_cut += 1;
    }
    let faces_removed_by_holes = before - faces.len();

    // Drop unused vertices.
    let mut remap = vec![u32::MAX; positions.len()];
    let mut kept = Vec::new();
    let faces: Vec<[u32; 3]> = faces
        .iter()
        .map(|f| {
            f.map(|v| {
                if remap[v as usize] == u32::MAX {
                    remap[v as usize] = kept.len() as u32;
                    kept.push(positions[v as usize]);
                }
                remap[v as usize]
            })
        })
        .collect();
    DegradedModel {
        positions_m: kept,
        faces,
        holes_cut,
        faces_removed_by_holes,
    }
}

/// "Insideness" of the building solids and the ground half-space: the negated signed distance
/// of their union, truncated to `±truncation` (positive inside).
fn inside_field(scene: &Scene, params: &DegradeParams) -> Grid {
    let voxel = params.voxel_m.max(0.05);
    let truncation = 3.0 * params.smoothing_sigma_m + 3.0 * voxel;
    let margin = params.ground_margin_m * 1.7 + truncation + 2.0 * voxel;
    let mut min = Vec3::splat(f32::INFINITY);
    let mut max = Vec3::splat(f32::NEG_INFINITY);
    for solid in &scene.building_solids {
        let (a, b) = solid.bounds_m();
        min = min.min(a);
        max = max.max(b);
    }
    if !min.is_finite() {
        min = Vec3::new(-1.0, -1.0, 0.0);
        max = Vec3::new(1.0, 1.0, 1.0);
    }
    let min = Vec3::new(min.x - margin, min.y - margin, -truncation - 2.0 * voxel);
    let max = Vec3::new(max.x + margin, max.y + margin, max.z + truncation + voxel);
    let size = [
        ((max.x - min.x) / voxel).ceil() as usize + 1,
        ((max.y - min.y) / voxel).ceil() as usize + 1,
        ((max.z - min.z) / voxel).ceil() as usize + 1,
    ];
    let mut grid = Grid {
        origin_m: min,
        voxel_m: voxel,
        size,
        values: vec![0.0; size[0] * size[1] * size[2]],
    };
    let plane = size[0] * size[1];
    let origin = grid.origin_m;
    let solids = &scene.building_solids;
    let solid_bounds: Vec<(Vec3, Vec3)> = solids
        .iter()
        .map(|s| {
            let (a, b) = s.bounds_m();
            (a - truncation, b + truncation)
        })
        .collect();
    grid.values
        .par_chunks_mut(plane)
        .enumerate()
        .for_each(|(k, layer)| {
            let z = origin.z + (k as f32 + 0.5) * voxel;
            let near: Vec<usize> = (0..solids.len())
                .filter(|&s| z >= solid_bounds[s].0.z && z <= solid_bounds[s].1.z)
                .collect();
            for j in 0..size[1] {
                let y = origin.y + (j as f32 + 0.5) * voxel;
                for i in 0..size[0] {
                    let x = origin.x + (i as f32 + 0.5) * voxel;
                    let p = Vec3::new(x, y, z);
                    let mut distance = p.z;
                    for &s in &near {
                        let (a, b) = solid_bounds[s];
                        if p.x >= a.x && p.x <= b.x && p.y >= a.y && p.y <= b.y {
                            distance = distance.min(solids[s].signed_distance_m(p));
                        }
                    }
                    layer[j * size[0] + i] = (-distance).clamp(-truncation, truncation);
                }
            }
        });
    grid
}

/// Separable Gaussian blur in place (edges clamp).
fn blur(mut grid: Grid, sigma_m: f32) -> Grid {
    let sigma = sigma_m / grid.voxel_m;
    if sigma < 0.3 {
        return grid;
    }
    let radius = (3.0 * sigma).ceil() as i64;
    let kernel: Vec<f32> = (-radius..=radius)
        .map(|d| (-(d * d) as f32 / (2.0 * sigma * sigma)).exp())
        .collect();
    let total: f32 = kernel.iter().sum();
    let kernel: Vec<f32> = kernel.iter().map(|w| w / total).collect();
    let [nx, ny, nz] = grid.size;
    for axis in 0..3 {
        let (stride, len) = match axis {
            0 => (1, nx),
            1 => (nx, ny),
            _ => (nx * ny, nz),
        };
        let source = grid.values.clone();
        let values = &mut grid.values;
        // Lines along `axis`: start index of each line.
        let starts: Vec<usize> = match axis {
            0 => (0..ny * nz).map(|l| l * nx).collect(),
            1 => (0..nz)
                .flat_map(|k| (0..nx).map(move |i| k * nx * ny + i))
                .collect(),
            _ => (0..nx * ny).collect(),
        };
        let results: Vec<Vec<f32>> = starts
            .par_iter()
            .map(|&start| {
                (0..len as i64)
                    .map(|t| {
                        kernel
                            .iter()
                            .enumerate()
                            .map(|(q, w)| {
                                let s = (t + q as i64 - radius).clamp(0, len as i64 - 1) as usize;
                                w * source[start + s * stride]
                            })
                            .sum()
                    })
                    .collect()
            })
            .collect();
        for (start, line) in starts.iter().zip(results) {
            for (t, v) in line.into_iter().enumerate() {
                values[start + t * stride] = v;
            }
        }
    }
    grid
}

/// Naive surface nets on the iso-level: one vertex per sign-changing cell, one quad per
/// sign-changing grid edge, oriented so the normal points from inside (value > iso) to outside.
fn surface_nets(grid: &Grid, iso: f32) -> (Vec<Vec3>, Vec<[u32; 3]>) {
    let [nx, ny, nz] = grid.size;
    let inside = |i: usize, j: usize, k: usize| grid.values[grid.index(i, j, k)] > iso;
    // Cells are indexed by their lowest corner (i, j, k) in 0..n-1.
    let cell_index = |i: usize, j: usize, k: usize| (k * (ny - 1) + j) * (nx - 1) + i;
    let mut cell_vertex = vec![u32::MAX; (nx - 1) * (ny - 1) * (nz - 1)];
    let mut positions = Vec::new();
    const EDGES: [([usize; 3], [usize; 3]); 12] = [
        ([0, 0, 0], [1, 0, 0]),
        ([0, 1, 0], [1, 1, 0]),
        ([0, 0, 1], [1, 0, 1]),
        ([0, 1, 1], [1, 1, 1]),
        ([0, 0, 0], [0, 1, 0]),
        ([1, 0, 0], [1, 1, 0]),
        ([0, 0, 1], [0, 1, 1]),
        ([1, 0, 1], [1, 1, 1]),
        ([0, 0, 0], [0, 0, 1]),
        ([1, 0, 0], [1, 0, 1]),
        ([0, 1, 0], [0, 1, 1]),
        ([1, 1, 0], [1, 1, 1]),
    ];
    for k in 0..nz - 1 {
        for j in 0..ny - 1 {
            for i in 0..nx - 1 {
                let mut sum = Vec3::ZERO;
                let mut count = 0;
                for (a, b) in EDGES {
                    let va = grid.values[grid.index(i + a[0], j + a[1], k + a[2])];
                    let vb = grid.values[grid.index(i + b[0], j + b[1], k + b[2])];
                    if (va > iso) != (vb > iso) {
                        let t = (iso - va) / (vb - va);
                        let pa = grid.centre(i + a[0], j + a[1], k + a[2]);
                        let pb = grid.centre(i + b[0], j + b[1], k + b[2]);
                        sum += pa + (pb - pa) * t;
                        count += 1;
                    }
                }
                if count > 0 {
                    cell_vertex[cell_index(i, j, k)] = positions.len() as u32;
                    positions.push(sum / count as f32);
                }
            }
        }
    }
    let mut faces = Vec::new();
    let mut emit = |quad: [u32; 4], outward: Vec3, positions: &[Vec3]| {
        if quad.contains(&u32::MAX) {
            return;
        }
        let p = quad.map(|v| positions[v as usize]);
        // Split along the shorter diagonal.
        let (t0, t1) = if (p[0] - p[2]).length_squared() <= (p[1] - p[3]).length_squared() {
            ([0, 1, 2], [0, 2, 3])
        } else {
            ([0, 1, 3], [1, 2, 3])
        };
        for t in [t0, t1] {
            let normal = (p[t[1]] - p[t[0]]).cross(p[t[2]] - p[t[0]]);
            let face = if normal.dot(outward) >= 0.0 {
                [quad[t[0]], quad[t[1]], quad[t[2]]]
            } else {
                [quad[t[0]], quad[t[2]], quad[t[1]]]
            };
            faces.push(face);
        }
    };
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let here = inside(i, j, k);
                // Edge along x to (i+1, j, k): cells (i, j-1..j, k-1..k).
                if i + 1 < nx && (1..ny - 1).contains(&j) && (1..nz - 1).contains(&k) {
                    let there = inside(i + 1, j, k);
                    if here != there {
                        let quad = [
                            cell_vertex[cell_index(i, j - 1, k - 1)],
                            cell_vertex[cell_index(i, j, k - 1)],
                            cell_vertex[cell_index(i, j, k)],
                            cell_vertex[cell_index(i, j - 1, k)],
                        ];
                        let outward = if here { Vec3::X } else { -Vec3::X };
                        emit(quad, outward, &positions);
                    }
                }
                // Edge along y: cells (i-1..i, j, k-1..k).
                if j + 1 < ny && (1..nx - 1).contains(&i) && (1..nz - 1).contains(&k) {
                    let there = inside(i, j + 1, k);
                    if here != there {
                        let quad = [
                            cell_vertex[cell_index(i - 1, j, k - 1)],
                            cell_vertex[cell_index(i, j, k - 1)],
                            cell_vertex[cell_index(i, j, k)],
                            cell_vertex[cell_index(i - 1, j, k)],
                        ];
                        let outward = if here { Vec3::Y } else { -Vec3::Y };
                        emit(quad, outward, &positions);
                    }
                }
                // Edge along z: cells (i-1..i, j-1..j, k).
                if k + 1 < nz && (1..nx - 1).contains(&i) && (1..ny - 1).contains(&j) {
                    let there = inside(i, j, k + 1);
                    if here != there {
                        let quad = [
                            cell_vertex[cell_index(i - 1, j - 1, k)],
                            cell_vertex[cell_index(i, j - 1, k)],
                            cell_vertex[cell_index(i, j, k)],
                            cell_vertex[cell_index(i - 1, j, k)],
                        ];
                        let outward = if here { Vec3::Z } else { -Vec3::Z };
                        emit(quad, outward, &positions);
                    }
                }
            }
        }
    }
    (positions, faces)
}

/// Two octaves of value noise with a quintic fade (C2: its second derivatives, which the ASG of a
/// displaced surface shows, have no creases along the lattice), centred on 0 (about ±0.5).
fn smooth_noise(seed: u64, p: Vec3, scale_m: f32) -> f32 {
    let octave = |seed: u64, q: Vec3| {
        let base = q.floor();
        let f = q - base;
        let fade = |t: f32| t * t * t * (t * (t * 6.0 - 15.0) + 10.0);
        let (u, v, w) = (fade(f.x), fade(f.y), fade(f.z));
        let (x, y, z) = (base.x as i64, base.y as i64, base.z as i64);
        let c = |dx: i64, dy: i64, dz: i64| hash_unit(seed, x + dx, y + dy, z + dz);
        let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
        let x00 = lerp(c(0, 0, 0), c(1, 0, 0), u);
        let x10 = lerp(c(0, 1, 0), c(1, 1, 0), u);
        let x01 = lerp(c(0, 0, 1), c(1, 0, 1), u);
        let x11 = lerp(c(0, 1, 1), c(1, 1, 1), u);
        lerp(lerp(x00, x10, v), lerp(x01, x11, v), w) - 0.5
    };
    (octave(seed, p / scale_m) * 2.0 + octave(seed ^ 7, p * 2.0 / scale_m)) / 3.0 * 1.5
}

/// Newton steps along the field gradient onto the iso-surface of the trilinear interpolation.
fn project_to_iso_surface(grid: &Grid, positions: &mut [Vec3], iso: f32) {
    let h = grid.voxel_m;
    positions.par_iter_mut().for_each(|p| {
        for _ in 0..4 {
            let value = grid.sample(*p);
            let gradient = Vec3::new(
                grid.sample(*p + Vec3::X * h * 0.5) - grid.sample(*p - Vec3::X * h * 0.5),
                grid.sample(*p + Vec3::Y * h * 0.5) - grid.sample(*p - Vec3::Y * h * 0.5),
                grid.sample(*p + Vec3::Z * h * 0.5) - grid.sample(*p - Vec3::Z * h * 0.5),
            ) / h;
            let length_squared = gradient.length_squared();
            if length_squared < 1e-6 {
                return;
            }
            let step = gradient * ((iso - value) / length_squared);
            // Never move more than half a voxel per step.
            *p += step.clamp_length_max(h * 0.5);
        }
    });
}

fn vertex_neighbours(vertex_count: usize, faces: &[[u32; 3]]) -> Vec<Vec<u32>> {
    let mut neighbours = vec![Vec::new(); vertex_count];
    for f in faces {
        for e in 0..3 {
            let a = f[e];
            let b = f[(e + 1) % 3];
            neighbours[a as usize].push(b);
            neighbours[b as usize].push(a);
        }
    }
    for n in &mut neighbours {
        n.sort_unstable();
        n.dedup();
    }
    neighbours
}

/// Taubin λ|μ smoothing: smooths without the shrinking of plain Laplacian smoothing.
fn taubin(positions: &mut [Vec3], neighbours: &[Vec<u32>], iterations: u32) {
    const LAMBDA: f32 = 0.5;
    const MU: f32 = -0.53;
    let mut next = positions.to_vec();
    for _ in 0..iterations {
        for factor in [LAMBDA, MU] {
            next.par_iter_mut().enumerate().for_each(|(v, out)| {
                let around = &neighbours[v];
                if around.is_empty() {
                    *out = positions[v];
                    return;
                }
                let mean = around.iter().map(|&u| positions[u as usize]).sum::<Vec3>()
                    / around.len() as f32;
                *out = positions[v] + (mean - positions[v]) * factor;
            });
            positions.copy_from_slice(&next);
        }
    }
}

fn vertex_normals(positions: &[Vec3], faces: &[[u32; 3]]) -> Vec<Vec3> {
    let mut normals = vec![Vec3::ZERO; positions.len()];
    for f in faces {
        let [a, b, c] = f.map(|v| positions[v as usize]);
        let n = (b - a).cross(c - a);
        for &v in f {
            normals[v as usize] += n;
        }
    }
    normals.iter().map(|n| n.normalize_or_zero()).collect()
}

/// Mean distance from `points` to the nearest of `targets` (brute force over a uniform grid of
/// buckets; for tests and the summary).
pub fn mean_nearest_distance_m(points: &[Vec3], targets: &[Vec3], bucket_m: f32) -> f32 {
    use std::collections::HashMap;
    let key = |p: Vec3| {
        (
            (p.x / bucket_m).floor() as i32,
            (p.y / bucket_m).floor() as i32,
            (p.z / bucket_m).floor() as i32,
        )
    };
    let mut buckets: HashMap<(i32, i32, i32), Vec<Vec3>> = HashMap::new();
    for t in targets {
        buckets.entry(key(*t)).or_default().push(*t);
    }
    let total: f32 = points
        .iter()
        .map(|p| {
            let (x, y, z) = key(*p);
            let mut best = f32::INFINITY;
            for dx in -1..=1 {
                for dy in -1..=1 {
                    for dz in -1..=1 {
                        if let Some(list) = buckets.get(&(x + dx, y + dy, z + dz)) {
                            for t in list {
                                best = best.min((*t - *p).length());
                            }
                        }
                    }
                }
            }
            best.min(bucket_m)
        })
        .sum();
    total / points.len().max(1) as f32
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::geometry::build_house;
    use rand::SeedableRng;

    fn params() -> DegradeParams {
        DegradeParams {
            voxel_m: 0.25,
            smoothing_sigma_m: 0.15,
            taubin_iterations: 3,
            vertex_noise_m: 0.02,
            warp_m: 0.04,
            hole_count: 5,
            hole_radius_m: 0.8,
            ground_margin_m: 5.0,
        }
    }

    #[test]
    fn surface_nets_of_a_blurred_box_is_closed_and_near_the_box() {
        let voxel = 0.1;
        let size = [30, 30, 30];
        let mut grid = Grid {
            origin_m: Vec3::ZERO,
            voxel_m: voxel,
            size,
            values: vec![0.0; 27000],
        };
        for k in 0..30 {
            for j in 0..30 {
                for i in 0..30 {
                    let inside =
                        (8..22).contains(&i) && (8..22).contains(&j) && (8..22).contains(&k);
                    let index = grid.index(i, j, k);
                    grid.values[index] = if inside { 1.0 } else { 0.0 };
                }
            }
        }
        let grid = blur(grid, 0.1);
        let (positions, faces) = surface_nets(&grid, 0.5);
        assert!(faces.len() > 500);
        // Every edge is shared by exactly two faces (closed surface).
        let mut edges = std::collections::HashMap::new();
        for f in &faces {
            for e in 0..3 {
                let (a, b) = (f[e], f[(e + 1) % 3]);
                *edges.entry((a.min(b), a.max(b))).or_insert(0) += 1;
            }
        }
        assert!(edges.values().all(|&c| c == 2));
        // Faces point outwards from the box centre (1.5, 1.5, 1.5).
        let outward = faces
            .iter()
            .filter(|f| {
                let [a, b, c] = f.map(|v| positions[v as usize]);
                (b - a)
                    .cross(c - a)
                    .dot((a + b + c) / 3.0 - Vec3::splat(1.5))
                    > 0.0
            })
            .count();
        assert_eq!(outward, faces.len());
    }

    #[test]
    fn the_degraded_house_is_near_the_true_one_but_not_equal_and_has_no_chimney() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let scene = build_house(&mut rng);
        let model = degrade(&scene, &params(), &mut rng);
        assert!(model.faces.len() > 10_000, "{}", model.faces.len());
        assert_eq!(model.holes_cut, 5);
        assert!(model.faces_removed_by_holes > 10);
        // Degraded vertices lie close to (but not on) the true building surfaces: sample the true
        // building and ground faces densely and compare.
        let mut true_points = Vec::new();
        for (f, tag) in scene.faces.iter().zip(&scene.tags) {
            if !matches!(
                tag.part,
                super::super::geometry::PartKind::Building
                    | super::super::geometry::PartKind::NearGround
            ) {
                continue;
            }
            let [a, b, c] = f.map(|v| scene.positions_m[v as usize]);
            let n = (((b - a).length().max((c - a).length())) / 0.1).ceil() as usize;
            for s in 0..=n {
                for t in 0..=(n - s) {
                    let (u, v) = (s as f32 / n as f32, t as f32 / n as f32);
                    true_points.push(a + (b - a) * u + (c - a) * v);
                }
            }
        }
        let distance = mean_nearest_distance_m(&model.positions_m, &true_points, 1.0);
        println!("mean distance degraded → true: {distance:.3} m");
        assert!(distance > 0.015 && distance < 0.12, "{distance}");
        let (min, max) = scene.chimney_bounds_m.unwrap();
        let in_chimney = model
            .positions_m
            .iter()
            .filter(|p| p.cmpge(min + 0.05).all() && p.cmple(max - 0.05).all())
            .count();
        assert_eq!(in_chimney, 0);
    }
}
