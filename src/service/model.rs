//! The API's JSON shapes: the job body of DESIGN §7 with its defaults and field-by-field
//! validation, and the scene and job documents the API returns.
//!
//! How: the body is parsed with `serde_path_to_error`, so a type error or an unknown
//! field is reported with its dotted path (`stop.steps`), then checked against the
//! engine's ranges; [`JobSpec::to_request`] turns it into the engine's `BakeRequest`.
//! The service types are separate from the engine's so the wire format (degrees, plain
//! arrays) can stay fixed while the engine changes, and so the engine needs no OpenAPI.
//!
//! The server's [`Limits`] apply on top of the engine's ranges: `resolution`,
//! `stop.steps` and `stop.seconds` are capped, and a job whose `stop` has no `seconds`
//! gets the server's budget as its `seconds`, so no job can run unbounded.
//!
//! Limits: technique parameters (`params`) are checked by the technique when the job
//! runs, not at submission; a bad one fails the job with the technique's message.

use glam::Vec3;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use utoipa::ToSchema;

use crate::engine::atlas::unwrap::LightmapUvs;
use crate::engine::bake::StopCriteria;
use crate::engine::job::BakeRequest;
use crate::engine::output::OutputLayer;
use crate::engine::post::denoised::Denoiser;
use crate::engine::scene::{Hemisphere, Lighting, Sky, Sun};
use crate::engine::technique;
use crate::service::Limits;
use crate::service::problem::Problem;

/// The largest lightmap side the service accepts (the engine's own limit is higher, but
/// a 4096² CPU bake already takes hours).
pub const MAX_SERVICE_RESOLUTION: u32 = 4096;

/// `POST /v1/jobs` body. Every field but `scene` has a default; unknown fields are rejected.
#[derive(Clone, Debug, Serialize, Deserialize, ToSchema, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct JobSpec {
    /// A scene id from `POST /v1/scenes`.
    pub scene: String,
    /// One of the engine's techniques (`path` today).
    #[serde(default = "default_technique")]
    #[schema(default = "path")]
    pub technique: String,
    /// Lightmap width and height in texels, 1 to 4096.
    #[serde(default = "default_resolution")]
    #[schema(default = 256)]
    pub resolution: u32,
    #[serde(default)]
    pub lighting: LightingSpec,
    /// When to stop. Absent: 4096 steps, 120 s or 2 % error, whichever comes first. Given:
    /// exactly the criteria given (at least one).
    #[serde(default = "default_stop")]
    pub stop: StopSpec,
    /// Technique parameters (a JSON object; the technique rejects unknown ones).
    #[serde(default)]
    #[schema(value_type = Object)]
    pub params: Value,
    /// Extra EXR layers: `validity`, `direct`, `indirect`, `sh`, `ao` (techniques that compute it),
    /// `debug`, `shadowmask`.
    #[serde(default)]
    pub outputs: Vec<String>,
    /// The `shadowmask` layer's lights, one per channel (R, G, B, A): `sun`, a light's name
    /// in the scene, or `#index`. Absent: the sun and the scene's lights, at most four.
    /// Their direct light is left out of the lightmap and `direct.*`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub shadowmask_lights: Vec<String>,
    /// Light probes to bake after the lightmap (radiance SH to L2, docs/probes.md); the
    /// job's `probes.json` artifact. Absent: none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub probes: Option<ProbeSpec>,
    /// Higher runs first; equal priorities run oldest first.
    #[serde(default)]
    pub priority: i32,
    #[serde(default)]
    pub seed: u64,
    /// Denoiser: `auto` (OIDN when installed, else the own filter), `oidn`, `own`,
    /// `none`. Absent: `auto`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(default = "auto")]
    pub denoise: Option<String>,
    /// Lightmap UVs: `keep` (authored `TEXCOORD_1` only; a scene with a mesh without it is
    /// refused), `generate-missing` (authored kept, the others generated) or
    /// `regenerate-all` or `repack-instances` (as `generate-missing`, and an authored mesh
    /// placed by several nodes gets a rectangle per node, its UVs kept). Absent:
    /// `generate-missing`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(default = "generate-missing")]
    pub lightmap_uvs: Option<String>,
    /// Texel density of generated lightmap UVs in texels per metre (more texels than fit
    /// one page make more pages). Absent: the highest density at which they fit one page.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub texels_per_unit: Option<f32>,
    /// At a `texels_per_unit`, the widest a page grows (from `resolution`, doubling) before
    /// the charts take several pages of this size; at least `resolution`. Absent: 4096 or
    /// `resolution` if larger, within the server's `max_resolution`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_page_size: Option<u32>,
    /// A succeeded job of the same scene, texel layout (resolution, `lightmap_uvs`,
    /// `texels_per_unit`, `max_page_size`) and light whose lightmap is this job's reference: every history
    /// point then carries `true_error`, the measured error against it, and the plan's
    /// `reference` says which job and how accurate that reference is (docs/accuracy.md).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reference: Option<String>,
    /// Bake tasks to split the job into, baked by several workers at once and merged
    /// exactly (issue 25, docs/scaling.md): 1 to 1024, for techniques whose table row
    /// allows it (`path`), with `stop.steps` and without `stop.target_error`. Absent or 1:
    /// one worker bakes the job whole.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tasks: Option<u32>,
    /// With `tasks`: the tasks are this many regions of the lightmap grid, each baked as
    /// `tasks / regions` ranges of the steps. Regions are whole pages when there are at
    /// most as many as pages (one page each when as many), else bands of rows with equal
    /// texel counts (tiles). Must divide `tasks`; absent or 1: every task bakes the
    /// whole grid. A bake task of region r over step range s is task r × (tasks /
    /// regions) + s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub regions: Option<u32>,
    /// With `regions` of 2 or more: the regions are baked in this many rounds (block
    /// Jacobi, `engine::rounds`, docs/scaling.md "Pages in rounds"), for techniques whose
    /// light in one region depends on every other's (`hemicube`). Each round has one bake
    /// task a region (`tasks`, when given, must equal `regions`), baking its share of
    /// `stop.steps` (doubling shares: the last round about half) with every other
    /// region's light held at the round before's estimate; round r's tasks are queued
    /// once every task of round r-1 has succeeded, and the merge reads the last round's.
    /// Bake task r × regions + p is region p's task of round r. Absent or 1: no rounds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rounds: Option<u32>,
    /// What a worker must have to take the job or its tasks; the job's `waiting_for` says
    /// when no live worker has it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub requires: Option<Requires>,
}

