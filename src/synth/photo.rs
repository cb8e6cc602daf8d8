//! The synthetic photo renderer. It uses the rasteriser only for visibility (which face, at what
//! depth) and does its own shading, on purpose unrelated to ASG: procedural materials at the world
//! point, sun light with cast shadows from a shadow map (a depth rendering from far along the sun
//! direction, compared with a bias and filtered over 3×3 texels), sky ambient light, reflections on
//! glass, a sky with clouds and haze. Then camera effects: box-downsampling from a supersampled
//! rendering (antialiasing), auto-exposure jitter, vignetting, a tone curve, Gaussian lens blur,
//! signal-dependent sensor noise and 8-bit quantisation (JPEG compression happens when writing).
//! It also produces the MVS-like depth map of each photo.

use glam::{Vec2, Vec3};
use nalgebra::Vector3;
use rayon::prelude::*;

use super::geometry::{FaceTag, PartKind, Scene, NO_PANEL};
use super::texture::{self, fbm, hash_u64, value_noise, Material};
use crate::core::camera::PinholeIntrinsics;
use crate::core::image::Image;
use crate::core::mesh::Mesh;
use crate::core::raster::{Rasterizer, RenderBuffers, RenderOptions, NO_FACE};
use crate::core::rigid::Rigid3;

/// Lighting and camera-effect parameters of the photos.
#[derive(Clone, Copy, Debug)]
pub struct PhotoParams {
    pub sun_elevation_deg: f32,
    pub sun_azimuth_deg: f32,
    /// Samples per pixel along each axis (antialiasing).
    pub supersampling: u32,
    pub blur_sigma_px: f32,
    /// Sensor noise standard deviation at mid-grey, in 8-bit digital numbers.
    pub noise_sigma_dn: f32,
    /// Relative darkening in the image corners.
    pub vignetting: f32,
    /// Standard deviation of the per-photo exposure change (auto exposure), relative.
    pub exposure_jitter: f32,
    pub seed: u64,
}

/// Depth-map parameters (MVS-like).
#[derive(Clone, Copy, Debug)]
pub struct DepthParams {
    /// Relative standard deviation of the multiplicative depth noise.
    pub relative_noise: f32,
    /// Fraction of the image removed as random blob-shaped holes.
    pub hole_fraction: f32,
    /// Depths beyond this are background (no MVS depth), metres.
    pub max_depth_m: f32,
    /// Pixels whose 5×5 luma standard deviation (8-bit DN) is below this have no depth.
    pub untextured_std_dn: f32,
}

/// Luma (Rec. 601) in `[0, 255]` of a rendered photo (8-bit sRGB).
fn luma(photo: &Image<[u8; 3]>) -> Vec<f32> {
    photo
        .data()
        .iter()
        .map(|c| 0.299 * f32::from(c[0]) + 0.587 * f32::from(c[1]) + 0.114 * f32::from(c[2]))
        .collect()
}

struct ShadowMap {
    intrinsics: PinholeIntrinsics,
    cam_from_world: Rigid3,
    size_px: usize,
    depth_m: Image<f32>,
    texel_m: f32,
}

impl ShadowMap {
    /// Fraction of the sun visible at a world point (3×3 percentage-closer filtering).
    fn sun_visibility(&self, p: Vec3, normal_dot_sun: f32) -> f32 {
        let q = self.cam_from_world.transform_point(&Vector3::new(
            f64::from(p.x),
            f64::from(p.y),
            f64::from(p.z),
        ));
        let Some(pixel) = self.intrinsics.project(&q) else {
            return 1.0;
        };
        let depth = q.z as f32;
        let tan =
            (1.0 - normal_dot_sun * normal_dot_sun).max(0.0).sqrt() / normal_dot_sun.max(0.05);
        let bias = 0.03 + self.texel_m * (1.0 + 1.5 * tan.min(10.0));
        let (col, row) = (pixel.x as f32 - 0.5, pixel.y as f32 - 0.5);
        let mut lit = 0.0;
        for dy in -1..=1 {
            for dx in -1..=1 {
                let c = (col + dx as f32).round();
                let r = (row + dy as f32).round();
                if c < 0.0 || r < 0.0 || c >= self.size_px as f32 || r >= self.size_px as f32 {
                    lit += 1.0;
                    continue;
                }
                let stored = self.depth_m.data()[r as usize * self.size_px + c as usize];
                if stored == 0.0 || depth <= stored + bias {
                    lit += 1.0;
                }
            }
        }
        lit / 9.0
    }
}

