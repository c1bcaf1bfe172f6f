//! The shadowmask output (issue 26 point 3): per texel, the baked visibility of the sun and
//! of up to three other chosen lights, one per channel (`shadowmask.R`, `.G`, `.B`, `.A`,
//! in the order the job names them; the EXR header's `lightmapd:shadowmask` lists them),
//! so a renderer lights static geometry with those lights in real time, times the baked
//! visibility, as Unity's Shadowmask mode and Godot's shadowmask do. The lightmap and
//! `direct.*` then hold no direct light of the chosen lights (a renderer adds it), while
//! `indirect.*` and the lightmap keep their bounce: light = lightmap + Σ_c V_c · direct_c.
//!
//! How: for every technique alike, the shared GPU pass `gpu::shadowmask` is stepped once
//! per technique step ([`STEPS_BEFORE`] steps before the first, so both halves exist and
//! a short bake still has a usable penumbra), and every
//! snapshot's halves lose the pass's halves of the chosen lights' E/pi, even from even
//! and odd from odd: the halves stay independent, so the reported error includes the
//! subtraction's noise. What is subtracted is an unbiased estimate of what every
//! technique's direct light holds of those lights (the same terms as `gpu/lights.wgsl`'s
//! next-event estimate), so for an unbiased technique the result is unbiased; a biased
//! technique keeps its own bias on those lights' direct light (its control texels still
//! measure it, on the full light, before the subtraction). Values a noisy subtraction
//! leaves below zero are clamped to zero in what is delivered (the halves are not).
//!
//! Which lights: `shadowmask_lights` names them: `sun` (the job's sun), a light's name in
//! the glTF (`KHR_lights_punctual`), or `#k`, the k-th light of the scene in import order.
//! Left empty, the sun (if the job has one) and then the scene's lights, when that is at
//! most four. Emissive surfaces cannot be chosen (they are not lights a renderer has).
//!
//! Limits: KHR_lights_punctual lights have no size, so their channels are hard (0 or 1 at
//! the texel's sample point); only the sun's disc gives a soft penumbra. The `sh` layers
//! are refused beside a shadowmask: their directional moments would still hold the chosen
//! lights' direct light.

use std::sync::Arc;

use crate::engine::accumulate::{Estimate, Snapshot};
pub use crate::engine::accumulate::{MASK_CHANNEL_NAMES as CHANNEL_NAMES, ShadowmaskLayer};
use crate::engine::atlas::Atlas;
use crate::engine::gpu::scene_rays::SceneRays;
use crate::engine::gpu::{self, shadowmask as pass};
use crate::engine::output::OutputLayer;
use crate::engine::scene::{Lighting, Scene};
use crate::engine::technique::EngineError;

pub use crate::engine::gpu::shadowmask::{CHANNELS, MaskSource};

/// Sun directions per texel per step (the running mean converges like the bake does).
/// 32 doubled the time of an `sdf` bake of the Kenney level on lavapipe (2.0 s a step for
/// 88k texels against sdf's own 0.85 s); 8 keeps it near a quarter of a step's rays.
pub const SUN_SAMPLES_PER_STEP: u32 = 8;

/// Steps before the technique's first (both halves, and 128 sun directions a texel, so a
/// bake of few steps still gets a usable penumbra).
pub const STEPS_BEFORE: u32 = 16;

