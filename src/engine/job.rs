//! One bake from an imported scene to EXR bytes: the sequence the command line and the
//! service's workers share (texel set → technique → bake loop → dilation → EXR).
//!
//! The caller owns I/O: it imports the scene, decides where the bytes go, and turns
//! progress events into a progress bar or an event stream.

use std::sync::Arc;
use std::time::Duration;

use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::engine::accumulate::{ErrorSummary, Estimate};
use crate::engine::atlas::unwrap::{self, LightmapUvs, UnwrapReport};
use crate::engine::atlas::validate::{self, ValidationReport};
use crate::engine::atlas::{Atlas, AtlasReport};
use crate::engine::bake::{BakeEvent, BakeLoop, BakeObserver, StopCriteria, StopReason};
use crate::engine::control::{CONTROL_TEXELS, ControlTexels};
use crate::engine::footprint;
use crate::engine::gpu::scene_rays::SceneRays;
use crate::engine::output::pages::{self, Manifest, PageEntry, PageFile};
use crate::engine::output::{self, ExrMetadata, OutputLayer};
use crate::engine::plan::Plan;
use crate::engine::post::DEFAULT_RINGS;
use crate::engine::post::denoised::{self, Denoiser, Used};
use crate::engine::scene::{Lighting, Scene};
use crate::engine::shadowmask::{self, ShadowmaskBake};
use crate::engine::technique::obscurance::{Obscurance, ObscuranceState, UpdateReach};
use crate::engine::technique::path::probes::{self, ProbeBaker, ProbeSet};
use crate::engine::technique::{self, AlphaSupport, BakeInputs, EngineError, Technique};

/// The plan's word for a bake with nothing that emits: no emissive surface, punctual
/// light or sun in the scene, no sky in the job. Not refused (an `ao` layer needs no
/// light, and an exact zero is a correct answer), but the command line warns before the
/// bake, since a level exported without its lights is the usual cause.
pub const NO_LIGHT: &str = "the scene and job have no light at all: the lightmap is exactly zero";