/// Everything needed to render photos of one scene; reused for all images.
pub struct PhotoRenderer<'a> {
    scene: &'a Scene,
    mesh: Mesh,
    face_normals: Vec<Vec3>,
    shadow: ShadowMap,
    sun_direction: Vec3,
    params: PhotoParams,
    rasterizer: Rasterizer,
    buffers: RenderBuffers,
    depth_buffers: RenderBuffers,
}

const SUN_RADIANCE: Vec3 = Vec3::new(3.2, 3.0, 2.7);
const SKY_AMBIENT: Vec3 = Vec3::new(0.42, 0.5, 0.66);

impl<'a> PhotoRenderer<'a> {
    /// Prepares the full scene mesh (true geometry and clutter) and the sun's shadow map.
    pub fn new(
        scene: &'a Scene,
        params: PhotoParams,
    ) -> Result<Self, crate::core::mesh::MeshError> {
        let mesh = scene.to_mesh(|_| true)?;
        let face_normals: Vec<Vec3> = (0..mesh.face_count())
            .map(|f| mesh.face_normal(f))
            .collect();
        let elevation = params.sun_elevation_deg.to_radians();
        let azimuth = params.sun_azimuth_deg.to_radians();
        let sun_direction = Vec3::new(
            elevation.cos() * azimuth.cos(),
            elevation.cos() * azimuth.sin(),
            elevation.sin(),
        );
        // Shadow map: a narrow pinhole camera 2 km away along the sun direction, covering the
        // buildings and the clutter near them.
        let extent = scene
            .footprints
            .iter()
            .map(|f| f.frame.centre_m.length() + f.half_x_m.max(f.half_y_m))
            .fold(0.0f32, f32::max)
            + 30.0;
        let size_px = 3072usize;
        let distance = 2000.0f64;
        let eye = Vector3::new(
            f64::from(sun_direction.x),
            f64::from(sun_direction.y),
            f64::from(sun_direction.z),
        ) * distance;
        let up = if sun_direction.z.abs() > 0.99 {
            Vector3::x()
        } else {
            Vector3::z()
        };
        let mut rasterizer = Rasterizer::new();
        let cam_from_world = Rigid3::look_at(&eye, &Vector3::zeros(), &up).unwrap_or_default();
        let focal = size_px as f64 * 0.5 * distance / f64::from(extent);
        let intrinsics = PinholeIntrinsics::centered(focal, size_px as u32, size_px as u32);
        let mut shadow_buffers = RenderBuffers::new(size_px, size_px);
        rasterizer.render(
            &mesh,
            &intrinsics,
            &cam_from_world,
            &RenderOptions {
                near_m: 10.0,
                ..RenderOptions::default()
            },
            &mut shadow_buffers,
        );
        let shadow = ShadowMap {
            intrinsics,
            cam_from_world,
            size_px,
            depth_m: shadow_buffers.depth_m().clone(),
            texel_m: (distance / focal) as f32,
        };
        Ok(Self {
            scene,
            mesh,
            face_normals,
            shadow,
            sun_direction,
            params,
            rasterizer,
            buffers: RenderBuffers::default(),
            depth_buffers: RenderBuffers::default(),
        })
    }

    pub fn mesh(&self) -> &Mesh {
        &self.mesh
    }

    /// Face tag of a face of [`Self::mesh`] (faces keep the scene's order).
    pub fn tag(&self, face_index: u32) -> Option<&FaceTag> {
        self.scene.tags.get(face_index as usize)
    }

    /// Renders the depth (and face indices) of the full scene at the image size.
    pub fn render_visibility(
        &mut self,
        intrinsics: &PinholeIntrinsics,
        width_px: usize,
        height_px: usize,
        cam_from_world: &Rigid3,
    ) -> &RenderBuffers {
        self.depth_buffers.resize(width_px, height_px);
        self.rasterizer.render(
            &self.mesh,
            intrinsics,
            cam_from_world,
            &RenderOptions::default(),
            &mut self.depth_buffers,
        );
        &self.depth_buffers
    }