/// A job's requirements on the worker that runs it (issue 25 point 4).
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize, ToSchema, PartialEq, Eq)]
#[serde(deny_unknown_fields)]
pub struct Requires {
    /// A hardware GPU adapter (a software one, lavapipe, does not count).
    #[serde(default)]
    pub gpu: bool,
    /// Intel Open Image Denoise installed.
    #[serde(default)]
    pub oidn: bool,
}

#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize, ToSchema, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct LightingSpec {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sky: Option<SkySpec>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sun: Option<SunSpec>,
}

/// Uniform sky radiance (W/(sr·m²)).
#[derive(Clone, Copy, Debug, Serialize, Deserialize, ToSchema, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SkySpec {
    pub radiance: [f32; 3],
    #[serde(default)]
    pub hemisphere: HemisphereSpec,
}

#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize, ToSchema, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum HemisphereSpec {
    /// Directions with +Y > 0.
    #[default]
    Upper,
    Full,
}

#[derive(Clone, Copy, Debug, Serialize, Deserialize, ToSchema, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SunSpec {
    /// From the sun toward the scene.
    pub direction: [f32; 3],
    #[serde(default = "default_sun_diameter")]
    #[schema(default = 0.53)]
    pub angular_diameter_deg: f32,
    pub radiance: [f32; 3],
}

/// Where light probes go: a grid, given positions, and the scene's glTF nodes with
/// `extras.light_probe: true`, all together.
#[derive(Clone, Debug, Serialize, Deserialize, ToSchema, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ProbeSpec {
    /// Grid cell side in metres over the scene's bounds (a probe at each cell's centre).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub spacing: Option<f32>,
    /// Splits the grid's cells that geometry passes through into 8, this many levels down
    /// (0 to 4): denser probes near surfaces. Needs `spacing`.
    #[serde(default, skip_serializing_if = "is_zero")]
    #[schema(default = 0, maximum = 4)]
    pub subdivide: u32,
    /// Probe positions in the glTF's world coordinates.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub positions: Vec<[f64; 3]>,
    /// Steps of the probe bake, 64 samples a probe each (1 to 4096).
    #[serde(default = "default_probe_steps")]
    #[schema(default = 16)]
    pub steps: u32,
    /// Where the probes bake: `auto` (the GPU when the worker has a hardware adapter), `cpu`
    /// or `gpu`.
    #[serde(default)]
    pub device: ProbeDevice,
}

/// A probe bake's device (`probes.device`).
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize, ToSchema, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum ProbeDevice {
    #[default]
    Auto,
    Cpu,
    Gpu,
}

fn is_zero(v: &u32) -> bool {
    *v == 0
}

fn default_probe_steps() -> u32 {
    16
}

impl ProbeSpec {
    fn to_request(&self) -> crate::engine::job::ProbeRequest {
        crate::engine::job::ProbeRequest {
            spacing: self.spacing,
            subdivide: self.subdivide,
            positions: self.positions.clone(),
            steps: self.steps,
            device: match self.device {
                ProbeDevice::Auto => crate::engine::gpu::RayDevice::Auto,
                ProbeDevice::Cpu => crate::engine::gpu::RayDevice::Cpu,
                ProbeDevice::Gpu => crate::engine::gpu::RayDevice::Gpu,
            },
        }
    }
}

#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize, ToSchema, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct StopSpec {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub steps: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seconds: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target_error: Option<f32>,
}

fn default_technique() -> String {
    BakeRequest::default().technique
}

fn default_resolution() -> u32 {
    BakeRequest::default().resolution
}

fn default_stop() -> StopSpec {
    let s = BakeRequest::default().stop;
    StopSpec {
        steps: s.steps,
        seconds: s.seconds,
        target_error: s.target_error,
    }
}

fn default_sun_diameter() -> f32 {
    0.53
}

impl JobSpec {
    /// Parses a request body under the default limits.
    pub fn parse(body: &[u8]) -> Result<JobSpec, Problem> {
        JobSpec::parse_with(body, &Limits::default())
    }

    /// Parses a request body: malformed JSON is 400, anything else wrong (a range, a
    /// server limit) is 422 naming the field. A `stop` without `seconds` gets
    /// `limits.max_job_seconds`.
    pub fn parse_with(body: &[u8], limits: &Limits) -> Result<JobSpec, Problem> {
        let de = &mut serde_json::Deserializer::from_slice(body);
        let spec: JobSpec = serde_path_to_error::deserialize(de).map_err(|e| {
            let path = e.path().to_string();
            let inner = e.into_inner();
            if inner.is_syntax() || inner.is_eof() {
                return Problem::bad_request(format!("the body is not valid JSON: {inner}"));
            }
            let msg = inner.to_string();
            // serde names an unknown or missing field in its message, not in the path.
            let field = if let Some(name) = quoted_after(&msg, "unknown field `") {
                join_path(&path, &name)
            } else if let Some(name) = quoted_after(&msg, "missing field `") {
                join_path(&path, &name)
            } else {
                path
            };
            // serde's message carries its own position ("at line 1 column 40"), which is
            // noise next to the field name.
            let msg = match msg.rfind(" at line ") {
                Some(i) => msg[..i].to_string(),
                None => msg,
            };
            Problem::invalid_field(field, msg)
        })?;
        let mut spec = spec;
        spec.validate(limits)?;
        if spec.stop.seconds.is_none() {
            spec.stop.seconds = Some(limits.max_job_seconds);
        }
        // The engine's default page growth, within this server's largest lightmap side.
        let max_res = limits.max_resolution.min(crate::engine::atlas::MAX_RESOLUTION);
        if spec.max_page_size.is_none() && spec.to_request().max_page_size() > max_res {
            spec.max_page_size = Some(max_res);
        }
        Ok(spec)
    }

