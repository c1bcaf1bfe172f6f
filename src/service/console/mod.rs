//! The web console (issue 23) and the three things the service computes only for it.
//!
//! - [`page`]: `GET /` is one HTML document. `index.html`, `style.css`, `app.js` and
//!   `viewer.js` in this folder are embedded with `include_str!` and joined once into a
//!   single response, so the binary needs no file at run time, the page needs no second
//!   request (and no route besides `/` has to be reachable without a token under
//!   `--auth`: the page itself holds no data), and there is no build step, npm or CDN.
//! - [`techniques`]: the technique catalogue the bake form is built from (`GET
//!   /v1/techniques`). It is read from the engine's technique table (each row's
//!   summary, lights, layers and `default_params`: the names, types and defaults) and
//!   each technique's `plan()` for a scene that has every kind of light and material
//!   (what is left out then is what the technique cannot do), and the denoiser choices
//!   from the engine's `Denoiser::ALL`: no list is typed twice.
//! - [`rgba16f`]: a lightmap EXR as half floats (`GET /v1/jobs/{id}/lightmap.rgba16f`),
//!   which WebGL2 uploads as an `RGBA16F` texture as it is (filterable without any
//!   extension), and the page tone-maps for the 2D view with a 64 Ki lookup table. Half
//!   floats keep the range of the float lightmap (up to 65504, 11 bits of mantissa) at
//!   half the bytes of float32; an RGBM/RGBE PNG would be smaller but puts data in
//!   alpha, which browsers premultiply when a PNG is decoded for a 2D canvas, so the page
//!   would need a GPU pass just to show the image.
//!
//! Limits: the catalogue lists a technique's parameters by their default values; a
//! parameter whose default is `null` (for example obscurance's `dmax`) is shown without
//! its type, and enumerations are shown as text without their choices, until the
//! technique table carries that.

use std::sync::OnceLock;

use serde::Serialize;
use serde_json::{Value, json};
use utoipa::ToSchema;

use crate::engine::job::BakeRequest;
use crate::engine::output::OutputLayer;
use crate::engine::plan::{PlanItem, SceneFeatures};
use crate::engine::post::denoised::Denoiser;
use crate::engine::technique::{self, TECHNIQUES};
use crate::service::Limits;

const INDEX: &str = include_str!("index.html");
const STYLE: &str = include_str!("style.css");
const APP: &str = include_str!("app.js");
const VIEWER: &str = include_str!("viewer.js");

/// The console page: `index.html` with the style sheet and both scripts in place of its
/// `/*STYLE*/` and `/*SCRIPT*/` markers (assembled once).
pub fn page() -> &'static str {
    static PAGE: OnceLock<String> = OnceLock::new();
    PAGE.get_or_init(|| {
        INDEX
            .replace("/*STYLE*/", STYLE)
            .replace("/*SCRIPT*/", &format!("{VIEWER}\n{APP}"))
    })
}

/// One technique, as the bake form needs it.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct TechniqueInfo {
    pub id: String,
    /// The technique table's one-line description.
    pub summary: String,
    /// The output layers it can write (the technique table's row); a job asking for
    /// another is refused with 422.
    pub outputs: Vec<String>,
    /// The light it transports (`sky`, `sun`, `directional_lights`, `point_spot_lights`,
    /// `emitters`); a job with other light is refused with 422.
    #[schema(value_type = Vec<String>)]
    pub lights: Vec<technique::LightSource>,
    /// Every parameter with its default (the technique's parameter struct, serialised).
    #[schema(value_type = Object)]
    pub params: Value,
    /// Passes the technique runs for a scene with every kind of light and material.
    #[schema(value_type = Vec<Object>)]
    pub passes: Vec<PlanItem>,
    /// What it leaves out even then (a light type or transport it cannot do), with why.
    #[schema(value_type = Vec<Object>)]
    pub left_out: Vec<PlanItem>,
    /// What its live error estimate measures.
    pub error_estimate: String,
    /// How a job of it may be split across workers (issue 25, docs/scaling.md).
    pub split: SplitInfo,
}

/// How a technique's jobs split into tasks: what `tasks`, `regions` and `rounds` may ask.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct SplitInfo {
    /// `steps_and_regions` (step ranges of regions of the grid, merged exactly),
    /// `chains` (independent chains of the whole grid, each with its own seed) or
    /// `chains_and_regions` (chains within regions).
    pub tasks: String,
    /// Whether its regions can be baked in rounds (`regions` with `rounds`).
    pub rounds: bool,
    /// Why not step ranges or regions, for the techniques that split into chains.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub why: Option<String>,
}

