//! The scene as the map-based GPU passes see it: triangles with their lightmap UVs and
//! emission, the valid texels, distant lights and the environment. Built once per bake
//! from the scene, the texel set and the job's lighting ([`MapScene::new`]); `sdb` and
//! `obscurance` bake from it, and each adds what only it needs (sdb: the ambient-mode
//! correction and CPU-sampled small emitters).
//!
//! Point and spot lights are not in it: they are each technique's own business (their
//! plans say what they do with them).

use std::sync::Arc;

use glam::{Vec2, Vec3};

use crate::engine::atlas::Atlas;
use crate::engine::scene::{LightKind, Lighting, Scene};

/// One triangle as the illumination map needs it.
#[derive(Debug, Clone, Copy)]
pub struct MapTriangle {
    pub p: [Vec3; 3],
    /// Lightmap UV (TEXCOORD_1) of each corner.
    pub lm: [Vec2; 3],
    /// Emitted radiance of the material (factor x strength): exact, so emitters do not
    /// depend on the lightmap's resolution.
    pub emission: Vec3,
    /// The material has an emissive texture: its emission is read from the texels.
    pub emission_textured: bool,
    pub double_sided: bool,
    /// Mesh index (for reports).
    pub mesh: u32,
    /// Material index (the scene's tables, for the alpha test of `gpu/materials.wgsl`).
    pub material: u32,
    /// Each corner's UV in the set its base colour texture reads (alpha).
    pub alpha_uv: [Vec2; 3],
}

/// One valid lightmap texel.
#[derive(Debug, Clone, Copy)]
pub struct MapTexel {
    /// Linear pixel index j * width + i.
    pub pixel: u32,
    /// Sample point (already offset off the surface by the atlas).
    pub position: Vec3,
    /// Unit shading normal: the hemisphere the texel integrates (cosine weight).
    pub normal: Vec3,
    /// Unit geometric normal: the plane below which samples are rejected.
    pub geo_normal: Vec3,
    pub albedo: Vec3,
    pub emission: Vec3,
}

impl From<&crate::engine::atlas::Texel> for MapTexel {
    fn from(t: &crate::engine::atlas::Texel) -> Self {
        MapTexel {
            pixel: t.pixel,
            position: t.position,
            normal: t.normal,
            geo_normal: t.geo_normal,
            albedo: t.albedo,
            emission: t.emission,
        }
    }
}

/// A light of (near) zero solid angle handled with shadow maps: the sun, directional
/// lights.
#[derive(Debug, Clone, Copy)]
pub struct DirectionalLight {
    /// Direction the light travels (from the light toward the scene), unit.
    pub direction: Vec3,
    /// Irradiance on a surface facing the light, divided by pi.
    pub irradiance_over_pi: Vec3,
    /// Half the angular diameter in radians (0 for a directional light); the direction
    /// is jittered uniformly over this cone per direction step (soft shadows).
    pub cone_half_angle: f32,
}

/// Radiance arriving from direction w (unit, pointing from the receiver to the sky).
pub type Environment = Arc<dyn Fn(Vec3) -> Vec3 + Send + Sync>;

/// Everything a map-based pass bakes from.
pub struct MapScene {
    pub triangles: Vec<MapTriangle>,
    pub texels: Vec<MapTexel>,
    pub width: u32,
    pub height: u32,
    pub environment: Option<Environment>,
    pub lights: Vec<DirectionalLight>,
    pub seed: u64,
    /// Keep a direct-light layer: light arriving straight from emitters, the sky, the sun
    /// and directional lights (the `path` reference's definition: first vertex only).
    pub want_direct: bool,
}

impl MapScene {
    /// The scene, texel set and lighting in the terms of the map-based GPU passes.
    pub fn new(scene: &Scene, atlas: &Atlas, lighting: &Lighting, seed: u64, want_direct: bool) -> MapScene {
        let triangles = scene
            .triangles
            .iter()
            .map(|t| {
                let m = scene.material(t);
                MapTriangle {
                    p: t.p,
                    lm: t.lm,
                    emission: m.emissive,
                    emission_textured: m.emissive_texture.is_some(),
                    double_sided: m.double_sided,
                    mesh: t.mesh,
                    material: t.material,
                    alpha_uv: scene.base_color_uvs(t),
                }
            })
            .collect();
        let texels = atlas.texels.iter().map(MapTexel::from).collect();
        let mut lights = Vec::new();
        if let Some(sun) = lighting.sun {
            lights.push(DirectionalLight {
                direction: sun.direction.normalize(),
                irradiance_over_pi: sun.radiance * (sun.solid_angle() / std::f32::consts::PI),
                cone_half_angle: 0.5 * sun.angular_diameter,
            });
        }
        // Point and spot lights are each technique's own business (sdb: `punctual_direct`);
        // every technique's plan says what it does with them.
        for l in &scene.lights {
            if l.kind == LightKind::Directional {
                lights.push(DirectionalLight {
                    direction: l.direction.normalize(),
                    irradiance_over_pi: l.intensity / std::f32::consts::PI,
                    cone_half_angle: 0.0,
                });
            }
        }
        let environment: Option<Environment> = lighting.sky.map(|_| {
            let lighting = *lighting;
            Arc::new(move |w: Vec3| lighting.sky_radiance(w)) as Environment
        });
        MapScene {
            triangles,
            texels,
            width: atlas.width,
            height: atlas.height,
            environment,
            lights,
            seed,
            want_direct,
        }
    }
}
