//! `obscurance`'s incremental update (obscurances seed, section 5): what a finished bake
//! saves ([`ObscuranceState`], `--save-state`), and a new bake of a changed scene that
//! recomputes only the texels whose rays met a moved or added mesh
//! ([`Obscurance::update`], `--update-from`), copying every other texel's accumulators.
//! The influence masks it reads are written by the gather pass (module doc of
//! `obscurance`); [`UpdateReach`] chooses between any distance and dmax.

use glam::Vec3;
use serde::{Deserialize, Serialize};

use super::{MASK_BASE, Obscurance, ObscuranceParams};
use crate::engine::scene::Lighting;
use crate::engine::technique::api::{BakeInputs, EngineError, gpu_error};

/// Everything a finished bake leaves for an incremental update.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ObscuranceState {
    pub width: u32,
    pub height: u32,
    pub seed: u64,
    pub params: ObscuranceParams,
    pub half_steps: [u64; 2],
    pub dirs: [u64; 2],
    /// Lightmap pixel of each valid texel (the texel order of the arrays below).
    pub pixels: Vec<u32>,
    /// The accumulators as the GPU keeps them: for each of two regions (numerators;
    /// weight or sun), both halves (even then odd), texel order.
    pub acc: Vec<[f32; 4]>,
    pub direct: Vec<[f32; 4]>,
    /// Influence mask per texel: bit 16 + (mesh index mod 16) of every mesh a ray hit,
    /// bit (mesh index mod 16) of every mesh hit within dmax.
    pub masks: Vec<u32>,
    /// Mesh names by index when the state was saved.
    pub meshes: Vec<String>,
    /// The job's sky and sun: an update under other lighting would leave the texels it
    /// does not recompute lit by the old one, so it is refused.
    pub lighting: Lighting,
}

impl ObscuranceState {
    pub fn steps(&self) -> u64 {
        self.half_steps[0] + self.half_steps[1]
    }
}

/// Which recorded influence an incremental update follows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum UpdateReach {
    /// Texels whose rays hit a changed mesh at any distance (obscurance and direct light).
    #[default]
    All,
    /// Texels whose rays hit it within dmax (the obscurance it influenced: seed section 5).
    Dmax,
}

/// What an incremental update recomputes.
#[derive(Debug, Clone, Serialize)]
pub struct UpdateReport {
    pub recomputed_texels: usize,
    pub total_texels: usize,
    /// Steps to run (the finished bake's count) for the recomputed texels to match.
    pub steps: u64,
}

impl Obscurance {
    /// Saves what an incremental update needs (reads back; call after the last step).
    pub fn state(&self) -> Result<ObscuranceState, EngineError> {
        let n = self.n_texels as usize;
        let acc = self
            .ctx
            .read_buffer("obscurance accumulators", &self.acc_buf, 4 * n)
            .map_err(gpu_error)?;
        let direct = self
            .ctx
            .read_buffer("obscurance direct accumulators", &self.direct_acc_buf, 4 * n)
            .map_err(gpu_error)?;
        let counters: Vec<u32> = self
            .ctx
            .read_buffer("obscurance influence masks", &self.counters_buf, MASK_BASE + n)
            .map_err(gpu_error)?;
        let (width, height) = self.dims();
        Ok(ObscuranceState {
            width,
            height,
            seed: self.seed,
            params: self.params.clone(),
            half_steps: self.half_steps,
            dirs: self.dirs,
            pixels: self.texel_pixels.clone(),
            acc,
            direct,
            masks: counters[MASK_BASE..].to_vec(),
            meshes: self.mesh_names.clone(),
            lighting: self.lighting,
        })
    }