/// The plan for `request` on `scene` (DESIGN §6): the scene's features read off, then the
/// technique's own `plan()` through the technique table; an unknown technique is a
/// bad-input error.
pub fn plan_for(scene: &Scene, request: &BakeRequest) -> Result<Plan, EngineError> {
    let features = crate::engine::plan::SceneFeatures::of(scene, &request.lighting, &request.outputs);
    // What the technique cannot do is refused here, before any GPU work: an output layer
    // it does not write, parameters it does not take, light it does not transport.
    technique::check_request(&request.technique, &request.params, &request.outputs)?;
    technique::check_lights(&request.technique, &features)?;
    let masked = shadowmask::resolve(
        &request.outputs,
        &request.shadowmask_lights,
        &shadowmask::light_names(scene),
        request.lighting.sun.is_some(),
    )
    .map_err(EngineError::BadInput)?;
    let mut plan = technique::plan(&request.technique, &features)?;
    if !features.has_light() {
        plan.leave_out("light", NO_LIGHT);
    }
    plan.warnings.extend(request.lighting.faint_sun());
    if features.alpha_materials > 0 {
        let n = features.alpha_materials;
        match technique::entry(&request.technique)?.alpha {
            AlphaSupport::Everywhere => plan.run(
                "alpha test",
                &format!("{n} MASK/BLEND materials are alpha-tested in every visibility query (rays and maps)"),
            ),
            AlphaSupport::Partly { tested, opaque } => {
                plan.run(
                    "alpha test",
                    &format!("{n} MASK/BLEND materials are alpha-tested in {tested}"),
                );
                plan.leave_out(
                    "alpha test elsewhere",
                    &format!("{opaque} sees MASK/BLEND surfaces as opaque (they cast solid shadows there); path, vpl, hemicube and obscurance alpha-test everywhere"),
                );
            }
        }
    }

    if let Some(p) = &request.probes {
        p.validate().map_err(EngineError::BadInput)?;
        let at = probes::positions_for(scene, p.spacing, p.subdivide, &p.positions)?;
        plan.run(
            "light probes",
            &format!(
                "{} probes (grid {}, {} given, {} glTF nodes), radiance SH to L2 by path after the lightmap, {} steps",
                at.len(),
                p.spacing.map_or("none".into(), |s| if p.subdivide > 0 {
                    format!("{s} m split {} levels near geometry", p.subdivide)
                } else {
                    format!("{s} m")
                }),
                p.positions.len(),
                scene.probe_nodes.len(),
                p.steps
            ),
        );
    }
    if !masked.is_empty() {
        let channels: Vec<String> = masked
            .iter()
            .zip(shadowmask::CHANNEL_NAMES)
            .map(|((name, _), c)| format!("{name} in {c}"))
            .collect();
        plan.run(
            "shadowmask",
            &format!(
                "{}; their direct light is left out of the lightmap and direct.* for the renderer to add times the mask (their bounce stays baked)",
                channels.join(", ")
            ),
        );
    }
    Ok(plan)
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct BakeRequest {
    pub technique: String,
    pub resolution: u32,
    pub lighting: Lighting,
    pub stop: StopCriteria,
    pub params: Value,
    pub outputs: Vec<OutputLayer>,
    pub seed: u64,
    /// The denoiser for what is written (`engine::post::denoised`): `auto` (OIDN when
    /// installed, else the own filter), `oidn`, `own` or `none`; `true` / `false` mean
    /// `auto` / `none`.
    #[serde(default)]
    pub denoise: Denoiser,
    /// Which lightmap UVs are used: authored kept, missing generated (`atlas::unwrap`).
    #[serde(default)]
    pub lightmap_uvs: LightmapUvs,
    /// Texel density of generated charts (texels per metre, times each node's and mesh's
    /// `extras.lightmap_scale`); None: the highest that fits one `resolution`-wide page.
    /// Charts that need more than one page get several (`lightmap-P.exr` each).
    #[serde(default)]
    pub texels_per_unit: Option<f32>,
    /// The widest a page may grow at a fixed `texels_per_unit` before the charts take
    /// several pages (`atlas::unwrap::unwrap_paged`); None: the larger of
    /// [`DEFAULT_MAX_PAGE_SIZE`](unwrap::DEFAULT_MAX_PAGE_SIZE) and `resolution`.
    #[serde(default)]
    pub max_page_size: Option<u32>,
    /// The lights of the `shadowmask` layer, one per channel (`engine::shadowmask`):
    /// `sun`, a light's name or `#index`; empty: the sun and the scene's lights.
    #[serde(default)]
    pub shadowmask_lights: Vec<String>,
    /// Light probes to bake after the lightmap (`technique::path::probes`); none when
    /// absent.
    #[serde(default)]
    pub probes: Option<ProbeRequest>,
}

/// Where and how long to bake light probes (issue 26; docs/probes.md).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ProbeRequest {
    /// A grid of cells of this side (metres) over the scene's bounds, a probe at each
    /// cell's centre.
    #[serde(default)]
    pub spacing: Option<f32>,
    /// Splits the grid's cells that geometry passes through into 8, this many levels down
    /// (0: the plain grid; at most 4): denser probes near surfaces
    /// (`technique::path::probe_placement`).
    #[serde(default)]
    pub subdivide: u32,
    /// Probes at these world positions (the glTF's coordinates).
    #[serde(default)]
    pub positions: Vec<[f64; 3]>,
    /// Steps of `path`'s probe estimator, 64 samples a probe each.
    #[serde(default = "default_probe_steps")]
    pub steps: u32,
    /// Where the probes bake: `auto` (the GPU when a hardware adapter is there), `cpu` or
    /// `gpu` (any adapter, lavapipe included), as `path`'s `device`.
    #[serde(default)]
    pub device: crate::engine::gpu::RayDevice,
}

fn default_probe_steps() -> u32 {
    16
}

impl ProbeRequest {
    /// Checks what needs no scene; errors name the field.
    pub fn validate(&self) -> Result<(), String> {
        if !(1..=4096).contains(&self.steps) {
            return Err(format!("probes.steps must be in 1..=4096, got {}", self.steps));
        }
        if let Some(s) = self.spacing
            && !(s.is_finite() && s > 0.0)
        {
            return Err(format!("probes.spacing must be a positive distance, got {s}"));
        }
        if self.subdivide > probes::MAX_SUBDIVIDE {
            return Err(format!(
                "probes.subdivide must be in 0..={}, got {}",
                probes::MAX_SUBDIVIDE,
                self.subdivide
            ));
        }
        if self.subdivide > 0 && self.spacing.is_none() {
            return Err("probes.subdivide refines the grid of probes.spacing: give probes.spacing too".into());
        }
        if let Some(k) = self.positions.iter().position(|p| !p.iter().all(|c| c.is_finite())) {
            return Err(format!("probes.positions[{k}] is not finite"));
        }
        Ok(())
    }
}

impl BakeRequest {
    /// `max_page_size` in effect (its field's doc).
    pub fn max_page_size(&self) -> u32 {
        self.max_page_size
            .unwrap_or_else(|| unwrap::DEFAULT_MAX_PAGE_SIZE.max(self.resolution))
    }
}

impl Default for BakeRequest {
    fn default() -> Self {
        BakeRequest {
            technique: "path".into(),
            resolution: 256,
            lighting: Lighting::default(),
            stop: StopCriteria {
                steps: Some(4096),
                seconds: Some(120.0),
                target_error: Some(0.02),
            },
            params: Value::Null,
            outputs: Vec::new(),
            seed: 0,
            denoise: Denoiser::Auto,
            lightmap_uvs: LightmapUvs::default(),
            texels_per_unit: None,
            max_page_size: None,
            shadowmask_lights: Vec::new(),
            probes: None,
        }
    }
}