/// One choice of the job field `denoise`.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct DenoiserInfo {
    pub id: String,
    pub summary: String,
    /// Whether this server can run it.
    pub available: bool,
    /// What runs when it is chosen here (`auto`: OIDN or the own filter), or why it
    /// cannot.
    pub detail: String,
}

/// The denoiser choices, from the engine's own list.
fn denoisers() -> Vec<DenoiserInfo> {
    Denoiser::ALL
        .iter()
        .map(|d| {
            let resolved = d.resolve();
            DenoiserInfo {
                id: d.name().to_string(),
                summary: d.summary().to_string(),
                available: resolved.is_ok(),
                detail: match resolved {
                    Ok(used) => used.to_string(),
                    Err(e) => e,
                },
            }
        })
        .collect()
}

/// `GET /v1/techniques`.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct TechniqueList {
    pub techniques: Vec<TechniqueInfo>,
    /// The extra EXR layers a job may ask for in `outputs`.
    pub outputs: Vec<String>,
    /// The choices of the job field `denoise`, and whether this server's machine has
    /// each (`oidn` needs Intel Open Image Denoise's library; a worker elsewhere may
    /// differ, and refuses the job if it lacks it).
    pub denoisers: Vec<DenoiserInfo>,
    /// The job body's defaults (`technique`, `resolution`, `stop`).
    #[schema(value_type = Object)]
    pub defaults: Value,
    /// This server's limits on a job.
    #[schema(value_type = Object)]
    pub limits: Value,
}

/// A scene and job with every feature a plan looks at, so that what a technique leaves
/// out is what it cannot do.
fn everything() -> SceneFeatures {
    SceneFeatures {
        punctual_lights: 2,
        directional_lights: 1,
        emissive_triangles: 1,
        sky: true,
        sun: true,
        glossy_materials: 1,
        textured_materials: 1,
        double_sided_triangles: 1,
        alpha_materials: 1,
        want_direct: true,
        want_validity: true,
        want_sh: true,
    }
}

/// The output layer names a job may give.
pub fn output_layers() -> Vec<String> {
    OutputLayer::ALL.iter().map(|l| l.name().to_string()).collect()
}

/// The catalogue the console's bake form is built from.
pub fn techniques(limits: &Limits) -> TechniqueList {
    let features = everything();
    let techniques = TECHNIQUES
        .iter()
        .map(|id| {
            let plan = technique::plan(id, &features).unwrap_or_default();
            let row = technique::entry(id).ok();
            let outputs = OutputLayer::ALL
                .iter()
                .filter(|l| row.is_some_and(|r| r.writes(**l)))
                .map(|l| l.name().to_string())
                .collect();
            TechniqueInfo {
                id: id.to_string(),
                summary: row.map_or("", |r| r.summary).to_string(),
                outputs,
                lights: row.map_or(&[][..], |r| r.lights).to_vec(),
                params: row.map_or_else(|| json!({}), |r| (r.default_params)()),
                passes: plan.passes,
                left_out: plan.left_out,
                error_estimate: plan.error_estimate,
                split: split_info(row),
            }
        })
        .collect();
    let d = BakeRequest::default();
    TechniqueList {
        techniques,
        outputs: output_layers(),
        denoisers: denoisers(),
        defaults: json!({
            "technique": d.technique,
            "resolution": d.resolution,
            "stop": {"steps": d.stop.steps, "seconds": d.stop.seconds, "target_error": d.stop.target_error},
        }),
        limits: json!({
            "max_resolution": limits.max_resolution.min(crate::engine::atlas::MAX_RESOLUTION),
            "max_job_seconds": limits.max_job_seconds,
            "max_job_steps": limits.max_job_steps,
        }),
    }
}

/// A technique table row's task split, for [`TechniqueInfo::split`].
fn split_info(row: Option<&technique::TechniqueEntry>) -> SplitInfo {
    use technique::api::TaskSplit;
    let (tasks, why) = match row.map(|r| r.tasks) {
        Some(TaskSplit::StepsAndRegions) | None => ("steps_and_regions", None),
        Some(TaskSplit::Chains(why)) => ("chains", Some(why.to_string())),
        Some(TaskSplit::ChainsAndRegions(why)) => ("chains_and_regions", Some(why.to_string())),
    };
    SplitInfo {
        tasks: tasks.into(),
        rounds: row.is_some_and(|r| r.rounds),
        why,
    }
}

