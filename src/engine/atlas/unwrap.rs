//! Lightmap UV generation for meshes without `TEXCOORD_1`, packed beside the authored ones.
//!
//! How: each glTF mesh that needs UVs is unwrapped once, in its own space, by an
//! [`Unwrapper`]; the one used is the `uvunwrap` crate (region-growing charts within a
//! normal cone, LSCM + ARAP flattening, shape packing), behind this small trait because
//! the crate is young and xatlas-rs does not link here (../shared/NOTES.md). Every node
//! that places the mesh is an *instance*: `uvunwrap` gives each its own unrotated
//! rectangle on a page holding the mesh's layout at the instance's scale (the cube root of
//! its transform's |determinant| times `extras.lightmap_scale` of node and mesh, the
//! "scale in lightmap" of Unity and Bakery). The mesh's `TEXCOORD_1` is then its layout in
//! [0, 1], shared by all instances, and each instance's page UV is
//! `TEXCOORD_1 · (sx, sy) + (ox, oy)` (its `scale_offset`, Unity's `lightmapScaleOffset`;
//! docs/conventions.md). Charts never span primitives, so each primitive's vertices are
//! split only where one of its UV seams runs.
//!
//! Authored UVs are kept bit for bit (`lightmap_uvs: generate-missing`, the default, or
//! `keep`): a mesh is *authored* when every TRIANGLES primitive has `TEXCOORD_1`. The
//! packer cannot place charts around existing ones, so generated charts go on pages of
//! their own. A bake runs on one texel grid W wide in which the pages lie one under
//! another ([`PageRows`]): first the authored pages, W × W each, exactly as authored (an
//! input written by a multi-page bake names each node's page in `extras.lightmap.page`),
//! then the generated pages, also W × W (the last one too, however few rows the packer
//! filled: the convention names a node's page, not the page's height, so only square
//! pages are found again when a written file is read back). Each page is
//! written as its own EXR (`lightmap-P.exr`), and each node's `extras.lightmap` names its
//! page and its rectangle in that page ([`Scene::placements`]), so a scene never fails
//! because its charts do not fit one page. Why one grid rather than one per page: every
//! technique, the denoiser and the seam solver already work on one texel set, and pages
//! of one width stack without waste; dilation keeps to each page's rows. W is
//! `resolution`, except at a fixed `texels_per_unit`, where it doubles from there until
//! the generated charts fit one page at that density, up to `max_page_size`
//! (`unwrap_paged`): more pages only once a page cannot grow. The grid may not
//! exceed [`MAX_RESOLUTION`](super::MAX_RESOLUTION) rows (the GPU techniques' maps of it
//! are textures). Without authored meshes and with one page the page stays W × W
//! (`--resolution N` is one N × N page).
//!
//! Padding: 3 texels (charts at least 6 apart): enough for the gutter links, bilinear
//! filtering and one mip level; dilation fills the rest. `uvunwrap` is built without its
//! `direct-solver` feature: the output is then the same on every CPU, so a lightmap baked
//! on one machine fits UVs made on another.
//!
//! Stretched instances: an instance whose axis scales differ by more than
//! [`OWN_LAYOUT_RATIO`] gets a layout of its own, unwrapped in its stretched shape (the
//! mesh's positions times its transform's linear part over the cube root of its
//! determinant), shared with the mesh's other instances stretched the same way (equal
//! `NᵀN`, so shapes that differ by a rotation share); the written glTF gets a copy of the
//! mesh for them ([`MeshCopy`], `scene::export`), and the report warns, naming the node.
//! Instances below the ratio share the mesh's layout, their texels stretched by at most it.
//!
//! Limits: all instances of a layout share one set of charts padded for the smallest, so
//! a much larger instance gets proportionally wider padding (`repack-instances` sizes
//! each authored instance's rectangle on its own). A stretched instance's copy adds a
//! mesh to the written glTF, so its mesh count is the input's plus the copies.

use std::collections::HashMap;

use glam::{DMat3, Vec2};
use serde::{Deserialize, Serialize};

use crate::engine::scene::{GeneratedMesh, GeneratedPrimitive, LightmapLayout, MeshCopy, PageRows, Scene, warn_each};

/// Padding around each chart, in texels.
pub const PADDING: u32 = 3;

/// Axis-scale ratio of an instance's transform above which it gets a layout of its own,
/// unwrapped in its stretched shape: below it, texels on it are at most this much longer
/// one way than the other, which is within what the unwrapper allows itself (its charts
/// may distort area up to 4x); above it, a wall scaled (10, 3, 0.2) from a unit cube would
/// get texels 50 times longer across than along.
pub const OWN_LAYOUT_RATIO: f64 = 2.0;

/// Which lightmap UVs a bake uses (`lightmap_uvs` in a job, `--lightmap-uvs` on the CLI).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LightmapUvs {
    /// Only authored `TEXCOORD_1`; a mesh without is an error naming it.
    Keep,
    /// Authored UVs kept, the others generated (the default).
    #[default]
    GenerateMissing,
    /// Every mesh gets generated UVs (authored ones are replaced in the written glTF).
    RegenerateAll,
    /// As `generate-missing`, and an authored mesh placed by several nodes gets a
    /// rectangle per node for its authored layout, its UVs kept (`atlas::repack`).
    RepackInstances,
}

impl std::str::FromStr for LightmapUvs {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "keep" => Ok(LightmapUvs::Keep),
            "generate-missing" => Ok(LightmapUvs::GenerateMissing),
            "regenerate-all" => Ok(LightmapUvs::RegenerateAll),
            "repack-instances" => Ok(LightmapUvs::RepackInstances),
            _ => Err(format!(
                "lightmap_uvs must be keep, generate-missing, regenerate-all or repack-instances, got {s:?}"
            )),
        }
    }
}

