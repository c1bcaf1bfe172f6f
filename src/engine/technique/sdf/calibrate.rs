//! `sdf`'s calibration (sdf seed, section 9.7, and module doc of `sdf`): before the first
//! step, the constants k and alpha that the job left out are fitted against CPU ray-cast
//! sky visibility at a seeded random set of texels, by a log-spaced scan of k refined by
//! golden-section search for each alpha of [`CAL_ALPHAS`], each alpha's C averaged over
//! [`CAL_JITTERS`] fixed jitters so the fit matches what the steps converge to. The report
//! ([`CalibrationReport`]) goes into the plan and the job status.
//!
//! The texels are drawn from the whole grid by a seeded key of their *pixel*
//! ([`calibration_texels`]: the grid's coverage, the texels of the smallest keys built
//! alone and validated as the atlas validates), never from the bake's own texel list: a
//! task that bakes one page or band of the grid (`engine::tasks`) calibrates at the same
//! texels, with the same rays, as the single bake, so it bakes with the same k and alpha.
//! Costs a rasterisation of the whole grid into a bit a pixel (0.22 s for 15.6 M texels,
//! docs/scaling.md), a hash per covered pixel, and the candidates' texels and validation
//! rays.

#[allow(clippy::wildcard_imports)]
use super::*;
use crate::engine::atlas::{Atlas, Texel, validate};

