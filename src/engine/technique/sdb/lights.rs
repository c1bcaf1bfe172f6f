//! `sdb`'s light preparation, before the first step: the scene in `sdb`'s terms
//! ([`sdb_input`]); the light the illumination map cannot carry, emitters too small for it
//! and point and spot lights, estimated on the GPU by the shared direct-light pass
//! (`gpu::direct_light`: shadow rays through the scene's BVH, `path`'s rules) and fed
//! through the light accumulators so it bounces; and the ambient-mode gain of `average`
//! mode ([`ambient_mode`], stochastic-depth-buffering seed, section 5's coarse mode).
//!
//! Until issue 20 the small emitters were sampled on the CPU (one shadow ray a texel a
//! step, uploaded every step) and the point and spot lights computed once on the CPU;
//! the GPU pass makes neither cross the bus and keeps the step on the device.

use std::sync::Arc;

use glam::Vec3;
use rayon::prelude::*;

use super::{AmbientMode, SdbInput, SdbParams};
use crate::engine::atlas::Atlas;
use crate::engine::gpu::direct_light::DirectLight;
use crate::engine::gpu::map_scene::MapScene;
use crate::engine::gpu::scene_lights::LightSources;
use crate::engine::gpu::{GpuContext, GpuError};
use crate::engine::raytrace::{Tracer, cosine_sample};
use crate::engine::rng::Rng;
use crate::engine::scene::{LightKind, Scene};
use crate::engine::technique::api::BakeInputs;

/// The scene in `sdb`'s terms, and notes on what it leaves out.
pub fn sdb_input(
    ctx: &Arc<GpuContext>,
    inputs: &BakeInputs,
    params: &SdbParams,
) -> Result<(SdbInput, Vec<String>), GpuError> {
    let map = MapScene::new(
        &inputs.scene,
        &inputs.atlas,
        &inputs.lighting,
        inputs.seed,
        inputs.want_direct,
    );
    let (mut input, mut notes) = (SdbInput::from_map(map), Vec::new());
    let small = small_emitter_triangles(&inputs.scene, params.map_pixels());
    let mut sources = LightSources::NONE;
    if !small.is_empty() {
        notes.push(format!(
            "sdb samples {} emitter triangle(s) smaller than two map pixels by shadow rays on the GPU (one a texel a step)",
            small.len()
        ));
        // They shine through the direct-light pass instead; in the map they still reflect
        // and block.
        for &i in &small {
            input.triangles[i].emission = Vec3::ZERO;
        }
        sources = sources.with(LightSources::EMITTERS);
    }
    let punctual = inputs
        .scene
        .lights
        .iter()
        .filter(|l| l.kind != LightKind::Directional)
        .count();
    if punctual > 0 {
        notes.push(format!(
            "sdb bakes {punctual} point/spot light(s) by shadow rays on the GPU (one a texel and light)"
        ));
        sources = sources.with(LightSources::PUNCTUAL);
    }
    if sources != LightSources::NONE {
        let mut keep = vec![false; inputs.scene.triangles.len()];
        for &i in &small {
            keep[i] = true;
        }
        input.small_lights = DirectLight::new(
            ctx.clone(),
            "sdb",
            &inputs.rays,
            &inputs.atlas,
            &inputs.lighting,
            inputs.seed,
            sources,
            Some(&keep),
            1,
            false,
        )?
        .map(|mut light| {
            // sdb blends each step's estimate with its directions' weights itself.
            light.keep_latest();
            SmallLights {
                light,
                every_step: !small.is_empty(),
            }
        });
    }
    input.ambient = Some(ambient_mode(
        &inputs.scene,
        &inputs.rays.tracer(),
        &inputs.atlas,
        inputs.seed,
    ));
    Ok((input, notes))
}

/// The direct light the illumination map cannot carry (see the module doc).
pub struct SmallLights {
    /// Per half, its latest step's E/pi per texel (`DirectLight::keep_latest`).
    pub light: DirectLight,
    /// Whether it changes from step to step: small emitters are sampled (one point a
    /// step); point and spot lights alone are exact and the same every step, so two steps
    /// (one a half) compute them once.
    pub every_step: bool,
}