/// One mesh to unwrap, in its own space.
pub struct UnwrapMesh {
    pub positions: Vec<[f32; 3]>,
    pub indices: Vec<u32>,
    /// Per triangle, a group (the primitive): charts never span groups.
    pub groups: Vec<u32>,
    /// One scale per instance (> 0), see the module doc.
    pub instance_scales: Vec<f32>,
}

impl UnwrapMesh {
    /// Surface area in the mesh's own units.
    fn area(&self) -> f64 {
        let p = |i: u32| glam::DVec3::from(self.positions[i as usize].map(f64::from));
        self.indices
            .chunks_exact(3)
            .map(|c| 0.5 * (p(c[1]) - p(c[0])).cross(p(c[2]) - p(c[0])).length())
            .sum()
    }
}

/// One unwrapped mesh: split vertices (UV in the mesh's [0, 1] layout), the same triangles
/// over them, and per instance its page and rectangle `[min, max]` in page UV.
pub struct UnwrappedMesh {
    pub uv: Vec<Vec2>,
    pub indices: Vec<u32>,
    pub instances: Vec<(u32, Vec2, Vec2)>,
}

/// The unwrap of every mesh: pages of `width` × `page_height` texels.
pub struct Unwrapped {
    pub meshes: Vec<UnwrappedMesh>,
    pub width: u32,
    pub page_height: u32,
    pub pages: u32,
    pub charts: u32,
    pub texels_per_metre: f32,
}

/// Meshes in (each with its instances), layouts and rectangles out, in the same order.
pub trait Unwrapper {
    /// Pages are `resolution` wide; `texels_per_unit` None: the highest density at which
    /// everything fits one page (several pages only when it cannot fit at any density).
    fn unwrap(&self, meshes: &[UnwrapMesh], resolution: u32, texels_per_unit: Option<f32>)
    -> Result<Unwrapped, String>;
}

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct UnwrapReport {
    pub charts: u32,
    /// Fraction of the page covered by the charts of generated meshes.
    pub utilisation: f32,
    pub texels_per_metre: f32,
    /// The bake's grid: `width` × `height` texels, its W × W pages one under another
    /// (authored first, then generated).
    pub width: u32,
    pub height: u32,
    /// W × W pages of generated charts stacked in it.
    pub generated_pages: u32,
    /// Meshes unwrapped, and meshes whose authored UVs were kept.
    pub generated_meshes: usize,
    /// Extra layouts for instances stretched past [`OWN_LAYOUT_RATIO`] (each a copy of its
    /// mesh in the written glTF).
    pub own_layouts: usize,
    pub kept_meshes: usize,
    /// Nodes with their own rectangle (and `extras.lightmap` in the written glTF).
    pub instances: usize,
    /// Of those, instances of authored meshes given a rectangle each
    /// (`repack-instances`), and the pages they take after the generated ones.
    pub repacked_instances: usize,
    pub repacked_pages: u32,
    pub warnings: Vec<String>,
}

/// The `uvunwrap` crate.
pub struct UvUnwrap;

impl Unwrapper for UvUnwrap {
    fn unwrap(
        &self,
        meshes: &[UnwrapMesh],
        resolution: u32,
        texels_per_unit: Option<f32>,
    ) -> Result<Unwrapped, String> {
        let inputs: Vec<uvunwrap::MeshInput> = meshes
            .iter()
            .map(|m| uvunwrap::MeshInput {
                face_materials: Some(&m.groups),
                instance_scales: &m.instance_scales,
                ..uvunwrap::MeshInput::new(&m.positions, &m.indices)
            })
            .collect();
        let density = match texels_per_unit {
            None => uvunwrap::Density::Auto { page_size: resolution },
            Some(t) => uvunwrap::Density::Fixed {
                texels_per_unit: t,
                page_size: Some(resolution),
            },
        };
        let options = uvunwrap::Options {
            density,
            padding: PADDING,
            // A chart larger than a page is scaled down to fit it (with a lower density)
            // rather than failing the bake.
            max_chart_size: resolution.saturating_sub(2 * PADDING + 2).max(1),
            ..Default::default()
        };
        // uvunwrap is young (NOTES.md): a panic inside it on unusual input (measured: a
        // fuzzed mesh whose charts all vanish panics in its packer) becomes an error that
        // fails this bake, never the process.
        let atlas = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| uvunwrap::generate(&inputs, &options)))
            .map_err(|_| "the UV unwrapper failed on this geometry (degenerate or empty charts)".to_string())?
            .map_err(|e| e.to_string())?;
        let out = atlas
            .meshes
            .iter()
            .map(|mesh| UnwrappedMesh {
                uv: mesh
                    .vertices
                    .iter()
                    .map(|v| Vec2::from_array(v.uv).clamp(Vec2::ZERO, Vec2::ONE))
                    .collect(),
                indices: mesh.indices.clone(),
                instances: mesh
                    .instances
                    .iter()
                    .map(|r| (r.page, Vec2::from_array(r.min), Vec2::from_array(r.max)))
                    .collect(),
            })
            .collect();
        Ok(Unwrapped {
            meshes: out,
            width: atlas.width,
            page_height: atlas.height,
            pages: atlas.page_count,
            charts: atlas.chart_count,
            texels_per_metre: atlas.texels_per_unit,
        })
    }
}

/// Default of `max_page_size` (issue 19 point 2): the widest page a fixed density may grow
/// the page to before it adds pages. 4096 is the largest lightmap Unity's and Godot's
/// bakers offer by default and what every desktop GPU samples; four such pages fill the
/// bake's grid ([`MAX_RESOLUTION`](super::MAX_RESOLUTION) rows).
pub const DEFAULT_MAX_PAGE_SIZE: u32 = 4096;

/// Share of a page the packer is assumed to fill when the page width is first estimated
/// from the charts' texel area ([`page_width_for`]). The bundled levels measured 33–53 % at
/// 512 (docs/quality.md); a lower guess gives a wider page than needed (more empty texels),
/// a higher one an extra unwrap at twice the width.
const ASSUMED_FILL: f64 = 0.4;