    /// The engine's ranges and the server's limits, each failure naming its field.
    pub fn validate(&self, limits: &Limits) -> Result<(), Problem> {
        if self.scene.trim().is_empty() {
            return Err(Problem::invalid_field("scene", "scene must be a scene id"));
        }
        if let Err(e) = technique::entry(&self.technique) {
            return Err(Problem::invalid_field("technique", e.to_string()));
        }
        let max_res = limits.max_resolution.min(crate::engine::atlas::MAX_RESOLUTION);
        if !(1..=max_res).contains(&self.resolution) {
            return Err(Problem::invalid_field(
                "resolution",
                format!("resolution must be between 1 and {max_res}, got {}", self.resolution),
            ));
        }
        for (i, o) in self.outputs.iter().enumerate() {
            OutputLayer::parse(o).map_err(|e| Problem::invalid_field(format!("outputs[{i}]"), e))?;
        }
        if let Some(d) = &self.denoise {
            let d = Denoiser::parse(d).map_err(|e| Problem::invalid_field("denoise", e))?;
            d.resolve().map_err(|e| Problem::invalid_field("denoise", e))?;
        }
        if let Some(m) = &self.lightmap_uvs {
            m.parse::<LightmapUvs>()
                .map_err(|e| Problem::invalid_field("lightmap_uvs", e))?;
        }
        if let Some(t) = self.texels_per_unit
            && !(t.is_finite() && t > 0.0)
        {
            return Err(Problem::invalid_field(
                "texels_per_unit",
                format!("texels_per_unit must be a positive number, got {t}"),
            ));
        }
        if let Some(m) = self.max_page_size {
            if m > max_res {
                return Err(Problem::invalid_field(
                    "max_page_size",
                    format!("max_page_size must be between 1 and {max_res}, got {m}"),
                ));
            }
            crate::engine::atlas::unwrap::check_page_sizes(self.resolution, m)
                .map_err(|e| Problem::invalid_field("max_page_size", e))?;
        }
        if !(self.params.is_null() || self.params.is_object()) {
            return Err(Problem::invalid_field("params", "params must be a JSON object"));
        }
        let request = self.to_request();
        if let Some(p) = &request.probes {
            p.validate().map_err(|m| Problem::invalid_field(leading_field(&m), m))?;
        }
        // The technique's parameters and layers against its table row, so a job it
        // cannot run is refused now rather than failing when it runs. The engine's
        // message starts with the field ("params.samples_per_step ...", "outputs[1]: ...").
        technique::check_request(&self.technique, &self.params, &request.outputs).map_err(|e| {
            let m = e.to_string();
            Problem::invalid_field(leading_field(&m), m)
        })?;
        // The engine's messages start with the field they are about ("stop.steps must
        // be ...", "lighting.sun.radiance must be ..."): that is the field we name.
        request
            .lighting
            .validate()
            .map_err(|m| Problem::invalid_field(leading_field(&m), m))?;
        request
            .stop
            .validate()
            .map_err(|e| Problem::invalid_field(leading_field(&e.to_string()), e.to_string()))?;
        if let Some(n) = self.stop.steps
            && n > limits.max_job_steps
        {
            return Err(Problem::invalid_field(
                "stop.steps",
                format!(
                    "stop.steps must be at most {} on this server (--max-job-steps), got {n}",
                    limits.max_job_steps
                ),
            ));
        }
        if self.rounds.is_some_and(|r| r > 1) {
            self.validate_rounds()?;
        } else if self.regions.is_some_and(|r| r > 1) && self.tasks.is_none_or(|n| n < 2) {
            return Err(Problem::invalid_field(
                "regions",
                "regions splits a job's tasks: give tasks too (a multiple of regions)",
            ));
        }
        if let Some(n) = self.tasks.filter(|_| self.rounds.is_none_or(|r| r < 2)) {
            let shape = crate::engine::tasks::TaskShape {
                tasks: n,
                regions: self.regions.unwrap_or(1),
            };
            // The engine's own split: it names why a technique or a stop rule cannot be
            // split ("regions: sdb bakes are split into independent chains …", "needs stop.steps").
            crate::engine::tasks::split(&request, shape).map_err(|e| {
                let m = e.to_string();
                let field = if m.starts_with("regions") { "regions" } else { "tasks" };
                Problem::invalid_field(field, m)
            })?;
            if n > 1 && self.reference.is_some() {
                return Err(Problem::invalid_field(
                    "reference",
                    "a job split into tasks has no reference curve (its history is the merge's one point); submit it with tasks absent or 1",
                ));
            }
        }
        if let Some(t) = self.stop.seconds
            && t > limits.max_job_seconds
        {
            return Err(Problem::invalid_field(
                "stop.seconds",
                format!(
                    "stop.seconds must be at most {} on this server (--max-job-seconds), got {t}",
                    limits.max_job_seconds
                ),
            ));
        }
        Ok(())
    }

    /// A job in rounds: at least two regions, one task a region, and a request the engine
    /// splits into rounds (`tasks::split_rounds` names why not: a technique not baked in
    /// rounds, a stop rule about the whole bake, too few steps).
    fn validate_rounds(&self) -> Result<(), Problem> {
        let regions = self.regions.unwrap_or(1);
        if regions < 2 {
            return Err(Problem::invalid_field(
                "rounds",
                "rounds bake a job's regions in turn: give regions too (2 or more)",
            ));
        }
        if self.tasks.is_some_and(|n| n != regions) {
            return Err(Problem::invalid_field(
                "tasks",
                format!(
                    "a job in rounds has one task a region in each round: give tasks equal to regions ({regions}) or leave it out, got {}",
                    self.tasks.unwrap_or(0)
                ),
            ));
        }
        if self.reference.is_some() {
            return Err(Problem::invalid_field(
                "reference",
                "a job split into tasks has no reference curve (its history is the merge's one point); submit it with tasks absent or 1",
            ));
        }
        let rounds = self.rounds.unwrap_or(1);
        if u64::from(regions) * u64::from(rounds) > u64::from(crate::engine::tasks::MAX_TASKS) {
            return Err(Problem::invalid_field(
                "rounds",
                format!(
                    "regions x rounds must be at most {} bake tasks, got {regions} x {rounds}",
                    crate::engine::tasks::MAX_TASKS
                ),
            ));
        }
        crate::engine::tasks::split_rounds(&self.to_request(), regions, rounds)
            .map_err(|e| Problem::invalid_field("rounds", e.to_string()))?;
        Ok(())
    }