#[derive(Clone, Debug, Serialize)]
pub struct BakeSummary {
    pub technique: String,
    pub atlas: AtlasReport,
    pub steps: u64,
    pub seconds: f64,
    pub stopped_by: StopReason,
    pub error: ErrorSummary,
    pub plan: Plan,
    pub validation: ValidationReport,
    /// Set when the scene had no lightmap UVs and they were generated.
    pub generated_uvs: Option<UnwrapReport>,
    /// The denoiser that made the delivered lightmap (`none` for the raw estimate);
    /// `error` is the delivered lightmap's estimate, `error.raw_relative` the raw one's.
    pub denoiser: String,
    /// The pages written (`lightmap-P.exr`), as `lightmaps.json` lists them.
    pub pages: Vec<PageEntry>,
}

impl BakeResult {
    /// Page 0's EXR: the whole lightmap of a one-page bake.
    pub fn first_page(&self) -> &[u8] {
        &self.pages[0].exr
    }
}

pub struct BakeResult {
    /// The scene as baked: with generated lightmap UVs when it had none.
    pub scene: Arc<Scene>,
    /// One EXR per page (`lightmap-P.exr`, `output::pages`), in page order.
    pub pages: Vec<PageFile>,
    /// `lightmaps.json`.
    pub manifest: Manifest,
    /// Tone-mapped PNG of the dilated lightmap (the whole grid, pages one under another).
    pub preview_png: Vec<u8>,
    pub estimate: Estimate,
    pub atlas: Arc<Atlas>,
    pub summary: BakeSummary,
    /// The light probes, when the request asked for them.
    pub probes: Option<ProbeSet>,
}

/// How a caller wants a bake run, beyond what is baked.
#[derive(Clone, Debug)]
pub struct BakeOptions {
    /// Longest time between snapshots (each costs a readback and, in the service, an
    /// EXR upload).
    pub snapshot_interval: Duration,
    /// Measure a biased technique's bias at control texels (`engine::control`), so the
    /// reported error covers it; default true.
    pub control_texels: bool,
    /// Where the technique reports how far each step is (`bake::StepProgress`): a CLI's
    /// progress bar reads it while one long step runs. None: not reported.
    pub step_progress: Option<crate::engine::bake::StepProgress>,
    /// Refuse, before the texel set is built, a bake whose estimated peak memory
    /// (`engine::footprint`) on its real grid of pages is over this many bytes (a
    /// worker's `--max-job-memory-mb`); None: no limit.
    pub max_memory_bytes: Option<u64>,
}

impl Default for BakeOptions {
    fn default() -> Self {
        BakeOptions {
            snapshot_interval: Duration::from_secs(5),
            control_texels: true,
            step_progress: None,
            max_memory_bytes: None,
        }
    }
}

/// Runs `request` on `scene`; `on_atlas` is given the texel set before the first step
/// (the service keeps it to encode snapshot EXRs with [`delivered_exr`]). A bake the
/// observer cancelled is delivered raw, not denoised.
pub fn bake(
    scene: Arc<Scene>,
    request: &BakeRequest,
    options: &BakeOptions,
    observer: &mut dyn BakeObserver,
    on_atlas: &mut dyn FnMut(&Arc<Atlas>),
    on_plan: &mut dyn FnMut(&Plan),
) -> Result<BakeResult, EngineError> {
    bake_impl(scene, request, options, observer, on_atlas, on_plan, None).map(|(r, _)| r)
}

/// An `obscurance` bake that also returns what an incremental update needs
/// ([`ObscuranceState`]); with `update` = (a finished bake's state, the names of the
/// meshes that moved or were added, which influence to follow), only the texels those
/// meshes influenced are
/// recomputed (seed section 5, `technique::obscurance`), for as many steps as the
/// finished bake ran (`request.stop` is not used then).
pub fn bake_obscurance(
    scene: Arc<Scene>,
    request: &BakeRequest,
    options: &BakeOptions,
    observer: &mut dyn BakeObserver,
    update: Option<(&ObscuranceState, &[String], UpdateReach)>,
) -> Result<(BakeResult, ObscuranceState), EngineError> {
    if request.technique != "obscurance" {
        return Err(EngineError::BadInput(format!(
            "incremental updates and saved bake states are for the obscurance technique, not {:?}",
            request.technique
        )));
    }
    let (result, state) = bake_impl(
        scene,
        request,
        options,
        observer,
        &mut |_| {},
        &mut |_| {},
        Some(update),
    )?;
    let state = state.ok_or_else(|| EngineError::Internal("obscurance bake kept no state".into()))?;
    Ok((result, state))
}