/// The chosen lights, in channel order: what each is called in the job and what it is.
/// `light_names` are the scene's lights in import order, `has_sun` whether the job has a
/// sun. The error names the field (`shadowmask_lights[i]`, `outputs`).
pub fn resolve(
    outputs: &[OutputLayer],
    names: &[String],
    light_names: &[String],
    has_sun: bool,
) -> Result<Vec<(String, MaskSource)>, String> {
    let wanted = outputs.contains(&OutputLayer::Shadowmask);
    if !wanted {
        if names.is_empty() {
            return Ok(Vec::new());
        }
        return Err(
            "shadowmask_lights names lights but outputs has no \"shadowmask\": add it, or leave the lights out".into(),
        );
    }
    if outputs.contains(&OutputLayer::Sh) {
        return Err(
            "outputs: \"shadowmask\" and \"sh\" cannot be baked together: the sh layers' directional moments would still hold the masked lights' direct light"
                .into(),
        );
    }
    let available = || {
        let mut all: Vec<String> = has_sun.then(|| "sun".to_string()).into_iter().collect();
        all.extend(light_names.iter().enumerate().map(|(k, n)| format!("{n:?} (#{k})")));
        if all.is_empty() { "none".into() } else { all.join(", ") }
    };
    if names.is_empty() {
        let mut chosen: Vec<(String, MaskSource)> = Vec::new();
        if has_sun {
            chosen.push(("sun".into(), MaskSource::Sun));
        }
        chosen.extend(
            light_names
                .iter()
                .enumerate()
                .map(|(k, n)| (n.clone(), MaskSource::Light(k))),
        );
        if chosen.is_empty() {
            return Err(
                "outputs: \"shadowmask\" needs a light to mask, and the job has no lighting.sun and the scene no KHR_lights_punctual light"
                    .into(),
            );
        }
        if chosen.len() > CHANNELS {
            return Err(format!(
                "shadowmask_lights: the job has {} lights to mask and a shadowmask holds {CHANNELS}; name up to {CHANNELS} of: {}",
                chosen.len(),
                available()
            ));
        }
        return Ok(chosen);
    }
    if names.len() > CHANNELS {
        return Err(format!(
            "shadowmask_lights: a shadowmask holds {CHANNELS} lights, got {}",
            names.len()
        ));
    }
    let mut chosen: Vec<(String, MaskSource)> = Vec::new();
    for (i, name) in names.iter().enumerate() {
        let field = format!("shadowmask_lights[{i}]");
        let source = if name == "sun" {
            if !has_sun {
                return Err(format!("{field}: \"sun\", but the job has no lighting.sun"));
            }
            MaskSource::Sun
        } else if let Some(k) = name.strip_prefix('#') {
            let k: usize = k
                .parse()
                .map_err(|_| format!("{field}: {name:?} is not #<index of a light>"))?;
            if k >= light_names.len() {
                return Err(format!(
                    "{field}: {name:?}, but the scene has {} lights",
                    light_names.len()
                ));
            }
            MaskSource::Light(k)
        } else {
            let hits: Vec<usize> = light_names
                .iter()
                .enumerate()
                .filter(|(_, n)| *n == name)
                .map(|(k, _)| k)
                .collect();
            match hits.as_slice() {
                [k] => MaskSource::Light(*k),
                [] => {
                    return Err(format!(
                        "{field}: no light is called {name:?}; the job has: {}",
                        available()
                    ));
                }
                _ => {
                    return Err(format!(
                        "{field}: {} lights are called {name:?}; name one by index: {}",
                        hits.len(),
                        hits.iter().map(|k| format!("#{k}")).collect::<Vec<_>>().join(", ")
                    ));
                }
            }
        };
        if let Some((earlier, _)) = chosen.iter().find(|(_, s)| *s == source) {
            return Err(format!(
                "{field}: {name:?} is the same light as {earlier:?}, already chosen"
            ));
        }
        chosen.push((name.clone(), source));
    }
    Ok(chosen)
}

/// The scene's light names in import order, as [`resolve`] takes them.
pub fn light_names(scene: &Scene) -> Vec<String> {
    scene.lights.iter().map(|l| l.name.clone()).collect()
}

/// The shadowmask of one bake, stepped beside its technique by the bake loop.
pub struct ShadowmaskBake {
    pass: pass::ShadowmaskPass,
    lights: Vec<String>,
}

impl ShadowmaskBake {
    /// Resolves the request's lights and prepares the GPU pass; `None` when the job asks
    /// for no shadowmask.
    pub fn new(
        rays: &SceneRays,
        atlas: &Arc<Atlas>,
        lighting: &Lighting,
        seed: u64,
        outputs: &[OutputLayer],
        names: &[String],
    ) -> Result<Option<Self>, EngineError> {
        let scene = rays.scene();
        let chosen =
            resolve(outputs, names, &light_names(scene), lighting.sun.is_some()).map_err(EngineError::BadInput)?;
        if chosen.is_empty() {
            return Ok(None);
        }
        let ctx = gpu::shared(&gpu::Requirements::default()).map_err(|e| EngineError::Gpu(e.to_string()))?;
        let sources: Vec<MaskSource> = chosen.iter().map(|(_, s)| *s).collect();
        let mut pass = pass::ShadowmaskPass::new(ctx, rays, atlas, lighting, seed, &sources, SUN_SAMPLES_PER_STEP)
            .map_err(|e| EngineError::Gpu(e.to_string()))?;
        // Both halves, and a floor on the samples, before the technique's first snapshot.
        for _ in 0..STEPS_BEFORE {
            pass.step().map_err(|e| EngineError::Gpu(e.to_string()))?;
        }
        Ok(Some(ShadowmaskBake {
            pass,
            lights: chosen.into_iter().map(|(n, _)| n).collect(),
        }))
    }

    /// One more step of the pass (submitted, not waited for).
    pub fn step(&mut self) -> Result<(), EngineError> {
        self.pass.step().map_err(|e| EngineError::Gpu(e.to_string()))
    }

    /// The delivered estimate for `snapshot`, whose full-light estimate (error already
    /// assessed, control texels included) is `full`: the chosen lights' direct light taken
    /// out of both halves, the error rebased, the shadowmask layer attached.
    pub fn apply(&self, mut snapshot: Snapshot, full: &Estimate) -> Result<Estimate, EngineError> {
        let halves = self.pass.halves().map_err(|e| EngineError::Gpu(e.to_string()))?;
        for (half, mask) in [&mut snapshot.even, &mut snapshot.odd].into_iter().zip(&halves) {
            for (t, e) in half.total.iter_mut().zip(&mask.light) {
                *t -= *e;
            }
            if let Some(d) = &mut half.direct {
                for (t, e) in d.iter_mut().zip(&mask.light) {
                    *t -= *e;
                }
            }
        }
        let mut out = snapshot.estimate();
        out.ao = full.ao.clone();
        rebase_error(&mut out, full);
        let clamp = |v: &mut Vec<glam::Vec3>| v.iter_mut().for_each(|x| *x = x.max(glam::Vec3::ZERO));
        clamp(&mut out.total);
        if let Some(d) = &mut out.direct {
            clamp(d);
        }
        let [na, nb] = self.pass.half_steps();
        let n = (na + nb).max(1) as f32;
        let (wa, wb) = (na as f32 / n, nb as f32 / n);
        let values = halves[0]
            .visibility
            .iter()
            .zip(&halves[1].visibility)
            .map(|(a, b)| std::array::from_fn(|c| a[c] * wa + b[c] * wb))
            .collect();
        out.shadowmask = Some(ShadowmaskLayer {
            lights: self.lights.clone(),
            values,
        });
        Ok(out)
    }
}