/// The default `R`, `G`, `B` channels of a lightmap EXR as little-endian half floats,
/// four per texel (alpha 1), rows top first (the EXR's order, which is glTF's UV order:
/// v = 0 is the first row). Returns width, height and the bytes.
pub fn rgba16f(exr_bytes: &[u8]) -> std::result::Result<(usize, usize, Vec<u8>), String> {
    use exr::prelude::f16;
    let lightmap = crate::engine::output::decode_lightmap(exr_bytes)?;
    let (w, h) = (lightmap.width as usize, lightmap.height as usize);
    let one = f16::from_f32(1.0).to_le_bytes();
    let mut out = Vec::with_capacity(w * h * 8);
    for texel in &lightmap.rgb {
        for v in texel.to_array() {
            // Non-finite or negative texels never reach a stored lightmap; clamp anyway so
            // a texture never holds NaN.
            let v = if v.is_finite() { v.max(0.0) } else { 0.0 };
            out.extend_from_slice(&f16::from_f32(v).to_le_bytes());
        }
        out.extend_from_slice(&one);
    }
    Ok((w, h, out))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_page_has_everything_inlined() {
        let p = page();
        assert!(!p.contains("/*STYLE*/") && !p.contains("/*SCRIPT*/"));
        assert!(p.contains("class Viewer") && p.contains("function parseGlb"));
        // Nothing is fetched from another origin.
        assert!(
            !p.contains("http://") && !p.contains("https://"),
            "the page refers to another origin"
        );
    }

    #[test]
    fn every_technique_is_listed_with_its_params() {
        let list = techniques(&Limits::default());
        let ids: Vec<&str> = list.techniques.iter().map(|t| t.id.as_str()).collect();
        assert_eq!(ids, TECHNIQUES);
        let path = &list.techniques[0];
        assert!(
            path.params.get("samples_per_step").is_some_and(Value::is_u64),
            "{}",
            path.params
        );
        assert!(
            list.techniques
                .iter()
                .all(|t| t.params.is_object() && !t.passes.is_empty())
        );
        assert_eq!(
            list.outputs,
            ["validity", "direct", "indirect", "sh", "ao", "debug", "shadowmask"]
        );
        // The table's rows: only path keeps directional moments, only sdf and obscurance
        // write ao, and every technique bakes every light (the shared direct-light module).
        let by_id = |id: &str| list.techniques.iter().find(|t| t.id == id).unwrap();
        assert_eq!(
            by_id("path").outputs,
            ["validity", "direct", "indirect", "sh", "debug", "shadowmask"]
        );
        assert_eq!(
            by_id("sdf").outputs,
            ["validity", "direct", "indirect", "ao", "debug", "shadowmask"]
        );
        for t in &list.techniques {
            assert_eq!(t.lights, technique::LightSource::ALL, "{}", t.id);
        }
    }

    #[test]
    fn rgba16f_round_trips_the_exr() {
        use exr::prelude::*;
        let (w, h) = (3usize, 2usize);
        let vals: Vec<f32> = (0..w * h).map(|i| i as f32 * 0.5).collect();
        let chans = AnyChannels::sort(smallvec::smallvec![
            AnyChannel::new("R", FlatSamples::F32(vals.clone())),
            AnyChannel::new("G", FlatSamples::F32(vals.iter().map(|v| v * 2.0).collect())),
            AnyChannel::new("B", FlatSamples::F32(vec![1000.0; w * h])),
        ]);
        let img = Image::from_layer(Layer::new(
            (w, h),
            LayerAttributes::default(),
            Encoding::FAST_LOSSLESS,
            chans,
        ));
        let mut bytes = Vec::new();
        img.write().to_buffered(std::io::Cursor::new(&mut bytes)).unwrap();
        let (gw, gh, data) = rgba16f(&bytes).unwrap();
        assert_eq!((gw, gh, data.len()), (3, 2, 3 * 2 * 8));
        let half = |i: usize| f16::from_le_bytes([data[2 * i], data[2 * i + 1]]).to_f32();
        // Texel 5 (last of the second row): R = 2.5, G = 5, B = 1000, A = 1.
        assert_eq!([half(20), half(21), half(22), half(23)], [2.5, 5.0, 1000.0, 1.0]);
        assert_eq!(half(4), 0.5);
        assert!(rgba16f(b"not an exr").unwrap_err().contains("cannot read"));
    }
}