    /// Renders one photo, 8-bit sRGB. `image_seed` varies noise and exposure between photos.
    pub fn render_photo(
        &mut self,
        intrinsics: &PinholeIntrinsics,
        width_px: usize,
        height_px: usize,
        cam_from_world: &Rigid3,
        image_seed: u64,
    ) -> Image<[u8; 3]> {
        let ss = self.params.supersampling.max(1) as usize;
        let (sw, sh) = (width_px * ss, height_px * ss);
        let ss_intrinsics = intrinsics.scaled(ss as f64);
        self.buffers.resize(sw, sh);
        self.rasterizer.render(
            &self.mesh,
            &ss_intrinsics,
            cam_from_world,
            &RenderOptions::default(),
            &mut self.buffers,
        );

        let world_from_cam = cam_from_world.inverse();
        let eye = world_from_cam.translation;
        let eye = Vec3::new(eye.x as f32, eye.y as f32, eye.z as f32);
        let rotation = world_from_cam.rotation_matrix();
        let to_world_dir = |d: Vector3<f64>| {
            let w = rotation * d;
            Vec3::new(w.x as f32, w.y as f32, w.z as f32)
        };
        let footprint_per_m = 1.0 / ss_intrinsics.fx_px as f32;
        let seed = self.params.seed;
        let scene = self.scene;
        let shadow = &self.shadow;
        let sun = self.sun_direction;
        let face_normals = &self.face_normals;
        let (face_index, depth_m) = (
            self.buffers.face_index().data(),
            self.buffers.depth_m().data(),
        );
        let mut radiance = vec![Vec3::ZERO; sw * sh];
        radiance
            .par_chunks_mut(sw)
            .enumerate()
            .for_each(|(row, line)| {
                for (col, out) in line.iter_mut().enumerate() {
                    let index = row * sw + col;
                    let normalized = ss_intrinsics.pixel_to_normalized(nalgebra::Vector2::new(
                        col as f64 + 0.5,
                        row as f64 + 0.5,
                    ));
                    let ray_cam = Vector3::new(normalized.x, normalized.y, 1.0);
                    let ray = to_world_dir(ray_cam).normalize();
                    let face = face_index[index];
                    if face == NO_FACE {
                        *out = sky(seed, ray, sun);
                        continue;
                    }
                    let depth = depth_m[index];
                    let p = eye + to_world_dir(ray_cam * f64::from(depth));
                    let tag = scene.tags[face as usize];
                    let mut normal = face_normals[face as usize];
                    if normal.dot(ray) > 0.0 {
                        normal = -normal;
                    }
                    let panel = (tag.panel != NO_PANEL).then(|| &scene.panels[tag.panel as usize]);
                    let footprint_m = depth * footprint_per_m / normal.dot(-ray).max(0.2);
                    let surface = texture::evaluate(
                        tag.material,
                        panel,
                        &scene.ground,
                        p,
                        normal,
                        footprint_m,
                        seed,
                        tag.object_id,
                    );
                    // Leaves and grass scatter light in all directions: perturb their normals.
                    let shading_normal = match tag.material {
                        Material::Foliage { .. } => {
                            let jitter = Vec3::new(
                                value_noise(seed ^ 201, p / 0.15) - 0.5,
                                value_noise(seed ^ 202, p / 0.15) - 0.5,
                                value_noise(seed ^ 203, p / 0.15) - 0.5,
                            );
                            (normal + jitter * 1.6).normalize_or(normal)
                        }
                        _ => normal,
                    };
                    let n_dot_sun = shading_normal.dot(sun);
                    let geometric_dot_sun = normal.dot(sun);
                    let visibility = if n_dot_sun > 0.0 && geometric_dot_sun > -0.2 {
                        shadow.sun_visibility(p, geometric_dot_sun.max(0.01))
                    } else {
                        0.0
                    };
                    // Ambient occlusion stand-in: ground and walls darken near their junction.
                    let occlusion =
                        if matches!(tag.part, PartKind::NearGround | PartKind::FarGround) {
                            let d = scene.distance_to_buildings_m(Vec2::new(p.x, p.y));
                            0.55 + 0.45 * (d / 1.2).clamp(0.0, 1.0)
                        } else if matches!(tag.part, PartKind::Building) {
                            0.7 + 0.3 * (p.z / 0.8).clamp(0.0, 1.0)
                        } else {
                            1.0
                        };
                    let sky_light = SKY_AMBIENT * (0.55 + 0.45 * shading_normal.z) * occlusion;
                    let ground_bounce = Vec3::new(0.12, 0.12, 0.1) * (0.5 - 0.5 * shading_normal.z);
                    let diffuse = surface.albedo
                        * (SUN_RADIANCE * n_dot_sun.max(0.0) * visibility
                            + sky_light
                            + ground_bounce);
                    let mut colour = diffuse;
                    if surface.mirror > 0.0 {
                        let cos_view = normal.dot(-ray).clamp(0.0, 1.0);
                        let fresnel =
                            surface.mirror + (1.0 - surface.mirror) * (1.0 - cos_view).powi(5);
                        let reflected = ray - normal * 2.0 * ray.dot(normal);
                        let environment = if reflected.z > 0.0 {
                            sky(seed, reflected, sun) * 0.8
                        } else {
                            Vec3::new(0.12, 0.13, 0.1)
                        };
                        let glint = reflected.dot(sun).max(0.0).powi(300) * visibility * 20.0;
                        colour = diffuse * (1.0 - fresnel)
                            + (environment + SUN_RADIANCE * glint) * fresnel;
                    }
                    // Aerial perspective.
                    let haze = 1.0 - (-depth / 1800.0).exp();
                    *out = colour.lerp(horizon_colour(), haze);
                }
            });

        // Downsample, expose, vignette, tone-map.
        let exposure_noise =
            (texture::hash_unit(image_seed, 1, 2, 3) - 0.5) * 3.46 * self.params.exposure_jitter;
        let exposure = 1.25 * (1.0 + exposure_noise);
        let (cx, cy) = (width_px as f32 * 0.5, height_px as f32 * 0.5);
        let corner = (cx * cx + cy * cy).sqrt();
        let mut image = vec![Vec3::ZERO; width_px * height_px];
        let vignetting = self.params.vignetting;
        image
            .par_chunks_mut(width_px)
            .enumerate()
            .for_each(|(row, line)| {
                for (col, out) in line.iter_mut().enumerate() {
                    let mut sum = Vec3::ZERO;
                    for dy in 0..ss {
                        let start = (row * ss + dy) * sw + col * ss;
                        sum += radiance[start..start + ss].iter().copied().sum::<Vec3>();
                    }
                    let linear = sum / (ss * ss) as f32;
                    let r = ((col as f32 + 0.5 - cx).powi(2) + (row as f32 + 0.5 - cy).powi(2))
                        .sqrt()
                        / corner;
                    let v = 1.0 - vignetting * r * r;
                    *out = tone_map(linear * exposure * v) * 255.0;
                }
            });

        let blurred = gaussian_blur_rgb(&image, width_px, height_px, self.params.blur_sigma_px);
        let noise_sigma = self.params.noise_sigma_dn;
        let mut rgb = Image::filled(width_px, height_px, [0u8; 3]);
        rgb.data_mut()
            .par_chunks_mut(width_px)
            .enumerate()
            .for_each(|(row, line)| {
                for col in 0..width_px {
                    let value = blurred[row * width_px + col];
                    for channel in 0..3 {
                        let v = value[channel];
                        let sigma = noise_sigma * (0.35 + 0.65 * (v.max(0.0) / 128.0).sqrt());
                        let key = hash_u64(
                            image_seed ^ ((row * width_px + col) as u64 * 3 + channel as u64),
                        );
                        let noisy = v + sigma * gaussian_from_hash(key);
                        line[col][channel] = noisy.round().clamp(0.0, 255.0) as u8;
                    }
                }
            });
        rgb
    }