    /// How the job is split into tasks, when it is (`tasks` of 2 or more) and not in
    /// rounds ([`JobSpec::task_ranges`] covers both).
    pub fn task_shape(&self) -> Option<crate::engine::tasks::TaskShape> {
        if self.in_rounds() {
            return None;
        }
        self.tasks
            .filter(|n| *n > 1)
            .map(|tasks| crate::engine::tasks::TaskShape {
                tasks,
                regions: self.regions.unwrap_or(1),
            })
    }

    /// Whether the job's regions are baked in rounds (`rounds` of 2 or more).
    pub fn in_rounds(&self) -> bool {
        self.rounds.is_some_and(|r| r > 1)
    }

    /// The job's bake tasks in the queue (the merge is one more), or 0 when one worker
    /// bakes it whole: `tasks`, or in rounds `regions` × `rounds`.
    pub fn bake_tasks(&self) -> u32 {
        if self.in_rounds() {
            self.regions.unwrap_or(1) * self.rounds.unwrap_or(1)
        } else {
            self.tasks.filter(|n| *n > 1).unwrap_or(0)
        }
    }

    /// The bake tasks queued when the job is submitted: all of them, or in rounds round
    /// 0's (the others wait for the round before, `queue::round_after`).
    pub fn first_queued(&self) -> u32 {
        if self.in_rounds() {
            self.regions.unwrap_or(1)
        } else {
            self.bake_tasks()
        }
    }

    /// The request a bake task of this job bakes: [`JobSpec::to_request`], except that a
    /// job in rounds drops `stop.seconds`. A submitted `stop.seconds` is refused for a job
    /// in rounds (no round sees the whole bake's time); the one left is the server's
    /// `--max-job-seconds` that [`JobSpec::parse`] fills in, and rounds are bounded by
    /// `stop.steps` (at most `--max-job-steps`) instead.
    pub fn task_request(&self) -> BakeRequest {
        let mut request = self.to_request();
        if self.in_rounds() {
            request.stop.seconds = None;
        }
        request
    }

    /// Every bake task's range, in queue order (index k is bake task k): the engine's
    /// split, or in rounds its rounds one after another (task r × regions + p is region
    /// p of round r).
    pub fn task_ranges(&self) -> Result<Vec<crate::engine::tasks::TaskRange>, crate::engine::technique::EngineError> {
        if self.in_rounds() {
            let rounds = crate::engine::tasks::split_rounds(
                &self.task_request(),
                self.regions.unwrap_or(1),
                self.rounds.unwrap_or(1),
            )?;
            return Ok(rounds.into_iter().flatten().collect());
        }
        match self.task_shape() {
            Some(shape) => crate::engine::tasks::split(&self.to_request(), shape),
            None => Ok(Vec::new()),
        }
    }

    /// The engine's request for this job.
    pub fn to_request(&self) -> BakeRequest {
        let lighting = Lighting {
            sky: self.lighting.sky.map(|s| Sky {
                radiance: Vec3::from_array(s.radiance),
                hemisphere: match s.hemisphere {
                    HemisphereSpec::Upper => Hemisphere::Upper,
                    HemisphereSpec::Full => Hemisphere::Full,
                },
            }),
            sun: self.lighting.sun.map(|s| {
                let d = Vec3::from_array(s.direction);
                Sun {
                    // A zero or non-finite direction stays as it is, so validation names it.
                    direction: if d.length() > 1e-6 && d.is_finite() {
                        d.normalize()
                    } else {
                        d
                    },
                    angular_diameter: s.angular_diameter_deg.to_radians(),
                    radiance: Vec3::from_array(s.radiance),
                }
            }),
        };
        BakeRequest {
            technique: self.technique.clone(),
            resolution: self.resolution,
            lighting,
            stop: StopCriteria {
                steps: self.stop.steps,
                seconds: self.stop.seconds,
                target_error: self.stop.target_error,
            },
            params: self.params.clone(),
            outputs: self.outputs.iter().filter_map(|o| OutputLayer::parse(o).ok()).collect(),
            seed: self.seed,
            denoise: self
                .denoise
                .as_deref()
                .and_then(|d| Denoiser::parse(d).ok())
                .unwrap_or_default(),
            lightmap_uvs: self
                .lightmap_uvs
                .as_deref()
                .and_then(|m| m.parse().ok())
                .unwrap_or_default(),
            texels_per_unit: self.texels_per_unit,
            max_page_size: self.max_page_size,
            shadowmask_lights: self.shadowmask_lights.clone(),
            probes: self.probes.as_ref().map(ProbeSpec::to_request),
        }
    }
}

fn quoted_after(msg: &str, marker: &str) -> Option<String> {
    let start = msg.find(marker)? + marker.len();
    let end = msg[start..].find('`')?;
    Some(msg[start..start + end].to_string())
}

fn join_path(path: &str, name: &str) -> String {
    if path.is_empty() || path == "." {
        name.to_string()
    } else {
        // For an unknown field serde_path_to_error's path already ends at it.
        if path.ends_with(name) {
            path.to_string()
        } else {
            format!("{path}.{name}")
        }
    }
}

fn leading_field(msg: &str) -> String {
    msg.split_whitespace()
        .next()
        .unwrap_or("")
        .trim_end_matches(':')
        .to_string()
}