    /// Prepares an incremental update of the bake `previous` (seed section 5) for the
    /// scene in `inputs`, where the meshes named in `changed` moved or were added: only
    /// the texels they influenced are recomputed (see the module doc for the set). Run
    /// [`UpdateReport::steps`] steps, then snapshot as usual.
    pub fn update(
        inputs: BakeInputs,
        previous: &ObscuranceState,
        changed: &[String],
        reach: UpdateReach,
    ) -> Result<(Self, UpdateReport), EngineError> {
        let bad = |m: String| EngineError::BadInput(format!("incremental obscurance update: {m}"));
        if (inputs.atlas.width, inputs.atlas.height) != (previous.width, previous.height) {
            return Err(bad(format!(
                "the lightmap is {}x{} but the finished bake's was {}x{}",
                inputs.atlas.width, inputs.atlas.height, previous.width, previous.height
            )));
        }
        if inputs.lighting != previous.lighting {
            return Err(bad(
                "the job's lighting (sky, sun) differs from the finished bake's: texels that are not recomputed \
                 would keep the old light; bake from scratch"
                    .into(),
            ));
        }
        let n_old = previous.pixels.len();
        if previous.acc.len() != 4 * n_old || previous.direct.len() != 4 * n_old || previous.masks.len() != n_old {
            return Err(bad("the saved state is inconsistent (array lengths differ)".into()));
        }
        let scene = inputs.scene.clone();
        let atlas = inputs.atlas.clone();
        let mut old_bits = 0u32;
        let mut new_meshes = Vec::new();
        for name in changed {
            let new = scene.meshes.iter().position(|m| &m.name == name);
            let old = previous.meshes.iter().position(|m| m == name);
            if new.is_none() && old.is_none() {
                return Err(bad(format!("no mesh named {name:?} in the scene or the finished bake")));
            }
            if let Some(o) = old {
                old_bits |= match reach {
                    UpdateReach::All => 1 << (16 + o % 16),
                    UpdateReach::Dmax => 1 << (o % 16),
                };
            }
            if let Some(k) = new {
                new_meshes.push(k as u32);
            }
        }
        let mut tech = Self::with_params(
            BakeInputs {
                seed: previous.seed,
                ..inputs
            },
            previous.params.clone(),
        )?;
        // The changed meshes' new bounds, grown by dmax: texels there may now see them.
        let (mut lo, mut hi) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
        for t in scene.triangles.iter().filter(|t| new_meshes.contains(&t.mesh)) {
            for p in t.p {
                lo = lo.min(p);
                hi = hi.max(p);
            }
        }
        let reach = tech.dmax();
        let (lo, hi) = (lo - Vec3::splat(reach), hi + Vec3::splat(reach));
        let mut old_of_pixel = vec![u32::MAX; (previous.width * previous.height) as usize];
        for (k, p) in previous.pixels.iter().enumerate() {
            if let Some(slot) = old_of_pixel.get_mut(*p as usize) {
                *slot = k as u32;
            }
        }
        let n = atlas.texels.len();
        let mut acc = vec![[0.0f32; 4]; 4 * n];
        let mut direct = vec![[0.0f32; 4]; 4 * n];
        let mut masks = vec![0u32; n];
        let mut subset = Vec::new();
        for (k, t) in atlas.texels.iter().enumerate() {
            let old = old_of_pixel[t.pixel as usize];
            let near = t.position.cmpge(lo).all() && t.position.cmple(hi).all();
            let recompute =
                old == u32::MAX || new_meshes.contains(&t.mesh) || near || previous.masks[old as usize] & old_bits != 0;
            if recompute {
                subset.push(k as u32);
            } else {
                let o = old as usize;
                for h in 0..4 {
                    acc[h * n + k] = previous.acc[h * n_old + o];
                    direct[h * n + k] = previous.direct[h * n_old + o];
                }
                masks[k] = previous.masks[o];
            }
        }
        let q = &tech.ctx.queue;
        q.write_buffer(&tech.acc_buf, 0, bytemuck::cast_slice(&acc));
        q.write_buffer(&tech.direct_acc_buf, 0, bytemuck::cast_slice(&direct));
        q.write_buffer(&tech.counters_buf, (MASK_BASE * 4) as u64, bytemuck::cast_slice(&masks));
        if !subset.is_empty() {
            q.write_buffer(&tech.subset_buf, 0, bytemuck::cast_slice(&subset));
        }
        tech.subset_len = Some(subset.len() as u32);
        let report = UpdateReport {
            recomputed_texels: subset.len(),
            total_texels: n,
            steps: previous.steps(),
        };
        tracing::info!(?report, "obscurance incremental update");
        Ok((tech, report))
    }
}