type ObscuranceUpdate<'a> = Option<(&'a ObscuranceState, &'a [String], UpdateReach)>;

/// What every bake of a request starts from, before a technique is prepared: the plan,
/// the scene as baked (with generated lightmap UVs when it had none) and its texel set.
/// Deterministic for a scene and request, so the tasks of a split bake and their merge
/// (`engine::tasks`) each build the same one.
pub(crate) struct Prepared {
    pub scene: Arc<Scene>,
    /// The scene's rays, shared by the technique, the control texels, the shadowmask and
    /// the validation: one BVH and one GPU upload per bake.
    pub rays: Arc<SceneRays>,
    pub atlas: Arc<Atlas>,
    pub plan: Plan,
    pub validation: ValidationReport,
    pub unwrap: Option<UnwrapReport>,
    pub denoiser: Used,
    /// Control texels measure the technique's bias (`engine::control`).
    pub control: bool,
    /// With [`prepare_regions`]: the regions' pixel ranges of the grid, in order.
    pub region_pixels: Vec<std::ops::Range<u32>>,
}

/// Which regions of the grid to prepare (`engine::tasks`): cut it into `count` regions
/// (`atlas::regions`, on the texel set before validation) and keep only region `keep`'s
/// texels (validating only those), or all of them when `keep` is `None` (a merge).
#[derive(Clone, Debug)]
pub(crate) struct RegionsOf<'a> {
    pub count: u32,
    pub keep: Option<u32>,
    /// A merge's: the pixels of every texel the tasks kept after their own validation,
    /// in pixel order. Given, the merge takes the tasks' decisions instead of tracing
    /// validation's rays again (for a large level most of its preparation).
    pub validated: Option<&'a [u32]>,
    /// Round 0 of a bake in rounds (`engine::rounds`), with `keep` `None`: the whole grid
    /// is built but only region `trace`'s texels are validated (traced); the others stay
    /// as rasterised, so the round's region tasks together trace the grid's validation
    /// once instead of once each. A region whose every texel is inside geometry keeps
    /// them, as a split bake's region task does. What the untested texels change in the
    /// round's bake is in `engine::rounds`' limits.
    pub trace: Option<u32>,
}

pub(crate) fn prepare(
    scene: Arc<Scene>,
    request: &BakeRequest,
    options: &BakeOptions,
    on_atlas: &mut dyn FnMut(&Arc<Atlas>),
    on_plan: &mut dyn FnMut(&Plan),
) -> Result<Prepared, EngineError> {
    prepare_regions(scene, request, options, None, on_atlas, on_plan)
}