/// The job against the job it names as its `reference` (`id`, with that job's record if
/// the caller may see it): a succeeded bake of the same scene, texel layout and light,
/// so both lightmaps are estimates of one answer on one texel grid. Each refusal names
/// `reference` and the first thing that differs.
pub fn check_reference(spec: &JobSpec, id: &str, reference: Option<(&JobSpec, JobStatus)>) -> Result<(), Problem> {
    let refuse = |why: String| Err(Problem::invalid_field("reference", why));
    let Some((r, status)) = reference else {
        return refuse(format!(
            "no job with id {id:?}: a reference is one of your succeeded jobs"
        ));
    };
    if status != JobStatus::Succeeded {
        return refuse(format!(
            "job {id} is {}: a reference must be a succeeded job",
            status.as_str()
        ));
    }
    if r.scene != spec.scene {
        return refuse(format!(
            "job {id} baked scene {}, this job bakes scene {}: a reference must bake the same scene",
            r.scene, spec.scene
        ));
    }
    let uvs = |s: &JobSpec| s.lightmap_uvs.clone().unwrap_or_else(|| "generate-missing".into());
    let differs: Option<(&str, String, String)> = if r.resolution != spec.resolution {
        Some(("resolution", r.resolution.to_string(), spec.resolution.to_string()))
    } else if uvs(r) != uvs(spec) {
        Some(("lightmap_uvs", uvs(r), uvs(spec)))
    } else if r.texels_per_unit != spec.texels_per_unit {
        let d = |v: Option<f32>| v.map_or("the default".to_string(), |v| v.to_string());
        Some(("texels_per_unit", d(r.texels_per_unit), d(spec.texels_per_unit)))
    } else if r.to_request().max_page_size() != spec.to_request().max_page_size() {
        let m = |s: &JobSpec| s.to_request().max_page_size().to_string();
        Some(("max_page_size", m(r), m(spec)))
    } else if r.lighting != spec.lighting {
        let j = |s: &JobSpec| serde_json::to_string(&s.lighting).unwrap_or_default();
        Some(("lighting", j(r), j(spec)))
    } else {
        let mask = |s: &JobSpec| {
            s.outputs
                .iter()
                .any(|o| o == "shadowmask")
                .then(|| s.shadowmask_lights.clone())
        };
        (mask(r) != mask(spec)).then(|| {
            let d = |m: Option<Vec<String>>| match m {
                None => "no shadowmask".to_string(),
                Some(l) if l.is_empty() => "a shadowmask of the default lights".to_string(),
                Some(l) => format!("a shadowmask of {}", l.join(", ")),
            };
            ("outputs", d(mask(r)), d(mask(spec)))
        })
    };
    match differs {
        Some((field, theirs, ours)) => refuse(format!(
            "job {id} has {field} {theirs}, this job {ours}: a reference must bake the same texel grid and light"
        )),
        None => Ok(()),
    }
}

/// The light a job will bake with, read off its scene's import report: the scene's
/// emitters and punctual lights and the job's sky and sun. The flag says whether the
/// report counts the punctual lights: one stored before it counted directional lights
/// reads as having none, and leaves them to the bake's own check.
fn light_features(report: &Value, spec: &JobSpec) -> (crate::engine::plan::SceneFeatures, bool) {
    let count = |k: &str| report.get(k).and_then(Value::as_u64).map(|n| n as usize);
    let lighting = spec.to_request().lighting;
    let (punctual_lights, directional_lights, counted) = match count("directional_lights") {
        Some(d) => (count("lights").unwrap_or(0), d, true),
        None => (0, 0, false),
    };
    let features = crate::engine::plan::SceneFeatures {
        punctual_lights,
        directional_lights,
        emissive_triangles: count("emissive_triangles").unwrap_or(0),
        sky: lighting.sky.is_some_and(|s| s.radiance != glam::Vec3::ZERO),
        sun: lighting.sun.is_some_and(|s| s.radiance != glam::Vec3::ZERO),
        ..Default::default()
    };
    (features, counted)
}

/// What the submitter is told with a job that is accepted (`JobCreated::warnings`): a bake
/// with no light at all, which is not refused (an exact zero is a correct answer, and an
/// `ao` layer needs no light) but is almost always a level exported without its lights or
/// a job without its sky, which a user should learn at submit rather than from a black
/// lightmap; and a sun too faint to matter beside the sky (`Lighting::faint_sun`).
pub fn job_warnings(report: &Value, spec: &JobSpec) -> Vec<String> {
    let (features, counted) = light_features(report, spec);
    let mut warnings = Vec::new();
    if counted && !features.has_light() {
        warnings.push(
            "the scene has no emissive surface or punctual light and the job no lighting.sky or lighting.sun: the lightmap will be exactly zero (give lighting.sky for a uniform sky; `lightmapd submit` takes it as --sky R,G,B)"
                .to_string(),
        );
    }
    warnings.extend(spec.to_request().lighting.faint_sun());
    warnings
}

/// The job against its stored scene (read off the scene's import report), at submit: the
/// scene's and the job's light against the technique's table row (light the technique
/// does not transport is refused, naming `lighting.sun`, or `technique` for the scene's
/// own lights), `lightmap_uvs: keep` against a scene with meshes without UVs, and probes
/// that have nowhere to go. The bake checks the scene itself again before it starts.
pub fn check_against_scene(report: &Value, spec: &JobSpec) -> Result<(), Problem> {
    let lighting = spec.to_request().lighting;
    let (features, _) = light_features(report, spec);
    technique::check_lights(&spec.technique, &features).map_err(|e| {
        let m = e.to_string();
        Problem::invalid_field(leading_field(&m), m)
    })?;
    // `keep` bakes authored UVs only: a scene with a mesh without them cannot bake.
    if spec.to_request().lightmap_uvs == LightmapUvs::Keep
        && report.get("has_lightmap_uvs").and_then(Value::as_bool) == Some(false)
    {
        return Err(Problem::invalid_field(
            "lightmap_uvs",
            "lightmap_uvs is keep, and the scene has meshes without TEXCOORD_1 (its report's warnings name them): use generate-missing",
        ));
    }
    // Probes need somewhere to go: a grid, positions, or the scene's probe nodes.
    if let Some(p) = &spec.probes
        && p.spacing.is_none()
        && p.positions.is_empty()
        && report.get("probe_nodes").and_then(Value::as_u64) == Some(0)
    {
        return Err(Problem::invalid_field(
            "probes",
            "probes: no position: give probes.spacing or probes.positions, or mark glTF nodes with extras.light_probe = true",
        ));
    }
    // The shadowmask's lights against the scene's, by name; a report stored before it
    // listed light names leaves the names to the bake's own check.
    if let Some(names) = report.get("light_names").and_then(Value::as_array) {
        let names: Vec<String> = names.iter().filter_map(|n| n.as_str().map(str::to_string)).collect();
        let request = spec.to_request();
        crate::engine::shadowmask::resolve(
            &request.outputs,
            &request.shadowmask_lights,
            &names,
            lighting.sun.is_some(),
        )
        .map_err(|m| Problem::invalid_field(leading_field(&m), m))?;
    }
    Ok(())
}

/// A job's lifecycle (DESIGN §7).
#[derive(Clone, Copy, Debug, Serialize, Deserialize, ToSchema, PartialEq, Eq, Hash)]
#[serde(rename_all = "snake_case")]
pub enum JobStatus {
    Queued,
    Running,
    Succeeded,
    Failed,
    Cancelled,
}