/// [`generate_lightmap_uvs_with`] with the default `generate-missing`.
pub fn generate_lightmap_uvs(
    scene: &mut Scene,
    resolution: u32,
    unwrapper: &dyn Unwrapper,
) -> Result<UnwrapReport, String> {
    generate_lightmap_uvs_with(scene, resolution, LightmapUvs::GenerateMissing, None, unwrapper)
}

/// [`generate_lightmap_uvs_paged`] with pages exactly `resolution` wide (no growth).
pub fn generate_lightmap_uvs_with(
    scene: &mut Scene,
    resolution: u32,
    mode: LightmapUvs,
    texels_per_unit: Option<f32>,
    unwrapper: &dyn Unwrapper,
) -> Result<UnwrapReport, String> {
    generate_lightmap_uvs_paged(scene, resolution, resolution, mode, texels_per_unit, unwrapper)
}

/// A mesh's layout among its instances: the normalised linear part of the first instance,
/// its metric for matching, and the instances with their scales.
type InstanceLayout = (Option<DMat3>, Option<DMat3>, Vec<(usize, f32)>);

/// Gives the meshes `mode` selects generated lightmap UVs, packed beside the authored
/// ones (module doc), and records the layout in `scene.layout` for the written glTF.
/// `resolution` is the page width W; at a fixed `texels_per_unit` the page grows (doubling
/// W, up to `max_page_size`) until the generated charts fit one page at that density, and
/// beyond that the bake gets several `max_page_size` pages (`unwrap_paged`). With the
/// automatic density the page stays `resolution` wide (the density is chosen to fit it).
pub fn generate_lightmap_uvs_paged(
    scene: &mut Scene,
    resolution: u32,
    max_page_size: u32,
    mode: LightmapUvs,
    texels_per_unit: Option<f32>,
    unwrapper: &dyn Unwrapper,
) -> Result<UnwrapReport, String> {
    if let Some(t) = texels_per_unit
        && !(t.is_finite() && t > 0.0)
    {
        return Err(format!("texels_per_unit must be a positive number, got {t}"));
    }
    check_page_sizes(resolution, max_page_size)?;
    let source = scene
        .source
        .clone()
        .ok_or("the scene has no source document to unwrap")?;
    let mesh_name = |m: usize| mesh_label(scene, m);
    // Which meshes get generated UVs: those placed by some node that did not opt out.
    let mut generate = vec![false; source.meshes.len()];
    let mut kept = vec![false; source.meshes.len()];
    for inst in source.instances.iter().filter(|i| !i.opt_out) {
        let Some(local) = source.meshes[inst.mesh].as_ref() else {
            continue;
        };
        let authored = local.authored();
        match mode {
            LightmapUvs::Keep if !authored => {
                return Err(format!(
                    "{} has no TEXCOORD_1 and lightmap_uvs is keep (use generate-missing)",
                    mesh_name(inst.mesh)
                ));
            }
            LightmapUvs::RegenerateAll => generate[inst.mesh] = true,
            _ if authored => kept[inst.mesh] = true,
            _ => generate[inst.mesh] = true,
        }
    }

    // Authored meshes placed by several nodes, under repack-instances: a rectangle each.
    let mut repack = vec![false; source.meshes.len()];
    if mode == LightmapUvs::RepackInstances {
        let mut users = vec![0usize; source.meshes.len()];
        for inst in source.instances.iter().filter(|i| !i.opt_out) {
            users[inst.mesh] += 1;
        }
        for m in 0..source.meshes.len() {
            repack[m] = kept[m] && users[m] > 1;
        }
    }

    // One UnwrapMesh per layout of a generated mesh: its primitives concatenated, a group
    // each. A mesh's instances share one layout, except those whose transform stretches
    // it (axis scales more than OWN_LAYOUT_RATIO apart): each distinct stretch gets a layout
    // of its own, unwrapped in the stretched shape, and a copy of the mesh in the written
    // glTF (`MeshCopy`).
    let mut warnings = Vec::new();
    let mut stretched: Vec<(String, String)> = Vec::new();
    // Per UnwrapMesh: the glTF mesh, and which of its copies (None: the mesh itself).
    let mut order: Vec<(usize, Option<usize>)> = Vec::new();
    let mut inputs: Vec<UnwrapMesh> = Vec::new();
    let mut instance_slot: Vec<Option<(usize, usize)>> = vec![None; source.instances.len()];
    let mut copies: Vec<MeshCopy> = Vec::new();
    for (m, local) in source.meshes.iter().enumerate() {
        let Some(local) = local.as_ref().filter(|_| generate[m]) else {
            continue;
        };
        // The mesh's instances by layout: (normalised linear part of the first, its
        // metric for matching, instances with their scales).
        let mut layouts: Vec<InstanceLayout> = Vec::new();
        for (k, inst) in source.instances.iter().enumerate() {
            if inst.mesh != m || inst.opt_out {
                continue;
            }
            let lin = DMat3::from_mat4(inst.world);
            let axes = [lin.x_axis.length(), lin.y_axis.length(), lin.z_axis.length()];
            let det = lin.determinant().abs();
            if !(det.is_finite() && det > 1e-30) {
                return Err(format!(
                    "node {} places {} with a singular transform (determinant {det:e})",
                    inst.node,
                    mesh_name(m)
                ));
            }
            let scale = (det.cbrt() as f32 * inst.lightmap_scale).max(1e-6);
            let ratio = axes.iter().cloned().fold(0.0, f64::max) / axes.iter().cloned().fold(f64::INFINITY, f64::min);
            let (shape, metric) = if ratio > OWN_LAYOUT_RATIO {
                let n = lin * (1.0 / det.cbrt());
                (Some(n), Some(n.transpose() * n))
            } else {
                (None, None)
            };
            let same = |g: &Option<DMat3>| match (g, &metric) {
                (None, None) => true,
                (Some(a), Some(b)) => (*a - *b).to_cols_array().iter().all(|d| d.abs() < 1e-4 * ratio * ratio),
                _ => false,
            };
            match layouts.iter_mut().find(|l| same(&l.1)) {
                Some(l) => l.2.push((k, scale)),
                None => {
                    if shape.is_some() {
                        stretched.push((
                            format!("node {} ({}) {ratio:.1}x", inst.node, mesh_name(m)),
                            format!(
                                "node {} scales {} {ratio:.1}x more along one axis than another: it gets a lightmap layout of its own (a copy of the mesh in the written glTF)",
                                inst.node,
                                mesh_name(m)
                            ),
                        ));
                    }
                    layouts.push((shape, metric, vec![(k, scale)]));
                }
            }
        }
        // The unstretched layout is the mesh's own; without one, the first stretched one.
        layouts.sort_by_key(|l| l.0.is_some());
        for (g, (shape, _, members)) in layouts.into_iter().enumerate() {
            let mut input = UnwrapMesh {
                positions: Vec::new(),
                indices: Vec::new(),
                groups: Vec::new(),
                instance_scales: Vec::new(),
            };
            for (p, prim) in local.primitives.iter().enumerate() {
                let Some(prim) = prim else { continue };
                let base = input.positions.len() as u32;
                input.positions.extend(prim.positions.iter().map(|v| match &shape {
                    Some(n) => (*n * v.as_dvec3()).as_vec3().to_array(),
                    None => v.to_array(),
                }));
                input.indices.extend(prim.indices.iter().map(|i| i + base));
                input
                    .groups
                    .extend(std::iter::repeat_n(p as u32, prim.indices.len() / 3));
            }
            if input.indices.is_empty() {
                continue;
            }
            for (k, scale) in &members {
                instance_slot[*k] = Some((inputs.len(), input.instance_scales.len()));
                input.instance_scales.push(*scale);
            }
            let copy = (g > 0).then(|| {
                copies.push(MeshCopy {
                    mesh: m,
                    generated: GeneratedMesh::default(),
                    instances: members.iter().map(|(k, _)| *k).collect(),
                });
                copies.len() - 1
            });
            order.push((m, copy));
            inputs.push(input);
        }
    }
    warn_each(&mut warnings, stretched, |n, names| {
        format!(
            "{n} nodes scale their meshes more along one axis than another ({names}): each gets a lightmap layout of its own (a copy of the mesh in the written glTF)"
        )
    });

    // Authored pages (an input written by a multi-page bake names several) first, each
    // W × W, in their own order.
    let authored_pages = source
        .instances
        .iter()
        .filter(|i| !i.opt_out && kept[i.mesh] && !repack[i.mesh])
        .map(|i| i.authored_page + 1)
        .max()
        .unwrap_or(0);
    let unwrapped = if inputs.is_empty() {
        None
    } else {
        Some(unwrap_paged(
            unwrapper,
            &inputs,
            resolution,
            max_page_size,
            texels_per_unit,
            &mut warnings,
        )?)
    };
    let items = repack_items(scene, &source.instances, &repack)?;
    // The page width: `resolution`, or wider where a fixed density needed it (for the
    // generated charts, or, with none, for the repacked rectangles).
    let w = match (&unwrapped, texels_per_unit) {
        (Some(u), _) => u.width,
        (None, Some(t)) if !items.is_empty() => {
            let mut w = resolution;
            while w < max_page_size && {
                let (pages, _, shrunk) = super::repack::place(&items, f64::from(t), w);
                pages > 1 || !shrunk.is_empty()
            } {
                w = w.saturating_mul(2).min(max_page_size);
            }
            w
        }
        _ => resolution,
    };
    let authored_rows = authored_pages.saturating_mul(w);
    // Page rows: the authored page first, then each generated page.
    let (page_h, pages) = unwrapped.as_ref().map_or((0, 0), |u| (u.page_height, u.pages));
    // Every page is W × W (`stride` rows), also where the packer filled fewer rows: the
    // convention's `extras.lightmap` names a page, not its height, so a file read back
    // can only find its texels again if every page has the width's height.
    let stride = w.max(page_h);
    // The repacked instances' rectangles: at the density asked, else the generated charts'
    // density, else the highest that fits one page.
    let mut repack_density = 0.0;
    let (repacked_pages, repacked_at) = if items.is_empty() {
        (0, Vec::new())
    } else {
        let density = match (texels_per_unit, &unwrapped) {
            (Some(t), _) => f64::from(t),
            (None, Some(u)) => f64::from(u.texels_per_metre),
            (None, None) => super::repack::fit_density(&items, w),
        };
        repack_density = density as f32;
        let (n, at, shrunk) = super::repack::place(&items, density, w);
        let shrunk = shrunk
            .into_iter()
            .map(|k| {
                let inst = &source.instances[items[k].instance];
                let name = format!("node {} ({})", inst.node, mesh_label(scene, inst.mesh));
                let own = format!(
                    "{name}: its rectangle was scaled down to fit a {w}x{w} page (raise max_page_size, or lower texels_per_unit or its extras.lightmap_scale)"
                );
                (name, own)
            })
            .collect();
        warn_each(&mut warnings, shrunk, |n, names| {
            format!(
                "{n} nodes' rectangles were scaled down to fit a {w}x{w} page ({names}) (raise max_page_size, or lower texels_per_unit or their extras.lightmap_scale)"
            )
        });
        (n, at)
    };
    let height = authored_rows + pages * stride + repacked_pages * w;
    if height > super::MAX_RESOLUTION {
        return Err(format!(
            "{authored_pages} authored page(s) of {w}x{w}, {pages} generated page(s) of {w}x{stride} and {repacked_pages} page(s) of repacked instances need {height} rows in all, more than the bake's grid may have ({}); lower the resolution, texels_per_unit or the meshes' extras.lightmap_scale",
            super::MAX_RESOLUTION
        ));
    }
    if let Some(u) = &unwrapped
        && !(resolution..=max_page_size.max(resolution)).contains(&u.width)
    {
        return Err(format!(
            "the unwrapper made {}-wide pages for a lightmap of pages {resolution} to {max_page_size} wide",
            u.width
        ));
    }
    let (wf, hf) = (w as f32, height as f32);

    let mut page_rows: Vec<PageRows> = (0..authored_pages)
        .map(|p| PageRows {
            first_row: p * w,
            rows: w,
        })
        .collect();
    page_rows.extend((0..pages).map(|p| PageRows {
        first_row: authored_rows + p * stride,
        rows: stride,
    }));
    let repacked_rows = authored_rows + pages * stride;
    page_rows.extend((0..repacked_pages).map(|p| PageRows {
        first_row: repacked_rows + p * w,
        rows: w,
    }));
    if page_rows.is_empty() {
        page_rows.push(PageRows {
            first_row: 0,
            rows: height,
        });
    }
    let mut layout = LightmapLayout {
        width: w,
        height,
        meshes: vec![None; source.meshes.len()],
        copies: Vec::new(),
        scale_offset: vec![None; source.instances.len()],
        pages: page_rows,
    };
    // Per generated mesh: per primitive, split vertices = distinct (original vertex,
    // unwrapped vertex) pairs over its corners.
    if let Some(u) = &unwrapped {
        for (slot, &(m, copy)) in order.iter().enumerate() {
            let local = source.meshes[m].as_ref().expect("generated meshes are placed");
            let out = &u.meshes[slot];
            let mut generated = GeneratedMesh {
                primitives: vec![None; local.primitives.len()],
            };
            let mut face = 0usize;
            for (p, prim) in local.primitives.iter().enumerate() {
                let Some(prim) = prim else { continue };
                let mut map: HashMap<(u32, u32), u32> = HashMap::new();
                let mut g = GeneratedPrimitive::default();
                for (c, &orig) in prim.indices.iter().enumerate() {
                    let new = out.indices[3 * face + c];
                    let next = g.xref.len() as u32;
                    let id = *map.entry((orig, new)).or_insert_with(|| {
                        g.xref.push(orig);
                        g.uv.push(out.uv[new as usize]);
                        next
                    });
                    g.indices.push(id);
                }
                face += prim.indices.len() / 3;
                generated.primitives[p] = Some(g);
            }
            match copy {
                None => layout.meshes[m] = Some(generated),
                Some(c) => copies[c].generated = generated,
            }
        }
        layout.copies = std::mem::take(&mut copies);
        for (k, slot) in instance_slot.iter().enumerate() {
            let Some((mi, ii)) = slot else { continue };
            let (page, lo, hi) = u.meshes[*mi].instances[*ii];
            let top = authored_rows as f32 + (page * stride) as f32;
            let size = (hi - lo) * Vec2::new(1.0, page_h as f32 / hf);
            layout.scale_offset[k] = Some([size.x, size.y, lo.x, (top + lo.y * page_h as f32) / hf]);
        }
    }
    // Repacked instances: their authored UVs into their rectangle.
    for (item, at) in items.iter().zip(&repacked_at) {
        let so = super::repack::scale_offset(item, at, repacked_rows + at.page * w, w, height);
        layout.scale_offset[item.instance] = Some(so);
        let inst = &source.instances[item.instance];
        let [sx, sy, ox, oy] = inst.authored_scale_offset;
        let (s0, o0) = (Vec2::new(sx, sy), Vec2::new(ox, oy));
        let (s1, o1) = (Vec2::new(so[0], so[1]), Vec2::new(so[2], so[3]));
        for t in &mut scene.triangles[inst.triangles.clone()] {
            // Back to TEXCOORD_1 (the import applied the node's authored scale_offset),
            // then into the rectangle.
            t.lm.iter_mut().for_each(|uv| *uv = ((*uv - o0) / s0) * s1 + o1);
        }
    }
    // Authored instances keep their UVs; their page moved to its rows of the grid.
    let squeeze = wf / hf;
    for (k, inst) in source.instances.iter().enumerate() {
        if !inst.opt_out && kept[inst.mesh] && !repack[inst.mesh] {
            let [sx, sy, ox, oy] = inst.authored_scale_offset;
            let page = inst.authored_page as f32;
            layout.scale_offset[k] = Some([sx, sy * squeeze, ox, (oy + page) * squeeze]);
        }
    }

    // The baked triangles: page UV of each corner.
    for (k, inst) in source.instances.iter().enumerate() {
        let range = inst.triangles.clone();
        if inst.opt_out {
            continue;
        }
        if repack[inst.mesh] {
            continue;
        }
        if kept[inst.mesh] {
            let page = inst.authored_page as f32;
            if squeeze != 1.0 || page != 0.0 {
                for t in &mut scene.triangles[range] {
                    t.lm.iter_mut().for_each(|uv| uv.y = (uv.y + page) * squeeze);
                }
            }
            continue;
        }
        let (Some(generated), Some(so)) = (layout.generated_for(k, inst.mesh), layout.scale_offset[k]) else {
            continue;
        };
        let (s, o) = (Vec2::new(so[0], so[1]), Vec2::new(so[2], so[3]));
        for ti in range {
            let src = scene.tri_source[ti];
            let Some(g) = generated.primitives[src.primitive as usize].as_ref() else {
                continue;
            };
            let c = |j: usize| {
                (g.uv[g.indices[3 * src.triangle as usize + j] as usize] * s + o).clamp(Vec2::ZERO, Vec2::ONE)
            };
            scene.triangles[ti].lm = if src.mirrored {
                [c(0), c(2), c(1)]
            } else {
                [c(0), c(1), c(2)]
            };
        }
    }

    // A chart larger than a page is scaled down to fit it (`max_chart_size`): name the
    // meshes whose texels came out sparser than asked, from each placed instance's texel
    // area over its world area (issue 19 point 2).
    if let Some(u) = &unwrapped {
        let mut sparse: Vec<(usize, f64, f64)> = Vec::new();
        for inst in source.instances.iter().filter(|i| !i.opt_out && generate[i.mesh]) {
            let (world, uv) = areas(&scene.triangles[inst.triangles.clone()]);
            let target = f64::from(u.texels_per_metre) * f64::from(inst.lightmap_scale);
            if world <= 0.0 || sparse.iter().any(|s| s.0 == inst.mesh) {
                continue;
            }
            let achieved = (uv * f64::from(wf) * f64::from(hf) / world).sqrt();
            if achieved < SCALED_DOWN * target {
                sparse.push((inst.mesh, achieved, target));
            }
        }
        let sparse = sparse
            .into_iter()
            .map(|(m, achieved, target)| {
                let name = mesh_label(scene, m);
                let own = format!(
                    "{name}: its charts were scaled down to fit a {w}x{page_h} page, {achieved:.2} texels/m instead of {target:.2} (raise max_page_size, or lower texels_per_unit or its extras.lightmap_scale)"
                );
                (format!("{name} at {achieved:.2} texels/m instead of {target:.2}"), own)
            })
            .collect();
        warn_each(&mut warnings, sparse, |n, names| {
            format!(
                "{n} meshes' charts were scaled down to fit a {w}x{page_h} page ({names}) (raise max_page_size, or lower texels_per_unit or their extras.lightmap_scale)"
            )
        });
    }

    if let Some(u) = unwrapped.as_ref().filter(|_| texels_per_unit.is_none()) {
        padding_bound(scene, &source.instances, &generate, &layout, u, (wf, hf), &mut warnings);
    }

    let report = UnwrapReport {
        charts: unwrapped.as_ref().map_or(0, |u| u.charts),
        utilisation: utilisation(
            scene,
            &source.instances,
            &generate.iter().zip(&repack).map(|(g, r)| *g || *r).collect::<Vec<_>>(),
        ),
        texels_per_metre: unwrapped.as_ref().map_or(repack_density, |u| u.texels_per_metre),
        width: w,
        height,
        generated_pages: pages,
        generated_meshes: order.iter().filter(|(_, copy)| copy.is_none()).count(),
        own_layouts: layout.copies.len(),
        kept_meshes: kept.iter().filter(|k| **k).count(),
        instances: layout.scale_offset.iter().filter(|s| s.is_some()).count(),
        repacked_instances: items.len(),
        repacked_pages,
        warnings,
    };
    scene.layout = Some(std::sync::Arc::new(layout));
    scene.needs_lightmap_uvs = false;
    Ok(report)
}