    /// The MVS-like depth map of a photo: true depth incl. clutter with multiplicative noise,
    /// holes in blobs, background and untextured regions (0.0).
    pub fn depth_map(
        &mut self,
        intrinsics: &PinholeIntrinsics,
        photo: &Image<[u8; 3]>,
        cam_from_world: &Rigid3,
        params: &DepthParams,
        image_seed: u64,
    ) -> Image<f32> {
        let (w, h) = photo.size();
        self.render_visibility(intrinsics, w, h, cam_from_world);
        let luma = luma(photo);
        let local_std = local_std_dev(&luma, w, h, 2);
        // Blob holes: threshold a smooth noise field so that about `hole_fraction` is removed.
        let blob_threshold = hole_threshold(params.hole_fraction);
        let depth = self.depth_buffers.depth_m().data();
        Image::from_fn(w, h, |col, row| {
            let index = row * w + col;
            let d = depth[index];
            if d <= 0.0 || d > params.max_depth_m || local_std[index] < params.untextured_std_dn {
                return 0.0;
            }
            let p = Vec3::new(col as f32 / 14.0, row as f32 / 14.0, 0.0);
            let blob = 0.65 * value_noise(image_seed ^ 301, p)
                + 0.35 * value_noise(image_seed ^ 302, p * 2.7);
            if blob > blob_threshold {
                return 0.0;
            }
            let correlated = fbm(
                image_seed ^ 303,
                Vec3::new(col as f32, row as f32, 0.0),
                20.0,
                3,
                0.0,
            );
            let white = gaussian_from_hash(hash_u64(image_seed ^ 0xD1 ^ index as u64));
            d * (1.0 + params.relative_noise * (0.6 * white + 1.6 * correlated))
        })
    }
}