impl Sdf {
    /// Fits k and alpha (whichever the job left out) against CPU ray-cast sky
    /// visibility at a seeded random set of texels, and reports the fit.
    pub(super) fn calibrate(&mut self, inputs: &BakeInputs) -> Result<CalibrationReport, GpuError> {
        let g = self.gpu.as_ref().expect("calibration runs after the volume");
        let scene = &inputs.scene;
        let upper = self.upper;
        let open = |n: Vec3| {
            if upper {
                (0.5 * (1.0 + n.y)).clamp(0.0, 1.0)
            } else {
                1.0
            }
        };
        // Texels that can see sky at all, picked in a seeded random order of their
        // pixels over the whole grid and validated as the atlas validates (module doc):
        // the same texels whether the bake holds the whole grid or one region of it.
        let picked = calibration_texels(inputs, self.params.calibration_texels as usize, |t: &Texel| {
            open(t.normal) > 1e-3
        })
        .map_err(|e| GpuError::Device {
            during: "sdf calibration's texels".into(),
            message: e.to_string(),
        })?;
        let n = picked.len() as u32;
        if n == 0 {
            return Ok(CalibrationReport {
                texels: 0,
                rays: 0,
                rms_fitted: 0.0,
                rms_unoccluded: 0.0,
                rms_ray_noise: 0.0,
                mean_bias: 0.0,
            });
        }
        // The reference: cosine rays that escape into the sky (path's first bounce).
        let rays = self.params.calibration_rays;
        let tracer = inputs.rays.tracer();
        let shapes: Vec<(DynamicShape, Vec3)> = self
            .params
            .dynamic
            .iter()
            .map(|s| (s.clone(), (s.centre() - g.origin_offset).as_vec3()))
            .collect();
        let sky_of = |w: Vec3| inputs.lighting.sky_radiance(w) != Vec3::ZERO;
        let reference: Vec<f32> = picked
            .par_iter()
            .map(|t| {
                let mut rng = Rng::new(inputs.prepare_seed, 0x5DF_CA1, u64::from(t.pixel), 0);
                let mut seen = 0u32;
                for _ in 0..rays {
                    let dir = cosine_sample(t.normal, rng.next_f32(), rng.next_f32());
                    if dir.dot(t.geo_normal) <= 0.0 || !sky_of(dir) {
                        continue;
                    }
                    if shapes.iter().any(|(s, c)| ray_hits_shape(s, *c, t.position, dir)) {
                        continue;
                    }
                    if tracer.trace(scene, t.position, dir, f32::INFINITY).is_none() {
                        seen += 1;
                    }
                }
                seen as f32 / rays as f32
            })
            .collect();
        let opens: Vec<f32> = picked.iter().map(|t| open(t.normal)).collect();

        // GPU sums for every alpha tried and every fixed jitter.
        let alphas: Vec<f32> = match self.params.alpha {
            Some(a) => vec![a],
            None => CAL_ALPHAS.to_vec(),
        };
        let texels: Vec<GpuTexelGeom> = picked
            .iter()
            .map(|t| {
                let p = (t.position - g.centre) / g.scale;
                GpuTexelGeom {
                    position: [p.x, p.y, p.z, 0.0],
                    normal: [t.normal.x, t.normal.y, t.normal.z, 0.0],
                    geo_normal: [t.geo_normal.x, t.geo_normal.y, t.geo_normal.z, 0.0],
                }
            })
            .collect();
        let count = alphas.len() as u32 * n * CAL_JITTERS;
        let ctx = &g.ctx;
        let tex_buf = ctx.buffer_init("sdf calibration texels", &texels, STORAGE);
        let out_buf = ctx.buffer_zeroed(
            "sdf calibration sums",
            16 * count as u64,
            STORAGE | wgpu::BufferUsages::COPY_SRC,
        );
        let mut a4 = [[0f32; 4]; 4];
        for (k, a) in alphas.iter().enumerate() {
            a4[k / 4][k % 4] = *a;
        }
        let params = ctx.uniform(
            "sdf calibration params",
            &GpuSkyParams {
                sky: [1.0, 1.0, 1.0, if upper { 1.0 } else { 0.0 }],
                fit: [0.0, 0.0, 0.0, self.weighting_flag()],
                misc: [n, self.params.samples, 0, 0],
                cal: [CAL_JITTERS, alphas.len() as u32, 0, 0],
                alphas: a4,
                // Read by the sky step only.
                slice: [0, 0, 0, 0],
            },
        );
        let bg = group_of(
            ctx,
            "sdf calibrate",
            &g.cal_layout,
            &[
                Bind::Uniform(&g.vol_buf),
                Bind::Read(&g.levels_buf),
                Bind::Read(&tex_buf),
                Bind::Write(&out_buf),
                Bind::Uniform(&params),
            ],
        );
        let mut encoder = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("sdf calibrate"),
        });
        run_pass(
            &mut encoder,
            "sdf calibrate",
            &g.cal_pipeline,
            &bg,
            gpu::dispatch_size_64(count),
        );
        ctx.queue.submit([encoder.finish()]);
        let sums: Vec<[f32; 4]> = ctx.read_buffer("sdf calibration sums", &out_buf, count as usize)?;
        let sums: Vec<f32> = sums.iter().map(|s| s[0]).collect();

        let per_alpha = (n * CAL_JITTERS) as usize;
        let model = |a: usize, k: f32| -> Vec<f32> {
            (0..n as usize)
                .map(|t| {
                    let s = &sums[a * per_alpha + t * CAL_JITTERS as usize..][..CAL_JITTERS as usize];
                    let c: f32 = s.iter().map(|x| (k * x).exp().min(1.0)).sum::<f32>() / CAL_JITTERS as f32;
                    opens[t] * c
                })
                .collect()
        };
        let rms = |v: &[f32]| {
            (v.iter()
                .zip(&reference)
                .map(|(a, b)| ((a - b) as f64).powi(2))
                .sum::<f64>()
                / n as f64)
                .sqrt() as f32
        };
        let (mut best_a, mut best_k, mut best_e) = (0usize, self.k, f32::MAX);
        for a in 0..alphas.len() {
            let (k, e) = match self.params.k {
                Some(k) => (k, rms(&model(a, k))),
                None => fit_k(|k| rms(&model(a, k))),
            };
            if e < best_e {
                (best_a, best_k, best_e) = (a, k, e);
            }
        }
        self.k = best_k;
        self.alpha = alphas[best_a];
        let fitted = model(best_a, best_k);
        let mean_bias = fitted.iter().zip(&reference).map(|(a, b)| (a - b) as f64).sum::<f64>() as f32 / n as f32;
        let noise = (reference
            .iter()
            .map(|v| (v * (1.0 - v) / rays as f32) as f64)
            .sum::<f64>()
            / n as f64)
            .sqrt() as f32;
        Ok(CalibrationReport {
            texels: n,
            rays,
            rms_fitted: best_e,
            rms_unoccluded: rms(&opens),
            rms_ray_noise: noise,
            mean_bias,
        })
    }
}