/// The instances `repack` selects, each with its mesh's authored UV box and its scale
/// (`atlas::repack::Item`), from its triangles as imported: their `lm` is TEXCOORD_1 after
/// the node's authored `scale_offset`, which is undone here.
fn repack_items(
    scene: &Scene,
    instances: &[crate::engine::scene::Instance],
    repack: &[bool],
) -> Result<Vec<super::repack::Item>, String> {
    let mut items = Vec::new();
    for (k, inst) in instances.iter().enumerate() {
        if inst.opt_out || !repack[inst.mesh] {
            continue;
        }
        let [sx, sy, ox, oy] = inst.authored_scale_offset;
        if sx == 0.0 || sy == 0.0 {
            return Err(format!(
                "node {}: extras.lightmap.scale_offset has a zero scale, so its TEXCOORD_1 cannot be repacked",
                inst.node
            ));
        }
        let (s0, o0) = (Vec2::new(sx, sy), Vec2::new(ox, oy));
        let (mut lo, mut hi) = (Vec2::splat(f32::INFINITY), Vec2::splat(f32::NEG_INFINITY));
        let (mut world, mut uv) = (0.0f64, 0.0f64);
        for t in &scene.triangles[inst.triangles.clone()] {
            let raw = t.lm.map(|l| (l - o0) / s0);
            for r in raw {
                lo = lo.min(r);
                hi = hi.max(r);
            }
            world += 0.5 * f64::from((t.p[1] - t.p[0]).cross(t.p[2] - t.p[0]).length());
            uv += 0.5 * f64::from((raw[1] - raw[0]).perp_dot(raw[2] - raw[0]).abs());
        }
        if !(world > 0.0 && uv > 0.0) {
            // No area to give texels to (degenerate UVs or geometry): nothing to place.
            continue;
        }
        items.push(super::repack::Item {
            instance: k,
            lo,
            hi,
            uv_scale: (world / uv).sqrt() * f64::from(inst.lightmap_scale),
        });
    }
    Ok(items)
}

