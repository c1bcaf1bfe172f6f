//! `sdb`'s light preparation on the CPU, before the first step: the scene in `sdb`'s terms
//! ([`sdb_input`]), the emitters too small for the illumination map and the point and spot
//! lights (sampled by CPU shadow rays, fed through the light accumulators so they bounce),
//! and the ambient-mode gain of `average` mode ([`ambient_mode`], stochastic-depth-buffering
//! seed, section 5's coarse mode).

use glam::Vec3;
use rayon::prelude::*;

use super::{AmbientMode, EmitterSampler, SdbInput, SdbParams};
use crate::engine::atlas::Atlas;
use crate::engine::gpu::map_scene::MapScene;
use crate::engine::raytrace::{Tracer, cosine_sample};
use crate::engine::rng::Rng;
use crate::engine::scene::{LightKind, PunctualLight, Scene};
use crate::engine::technique::api::BakeInputs;

/// The scene in `sdb`'s terms, and notes on what it leaves out.
pub fn sdb_input(inputs: &BakeInputs, params: &SdbParams) -> (SdbInput, Vec<String>) {
    let map = MapScene::new(
        &inputs.scene,
        &inputs.atlas,
        &inputs.lighting,
        inputs.seed,
        inputs.want_direct,
    );
    let (mut input, mut notes) = (SdbInput::from_map(map), Vec::new());
    let small = small_emitter_triangles(&inputs.scene, params.map_size);
    if !small.is_empty() {
        notes.push(format!(
            "sdb samples {} emitter triangle(s) smaller than two map pixels on the CPU (one shadow ray per texel a step)",
            small.len()
        ));
        // They shine through the CPU sampler instead; in the map they still reflect and
        // block.
        for &i in &small {
            input.triangles[i].emission = Vec3::ZERO;
        }
        input.small_emitters = Some(small_emitter_sampler(inputs, small));
    }
    let punctual = inputs
        .scene
        .lights
        .iter()
        .filter(|l| l.kind != LightKind::Directional)
        .count();
    if punctual > 0 {
        notes.push(format!(
            "sdb bakes {punctual} point/spot light(s) by one CPU shadow ray per texel and light, once"
        ));
        let direct = punctual_direct(inputs);
        input.small_emitters = Some(match input.small_emitters.take() {
            Some(mut sampler) => Box::new(move |step| {
                let mut v = sampler(step);
                v.iter_mut().zip(&direct).for_each(|(a, b)| *a += *b);
                v
            }),
            None => Box::new(move |_| direct.clone()),
        });
    }
    input.ambient = Some(ambient_mode(
        &inputs.scene,
        &inputs.rays.tracer(),
        &inputs.atlas,
        inputs.seed,
    ));
    (input, notes)
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

/// Next-event estimation toward the small emitters, one sample per texel per step: a
/// triangle picked by power, a uniform point on it, a CPU shadow ray (the `path`
/// reference's rules: a single-sided emitter shines from its front only).
fn small_emitter_sampler(inputs: &BakeInputs, small: Vec<usize>) -> EmitterSampler {
    let scene = inputs.scene.clone();
    let atlas = inputs.atlas.clone();
    let seed = inputs.seed;
    let power: Vec<f64> = small
        .iter()
        .map(|&i| {
            let t = &scene.triangles[i];
            scene.material(t).emissive.dot(Vec3::splat(1.0 / 3.0)) as f64 * t.area() as f64
        })
        .collect();
    let total: f64 = power.iter().sum();
    let cdf: Vec<f64> = power
        .iter()
        .scan(0.0, |acc, p| {
            *acc += p / total;
            Some(*acc)
        })
        .collect();
    let tracer = inputs.rays.tracer();
    Box::new(move |step: u64| {
        atlas
            .texels
            .par_iter()
            .enumerate()
            .map(|(k, texel)| {
                let mut rng = Rng::new(seed, 0x5A11_E417, step, k as u64);
                let u = rng.next_f32() as f64;
                let j = cdf.partition_point(|&c| c <= u).min(small.len() - 1);
                let tri = &scene.triangles[small[j]];
                let (a, b) = (rng.next_f32().sqrt(), rng.next_f32());
                let q = tri.point(Vec3::new(1.0 - a, a * (1.0 - b), a * b));
                let to = q - texel.position;
                let d2 = to.length_squared();
                if d2 <= 0.0 {
                    return Vec3::ZERO;
                }
                let dist = d2.sqrt();
                let w = to / dist;
                let cos_r = texel.normal.dot(w);
                let material = scene.material(tri);
                let cos_e = -tri.geometric_normal().dot(w);
                let cos_e = if material.double_sided { cos_e.abs() } else { cos_e };
                if cos_r <= 0.0 || texel.geo_normal.dot(w) <= 0.0 || cos_e <= 0.0 {
                    return Vec3::ZERO;
                }
                if !tracer.unoccluded(&scene, texel.position, w, dist * (1.0 - 1e-4)) {
                    return Vec3::ZERO;
                }
                // pdf over area: (power share) / (triangle area).
                let pdf = (power[j] / total) as f32 / tri.area();
                material.emissive * (cos_r * cos_e / (d2 * pdf * std::f32::consts::PI))
            })
            .collect()
    })
}

/// E/pi per valid texel from the scene's point and spot lights: one shadow ray per texel
/// and light, with `path`'s rules (the light must be in front of both the shading and the
/// geometric normal; [`PunctualLight::attenuation`] for range and cone). Exact for a
/// point source, so it is computed once, not per step.
fn punctual_direct(inputs: &BakeInputs) -> Vec<Vec3> {
    let scene = &inputs.scene;
    let tracer = inputs.rays.tracer();
    let lights: Vec<&PunctualLight> = scene
        .lights
        .iter()
        .filter(|l| l.kind != LightKind::Directional)
        .collect();
    inputs
        .atlas
        .texels
        .par_iter()
        .map(|texel| {
            let mut sum = Vec3::ZERO;
            for l in &lights {
                let to = l.position - texel.position;
                let d2 = to.length_squared();
                if d2 <= 0.0 {
                    continue;
                }
                let dist = d2.sqrt();
                let w = to / dist;
                let cos = texel.normal.dot(w);
                if cos <= 0.0 || texel.geo_normal.dot(w) <= 0.0 {
                    continue;
                }
                let falloff = l.attenuation(dist, -w) / d2;
                if falloff > 0.0 && tracer.unoccluded(scene, texel.position, w, dist * (1.0 - 1e-4)) {
                    sum += l.intensity * (falloff * cos / std::f32::consts::PI);
                }
            }
            sum
        })
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
    let gain = (0..AMBIENT_RAYS)
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
        .reduce(|| Vec3::ZERO, |a, b| a + b);
    AmbientMode {
        gain: gain / AMBIENT_RAYS as f32,
        texel_area,
    }
}