impl JobStatus {
    pub const ALL: [JobStatus; 5] = [
        JobStatus::Queued,
        JobStatus::Running,
        JobStatus::Succeeded,
        JobStatus::Failed,
        JobStatus::Cancelled,
    ];

    pub fn as_str(self) -> &'static str {
        match self {
            JobStatus::Queued => "queued",
            JobStatus::Running => "running",
            JobStatus::Succeeded => "succeeded",
            JobStatus::Failed => "failed",
            JobStatus::Cancelled => "cancelled",
        }
    }

    pub fn parse(s: &str) -> Option<JobStatus> {
        JobStatus::ALL.into_iter().find(|j| j.as_str() == s)
    }

    pub fn is_terminal(self) -> bool {
        matches!(self, JobStatus::Succeeded | JobStatus::Failed | JobStatus::Cancelled)
    }
}

/// Where a running bake is.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize, ToSchema, PartialEq)]
pub struct Progress {
    pub steps: u64,
    /// 0 to 1: the furthest of steps, time and error toward their stop criteria.
    pub fraction: f64,
    pub elapsed_s: f64,
    /// The estimated relative error at the latest snapshot.
    #[serde(default)]
    pub error: Option<f32>,
    /// Light probes baked after the lightmap, once they have started.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub probes: Option<ProbeProgress>,
    /// 0 to 1: how far the step after `steps` is, while one runs, for techniques that
    /// report it (CPU `path`, whose steps can take minutes on a large level); absent
    /// otherwise. `fraction` and `elapsed_s` move with it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub step_fraction: Option<f64>,
}

/// How far the light probes of a job are (`probes` in the job; docs/probes.md).
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize, ToSchema, PartialEq)]
pub struct ProbeProgress {
    /// Probe steps done (64 samples a probe each).
    pub steps: u32,
    /// Probe steps asked for.
    pub of: u32,
    /// Probes placed (valid and invalid).
    pub probes: usize,
}

impl Progress {
    pub fn new(steps: u64, elapsed_s: f64, error: Option<f32>, stop: &StopSpec) -> Progress {
        let mut f: f64 = 0.0;
        if let Some(n) = stop.steps {
            f = f.max(steps as f64 / n as f64);
        }
        if let Some(s) = stop.seconds {
            f = f.max(elapsed_s / s);
        }
        // The error falls as 1/sqrt(steps), so (target / error)² tracks the work done.
        if let (Some(t), Some(e)) = (stop.target_error, error)
            && e > 0.0
        {
            f = f.max(((t / e) as f64).powi(2));
        }
        Progress {
            steps,
            fraction: f.clamp(0.0, 1.0),
            elapsed_s,
            error,
            probes: None,
            step_fraction: None,
        }
    }

    /// This progress carried on to `elapsed_s` seconds into the bake loop and `within`
    /// (0 to 1) of the way through the step after `steps`: what a watcher is told while
    /// one long step runs.
    pub fn within_step(self, elapsed_s: f64, within: f64, stop: &StopSpec) -> Progress {
        let within = within.clamp(0.0, 1.0);
        let mut p = Progress::new(self.steps, elapsed_s.max(self.elapsed_s), self.error, stop);
        if let Some(n) = stop.steps.filter(|n| *n > 0) {
            p.fraction = p.fraction.max(((self.steps as f64 + within) / n as f64).min(1.0));
        }
        p.probes = self.probes;
        p.step_fraction = Some(within);
        p
    }
}

/// One point of a bake's error against time: one per stored snapshot, and the final
/// lightmap's last.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, ToSchema, PartialEq)]
pub struct HistoryPoint {
    pub seconds: f64,
    pub steps: u64,
    /// The relative error of the lightmap as delivered at that point (the snapshot EXR's
    /// `lightmapd:relative_error`: denoised and blended when a denoiser runs; for a biased
    /// technique, bias and noise measured at control texels; `docs/accuracy.md`). A job
    /// split into tasks: its running snapshots' points are the same; before its first,
    /// its points hold the tasks' raw estimates merged (`queue::running_history`), here
    /// and in `raw_error`; `seconds` is the wall time since it started.
    pub error: Option<f32>,
    /// The raw estimate's, before denoising (what `stop.target_error` is checked against).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub raw_error: Option<f32>,
    /// Its noise part (the halves' difference), when `error` covers bias too.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise: Option<f32>,
    /// Its bias part, measured at control texels against `path`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bias: Option<f32>,
    /// With a `reference` job: the delivered lightmap's relative error measured against
    /// the reference's (`docs/accuracy.md`'s metric; it cannot read much below the
    /// reference's own error, `plan.reference.error`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub true_error: Option<f32>,
}

/// `GET /v1/jobs/{id}`.
#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct JobView {
    pub id: String,
    pub status: JobStatus,
    pub scene: String,
    /// The job body with defaults filled in.
    pub spec: JobSpec,
    pub priority: i32,
    /// How many times a worker has taken the job up (a graceful shutdown does not count).
    pub attempts: u32,
    /// The worker holding the lease while running.
    pub worker: Option<String>,
    pub created_at: String,
    pub started_at: Option<String>,
    pub finished_at: Option<String>,
    pub progress: Option<Progress>,
    /// What the bake runs: technique, resolution, texel set, layers.
    #[schema(value_type = Object)]
    pub plan: Option<Value>,
    pub history: Vec<HistoryPoint>,
    /// Snapshots stored so far (`?snapshot=1..=snapshots`).
    pub snapshots: u32,
    /// The engine's summary of a finished bake (steps, seconds, error, stop reason).
    #[schema(value_type = Object)]
    pub summary: Option<Value>,
    /// Why the job failed.
    pub failure: Option<String>,
    pub cancel_requested: bool,
    /// A job split into tasks: each task's state (issue 25).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tasks: Option<TasksView>,
    /// Why nobody takes the queued job (or its queued tasks): no live worker meets its
    /// `requires`, or every one that does is blocklisted for it. Absent when it just
    /// waits its turn.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub waiting_for: Option<String>,
}