/// `out`'s error from the halves (the technique's noise and the subtraction's) combined
/// with what `full`'s assessment found beyond noise (its bias at the control texels), in
/// units of `out`'s own RMS: the bias of the technique's light is unchanged in absolute
/// terms by subtracting an unbiased estimate, and the subtraction's noise adds in
/// quadrature.
fn rebase_error(out: &mut Estimate, full: &Estimate) {
    let (Some(noise_new), Some(rel_full)) = (out.error.relative, full.error.relative) else {
        return;
    };
    if out.error.rms_luminance <= 0.0 {
        return;
    }
    let s = full.error.rms_luminance / out.error.rms_luminance;
    let noise_full = full.error.noise.unwrap_or(rel_full) * s;
    let extra = (noise_new * noise_new - noise_full * noise_full).max(0.0);
    let grow = |r: f32| ((r * s).powi(2) + extra).sqrt();
    out.error.relative = Some(grow(rel_full));
    if full.error.noise.is_some() {
        out.error.noise = Some(noise_new);
    }
    out.error.bias = full.error.bias.map(|b| b * s);
    out.error.interval = full.error.interval.map(|[lo, hi]| [grow(lo), grow(hi)]);
    out.error.control_texels = full.error.control_texels;
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(v: &[&str]) -> Vec<String> {
        v.iter().map(|s| s.to_string()).collect()
    }

    const MASK: &[OutputLayer] = &[OutputLayer::Shadowmask];

    #[test]
    fn default_lights_are_the_sun_then_the_scene_lights() {
        let got = resolve(MASK, &[], &names(&["Lamp", "Key"]), true).unwrap();
        assert_eq!(
            got,
            vec![
                ("sun".to_string(), MaskSource::Sun),
                ("Lamp".to_string(), MaskSource::Light(0)),
                ("Key".to_string(), MaskSource::Light(1)),
            ]
        );
        assert!(resolve(&[], &[], &names(&["Lamp"]), true).unwrap().is_empty());
    }

    #[test]
    fn lights_are_named_by_name_or_index_and_checked() {
        let scene = names(&["Lamp", "Key", "Key"]);
        let got = resolve(MASK, &names(&["#2", "Lamp", "sun"]), &scene, true).unwrap();
        assert_eq!(got[0].1, MaskSource::Light(2));
        assert_eq!(got[1].1, MaskSource::Light(0));
        assert_eq!(got[2].1, MaskSource::Sun);
        let err = |n: &[&str], sun: bool| resolve(MASK, &names(n), &scene, sun).unwrap_err();
        assert!(
            err(&["Key"], true)
                .starts_with("shadowmask_lights[0]: 2 lights are called \"Key\"; name one by index: #1, #2")
        );
        assert!(err(&["Lamp", "Fill"], true).starts_with("shadowmask_lights[1]: no light is called \"Fill\""));
        assert_eq!(
            err(&["sun"], false),
            "shadowmask_lights[0]: \"sun\", but the job has no lighting.sun"
        );
        assert!(err(&["#3"], true).starts_with("shadowmask_lights[0]: \"#3\", but the scene has 3 lights"));
        assert!(err(&["Lamp", "#0"], true).starts_with("shadowmask_lights[1]: \"#0\" is the same light as \"Lamp\""));
        assert!(
            err(&["sun", "#0", "#1", "#2", "Lamp"], true)
                .starts_with("shadowmask_lights: a shadowmask holds 4 lights, got 5")
        );
    }

    #[test]
    fn impossible_requests_name_their_field() {
        let five = names(&["a", "b", "c", "d"]);
        assert!(
            resolve(MASK, &[], &five, true)
                .unwrap_err()
                .starts_with("shadowmask_lights: the job has 5 lights to mask")
        );
        assert!(
            resolve(MASK, &[], &[], false)
                .unwrap_err()
                .starts_with("outputs: \"shadowmask\" needs a light")
        );
        assert!(
            resolve(&[], &names(&["sun"]), &[], true)
                .unwrap_err()
                .starts_with("shadowmask_lights names lights but outputs has no")
        );
        let both = [OutputLayer::Shadowmask, OutputLayer::Sh];
        assert!(
            resolve(&both, &[], &[], true)
                .unwrap_err()
                .starts_with("outputs: \"shadowmask\" and \"sh\"")
        );
    }
}