/// Emitters whose triangles' longest edge is under two illumination-map pixels: the map
/// would show each as a pixel or none, and the k x k lookup would make it k pixels wide
/// (the 1 cm² lamp of the stability suite read 200 times too bright). Untextured only:
/// a textured emitter's emission varies over it, and it is sampled by the map as before.
/// Sorted triangle indices.
fn small_emitter_triangles(scene: &Scene, map_size: u32) -> Vec<usize> {
    let (mut lo, mut hi) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
    for t in &scene.triangles {
        for p in t.p {
            lo = lo.min(p);
            hi = hi.max(p);
        }
    }
    // The map spans the scene's bounding sphere's diameter (about; `make_view`).
    let pixel = (hi - lo).length() / map_size as f32;
    scene
        .triangles
        .iter()
        .enumerate()
        .filter(|(_, t)| {
            let m = scene.material(t);
            let edge = (0..3)
                .map(|k| (t.p[(k + 1) % 3] - t.p[k]).length())
                .fold(0.0f32, f32::max);
            m.emissive.max_element() > 0.0 && m.emissive_texture.is_none() && edge < 2.0 * pixel
        })
        .map(|(i, _)| i)
        .collect()
}

/// Rays cast to measure the ambient gain: its standard error is at most
/// 0.5 / sqrt(AMBIENT_RAYS) = 0.2 % where some rays escape, and 0 in a closed room of one
/// albedo (every ray sees the same albedo), the case where its precision matters.
const AMBIENT_RAYS: u32 = 65_536;

/// The ambient gain g = <T 1> (see [`AmbientMode`]) by casting cosine-distributed rays
/// from area-weighted random texels on the CPU, with the `path` reference's rules: the
/// back of a single-sided surface is black, a double-sided one reflects on both faces.
/// A few tens of milliseconds at 64k rays.
pub fn ambient_mode(scene: &Scene, tracer: &Tracer, atlas: &Atlas, seed: u64) -> AmbientMode {
    let texel_area: Vec<f32> = atlas.texels.iter().map(|t| t.size * t.size).collect();
    let mut cdf = Vec::with_capacity(texel_area.len());
    let mut total = 0.0f64;
    for a in &texel_area {
        total += *a as f64;
        cdf.push(total);
    }
    if total <= 0.0 || scene.triangles.is_empty() {
        return AmbientMode {
            gain: Vec3::ZERO,
            texel_area,
        };
    }
    // Each ray's albedo is collected in ray order and summed in that order: a parallel
    // reduce adds in an order that depends on the threads' work stealing, and the
    // gain's last bits then differ between two bakes of one seed (1e-5 of a lightmap).
    let per_ray: Vec<Vec3> = (0..AMBIENT_RAYS)
        .into_par_iter()
        .map(|i| {
            let mut rng = Rng::new(seed, 0x0A4B_1E47, i as u64, 0);
            let pick = rng.next_f32() as f64 * total;
            let k = cdf.partition_point(|&c| c <= pick).min(cdf.len() - 1);
            let t = &atlas.texels[k];
            let dir = cosine_sample(t.normal, rng.next_f32(), rng.next_f32());
            if dir.dot(t.geo_normal) <= 0.0 {
                return Vec3::ZERO; // below the surface: the surface itself blocks it
            }
            let Some(hit) = tracer.trace(scene, t.position, dir, f32::INFINITY) else {
                return Vec3::ZERO;
            };
            let tri = &scene.triangles[hit.triangle as usize];
            let front = dir.dot(tri.geometric_normal()) < 0.0;
            if front || scene.material(tri).double_sided {
                scene.albedo(tri, hit.bary)
            } else {
                Vec3::ZERO
            }
        })
        .collect();
    let gain = per_ray
        .iter()
        .fold(glam::DVec3::ZERO, |a, b| a + b.as_dvec3())
        .as_vec3();
    AmbientMode {
        gain: gain / AMBIENT_RAYS as f32,
        texel_area,
    }
}