/// A split job's tasks.
#[derive(Clone, Debug, Serialize, Deserialize, ToSchema, PartialEq)]
pub struct TasksView {
    /// Bake tasks (the merge is one more, last in `list`).
    pub count: u32,
    /// Regions of the grid the bake tasks are cut into (1: each bakes the whole grid).
    pub regions: u32,
    /// Rounds the regions are baked in (`JobSpec::rounds`); absent when not in rounds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rounds: Option<u32>,
    pub list: Vec<TaskView>,
    /// Workers that take no more of this job's tasks, with their failed attempts.
    pub blocklisted: Vec<BlocklistEntry>,
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema, PartialEq)]
pub struct BlocklistEntry {
    pub worker: String,
    pub failures: u32,
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema, PartialEq)]
pub struct TaskView {
    pub index: u32,
    /// `bake` (a range of the job's steps of one region) or `merge`.
    pub kind: String,
    /// A bake task's region of the grid (`TasksView.regions`).
    pub region: Option<u32>,
    /// A bake task's round (0-based; `TasksView.rounds`), when the job is in rounds: it
    /// is `waiting` until every task of the round before has succeeded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub round: Option<u32>,
    /// A bake task's steps of the job, `[first, end)`; a chain's start at 0.
    pub step_range: Option<[u64; 2]>,
    /// The seed of a bake task that is an independent chain (every technique but
    /// `path`: the whole grid baked with its own seed, `engine::tasks`); absent for
    /// `path`'s step ranges, which share the job's.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub chain_seed: Option<u64>,
    pub status: crate::service::queue::TaskStatus,
    pub attempts: u32,
    pub worker: Option<String>,
    /// Steps its current (or last) attempt baked.
    pub steps: u64,
    pub seconds: f64,
    /// Its own relative error estimate.
    pub error: Option<f32>,
    pub failure: Option<String>,
    /// Wall time of its current (or last) attempt, from its claim to its end (so far,
    /// while it runs): the merge's includes reading the results and storing the lightmap.
    pub wall_s: Option<f64>,
}

/// `GET /v1/jobs`.
#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct JobList {
    pub jobs: Vec<JobView>,
    /// Jobs matching the filter, over all pages.
    pub total: u64,
    pub limit: u32,
    pub offset: u64,
}

/// `POST /v1/jobs` response.
#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct JobCreated {
    pub id: String,
    pub status: JobStatus,
    /// What the job will bake that is accepted but probably not meant (today: no light at
    /// all, so an exactly zero lightmap). Absent when there is nothing to say.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
}

/// `POST /v1/scenes`, `GET /v1/scenes/{id}`.
#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct SceneView {
    pub id: String,
    /// `sha256:` and the hex digest of the uploaded bytes.
    pub content_hash: String,
    /// `glb` or `gltf`.
    pub format: String,
    pub files: Vec<String>,
    pub size_bytes: u64,
    /// The importer's report: counts, bounds, whether every mesh has lightmap UVs
    /// (`has_lightmap_uvs`), warnings.
    #[schema(value_type = Object)]
    pub report: Value,
    pub created_at: String,
}

/// `GET /healthz`.
#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct Health {
    pub status: String,
    pub version: String,
    pub workers: usize,
}

/// The file name a relative glTF URI names: percent-decoded (`quad%20data.bin` is the
/// file `quad data.bin`), as the importer reads it.
pub fn uri_file_name(uri: &str) -> String {
    let b = uri.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        let hex = |c: u8| (c as char).to_digit(16);
        if b[i] == b'%'
            && i + 2 < b.len()
            && let (Some(h), Some(l)) = (hex(b[i + 1]), hex(b[i + 2]))
        {
            out.push((h * 16 + l) as u8);
            i += 3;
        } else {
            out.push(b[i]);
            i += 1;
        }
    }
    String::from_utf8_lossy(&out).into_owned()
}

/// Unix milliseconds as RFC 3339 UTC (`2026-11-01T12:00:00.000Z`).
pub fn rfc3339(ms: i64) -> String {
    let secs = ms.div_euclid(1000);
    let millis = ms.rem_euclid(1000);
    let days = secs.div_euclid(86_400);
    let rem = secs.rem_euclid(86_400);
    // Howard Hinnant's days-to-civil.
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02}T{:02}:{:02}:{:02}.{millis:03}Z",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60
    )
}

#[cfg(test)]
mod tests {

    use super::*;
    use serde_json::json;

    #[test]
    fn a_reference_must_be_a_succeeded_bake_of_the_same_grid_and_light() {
        let spec = |v: Value| JobSpec::parse_with(v.to_string().as_bytes(), &Limits::default()).unwrap();
        let ours = spec(json!({"scene": "s1", "resolution": 64, "outputs": ["shadowmask"]}));
        let detail = |r: Result<(), Problem>| r.unwrap_err().detail;
        assert!(check_reference(&ours, "r", Some((&ours, JobStatus::Succeeded))).is_ok());
        assert_eq!(
            detail(check_reference(&ours, "r", None)),
            "no job with id \"r\": a reference is one of your succeeded jobs"
        );
        assert_eq!(
            detail(check_reference(&ours, "r", Some((&ours, JobStatus::Running)))),
            "job r is running: a reference must be a succeeded job"
        );
        let theirs = spec(json!({"scene": "s2", "resolution": 64, "outputs": ["shadowmask"]}));
        assert_eq!(
            detail(check_reference(&ours, "r", Some((&theirs, JobStatus::Succeeded)))),
            "job r baked scene s2, this job bakes scene s1: a reference must bake the same scene"
        );
        let theirs =
            spec(json!({"scene": "s1", "resolution": 64, "lightmap_uvs": "regenerate-all", "outputs": ["shadowmask"]}));
        assert_eq!(
            detail(check_reference(&ours, "r", Some((&theirs, JobStatus::Succeeded)))),
            "job r has lightmap_uvs regenerate-all, this job generate-missing: a reference must bake the same texel grid and light"
        );
        let theirs = spec(json!({"scene": "s1", "resolution": 64, "texels_per_unit": 8.0, "outputs": ["shadowmask"]}));
        assert_eq!(
            detail(check_reference(&ours, "r", Some((&theirs, JobStatus::Succeeded)))),
            "job r has texels_per_unit 8, this job the default: a reference must bake the same texel grid and light"
        );
        let theirs = spec(json!({"scene": "s1", "resolution": 64, "max_page_size": 1024, "outputs": ["shadowmask"]}));
        assert_eq!(
            detail(check_reference(&ours, "r", Some((&theirs, JobStatus::Succeeded)))),
            "job r has max_page_size 1024, this job 4096: a reference must bake the same texel grid and light"
        );
        // A shadowmask takes its lights out of the lightmap: with and without differ.
        let theirs = spec(json!({"scene": "s1", "resolution": 64}));
        assert_eq!(
            detail(check_reference(&ours, "r", Some((&theirs, JobStatus::Succeeded)))),
            "job r has outputs no shadowmask, this job a shadowmask of the default lights: a reference must bake the same texel grid and light"
        );
        // What does not change the answer may differ: technique, steps, seed, denoiser.
        let theirs = spec(
            json!({"scene": "s1", "resolution": 64, "outputs": ["shadowmask", "direct"], "technique": "sdb",
            "seed": 7, "stop": {"steps": 9}, "denoise": "none"}),
        );
        assert!(check_reference(&ours, "r", Some((&theirs, JobStatus::Succeeded))).is_ok());
    }