/// `max_page_size` must be a page width the grid can hold and not below `resolution`.
pub fn check_page_sizes(resolution: u32, max_page_size: u32) -> Result<(), String> {
    if !(1..=super::MAX_RESOLUTION).contains(&max_page_size) {
        return Err(format!(
            "max_page_size must be between 1 and {}, got {max_page_size}",
            super::MAX_RESOLUTION
        ));
    }
    if max_page_size < resolution {
        return Err(format!(
            "max_page_size {max_page_size} is below resolution {resolution}: pages start resolution wide and grow up to max_page_size"
        ));
    }
    Ok(())
}

/// The unwrap on pages as narrow as they can be: with the automatic density, pages
/// `resolution` wide (the density is the highest that fits one). At a fixed density the
/// width starts at [`page_width_for`]'s estimate and doubles, up to `max_page_size`, while
/// the charts need more than one page or a chart had to be scaled down to fit one; at
/// `max_page_size` they take as many pages as they need ([`unwrap_fitting`]). Why grow the
/// page before adding pages: a level designer who sets a density expects one lightmap
/// where one is enough (Unity and Bakery pack into as few atlases as their maximum size
/// allows), and a 256-wide page at 40 texels/m splits a room's floor.
fn unwrap_paged(
    unwrapper: &dyn Unwrapper,
    inputs: &[UnwrapMesh],
    resolution: u32,
    max_page_size: u32,
    texels_per_unit: Option<f32>,
    warnings: &mut Vec<String>,
) -> Result<Unwrapped, String> {
    let Some(t) = texels_per_unit.filter(|_| max_page_size > resolution) else {
        return unwrap_fitting(unwrapper, inputs, resolution, texels_per_unit, warnings);
    };
    let mut w = page_width_for(inputs, t, resolution, max_page_size);
    while w < max_page_size {
        match unwrapper.unwrap(inputs, w, Some(t)) {
            Ok(u) if u.pages == 1 && !scaled_down(inputs, &u, t) => {
                tracing::debug!(width = w, "the charts fit one page");
                return Ok(u);
            }
            Err(e) if !e.contains("doesn't fit") => return Err(e),
            _ => {}
        }
        w = w.saturating_mul(2).min(max_page_size);
    }
    unwrap_fitting(unwrapper, inputs, max_page_size, Some(t), warnings)
}