/// [`prepare`] for a task of a bake split by regions, or for its merge. The regions are
/// cut before texel validation, so a region task validates (traces) only its own
/// texels: validation is per texel (its rays are keyed by the texel's pixel), so each
/// region's validated texels are the whole grid's validated texels in its pixel range,
/// and the merge, which validates the whole grid, finds each region's texels there. A
/// region whose every texel lies inside geometry keeps them (validation never empties a
/// texel set) where the whole grid's validation would drop them. A merge given the
/// tasks' kept pixels (`RegionsOf::validated`) takes their decisions instead of tracing
/// again, so it agrees with its tasks in that case too.
pub(crate) fn prepare_regions(
    scene: Arc<Scene>,
    request: &BakeRequest,
    options: &BakeOptions,
    regions: Option<RegionsOf<'_>>,
    on_atlas: &mut dyn FnMut(&Arc<Atlas>),
    on_plan: &mut dyn FnMut(&Plan),
) -> Result<Prepared, EngineError> {
    request.lighting.validate().map_err(EngineError::BadInput)?;
    request.stop.validate()?;
    unwrap::check_page_sizes(request.resolution, request.max_page_size()).map_err(EngineError::BadInput)?;
    let mut plan = plan_for(&scene, request)?;
    let control = options.control_texels && !technique::entry(&request.technique)?.unbiased;
    if control {
        plan.run(
            "control texels",
            &format!(
                "up to {CONTROL_TEXELS} stratified texels traced by path alongside (at most a fifth of the time) to measure the bias"
            ),
        );
        plan.error_estimate = format!(
            "noise and bias, measured at up to {CONTROL_TEXELS} control texels against path (90 % interval in error.interval); \
             without them: {}",
            plan.error_estimate
        );
    }
    let denoiser = request.denoise.resolve().map_err(EngineError::BadInput)?;
    if denoiser == Used::None {
        plan.leave_out("denoiser", "the job asks for the raw estimate");
    } else {
        plan.run(
            "denoiser",
            &format!("{denoiser}; the error reported is the denoised lightmap's"),
        );
    }
    on_plan(&plan);
    let (scene, unwrap) = lightmap_uvs(scene, request)?;
    // The grid: one W x W page, or several one under another (`atlas::unwrap`).
    let (width, height) = scene
        .layout
        .as_ref()
        .map_or((request.resolution, request.resolution), |l| (l.width, l.height));
    if let Some(limit) = options.max_memory_bytes {
        let texture_texels = scene
            .textures
            .iter()
            .map(|t| u64::from(t.width) * u64::from(t.height))
            .sum();
        let shape = footprint::JobShape::new(
            scene.triangles.len() as u64,
            texture_texels,
            request.resolution,
            &request.outputs,
        )
        .on_grid(width, height);
        let need = footprint::estimate_bytes(&shape);
        if need > limit {
            return Err(EngineError::BadInput(format!(
                "the lightmap's {} page(s), {width}x{height} texels in all, need an estimated {} MiB, more than this worker's limit of {} MiB (--max-job-memory-mb): lower the resolution, texels_per_unit or the meshes' extras.lightmap_scale",
                scene.layout.as_ref().map_or(1, |l| l.pages.len()),
                need >> 20,
                limit >> 20
            )));
        }
    }
    let atlas_error = |e: crate::engine::atlas::AtlasError| EngineError::BadInput(e.to_string());
    let region_error =
        |m: String| EngineError::BadInput(format!("tasks: {m}; ask for fewer regions or a higher resolution"));
    let mut region_pixels = Vec::new();
    let mut validated = None;
    let mut trace_region: Option<u32> = None;
    let mut atlas = match regions {
        // A region's task: the cut from the grid's coverage (a bit a pixel), then only
        // the region's rows rasterised and only its texels built, so a page task's
        // texel set costs its page, not the whole grid (`Atlas::build_pixels`).
        Some(RegionsOf {
            count,
            keep: Some(k),
            validated: kept,
            ..
        }) if count > 1 => {
            validated = kept;
            let coverage = Atlas::coverage(&scene, width, height).map_err(atlas_error)?;
            region_pixels = coverage.region_pixels(count).map_err(region_error)?;
            let pixels = region_pixels
                .get(k as usize)
                .cloned()
                .ok_or_else(|| EngineError::Internal(format!("region {k} of {count} asked for")))?;
            let atlas = Atlas::build_pixels(&scene, width, height, pixels).map_err(atlas_error)?;
            tracing::info!(
                region = k,
                regions = count,
                texels = atlas.texels.len(),
                of = coverage.texels(),
                "the task's region of the grid"
            );
            atlas
        }
        Some(RegionsOf {
            count,
            validated: kept,
            trace,
            ..
        }) => {
            validated = kept;
            trace_region = trace;
            let atlas = Atlas::build(&scene, width, height).map_err(atlas_error)?;
            region_pixels = atlas.region_pixels(count).map_err(region_error)?;
            atlas
        }
        None => Atlas::build(&scene, width, height).map_err(atlas_error)?,
    };
    let rays = SceneRays::new(scene.clone());
    // The texels validation traces: all of them, or one region's in round 0 of a bake in
    // rounds (the others read as outside geometry: kept).
    let traced = match trace_region {
        Some(k) => {
            let pixels = region_pixels
                .get(k as usize)
                .cloned()
                .ok_or_else(|| EngineError::Internal(format!("region {k} of {} traced", region_pixels.len())))?;
            atlas.texels_in(pixels)
        }
        None => 0..atlas.texels.len(),
    };
    let fractions = match validated {
        // A texel the tasks kept has no back-face hit to speak of, any other was inside.
        Some(kept) => atlas
            .texels
            .iter()
            .map(|t| if kept.binary_search(&t.pixel).is_ok() { 0.0 } else { 1.0 })
            .collect(),
        None => {
            let texels = &atlas.texels[traced.clone()];
            // On a hardware GPU its rays go through the BVH query pass (issue 20 point 3:
            // 56.6 s of a 15.6 M-texel level's 60.5 s preparation was the CPU's tracing);
            // elsewhere the CPU's.
            let gpu = crate::engine::gpu::hardware_context("texel validation").and_then(|ctx| {
                crate::engine::gpu::validate::backface_fractions(&ctx, &rays, texels)
                    .inspect_err(
                        |e| tracing::warn!(error = %e, "texel validation on the GPU failed; tracing on the CPU"),
                    )
                    .ok()
            });
            let some = gpu.unwrap_or_else(|| validate::backface_fractions(&scene, &rays.tracer(), texels));
            let mut all = vec![0.0; atlas.texels.len()];
            // One region traced: it keeps its texels when every one of them is inside
            // geometry (validation never empties a texel set), as a split bake's region
            // task does; the untraced texels around it would otherwise keep the set from
            // being empty and the region would lose them all.
            let whole = traced.len() == atlas.texels.len();
            if whole || some.iter().any(|f| *f <= validate::BACKFACE_TOLERANCE) {
                all[traced].copy_from_slice(&some);
            }
            all
        }
    };
    let validation = validate::validate_from(&scene, &mut atlas, &fractions);
    let atlas = Arc::new(atlas);
    on_atlas(&atlas);
    Ok(Prepared {
        scene,
        rays,
        atlas,
        plan,
        validation,
        unwrap,
        denoiser,
        control,
        region_pixels,
    })
}