    #[test]
    fn progress_within_a_step_moves_fraction_and_time_on() {
        let by_steps = StopSpec {
            steps: Some(4),
            ..Default::default()
        };
        let p = Progress::new(1, 2.0, Some(0.1), &by_steps);
        assert_eq!(p.fraction, 0.25);
        let q = p.within_step(3.0, 0.5, &by_steps);
        assert_eq!(
            (q.steps, q.fraction, q.elapsed_s, q.error, q.step_fraction),
            (1, 0.375, 3.0, Some(0.1), Some(0.5))
        );
        // Time never goes back; the step's share is clamped to a step.
        let r = p.within_step(1.0, 7.0, &by_steps);
        assert_eq!((r.fraction, r.elapsed_s, r.step_fraction), (0.5, 2.0, Some(1.0)));
        // A time limit: the fraction follows the clock, which runs during the step.
        let by_time = StopSpec {
            seconds: Some(10.0),
            ..Default::default()
        };
        let t = Progress::new(0, 0.0, None, &by_time).within_step(4.0, 0.9, &by_time);
        assert_eq!((t.fraction, t.step_fraction), (0.4, Some(0.9)));
    }

    #[test]
    fn uri_file_names_are_percent_decoded() {
        assert_eq!(uri_file_name("quad%20data.bin"), "quad data.bin");
        assert_eq!(uri_file_name("plain.bin"), "plain.bin");
        assert_eq!(uri_file_name("odd%2"), "odd%2");
    }

    #[test]
    fn rfc3339_known_dates() {
        assert_eq!(rfc3339(0), "1970-01-01T00:00:00.000Z");
        assert_eq!(rfc3339(951_782_400_123), "2000-02-29T00:00:00.123Z");
        assert_eq!(rfc3339(1_793_534_400_000), "2026-11-01T12:00:00.000Z");
    }

    #[test]
    fn defaults_fill_every_field_but_scene() {
        let s = JobSpec::parse(br#"{"scene": "s1"}"#).unwrap();
        assert_eq!(s.technique, "path");
        assert_eq!(s.resolution, 256);
        assert_eq!(s.stop.steps, Some(4096));
        assert_eq!(s.priority, 0);
    }

    #[test]
    fn server_limits_cap_the_budget_and_fill_in_seconds() {
        let limits = Limits {
            max_job_steps: 100,
            max_job_seconds: 10.0,
            max_resolution: 64,
            ..Limits::default()
        };
        let parse = |b: &str| JobSpec::parse_with(b.as_bytes(), &limits);
        let s = parse(r#"{"scene":"a","resolution":64,"stop":{"steps":100}}"#).unwrap();
        assert_eq!((s.stop.steps, s.stop.seconds), (Some(100), Some(10.0)));
        let s = parse(r#"{"scene":"a","resolution":8,"stop":{"target_error":0.1,"seconds":2}}"#).unwrap();
        assert_eq!(s.stop.seconds, Some(2.0));
        for (body, field) in [
            (r#"{"scene":"a","resolution":8,"stop":{"steps":101}}"#, "stop.steps"),
            (
                r#"{"scene":"a","resolution":8,"stop":{"seconds":10.5}}"#,
                "stop.seconds",
            ),
            (r#"{"scene":"a","resolution":65}"#, "resolution"),
        ] {
            let p = parse(body).unwrap_err();
            assert_eq!((p.status, p.field.as_deref()), (422, Some(field)), "{body}");
        }
    }

    #[test]
    fn errors_name_the_field() {
        let field = |body: &str| JobSpec::parse(body.as_bytes()).unwrap_err().field;
        assert_eq!(field(r#"{}"#).as_deref(), Some("scene"));
        assert_eq!(field(r#"{"scene":"a","colour":1}"#).as_deref(), Some("colour"));
        assert_eq!(
            field(r#"{"scene":"a","stop":{"steps":-1}}"#).as_deref(),
            Some("stop.steps")
        );
        assert_eq!(field(r#"{"scene":"a","stop":{"spp":1}}"#).as_deref(), Some("stop.spp"));
        assert_eq!(
            field(r#"{"scene":"a","stop":{"seconds":-1}}"#).as_deref(),
            Some("stop.seconds")
        );
        assert_eq!(field(r#"{"scene":"a","stop":{}}"#).as_deref(), Some("stop"));
        assert_eq!(field(r#"{"scene":"a","resolution":0}"#).as_deref(), Some("resolution"));
        assert_eq!(field(r#"{"scene":"a","technique":"x"}"#).as_deref(), Some("technique"));
        assert_eq!(
            field(r#"{"scene":"a","outputs":["bent_normals"]}"#).as_deref(),
            Some("outputs[0]")
        );
        assert_eq!(
            field(r#"{"scene":"a","lighting":{"sky":{"radiance":[-1,0,0]}}}"#).as_deref(),
            Some("lighting.sky.radiance")
        );
        assert_eq!(
            field(r#"{"scene":"a","lighting":{"sun":{"direction":[0,-1,0],"radiance":[1,1,1],"x":1}}}"#).as_deref(),
            Some("lighting.sun.x")
        );
        assert_eq!(JobSpec::parse(b"{").unwrap_err().status, 400);
    }
}