/// The first page width [`unwrap_paged`] tries: `resolution` doubled until one page holds
/// the charts' texel area at density `t` (each instance's surface area × (its scale × t)²)
/// at [`ASSUMED_FILL`], and its largest instance's bounding box, capped at `max_page_size`.
fn page_width_for(inputs: &[UnwrapMesh], t: f32, resolution: u32, max_page_size: u32) -> u32 {
    let mut area = 0.0f64;
    let mut side = 0.0f64;
    for m in inputs {
        let p = |i: u32| glam::DVec3::from(m.positions[i as usize].map(f64::from));
        let local = m.area();
        // The largest face of the mesh's box: a flat mesh unwraps to about that.
        let (lo, hi) = m.indices.iter().fold(
            (glam::DVec3::splat(f64::INFINITY), glam::DVec3::splat(f64::NEG_INFINITY)),
            |(lo, hi), &i| (lo.min(p(i)), hi.max(p(i))),
        );
        let e = (hi - lo).max(glam::DVec3::ZERO);
        let face = (e.x * e.y).max(e.y * e.z).max(e.x * e.z).sqrt().min(local.sqrt());
        for &s in &m.instance_scales {
            let k = f64::from(s) * f64::from(t);
            area += local * k * k;
            side = side.max(face * k);
        }
    }
    let need = (area / ASSUMED_FILL).sqrt().max(side + f64::from(2 * PADDING));
    let mut w = resolution.max(1);
    while f64::from(w) < need && w < max_page_size {
        w = w.saturating_mul(2).min(max_page_size);
    }
    w
}