/// The scene as `request` bakes it: with its lightmap UVs generated (a layout of one
/// page or several) where it has meshes without them, the request regenerates or
/// repacks them, or its authored UVs lie on several pages; as it is otherwise, or when
/// it has its layout already (the report is then `None`). Deterministic, so every task
/// of a split bake generates the same UVs; [`crate::engine::rounds::bake_in_rounds`]
/// generates them once for all its tasks.
pub(crate) fn lightmap_uvs(
    scene: Arc<Scene>,
    request: &BakeRequest,
) -> Result<(Arc<Scene>, Option<UnwrapReport>), EngineError> {
    let regenerate = matches!(
        request.lightmap_uvs,
        LightmapUvs::RegenerateAll | LightmapUvs::RepackInstances
    ) && scene.source.is_some();
    // Authored UVs on several pages (a file a multi-page bake wrote) are stacked into
    // one grid by the same layout step, with nothing to unwrap.
    let stack_pages = scene.authored_pages() > 1;
    if !((scene.needs_lightmap_uvs || regenerate || stack_pages) && scene.layout.is_none()) {
        return Ok((scene, None));
    }
    let mut generated = (*scene).clone();
    let started = std::time::Instant::now();
    let report = unwrap::generate_lightmap_uvs_paged(
        &mut generated,
        request.resolution,
        request.max_page_size(),
        request.lightmap_uvs,
        request.texels_per_unit,
        &unwrap::UvUnwrap,
    )
    .map_err(|e| EngineError::BadInput(format!("generating lightmap UVs: {e}")))?;
    tracing::info!(
        charts = report.charts,
        width = report.width,
        height = report.height,
        generated_meshes = report.generated_meshes,
        kept_meshes = report.kept_meshes,
        seconds = started.elapsed().as_secs_f64(),
        "lightmap UVs generated"
    );
    for w in &report.warnings {
        tracing::warn!("{w}");
    }
    Ok((Arc::new(generated), Some(report)))
}

impl Prepared {
    pub fn inputs(&self, request: &BakeRequest) -> BakeInputs {
        BakeInputs {
            want_direct: self.plan.runs(crate::engine::plan::DIRECT_LAYER),
            ..BakeInputs::sharing(
                self.rays.clone(),
                self.atlas.clone(),
                request.lighting,
                request.seed,
                self.plan.clone(),
            )
        }
    }

    /// What is delivered for a bake's final raw estimate: denoised (unless cancelled:
    /// whoever cancelled does not keep it, and denoising would hold the cancellation up by
    /// a whole denoise), the EXR, the preview, the summary, and the probes when asked for.
    pub fn deliver(
        self,
        request: &BakeRequest,
        raw: &Estimate,
        params: &Value,
        elapsed: Duration,
        stopped_by: StopReason,
        observer: &mut dyn BakeObserver,
    ) -> Result<BakeResult, EngineError> {
        // Denoised once: the EXR and the preview show the same delivered lightmap.
        let finished = if stopped_by == StopReason::Cancelled {
            raw.clone()
        } else {
            finish(&self.atlas, raw, request)
        };
        tracing::debug!(builds = ?self.rays.builds(), "the bake's shared scene rays");
        let pages = delivered_pages(&self.atlas, &finished, request, params, elapsed)?;
        let preview_png = preview_png(&self.atlas, &finished)?;
        let summary = BakeSummary {
            technique: request.technique.clone(),
            atlas: self.atlas.report(),
            steps: raw.steps,
            seconds: elapsed.as_secs_f64(),
            stopped_by,
            error: finished.error,
            plan: self.plan,
            validation: self.validation,
            generated_uvs: self.unwrap,
            denoiser: if finished.error.raw_relative.is_some() {
                self.denoiser.to_string()
            } else {
                "none".into()
            },
            pages: pages.iter().map(|p| p.entry.clone()).collect(),
        };
        let manifest = Manifest {
            format: pages::MANIFEST_FORMAT,
            technique: summary.technique.clone(),
            steps: summary.steps,
            seconds: summary.seconds,
            relative_error: summary.error.relative,
            denoiser: summary.denoiser.clone(),
            quantity: output::QUANTITY,
            pages: summary.pages.clone(),
            nodes: pages::node_entries(&self.scene),
        };
        let probes = match &request.probes {
            Some(p) if stopped_by != StopReason::Cancelled => Some(bake_probes(&self.rays, request, p, observer)?),
            _ => None,
        };
        Ok(BakeResult {
            scene: self.scene,
            pages,
            manifest,
            preview_png,
            estimate: finished,
            atlas: self.atlas,
            summary,
            probes,
        })
    }
}