/// Threshold on the blob noise (≈ uniform-ish around 0.5) giving the wanted hole fraction.
fn hole_threshold(hole_fraction: f32) -> f32 {
    // The sum of two value noises concentrates around 0.5 with std ≈ 0.12; map the fraction
    // through a logistic-ish approximation of that distribution's upper tail.
    let f = hole_fraction.clamp(0.0, 0.99);
    if f <= 0.0 {
        return f32::INFINITY;
    }
    // Inverse of an approximate normal upper tail: z with P(Z > z) = f.
    let z = inverse_normal_upper_tail(f);
    0.5 + 0.12 * z
}

fn inverse_normal_upper_tail(p: f32) -> f32 {
    // Bisection on the complementary error function approximation.
    let tail = |z: f32| 0.5 * erfc_approx(z / std::f32::consts::SQRT_2);
    let (mut lo, mut hi) = (-6.0f32, 6.0f32);
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if tail(mid) > p {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

fn erfc_approx(x: f32) -> f32 {
    // Abramowitz–Stegun 7.1.26.
    let t = 1.0 / (1.0 + 0.327_591_1 * x.abs());
    let y = t
        * (0.254_829_6
            + t * (-0.284_496_7 + t * (1.421_413_7 + t * (-1.453_152 + t * 1.061_405_4))));
    let erfc = y * (-x * x).exp();
    if x >= 0.0 {
        erfc
    } else {
        2.0 - erfc
    }
}

/// A standard normal number from a hash (Box–Muller on two 24-bit uniforms).
fn gaussian_from_hash(key: u64) -> f32 {
    let u1 = ((key >> 40) as f32 + 0.5) / (1u64 << 24) as f32;
    let u2 = (((key >> 8) & 0xFF_FFFF) as f32 + 0.5) / (1u64 << 24) as f32;
    (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
}

fn horizon_colour() -> Vec3 {
    Vec3::new(0.78, 0.82, 0.88)
}

/// Sky radiance for a world direction: blue zenith, pale horizon, clouds, a bright sun disc.
fn sky(seed: u64, direction: Vec3, sun: Vec3) -> Vec3 {
    let up = direction.z.max(0.0);
    let zenith = Vec3::new(0.28, 0.45, 0.85);
    let mut colour = horizon_colour().lerp(zenith, up.powf(0.45));
    if up > 0.02 {
        let plane = Vec2::new(direction.x, direction.y) / (up + 0.08) * 1.5;
        let clouds = fbm(seed ^ 401, Vec3::new(plane.x, plane.y, 0.0), 1.2, 5, 0.0);
        let cover = ((clouds + 0.05) * 3.0).clamp(0.0, 1.0);
        colour = colour.lerp(Vec3::new(0.95, 0.95, 0.97), cover * 0.85);
    }
    let cos_sun = direction.dot(sun);
    colour += Vec3::new(1.0, 0.9, 0.7) * (cos_sun.max(0.0).powi(60) * 0.6);
    if cos_sun > 0.99996 {
        colour = Vec3::splat(20.0);
    }
    colour
}

/// A filmic-like tone curve to display range `[0, 1]` (gamma included).
fn tone_map(linear: Vec3) -> Vec3 {
    let map = |x: f32| {
        let x = x.max(0.0);
        let compressed = x * (1.0 + x / 6.0) / (1.0 + x);
        compressed.clamp(0.0, 1.0).powf(1.0 / 2.2)
    };
    Vec3::new(map(linear.x), map(linear.y), map(linear.z))
}

fn gaussian_blur_rgb(image: &[Vec3], w: usize, h: usize, sigma_px: f32) -> Vec<Vec3> {
    if sigma_px < 0.1 {
        return image.to_vec();
    }
    let radius = (3.0 * sigma_px).ceil() as i64;
    let kernel: Vec<f32> = (-radius..=radius)
        .map(|d| (-(d * d) as f32 / (2.0 * sigma_px * sigma_px)).exp())
        .collect();
    let total: f32 = kernel.iter().sum();
    let kernel: Vec<f32> = kernel.iter().map(|k| k / total).collect();
    let mut horizontal = vec![Vec3::ZERO; w * h];
    horizontal
        .par_chunks_mut(w)
        .enumerate()
        .for_each(|(row, line)| {
            for (col, out) in line.iter_mut().enumerate() {
                *out = kernel
                    .iter()
                    .enumerate()
                    .map(|(q, k)| {
                        let c = (col as i64 + q as i64 - radius).clamp(0, w as i64 - 1) as usize;
                        image[row * w + c] * *k
                    })
                    .sum();
            }
        });
    let mut out = vec![Vec3::ZERO; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(row, line)| {
        for (col, value) in line.iter_mut().enumerate() {
            *value = kernel
                .iter()
                .enumerate()
                .map(|(q, k)| {
                    let r = (row as i64 + q as i64 - radius).clamp(0, h as i64 - 1) as usize;
                    horizontal[r * w + col] * *k
                })
                .sum();
        }
    });
    out
}

/// Standard deviation over a `(2r+1)²` window (clamped at the border).
fn local_std_dev(values: &[f32], w: usize, h: usize, r: usize) -> Vec<f32> {
    (0..w * h)
        .into_par_iter()
        .map(|index| {
            let (row, col) = (index / w, index % w);
            let (mut sum, mut sum_sq, mut n) = (0.0f32, 0.0f32, 0.0f32);
            for rr in row.saturating_sub(r)..(row + r + 1).min(h) {
                for cc in col.saturating_sub(r)..(col + r + 1).min(w) {
                    let v = values[rr * w + cc];
                    sum += v;
                    sum_sq += v * v;
                    n += 1.0;
                }
            }
            let mean = sum / n;
            (sum_sq / n - mean * mean).max(0.0).sqrt()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hole_threshold_removes_about_the_requested_fraction() {
        let threshold = hole_threshold(0.1);
        let mut removed = 0;
        let n = 200 * 200;
        for row in 0..200 {
            for col in 0..200 {
                let p = Vec3::new(col as f32 / 14.0, row as f32 / 14.0, 0.0);
                let blob = 0.65 * value_noise(5 ^ 301, p) + 0.35 * value_noise(5 ^ 302, p * 2.7);
                if blob > threshold {
                    removed += 1;
                }
            }
        }
        let fraction = removed as f32 / n as f32;
        assert!(fraction > 0.03 && fraction < 0.25, "{fraction}");
    }

    #[test]
    fn the_house_casts_a_shadow_away_from_the_sun() {
        use rand::SeedableRng;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let scene = crate::synth::geometry::build_house(&mut rng);
        let params = PhotoParams {
            sun_elevation_deg: 35.0,
            sun_azimuth_deg: 200.0,
            supersampling: 1,
            blur_sigma_px: 0.0,
            noise_sigma_dn: 0.0,
            vignetting: 0.0,
            exposure_jitter: 0.0,
            seed: 1,
        };
        let renderer = PhotoRenderer::new(&scene, params).unwrap();
        let sun = renderer.sun_direction;
        let away = -Vec3::new(sun.x, sun.y, 0.0).normalize();
        let footprint = scene.footprints[0];
        // Ground just behind the house (seen from the sun) is in shadow; ground on the sun's side
        // and far behind it is lit.
        let behind = away * (footprint.half_x_m.min(footprint.half_y_m) + 2.0);
        let in_front = -away * (footprint.half_x_m.max(footprint.half_y_m) + 4.0);
        let far_behind = away * 40.0;
        assert_eq!(renderer.shadow.sun_visibility(behind, sun.z), 0.0);
        assert_eq!(renderer.shadow.sun_visibility(in_front, sun.z), 1.0);
        assert_eq!(renderer.shadow.sun_visibility(far_behind, sun.z), 1.0);
    }

    #[test]
    fn gaussian_from_hash_has_unit_variance() {
        let n = 20000;
        let values: Vec<f32> = (0..n).map(|i| gaussian_from_hash(hash_u64(i))).collect();
        let mean = values.iter().sum::<f32>() / n as f32;
        let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / n as f32;
        assert!(
            mean.abs() < 0.05 && (var - 1.0).abs() < 0.05,
            "{mean} {var}"
        );
    }
}