/// Whether some instance's texels came out sparser than [`SCALED_DOWN`] × its density
/// asked (a chart larger than the page, scaled down to fit it): its rectangle's texel area
/// times the layout's covered share, over its surface area.
fn scaled_down(inputs: &[UnwrapMesh], u: &Unwrapped, t: f32) -> bool {
    let page = glam::DVec2::new(f64::from(u.width), f64::from(u.page_height));
    inputs.iter().zip(&u.meshes).any(|(m, out)| {
        let local = m.area();
        let uv = |i: u32| out.uv[i as usize].as_dvec2();
        let covered: f64 = out
            .indices
            .chunks_exact(3)
            .map(|c| 0.5 * (uv(c[1]) - uv(c[0])).perp_dot(uv(c[2]) - uv(c[0])).abs())
            .sum();
        if local <= 0.0 || covered <= 0.0 {
            return false;
        }
        m.instance_scales.iter().zip(&out.instances).any(|(&s, (_, lo, hi))| {
            let rect = (hi.as_dvec2() - lo.as_dvec2()) * page;
            let achieved = (rect.x * rect.y * covered / local).sqrt();
            achieved < SCALED_DOWN * f64::from(s) * f64::from(t)
        })
    })
}

/// The unwrap at `texels_per_unit`, or, when a layout does not fit a page at that fixed
/// density, at the highest of 8 densities lowered by a quarter each that fits, with a
/// warning. Why: uvunwrap 0.3 scales a single chart down to fit a page
/// (`max_chart_size`), but not the layout of an instanced mesh's charts, which it places
/// as one rectangle per instance; at a fixed density that layout can be taller than a
/// page and the whole unwrap fails (the Kenney level at 40 texels/m on 256-wide pages:
/// "chart of 209x947 texels doesn't fit a 256x256 page"). A bake at a lower density with
/// a warning is what a level designer can use; a failure is not.
fn unwrap_fitting(
    unwrapper: &dyn Unwrapper,
    inputs: &[UnwrapMesh],
    resolution: u32,
    texels_per_unit: Option<f32>,
    warnings: &mut Vec<String>,
) -> Result<Unwrapped, String> {
    let first = unwrapper.unwrap(inputs, resolution, texels_per_unit);
    let (Err(e), Some(asked)) = (&first, texels_per_unit) else {
        return first;
    };
    if !e.contains("doesn't fit") {
        return first;
    }
    let why = e.split(';').next().unwrap_or(e);
    let mut t = asked;
    for _ in 0..8 {
        t *= 0.75;
        if let Ok(u) = unwrapper.unwrap(inputs, resolution, Some(t)) {
            warnings.push(format!(
                "texels_per_unit {asked}: {why}; baked at {t:.2} texels/m instead (an instanced mesh's charts are not scaled down alone; raise max_page_size for the density asked)"
            ));
            return Ok(u);
        }
    }
    first
}

