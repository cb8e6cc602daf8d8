//! The synthetic photo renderer. It uses the rasteriser only for visibility (which face, at what
//! depth) and does its own shading, on purpose unrelated to ASG: procedural materials at the world
//! point, sun light with cast shadows from a shadow map (a depth rendering from far along the sun
//! direction, compared with a bias and filtered over 3×3 texels), sky ambient light, reflections on
//! glass, a sky with clouds and haze. Then camera effects: box-downsampling from a supersampled
//! rendering (antialiasing), auto-exposure jitter, vignetting, a tone curve, Gaussian lens blur,
//! signal-dependent sensor noise and 8-bit quantisation (JPEG compression happens when writing).
//! It also produces each photo's exact depth and its MVS-like depth (`depth.rs`).

use glam::{Vec2, Vec3};
use nalgebra::Vector3;
use rayon::prelude::*;

use super::depth::{gaussian_from_hash, mvs_like_depth, DepthParams, TrueSurfaces};
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

    /// The MVS-like depth map of a photo (`depth::mvs_like_depth`: holes 0.0 where stereo
    /// would find nothing, fattened occlusion edges, noise growing with depth) and the exact
    /// depth of the full scene (clutter included, 0.0 where nothing is hit).
    pub fn depth_maps(
        &mut self,
        intrinsics: &PinholeIntrinsics,
        photo: &Image<[u8; 3]>,
        cam_from_world: &Rigid3,
        params: &DepthParams,
        image_seed: u64,
    ) -> (Image<f32>, Image<f32>) {
        let (w, h) = photo.size();
        self.render_visibility(intrinsics, w, h, cam_from_world);
        let luma = luma(photo);
        let rotation = cam_from_world.inverse().rotation_matrix();
        let (depth, faces) = (
            self.depth_buffers.depth_m().data(),
            self.depth_buffers.face_index().data(),
        );
        let eye = cam_from_world.camera_center();
        let eye = Vec3::new(eye.x as f32, eye.y as f32, eye.z as f32);
        let footprint_per_m = 1.0 / intrinsics.fx_px as f32;
        let (scene, face_normals, seed) = (self.scene, &self.face_normals, self.params.seed);
        // Per pixel: |cos| of the incidence angle and whether the surface is view-dependent.
        let surfaces: Vec<(f32, bool)> = (0..w * h)
            .into_par_iter()
            .map(|index| {
                let face = faces[index];
                if face == NO_FACE || depth[index] <= 0.0 {
                    return (0.0, false);
                }
                let (col, row) = (index % w, index / w);
                let normalized = intrinsics.pixel_to_normalized(nalgebra::Vector2::new(
                    col as f64 + 0.5,
                    row as f64 + 0.5,
                ));
                let ray_cam = Vector3::new(normalized.x, normalized.y, 1.0);
                let ray_world = rotation * ray_cam;
                let ray = Vec3::new(ray_world.x as f32, ray_world.y as f32, ray_world.z as f32);
                let normal = face_normals[face as usize];
                let cos = normal.dot(ray.normalize()).abs();
                let p = eye + ray * depth[index];
                let tag = scene.tags[face as usize];
                let view_dependent = match tag.material {
                    Material::Foliage { .. } => true,
                    Material::Ground => {
                        texture::ground_kind(seed, &scene.ground, p, depth[index] * footprint_per_m)
                            == texture::GroundKind::Grass
                    }
                    Material::Opening | Material::CarGlass => {
                        let panel =
                            (tag.panel != NO_PANEL).then(|| &scene.panels[tag.panel as usize]);
                        let surface = texture::evaluate(
                            tag.material,
                            panel,
                            &scene.ground,
                            p,
                            normal,
                            depth[index] * footprint_per_m,
                            seed,
                            tag.object_id,
                        );
                        surface.mirror > MIRROR_VIEW_DEPENDENT
                    }
                    _ => false,
                };
                (cos, view_dependent)
            })
            .collect();
        let cos_incidence: Vec<f32> = surfaces.iter().map(|s| s.0).collect();
        let view_dependent: Vec<bool> = surfaces.iter().map(|s| s.1).collect();
        let truth = TrueSurfaces {
            depth_m: depth,
            cos_incidence: &cos_incidence,
            view_dependent: &view_dependent,
        };
        let mvs = mvs_like_depth(
            &luma,
            w,
            h,
            &truth,
            intrinsics.fx_px as f32,
            params,
            image_seed,
        );
        let exact = Image::from_fn(w, h, |col, row| depth[row * w + col].max(0.0));
        (mvs, exact)
    }
}

/// Mirror reflectance above which a surface shows mostly the reflected world (glass): stereo
/// matches the reflection, not the surface.
const MIRROR_VIEW_DEPENDENT: f32 = 0.2;

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

#[cfg(test)]
mod tests {
    use super::*;

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
}
