//! What a given scene and job need, decided before any GPU work (DESIGN §6).
//!
//! How: [`SceneFeatures`] reads off the scene and the job what light and material data
//! exist (punctual lights, emitters, sky, sun, glossy materials, textures, layers asked
//! for); each technique turns those into its [`Plan`] in its own module (`plan()` next
//! to the technique, so a reader finds a technique's passes in one place; the technique
//! table dispatches, and `job::plan_for` is the entry point for a job, so this module
//! depends on no technique and no job). A technique
//! creates only the passes, buffers and shader variants its plan lists; everything it
//! leaves out is listed with the reason, and the plan is shown in `bake`'s summary and
//! in a job's status. A technique that cannot handle something the scene has (a light
//! type, glossy transport) says so here: light is never dropped silently.

use serde::Serialize;

use crate::engine::output::OutputLayer;
use crate::engine::scene::{Lighting, Scene};

/// The plan item of the separate direct-light layer (`direct` / `indirect` outputs):
/// every technique's plan decides it, and the job reads it to keep the layer.
pub const DIRECT_LAYER: &str = "direct-light layer";
/// The plan item of the directional (`sh`) layer.
pub const SH_LAYER: &str = "directional (sh) layer";

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct PlanItem {
    pub name: String,
    pub why: String,
}

#[derive(Clone, Debug, Default, Serialize, PartialEq)]
pub struct Plan {
    pub technique: String,
    /// Passes and resources that will be created, each with why it is needed.
    pub passes: Vec<PlanItem>,
    /// What this scene and job do not need (or this technique cannot do), and why.
    pub left_out: Vec<PlanItem>,
    /// What the live error estimate measures for this technique (DESIGN §4): all of the
    /// error for an unbiased technique, only the noise for a biased one.
    pub error_estimate: String,
    /// What the job asks for that bakes but was probably not meant (a sun too faint to
    /// matter beside its sky: `scene::Lighting::faint_sun`), kept with the job so an API
    /// user who missed the submit answer's `warnings` still finds it.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
}

impl Plan {
    pub fn new(technique: &str) -> Self {
        Plan {
            technique: technique.into(),
            ..Default::default()
        }
    }

    /// Records `name` as run when `needed`, else as left out; returns `needed`.
    pub fn decide(&mut self, name: &str, needed: bool, why_run: &str, why_not: &str) -> bool {
        let item = PlanItem {
            name: name.into(),
            why: if needed { why_run } else { why_not }.into(),
        };
        if needed {
            self.passes.push(item)
        } else {
            self.left_out.push(item)
        }
        needed
    }

    pub fn run(&mut self, name: &str, why: &str) {
        self.passes.push(PlanItem {
            name: name.into(),
            why: why.into(),
        });
    }

    pub fn leave_out(&mut self, name: &str, why: &str) {
        self.left_out.push(PlanItem {
            name: name.into(),
            why: why.into(),
        });
    }

    pub fn runs(&self, name: &str) -> bool {
        self.passes.iter().any(|p| p.name == name)
    }

    /// One line for a terminal: `ran: a, b; left out: c (why), d (why)`.
    pub fn summary_line(&self) -> String {
        let ran: Vec<&str> = self.passes.iter().map(|p| p.name.as_str()).collect();
        let left: Vec<String> = self
            .left_out
            .iter()
            .map(|p| format!("{} ({})", p.name, p.why))
            .collect();
        format!(
            "ran: {}; left out: {}",
            ran.join(", "),
            if left.is_empty() {
                "nothing".into()
            } else {
                left.join(", ")
            }
        )
    }
}

/// What the scene and the job contain, as far as any technique's plan cares.
#[derive(Clone, Debug, Default, Serialize)]
pub struct SceneFeatures {
    pub punctual_lights: usize,
    /// How many of `punctual_lights` are directional (the rest are point or spot).
    pub directional_lights: usize,
    pub emissive_triangles: usize,
    pub sky: bool,
    pub sun: bool,
    /// Materials that are not fully rough dielectrics, on at least one triangle.
    pub glossy_materials: usize,
    pub textured_materials: usize,
    pub double_sided_triangles: usize,
    /// Materials with `alphaMode` MASK or BLEND, on at least one triangle.
    pub alpha_materials: usize,
    pub want_direct: bool,
    pub want_validity: bool,
    pub want_sh: bool,
}

impl SceneFeatures {
    pub fn of(scene: &Scene, lighting: &Lighting, outputs: &[OutputLayer]) -> Self {
        let mut used = vec![false; scene.materials.len()];
        let mut emissive_triangles = 0;
        let mut double_sided_triangles = 0;
        for t in &scene.triangles {
            used[t.material as usize] = true;
            let m = &scene.materials[t.material as usize];
            emissive_triangles += usize::from(m.emissive != glam::Vec3::ZERO);
            double_sided_triangles += usize::from(m.double_sided);
        }
        let used_materials = || scene.materials.iter().zip(&used).filter(|(_, u)| **u).map(|(m, _)| m);
        SceneFeatures {
            punctual_lights: scene.lights.len(),
            directional_lights: scene
                .lights
                .iter()
                .filter(|l| matches!(l.kind, crate::engine::scene::LightKind::Directional))
                .count(),
            emissive_triangles,
            sky: lighting.sky.is_some_and(|s| s.radiance != glam::Vec3::ZERO),
            sun: lighting.sun.is_some_and(|s| s.radiance != glam::Vec3::ZERO),
            glossy_materials: used_materials()
                .filter(|m| m.metallic > 0.0 || m.roughness < 1.0)
                .count(),
            textured_materials: used_materials()
                .filter(|m| m.base_color_texture.is_some() || m.emissive_texture.is_some())
                .count(),
            double_sided_triangles,
            alpha_materials: used_materials()
                .filter(|m| m.alpha_mode != crate::engine::scene::AlphaMode::Opaque)
                .count(),
            want_direct: outputs
                .iter()
                .any(|o| matches!(o, OutputLayer::Direct | OutputLayer::Indirect)),
            want_validity: outputs.contains(&OutputLayer::Validity),
            want_sh: outputs.contains(&OutputLayer::Sh),
        }
    }

    /// Whether any light reaches the scene at all.
    pub fn has_light(&self) -> bool {
        self.punctual_lights > 0 || self.emissive_triangles > 0 || self.sky || self.sun
    }
}