/// World area and lightmap UV area of `triangles`.
fn areas(triangles: &[crate::engine::scene::Triangle]) -> (f64, f64) {
    triangles.iter().fold((0.0, 0.0), |(world, uv), t| {
        (
            world + 0.5 * f64::from((t.p[1] - t.p[0]).cross(t.p[2] - t.p[0]).length()),
            uv + 0.5 * f64::from((t.lm[1] - t.lm[0]).perp_dot(t.lm[2] - t.lm[0]).abs()),
        )
    })
}

/// Below this share of the generated pages covered by triangles, at the automatic
/// density, [`padding_bound`] warns. The bundled levels at 256² cover 23 % (the living
/// room) and 40 % (the occlusion room); the Kenney level 1 % (at 512², 33 %).
const LOW_FILL: f64 = 0.10;

/// At the automatic density, warns when the generated charts cover less than [`LOW_FILL`]
/// of their pages, naming the meshes whose instances take the most page beyond their
/// share of the surface. Why: the packer's padding is [`PADDING`] texels around every
/// chart whatever the density, and a mesh's layout is placed once per instance, so a
/// level of many small charts in many instances (grass tufts, props) fills a small page
/// with padding, and the density that fits it collapses: the Kenney level at 256² bakes 1,005 texels at 1.0 texels/m, at 512²
/// 88,285 at 9.8. Nothing is wrong with such a bake, but it is not what a level designer
/// wants, and what to change is not obvious from the texel count alone. The advice is a
/// larger page or opting the detail out (its grass and grass-small out: 8,148 texels at
/// 3.0 texels/m on the same 256² page), not `extras.lightmap_scale`: its padding does not
/// shrink with its charts (the grass at 0.1: 292 texels at 0.57 texels/m).
fn padding_bound(
    scene: &Scene,
    instances: &[crate::engine::scene::Instance],
    generate: &[bool],
    layout: &LightmapLayout,
    u: &Unwrapped,
    (wf, hf): (f32, f32),
    warnings: &mut Vec<String>,
) {
    let page = f64::from(u.width) * f64::from(u.width.max(u.page_height)) * f64::from(u.pages.max(1));
    // Per mesh: instances, texels of their rectangles, world area of their triangles.
    let mut per_mesh: Vec<(usize, u32, f64, f64)> = Vec::new();
    let (mut covered, mut surface) = (0.0f64, 0.0f64);
    for (k, inst) in instances.iter().enumerate() {
        let Some(so) = layout.scale_offset[k].filter(|_| !inst.opt_out && generate[inst.mesh]) else {
            continue;
        };
        let (world, uv) = areas(&scene.triangles[inst.triangles.clone()]);
        covered += uv * f64::from(wf) * f64::from(hf);
        surface += world;
        let rect = f64::from(so[0] * wf) * f64::from(so[1] * hf);
        match per_mesh.iter_mut().find(|m| m.0 == inst.mesh) {
            Some(m) => {
                m.1 += 1;
                m.2 += rect;
                m.3 += world;
            }
            None => per_mesh.push((inst.mesh, 1, rect, world)),
        }
    }
    let fill = covered / page;
    if !(page > 0.0 && surface > 0.0) || fill >= LOW_FILL {
        return;
    }
    // Page share beyond surface share: what a mesh's padding costs the rest.
    let excess = |m: &(usize, u32, f64, f64)| m.2 / page - m.3 / surface;
    per_mesh.sort_by(|a, b| excess(b).total_cmp(&excess(a)));
    let most: Vec<String> = per_mesh
        .iter()
        .filter(|m| excess(m) > 0.0)
        .take(3)
        .map(|&(m, n, rect, world)| {
            let of = if n == 1 {
                "1 instance".to_string()
            } else {
                format!("{n} instances")
            };
            format!(
                "{} ({of}: {:.0} % of the page for {:.1} % of the surface)",
                mesh_label(scene, m),
                100.0 * rect / page,
                100.0 * world / surface
            )
        })
        .collect();
    let pages = match u.pages {
        0 | 1 => format!("{}x{} page", u.width, u.width.max(u.page_height)),
        n => format!("{n} pages of {}x{}", u.width, u.width.max(u.page_height)),
    };
    warnings.push(format!(
        "the generated charts cover {:.0} % of their {pages} at {:.2} texels/m: the rest is padding ({PADDING} texels around each of {} charts, once for each instance of its mesh), which keeps the density low; the meshes taking the most page for their surface: {}. Raise the resolution (the density grows faster than the page), or opt such detail meshes out with extras.lightmap: false (they still cast shadows)",
        100.0 * fill,
        u.texels_per_metre,
        u.charts,
        most.join(", ")
    ));
}

/// Below this fraction of the asked density, a mesh's charts count as scaled down. Area
/// distortion moves single triangles, not a mesh's total, so the margin is for rounding;
/// the 4 m squares of tests/real_levels.rs at 100 texels/m, scaled from 400 texels to a
/// 256 page, measure 62.00.
const SCALED_DOWN: f64 = 0.85;

/// `mesh M "NAME"` for messages.
fn mesh_label(scene: &Scene, m: usize) -> String {
    match scene.meshes.get(m).map(|i| i.name.as_str()).filter(|n| !n.is_empty()) {
        Some(n) => format!("mesh {m} \"{n}\""),
        None => format!("mesh {m}"),
    }
}

/// UV area of the generated (and repacked) meshes' triangles over the grid's: how much of
/// it the new charts and rectangles cover.
fn utilisation(scene: &Scene, instances: &[crate::engine::scene::Instance], generate: &[bool]) -> f32 {
    let mut area = 0.0f64;
    for inst in instances.iter().filter(|i| !i.opt_out && generate[i.mesh]) {
        area += areas(&scene.triangles[inst.triangles.clone()]).1;
    }
    area as f32
}