/// Minimises `err(k)` over k in [1e-4, 100]: a log-spaced scan, then golden-section
/// refinement around the best grid point. Returns (k, err).
pub(super) fn fit_k(err: impl Fn(f32) -> f32) -> (f32, f32) {
    let (lo, hi, n) = (-4.0f32, 2.0f32, 61);
    let at = |x: f32| err(10f32.powf(x));
    let grid: Vec<(f32, f32)> = (0..n)
        .map(|i| {
            let x = lo + (hi - lo) * i as f32 / (n - 1) as f32;
            (x, at(x))
        })
        .collect();
    let (i, _) = grid
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.1.total_cmp(&b.1.1))
        .expect("grid");
    let step = (hi - lo) / (n - 1) as f32;
    let (mut a, mut b) = (grid[i].0 - step, grid[i].0 + step);
    let g = 0.618_034f32;
    for _ in 0..30 {
        let (c, d) = (b - g * (b - a), a + g * (b - a));
        if at(c) < at(d) {
            b = d;
        } else {
            a = c;
        }
    }
    let x = 0.5 * (a + b);
    let (k, e) = (10f32.powf(x), at(x));
    if e <= grid[i].1 {
        (k, e)
    } else {
        (10f32.powf(grid[i].0), grid[i].1)
    }
}

/// Whether the ray origin + t dir (t > 0) hits the analytic shape centred at `c`.
pub(super) fn ray_hits_shape(s: &DynamicShape, c: Vec3, origin: Vec3, dir: Vec3) -> bool {
    let size = s.size();
    // Both shapes are axis-aligned: scale space so the shape becomes a unit cube or sphere.
    let o = (origin - c) / size;
    let d = dir / size;
    if s.is_box() {
        let inv = d.recip();
        let t0 = (Vec3::NEG_ONE - o) * inv;
        let t1 = (Vec3::ONE - o) * inv;
        let tmin = t0.min(t1).max_element();
        let tmax = t0.max(t1).min_element();
        tmax >= tmin.max(0.0)
    } else {
        let (a, b, cc) = (d.dot(d), o.dot(d), o.dot(o) - 1.0);
        let disc = b * b - a * cc;
        disc >= 0.0 && (-b + disc.sqrt()) > 0.0
    }
}

/// Up to `n` texels of the whole grid that `accept` takes, in the order of a key of their
/// pixel seeded by the prepare seed, each kept only where the atlas's validation keeps it
/// (its back-face fraction within [`validate::BACKFACE_TOLERANCE`], the CPU's rays,
/// which are keyed by pixel): the same texels in a single bake and in a region's task.
/// Starts with 4 n candidates and widens fourfold while too few pass.
fn calibration_texels(
    inputs: &BakeInputs,
    n: usize,
    accept: impl Fn(&Texel) -> bool,
) -> Result<Vec<Texel>, crate::engine::atlas::AtlasError> {
    if n == 0 {
        return Ok(Vec::new());
    }
    let (scene, width, height) = (&inputs.scene, inputs.atlas.width, inputs.atlas.height);
    let coverage = Atlas::coverage(scene, width, height)?;
    let key = |p: u32| u64::from(Rng::new(inputs.prepare_seed, 0x5DF, u64::from(p), 0).next_u32());
    let tracer = inputs.rays.tracer();
    let total = coverage.texels();
    let mut m = (4 * n).min(total);
    loop {
        let order = coverage.smallest(m, key);
        let mut sorted = order.clone();
        sorted.sort_unstable();
        let candidates: Vec<Texel> = Atlas::texels_at(scene, width, height, &sorted)?
            .into_iter()
            .filter(|t| accept(t))
            .collect();
        let fractions = validate::backface_fractions(scene, &tracer, &candidates);
        let kept: std::collections::HashMap<u32, Texel> = candidates
            .into_iter()
            .zip(fractions)
            .filter(|(_, f)| *f <= validate::BACKFACE_TOLERANCE)
            .map(|(t, _)| (t.pixel, t))
            .collect();
        let picked: Vec<Texel> = order.iter().filter_map(|p| kept.get(p).cloned()).take(n).collect();
        if picked.len() == n || m >= total {
            return Ok(picked);
        }
        m = (4 * m).min(total);
    }
}