fn bake_impl(
    scene: Arc<Scene>,
    request: &BakeRequest,
    options: &BakeOptions,
    observer: &mut dyn BakeObserver,
    on_atlas: &mut dyn FnMut(&Arc<Atlas>),
    on_plan: &mut dyn FnMut(&Plan),
    obscurance: Option<ObscuranceUpdate<'_>>,
) -> Result<(BakeResult, Option<ObscuranceState>), EngineError> {
    let prepared = prepare(scene, request, options, on_atlas, on_plan)?;
    if prepared.unwrap.is_some() {
        // A cancellation asked for here is seen by the loop before its first step.
        let _ = observer.event(BakeEvent::GeneratedUvs { scene: &prepared.scene });
    }
    let inputs = prepared.inputs(request);
    let mut stop = request.stop;
    // An obscurance bake whose state is kept is held by its concrete type, so the state
    // can be read after the loop; every other bake goes through the trait object.
    let (mut concrete, mut boxed) = (None, None);
    match obscurance {
        None => boxed = Some(technique::create(&request.technique, inputs, &request.params)?),
        Some(None) => concrete = Some(Obscurance::prepare(inputs, &request.params)?),
        Some(Some((state, changed, reach))) => {
            let (tech, report) = Obscurance::update(inputs, state, changed, reach)?;
            stop = StopCriteria {
                steps: Some(report.steps.max(1)),
                seconds: None,
                target_error: None,
            };
            concrete = Some(tech);
        }
    }
    let tech: &mut dyn Technique = match (&mut concrete, &mut boxed) {
        (Some(t), _) => t,
        (None, Some(t)) => t.as_mut(),
        (None, None) => return Err(EngineError::Internal("no technique was prepared".into())),
    };
    let mut bake_loop = prepared.bake_loop(request, stop, options)?;
    let outcome = bake_loop.run(tech, observer)?;
    let params = tech.params();
    let state = concrete.map(|t| t.state()).transpose()?;
    let result = prepared.deliver(
        request,
        &outcome.estimate,
        &params,
        outcome.elapsed,
        outcome.stopped_by,
        observer,
    )?;
    Ok((result, state))
}

impl Prepared {
    /// The bake loop for `stop`, with the control texels and the shadowmask pass the
    /// request and plan call for.
    pub fn bake_loop(
        &self,
        request: &BakeRequest,
        stop: StopCriteria,
        options: &BakeOptions,
    ) -> Result<BakeLoop, EngineError> {
        self.bake_loop_picking(request, stop, options, request.seed)
    }

    /// [`bake_loop`](Self::bake_loop) whose control texels are picked with
    /// `control_pick` (a chain of a split bake: the job's seed, where `request` carries
    /// the chain's own).
    pub fn bake_loop_picking(
        &self,
        request: &BakeRequest,
        stop: StopCriteria,
        options: &BakeOptions,
        control_pick: u64,
    ) -> Result<BakeLoop, EngineError> {
        let mut bake_loop = BakeLoop::new(stop);
        bake_loop.snapshot_interval = options.snapshot_interval;
        bake_loop.step_progress = options.step_progress.clone();
        if self.control && !self.atlas.texels.is_empty() {
            bake_loop.control = Some(ControlTexels::new(
                &self.rays,
                &self.atlas,
                request.lighting,
                control_pick,
                request.seed,
            )?);
        }
        bake_loop.shadowmask = ShadowmaskBake::new(
            &self.rays,
            &self.atlas,
            &request.lighting,
            request.seed,
            &request.outputs,
            &request.shadowmask_lights,
        )?;
        Ok(bake_loop)
    }
}

/// The request's probes, baked by `path`'s probe estimator on the baked scene (the one
/// with generated lightmap UVs, the same geometry), telling `observer` after each step;
/// an observer that breaks (a cancelled job) stops them with the steps done so far.
fn bake_probes(
    rays: &SceneRays,
    request: &BakeRequest,
    p: &ProbeRequest,
    observer: &mut dyn BakeObserver,
) -> Result<ProbeSet, EngineError> {
    let started = std::time::Instant::now();
    let at = probes::positions_for(rays.scene(), p.spacing, p.subdivide, &p.positions)?;
    let mut baker = ProbeBaker::sharing(
        rays,
        request.lighting,
        at,
        &serde_json::json!({"samples_per_step": 64, "device": p.device}),
        request.seed,
    )?;
    let probes = baker.valid().len();
    let device = baker.device();
    let mut go = observer.event(BakeEvent::Probes {
        steps: 0,
        of: p.steps,
        probes,
    });
    for k in 1..=p.steps {
        if go.is_break() {
            tracing::info!(steps = k - 1, of = p.steps, "light probes stopped by the observer");
            break;
        }
        baker.step()?;
        go = observer.event(BakeEvent::Probes {
            steps: k,
            of: p.steps,
            probes,
        });
    }
    let set = baker.result()?;
    tracing::info!(
        probes = set.probes.len(),
        device,
        invalid = set.probes.iter().filter(|x| !x.valid).count(),
        steps = set.steps,
        relative_error = set.error,
        seconds = started.elapsed().as_secs_f64(),
        "light probes baked"
    );
    Ok(set)
}

/// [`bake`] with default options and nobody watching: for tests and tools that only
/// want the result.
pub fn bake_unobserved(scene: Arc<Scene>, request: &BakeRequest) -> Result<BakeResult, EngineError> {
    let mut observer = |_: crate::engine::bake::BakeEvent<'_>| std::ops::ControlFlow::Continue(());
    bake(
        scene,
        request,
        &BakeOptions::default(),
        &mut observer,
        &mut |_| {},
        &mut |_| {},
    )
}

/// The EXR of an estimate [`finish`] already delivered (a snapshot's or the final one):
/// dilated lightmap, requested layers, and the header attributes of DESIGN §2. The
/// caller denoises once and hands the same estimate to [`preview_png`].
pub fn delivered_exr(
    atlas: &Atlas,
    estimate: &Estimate,
    request: &BakeRequest,
    params: &Value,
    elapsed: Duration,
) -> Result<Vec<u8>, EngineError> {
    let channels =
        output::lightmap_channels(atlas, estimate, &request.outputs, DEFAULT_RINGS).map_err(EngineError::Internal)?;
    let meta = exr_metadata(estimate, request, params, elapsed);
    output::encode_exr(atlas.width, atlas.height, channels, &meta).map_err(EngineError::Internal)
}

/// The delivered estimate as one EXR per page (`output::pages`): the channels of
/// [`delivered_exr`], cut into the atlas's pages, each with its page number in the header.
pub fn delivered_pages(
    atlas: &Atlas,
    estimate: &Estimate,
    request: &BakeRequest,
    params: &Value,
    elapsed: Duration,
) -> Result<Vec<PageFile>, EngineError> {
    let channels =
        output::lightmap_channels(atlas, estimate, &request.outputs, DEFAULT_RINGS).map_err(EngineError::Internal)?;
    let entries = pages::page_entries(atlas, estimate);
    let count = entries.len() as u32;
    entries
        .into_iter()
        .zip(&atlas.pages)
        .map(|(entry, band)| {
            let mut meta = exr_metadata(estimate, request, params, elapsed);
            meta.page = Some((entry.page, count));
            let exr = output::encode_exr(
                atlas.width,
                band.rows,
                pages::crop_channels(&channels, atlas.width, *band),
                &meta,
            )
            .map_err(EngineError::Internal)?;
            Ok(PageFile { entry, exr })
        })
        .collect()
}

fn exr_metadata(estimate: &Estimate, request: &BakeRequest, params: &Value, elapsed: Duration) -> ExrMetadata {
    ExrMetadata {
        technique: request.technique.clone(),
        params: params.clone(),
        steps: estimate.steps,
        seconds: elapsed.as_secs_f64(),
        relative_error: estimate.error.relative,
        seed: request.seed,
        denoised: if estimate.error.raw_relative.is_some() {
            used(request).to_string()
        } else {
            "no".into()
        },
        raw_relative_error: estimate.error.raw_relative,
        shadowmask: estimate
            .shadowmask
            .as_ref()
            .map(|m| m.lights.clone())
            .unwrap_or_default(),
        page: None,
    }
}

/// The denoiser `request` gets: its choice, or the own filter where `oidn` was asked
/// for and the library is gone (a bake checks this before it starts).
fn used(request: &BakeRequest) -> Used {
    request.denoise.resolve().unwrap_or(Used::Own)
}

/// What is written for an estimate: denoised by the request's denoiser and blended so it
/// is never worse than raw, with the delivered error (`engine::post::denoised`), when
/// both halves have steps; else the raw estimate.
pub fn finish(atlas: &Atlas, estimate: &Estimate, request: &BakeRequest) -> Estimate {
    denoised::apply(atlas, estimate, used(request))
}

/// A tone-mapped PNG of an estimate, gutters filled.
pub fn preview_png(atlas: &Atlas, estimate: &Estimate) -> Result<Vec<u8>, EngineError> {
    let img = crate::engine::post::dilate(atlas, &estimate.total, DEFAULT_RINGS);
    output::encode_preview_png(atlas.width, atlas.height, &img).map_err(EngineError::Internal)
}
