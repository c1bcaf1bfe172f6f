//! The scene as every technique sees it: world-space triangles with their lightmap UVs,
//! materials, punctual lights, and the lighting a job adds (sky, sun).
//!
//! Data flow: [`import`] reads glTF 2.0 (`.glb`, or `.gltf` with external or data-URI
//! buffers) and flattens the node hierarchy into one triangle list in world space, so no
//! technique ever walks a node tree. [`build`] goes the other way: it writes small scenes
//! made in code (the bundled Cornell box, the analytic test scenes) as `.glb`, so tests
//! exercise the same import path a user's file takes.
//!
//! Conventions (DESIGN §2): glTF's right-handed, +Y up, metres. Colours are linear RGB.
//! glTF's photometric light units are read as radiometric ones with no conversion
//! (candela as W/sr, lux as W/m²), the choice Godot and Blender's importers make; see
//! `docs/conventions.md`.
//!
//! Precision: the importer removes the centre of the scene's bounds from every position
//! (kept in [`Scene::origin_offset`], in f64), so a scene translated by 1e5 m keeps full
//! f32 precision near its geometry. Irradiance does not depend on where the scene sits.
//!
//! The import also keeps the input document ([`SourceDocument`]: its JSON, buffers, each
//! placed mesh's local geometry and every placing node as an [`Instance`]), and which
//! primitive triangle each scene triangle came from ([`TriSource`]): lightmap UVs are
//! generated per mesh (`atlas::unwrap`, [`LightmapLayout`]) and `export` writes the same
//! document back with them.
//!
//! Alpha: a MASK material's surface is there where its coverage (`baseColorFactor` alpha
//! × base colour texture alpha, [`Scene::coverage`]) reaches `alphaCutoff`; a BLEND one
//! stops a ray with probability equal to its coverage ([`Scene::stops_ray`]), decided by a
//! hash of the ray and the triangle so that the CPU and the GPU (`gpu/lights.wgsl`,
//! `bvh_alpha_accept`) decide the same ray the same way. Which visibility queries of
//! which technique honour it is each technique's `alpha` entry in the technique table.
//!
//! Limits: morph targets and skins are ignored (the bind pose is baked). A base colour `KHR_texture_transform` is
//! applied to TEXCOORD_0 at import, so an emissive texture on the same material reads
//! the transformed UVs too. Albedo is bounded by [`ALBEDO_BOUND`] and
//! [`DEFAULT_MATERIAL_ALBEDO`].

pub mod build;
mod error;
pub mod export;
pub mod import;
pub mod library;

pub use error::ImportError;

/// Largest diffuse albedo a material of the file keeps (every colour channel of
/// `baseColorFactor` is bounded at import, so texture × factor is too, for every
/// technique): an albedo of 1 reflects everything, and in a closed level a path then
/// bounces until it escapes. 0.999 changes no physical material and keeps deliberate
/// stiff test scenes (ρ = 0.99, 0.999) as they are.
pub const ALBEDO_BOUND: f32 = 0.999;

/// How many items a warning names before it counts the rest ([`listed`]).
pub(crate) const LISTED: usize = 8;

/// `items` joined by `sep`, the first [`LISTED`] of them and then a count of the rest: a
/// level of thousands of meshes or materials would otherwise make one warning of
/// thousands of names (a generated 256k-triangle level's, 2001 meshes without lightmap
/// UVs, was 100 kB on one line).
pub(crate) fn listed(items: &[String], sep: &str) -> String {
    let mut out = items.iter().take(LISTED).cloned().collect::<Vec<_>>().join(sep);
    if items.len() > LISTED {
        out.push_str(&format!("{sep}and {} more", items.len() - LISTED));
    }
    out
}

/// Warnings of one kind, one an item (`(name, its own warning)`): each its own while
/// there are at most [`LISTED`], else one warning, `many(count, names listed)`, so that a
/// level of thousands of nodes makes one line, not thousands.
pub(crate) fn warn_each(
    warnings: &mut Vec<String>,
    items: Vec<(String, String)>,
    many: impl FnOnce(usize, String) -> String,
) {
    if items.len() <= LISTED {
        warnings.extend(items.into_iter().map(|(_, own)| own));
    } else {
        let names: Vec<String> = items.iter().map(|(name, _)| name.clone()).collect();
        warnings.push(many(items.len(), listed(&names, "; ")));
    }
}

/// Albedo of glTF's default material (primitives without a material), for bounced light:
/// glTF says white (1), which makes a mostly closed level bounce without end (issue 19:
/// one 4-sample step of a 181k-texel level took 144 s); 0.8 is Blender's default base
/// colour, and bakers bound this case too (Unity, Lightmass and Bakery scale or clamp
/// albedo for bounced light). The import report states both bounds and names the
/// materials they changed.
pub const DEFAULT_MATERIAL_ALBEDO: f32 = 0.8;
pub use import::{ImportLimits, ImportReport, import_file, import_slice, import_slice_limited};

use std::sync::Arc;

use glam::{DVec3, Vec2, Vec3, Vec4};
use serde::{Deserialize, Serialize};

/// One world-space triangle with everything a technique needs at a hit point.
#[derive(Clone, Debug)]
pub struct Triangle {
    /// Positions, relative to [`Scene::origin_offset`].
    pub p: [Vec3; 3],
    /// Shading normals (unit length). Flat normals when the mesh has none.
    pub n: [Vec3; 3],
    /// TEXCOORD_0 (zero when absent): base-colour and emissive textures use it by default.
    pub uv: [Vec2; 3],
    /// TEXCOORD_1: the lightmap UV, in [0, 1].
    pub lm: [Vec2; 3],
    pub material: u32,
    /// Index into [`Scene::meshes`], for error messages and reports.
    pub mesh: u32,
}

impl Triangle {
    /// Unnormalised geometric normal, following the winding (counter-clockwise is front).
    pub fn cross(&self) -> Vec3 {
        (self.p[1] - self.p[0]).cross(self.p[2] - self.p[0])
    }

    /// The point at barycentric weights `b`.
    pub fn point(&self, b: Vec3) -> Vec3 {
        self.p[0] * b.x + self.p[1] * b.y + self.p[2] * b.z
    }

    pub fn area(&self) -> f32 {
        0.5 * self.cross().length()
    }

    pub fn geometric_normal(&self) -> Vec3 {
        self.cross().normalize_or_zero()
    }
}

/// A texture, decoded to linear RGBA f32 (sRGB-encoded colour textures are linearised
/// once at import, not at every lookup).
#[derive(Clone, Debug)]
pub struct Texture {
    pub width: u32,
    pub height: u32,
    pub texels: Vec<Vec4>,
    pub wrap_u: Wrap,
    pub wrap_v: Wrap,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Wrap {
    Repeat,
    Mirror,
    Clamp,
}

impl Texture {
    /// Bilinear lookup with the texture's wrap modes; `uv` in glTF's convention (v down).
    pub fn sample(&self, uv: Vec2) -> Vec4 {
        let x = uv.x * self.width as f32 - 0.5;
        let y = uv.y * self.height as f32 - 0.5;
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let fetch = |xi: i64, yi: i64| -> Vec4 {
            let xi = wrap(xi, self.width, self.wrap_u);
            let yi = wrap(yi, self.height, self.wrap_v);
            self.texels[(yi * self.width as usize) + xi]
        };
        let (xi, yi) = (x0 as i64, y0 as i64);
        let top = fetch(xi, yi).lerp(fetch(xi + 1, yi), fx);
        let bottom = fetch(xi, yi + 1).lerp(fetch(xi + 1, yi + 1), fx);
        top.lerp(bottom, fy)
    }
}

fn wrap(i: i64, n: u32, mode: Wrap) -> usize {
    let n = n as i64;
    let r = match mode {
        Wrap::Repeat => i.rem_euclid(n),
        Wrap::Clamp => i.clamp(0, n - 1),
        Wrap::Mirror => {
            let period = i.rem_euclid(2 * n);
            if period < n { period } else { 2 * n - 1 - period }
        }
    };
    r as usize
}

/// Which texture a material slot reads and with which UV set.
#[derive(Clone, Copy, Debug)]
pub struct TextureRef {
    pub texture: u32,
    /// 0 = TEXCOORD_0, 1 = TEXCOORD_1 (the lightmap UV).
    pub texcoord: u32,
}

/// glTF metallic-roughness material, reduced to what lightmap transport uses.
#[derive(Clone, Debug)]
pub struct Material {
    pub name: String,
    /// Linear RGBA; RGB is the diffuse albedo.
    pub base_color: Vec4,
    pub base_color_texture: Option<TextureRef>,
    /// Emitted radiance factor: `emissiveFactor` × `KHR_materials_emissive_strength`.
    pub emissive: Vec3,
    pub emissive_texture: Option<TextureRef>,
    pub metallic: f32,
    pub roughness: f32,
    pub double_sided: bool,
    /// glTF `alphaMode` / `alphaCutoff`: how the surface covers what is behind it.
    pub alpha_mode: AlphaMode,
}

/// glTF `alphaMode`, as visibility uses it.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub enum AlphaMode {
    /// The surface is there everywhere; alpha is ignored.
    #[default]
    Opaque,
    /// There where the coverage is at least `cutoff` (glTF's default 0.5).
    Mask { cutoff: f32 },
    /// Stops light in proportion to its coverage (a ray passes with probability
    /// 1 − coverage).
    Blend,
}

impl Default for Material {
    /// glTF's default material: white, dielectric, fully rough, single-sided.
    fn default() -> Self {
        Material {
            name: "default".into(),
            base_color: Vec4::ONE,
            base_color_texture: None,
            emissive: Vec3::ZERO,
            emissive_texture: None,
            metallic: 1.0,
            roughness: 1.0,
            double_sided: false,
            alpha_mode: AlphaMode::Opaque,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "type")]
pub enum LightKind {
    Directional,
    Point,
    /// Cone angles in radians from the axis; glTF's smooth falloff between them.
    Spot {
        inner_cone: f32,
        outer_cone: f32,
    },
}

/// A `KHR_lights_punctual` light, placed in the world.
#[derive(Clone, Debug, Serialize)]
pub struct PunctualLight {
    pub name: String,
    pub kind: LightKind,
    /// colour × intensity: W/sr for point and spot, W/m² for directional.
    pub intensity: Vec3,
    pub position: Vec3,
    /// The direction the light travels (the node's -Z), unit length.
    pub direction: Vec3,
    pub range: Option<f32>,
}

impl PunctualLight {
    /// The share of a point or spot light's intensity that leaves it along `dir` (unit,
    /// pointing away from the light) and reaches distance `dist`, without the 1/d²:
    /// `KHR_lights_punctual`'s recommended range window `clamp(1 - (d/range)^4)^2`, so a
    /// light ends at its range, times a spot's smooth edge, the square of the linear ramp
    /// from the outer cone (0) to the inner cone (1). Every technique that bakes punctual
    /// lights uses this, so they agree with `path`. 1 for a directional light.
    pub fn attenuation(&self, dist: f32, dir: Vec3) -> f32 {
        let window = self
            .range
            .map_or(1.0, |r| (1.0 - (dist / r).powi(4)).clamp(0.0, 1.0).powi(2));
        let cone = match self.kind {
            LightKind::Spot { inner_cone, outer_cone } => {
                let scale = 1.0 / (inner_cone.cos() - outer_cone.cos()).max(1e-3);
                let a = ((dir.dot(self.direction) - outer_cone.cos()) * scale).clamp(0.0, 1.0);
                a * a
            }
            LightKind::Point => 1.0,
            LightKind::Directional => return 1.0,
        };
        window * cone
    }
}

/// A mesh as the report and error messages name it.
#[derive(Clone, Debug, Serialize)]
pub struct MeshInfo {
    pub name: String,
    pub index: usize,
    /// Relative texel density when lightmap UVs are generated (glTF mesh `extras`
    /// `"lightmap_scale"`, default 1): 2 gives this mesh twice the texels per metre.
    pub lightmap_scale: f32,
}

#[derive(Clone, Copy, Debug, Serialize)]
pub struct Bounds {
    pub min: Vec3,
    pub max: Vec3,
}

impl Bounds {
    pub const EMPTY: Bounds = Bounds {
        min: Vec3::splat(f32::INFINITY),
        max: Vec3::splat(f32::NEG_INFINITY),
    };

    pub fn grow(&mut self, p: Vec3) {
        self.min = self.min.min(p);
        self.max = self.max.max(p);
    }

    pub fn extent(&self) -> Vec3 {
        (self.max - self.min).max(Vec3::ZERO)
    }

    pub fn diagonal(&self) -> f32 {
        self.extent().length()
    }

    pub fn center(&self) -> Vec3 {
        0.5 * (self.min + self.max)
    }
}

/// An imported scene: what every technique bakes.
#[derive(Clone, Debug)]
pub struct Scene {
    pub triangles: Vec<Triangle>,
    pub materials: Vec<Material>,
    pub textures: Vec<Texture>,
    pub lights: Vec<PunctualLight>,
    /// Light probe positions the file gives: every node whose `extras.light_probe` is
    /// true, at its world translation (relative to `origin_offset`), with its name.
    pub probe_nodes: Vec<(String, Vec3)>,
    pub meshes: Vec<MeshInfo>,
    /// Bounds of `triangles` (after re-centring).
    pub bounds: Bounds,
    /// What was subtracted from every glTF world position.
    pub origin_offset: DVec3,
    /// Some mesh had no TEXCOORD_1: `atlas::unwrap` must generate every triangle's
    /// lightmap UVs before a texel set can be built.
    pub needs_lightmap_uvs: bool,
    /// The glTF document the scene came from, with each placed mesh's local geometry:
    /// what `atlas::unwrap` unwraps (once per mesh) and `export` writes back.
    pub source: Option<Arc<SourceDocument>>,
    /// One entry per triangle of [`Scene::triangles`]: where it came from.
    pub tri_source: Vec<TriSource>,
    /// Generated lightmap UVs and each instance's rectangle, once `atlas::unwrap` ran.
    pub layout: Option<Arc<LightmapLayout>>,
}

/// The input document, kept so the written glTF is the same level with lightmap UVs added.
#[derive(Debug)]
pub struct SourceDocument {
    /// The document's JSON, as parsed (unknown extensions and extras included).
    pub json: serde_json::Value,
    /// Its buffers, resolved (GLB binary chunk, external files, data URIs).
    pub buffers: Vec<Vec<u8>>,
    /// Where relative image URIs resolve (None: only embedded data was allowed).
    pub base_dir: Option<std::path::PathBuf>,
    /// Per glTF mesh (by index), its local geometry when some node of the scene uses it.
    pub meshes: Vec<Option<LocalMesh>>,
    /// Every node of the default scene that places a mesh, in visiting order.
    pub instances: Vec<Instance>,
}

/// A glTF mesh in its own space.
#[derive(Debug, Clone)]
pub struct LocalMesh {
    /// Per primitive (by index), its TRIANGLES geometry (None for other modes).
    pub primitives: Vec<Option<LocalPrimitive>>,
}

impl LocalMesh {
    /// Every TRIANGLES primitive has `TEXCOORD_1`.
    pub fn authored(&self) -> bool {
        self.primitives.iter().flatten().all(|p| p.has_lightmap_uvs)
    }
}

#[derive(Debug, Clone)]
pub struct LocalPrimitive {
    pub positions: Vec<Vec3>,
    /// Triangle list (a multiple of 3), as read (non-indexed primitives get 0..n).
    pub indices: Vec<u32>,
    pub has_lightmap_uvs: bool,
}

/// A node of the scene that places a mesh.
#[derive(Debug, Clone)]
pub struct Instance {
    pub node: usize,
    pub mesh: usize,
    /// The node's world transform (glTF space, before re-centring).
    pub world: glam::DMat4,
    /// `extras.lightmap_scale` of the node times that of the mesh.
    pub lightmap_scale: f32,
    /// `extras.lightmap: false`: casts shadows, gets no texels.
    pub opt_out: bool,
    /// For authored UVs: the node's `extras.lightmap.scale_offset` (`[1, 1, 0, 0]` when
    /// absent), already applied to its triangles' `lm`.
    pub authored_scale_offset: [f32; 4],
    /// For authored UVs: the node's `extras.lightmap.page` (0 when absent): the page its
    /// `lm` address, which `atlas::unwrap` stacks in the bake's grid.
    pub authored_page: u32,
    /// Its triangles in [`Scene::triangles`].
    pub triangles: std::ops::Range<usize>,
}

/// Where a scene triangle came from: primitive, triangle of that primitive's index list,
/// and whether its corners were reordered (a mirroring transform flips the winding).
#[derive(Debug, Clone, Copy)]
pub struct TriSource {
    pub primitive: u32,
    pub triangle: u32,
    pub mirrored: bool,
}

/// Generated lightmap UVs: per mesh its new vertices, per instance its rectangle in the
/// bake's grid, and the pages that grid is cut into.
#[derive(Debug, Clone, Default)]
pub struct LightmapLayout {
    /// The bake's texel grid: every page, one under another (`width` × `height`).
    pub width: u32,
    pub height: u32,
    /// Per glTF mesh (by index): the generated UVs, when the mesh got them.
    pub meshes: Vec<Option<GeneratedMesh>>,
    /// Layouts of their own for instances whose transform stretches their mesh
    /// (`atlas::unwrap::OWN_LAYOUT_RATIO`): each written as a copy of the mesh.
    pub copies: Vec<MeshCopy>,
    /// Per entry of [`SourceDocument::instances`]: `[sx, sy, ox, oy]` such that the UV in
    /// the bake's grid = TEXCOORD_1 · (sx, sy) + (ox, oy); None for opted-out instances.
    /// [`Scene::placements`] turns it into the page and the page's own scale/offset.
    pub scale_offset: Vec<Option<[f32; 4]>>,
    /// The output pages, as row bands of the grid, top to bottom, covering it.
    pub pages: Vec<PageRows>,
}

/// A copy of a glTF mesh with a lightmap layout of its own, for the instances listed
/// (entries of [`SourceDocument::instances`]): `scene::export` appends it to the written
/// document's meshes and points those instances' nodes at it.
#[derive(Debug, Clone, Default)]
pub struct MeshCopy {
    pub mesh: usize,
    pub generated: GeneratedMesh,
    pub instances: Vec<usize>,
}

impl LightmapLayout {
    /// The generated UVs instance `instance` (of glTF mesh `mesh`) is baked with: its
    /// copy's, else its mesh's.
    pub fn generated_for(&self, instance: usize, mesh: usize) -> Option<&GeneratedMesh> {
        match self.copies.iter().find(|c| c.instances.contains(&instance)) {
            Some(c) => Some(&c.generated),
            None => self.meshes.get(mesh).and_then(Option::as_ref),
        }
    }
}

/// The rows of the bake's texel grid that make one output page (`lightmap-P.exr`): pages
/// share the grid's width and lie one under another, in page order (`atlas::unwrap`).
/// Each page is its own texel grid in DESIGN §2's sense: its first row is row 0.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct PageRows {
    pub first_row: u32,
    pub rows: u32,
}

impl PageRows {
    pub fn contains_row(&self, row: u32) -> bool {
        row >= self.first_row && row - self.first_row < self.rows
    }
}

/// Where a node's lightmap is: its page, and `[sx, sy, ox, oy]` such that the UV in that
/// page's texel grid = TEXCOORD_1 · (sx, sy) + (ox, oy) (`extras.lightmap` of the
/// written glTF, and the manifest's `nodes`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Placement {
    /// Its index in [`SourceDocument::instances`].
    #[serde(skip)]
    pub instance: usize,
    /// The glTF node.
    pub node: usize,
    /// The mesh the node uses in the written glTF: the input's, or the copy appended for
    /// a stretched instance's own layout ([`MeshCopy`]).
    pub mesh: usize,
    pub page: u32,
    pub scale_offset: [f32; 4],
}

/// The page of `pages` holding the rectangle `[sx, sy, ox, oy]` of a `height`-row grid
/// (the page of its centre row), and the rectangle in that page's own UV.
pub fn page_placement(pages: &[PageRows], height: u32, so: [f32; 4]) -> (u32, [f32; 4]) {
    let h = height as f64;
    let centre = ((so[3] as f64 + 0.5 * so[1] as f64) * h).floor().clamp(0.0, h - 1.0) as u32;
    let Some((p, rows)) = pages.iter().enumerate().find(|(_, r)| r.contains_row(centre)) else {
        return (0, so);
    };
    if rows.first_row == 0 && rows.rows == height {
        return (p as u32, so);
    }
    let (first, n) = (rows.first_row as f64, rows.rows as f64);
    (
        p as u32,
        [
            so[0],
            (so[1] as f64 * h / n) as f32,
            so[2],
            ((so[3] as f64 * h - first) / n) as f32,
        ],
    )
}

/// One mesh's generated lightmap UVs, per primitive: the split vertices (each an index
/// into the primitive's original vertices, and its UV in the mesh's own [0, 1] layout)
/// and the triangle list over them (same triangles, same order).
#[derive(Debug, Clone, Default)]
pub struct GeneratedMesh {
    pub primitives: Vec<Option<GeneratedPrimitive>>,
}

#[derive(Debug, Clone, Default)]
pub struct GeneratedPrimitive {
    pub xref: Vec<u32>,
    pub uv: Vec<Vec2>,
    pub indices: Vec<u32>,
}

impl Scene {
    /// Pages that authored lightmap UVs address (1 + the largest `extras.lightmap.page`
    /// of a placing node that did not opt out); 0 without authored instances' pages.
    pub fn authored_pages(&self) -> u32 {
        self.source.as_ref().map_or(0, |s| {
            s.instances
                .iter()
                .filter(|i| !i.opt_out)
                .map(|i| i.authored_page + 1)
                .max()
                .unwrap_or(0)
        })
    }

    /// Per node that places a mesh and did not opt out: its page and rectangle there
    /// (the layout's pages; authored UVs without a layout are on the page they name).
    pub fn placements(&self) -> Vec<Placement> {
        let Some(source) = self.source.as_ref() else {
            return Vec::new();
        };
        source
            .instances
            .iter()
            .enumerate()
            .filter(|(_, i)| !i.opt_out)
            .filter_map(|(k, inst)| {
                let (page, scale_offset) = match self.layout.as_deref() {
                    Some(l) => page_placement(&l.pages, l.height, l.scale_offset.get(k).copied().flatten()?),
                    None => (inst.authored_page, inst.authored_scale_offset),
                };
                // A copy of the mesh with its own layout is appended after the input's
                // meshes in the written glTF (`export`): that is the mesh the node uses.
                let mesh = self
                    .layout
                    .as_deref()
                    .and_then(|l| l.copies.iter().position(|c| c.instances.contains(&k)))
                    .map_or(inst.mesh, |c| source.json["meshes"].as_array().map_or(0, Vec::len) + c);
                Some(Placement {
                    instance: k,
                    node: inst.node,
                    mesh,
                    page,
                    scale_offset,
                })
            })
            .collect()
    }

    /// Diffuse albedo at barycentric `b` of triangle `t` (texture × factor, linear).
    pub fn albedo(&self, t: &Triangle, b: Vec3) -> Vec3 {
        let m = &self.materials[t.material as usize];
        let mut c = m.base_color.truncate();
        if let Some(r) = m.base_color_texture {
            c *= self.textures[r.texture as usize]
                .sample(interp_uv(t, r.texcoord, b))
                .truncate();
        }
        c
    }

    /// Emitted radiance at barycentric `b` of triangle `t` (factor × strength × texture).
    pub fn emission(&self, t: &Triangle, b: Vec3) -> Vec3 {
        let m = &self.materials[t.material as usize];
        let mut e = m.emissive;
        if e != Vec3::ZERO
            && let Some(r) = m.emissive_texture
        {
            e *= self.textures[r.texture as usize]
                .sample(interp_uv(t, r.texcoord, b))
                .truncate();
        }
        e
    }

    pub fn material(&self, t: &Triangle) -> &Material {
        &self.materials[t.material as usize]
    }

    /// The corners' UVs in the set `t`'s base colour texture reads (TEXCOORD_0 when the
    /// material has no texture): what an alpha test interpolates.
    pub fn base_color_uvs(&self, t: &Triangle) -> [Vec2; 3] {
        match self.materials[t.material as usize].base_color_texture {
            Some(r) if r.texcoord == 1 => t.lm,
            _ => t.uv,
        }
    }

    /// glTF alpha at barycentric `b` of `t`: `baseColorFactor` alpha × the base colour
    /// texture's alpha (bilinear, at the texture's UV set), whatever the alpha mode.
    pub fn coverage(&self, t: &Triangle, b: Vec3) -> f32 {
        let m = &self.materials[t.material as usize];
        let mut a = m.base_color.w;
        if let Some(r) = m.base_color_texture {
            a *= self.textures[r.texture as usize].sample(interp_uv(t, r.texcoord, b)).w;
        }
        a
    }

    /// Whether triangle `id`, hit at barycentric `b` by the ray `origin + t·dir`, stops
    /// it: always for an opaque material; where the coverage reaches the cutoff for MASK;
    /// for BLEND when [`blend_draw`] of the ray and the triangle falls below the coverage.
    pub fn stops_ray(&self, id: u32, b: Vec3, origin: Vec3, dir: Vec3) -> bool {
        let t = &self.triangles[id as usize];
        match self.materials[t.material as usize].alpha_mode {
            AlphaMode::Opaque => true,
            AlphaMode::Mask { cutoff } => self.coverage(t, b) >= cutoff,
            AlphaMode::Blend => blend_draw(origin, dir, id) < self.coverage(t, b),
        }
    }
}

/// The uniform number in [0, 1) that decides whether a BLEND surface stops a ray: a hash
/// of the ray's origin and direction (their f32 bits) and the triangle's index, chained
/// through the PCG hash as `gpu/lights.wgsl`'s `alpha_draw` chains it, so a ray decides
/// the same on the CPU and the GPU. Rays with other origins or directions draw
/// independently, which is what makes the transmission right on average; the same ray
/// asked twice gets the same answer.
pub fn blend_draw(origin: Vec3, dir: Vec3, id: u32) -> f32 {
    use crate::engine::rng::pcg_hash as h;
    let mut x = h(id);
    for c in [dir.z, dir.y, dir.x, origin.z, origin.y, origin.x] {
        x = h(c.to_bits() ^ x);
    }
    (x >> 8) as f32 * (1.0 / 16_777_216.0)
}

impl Scene {
    /// Some material of the scene is MASK or BLEND.
    pub fn has_alpha(&self) -> bool {
        self.materials.iter().any(|m| m.alpha_mode != AlphaMode::Opaque)
    }

    /// The scale every relative epsilon is taken against.
    pub fn scale(&self) -> f32 {
        self.bounds.diagonal().max(f32::MIN_POSITIVE)
    }
}

fn interp_uv(t: &Triangle, set: u32, b: Vec3) -> Vec2 {
    let uv = if set == 1 { &t.lm } else { &t.uv };
    uv[0] * b.x + uv[1] * b.y + uv[2] * b.z
}

/// Which part of the sphere a uniform sky covers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Hemisphere {
    /// Directions with +Y > 0 only; below the horizon is black.
    #[default]
    Upper,
    Full,
}

/// Uniform sky radiance (W/(sr·m²)) over the upper hemisphere or the full sphere.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Sky {
    pub radiance: Vec3,
    pub hemisphere: Hemisphere,
}

/// A sun: a disc of uniform radiance seen under a small angle.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Sun {
    /// From the sun toward the scene, unit length.
    pub direction: Vec3,
    /// Full angular diameter of the disc, radians (> 0).
    pub angular_diameter: f32,
    pub radiance: Vec3,
}

impl Sun {
    /// cos of the disc's half angle: a direction `w` toward the sun is inside the disc
    /// when `dot(w, -direction) >= cos_half_angle()`.
    pub fn cos_half_angle(&self) -> f32 {
        (0.5 * self.angular_diameter).cos()
    }

    /// Solid angle of the disc, 2π(1 - cos θ), in a form accurate for tiny discs.
    pub fn solid_angle(&self) -> f32 {
        let s = (0.25 * self.angular_diameter).sin();
        4.0 * std::f32::consts::PI * s * s
    }
}

/// Below this share of the sky's irradiance a sun is warned about ([`Lighting::faint_sun`]):
/// a clear day's sun gives five to ten times the sky's, a low evening sun still tens of
/// per cent of it.
pub const FAINT_SUN: f32 = 0.01;

/// The light a job adds to the scene's own emitters and punctual lights.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Lighting {
    pub sky: Option<Sky>,
    pub sun: Option<Sun>,
}

impl Lighting {
    /// Radiance arriving from direction `w` (pointing away from the receiver) from the
    /// sky alone; the sun is handled by its own estimator.
    pub fn sky_radiance(&self, w: Vec3) -> Vec3 {
        match self.sky {
            Some(s) if s.hemisphere == Hemisphere::Full || w.y > 0.0 => s.radiance,
            _ => Vec3::ZERO,
        }
    }

    /// A sun too faint to matter beside the sky: its irradiance on a surface facing it
    /// (radiance times the disc's solid angle) below [`FAINT_SUN`] of the sky's on a
    /// surface facing up (π times the sky's radiance), by their channels' means. Not an
    /// error (an evening sun may be faint), but the usual cause is a sun given as an
    /// irradiance where DESIGN's convention is radiance: a 0.53° disc is 6.7e-5 sr, so a
    /// radiance of 40 gives 0.003 W/m², nothing under any sky.
    pub fn faint_sun(&self) -> Option<String> {
        let (sun, sky) = (self.sun?, self.sky?);
        let mean = |v: Vec3| v.element_sum() / 3.0;
        let omega = sun.solid_angle();
        let from_sun = mean(sun.radiance) * omega;
        let from_sky = mean(sky.radiance) * std::f32::consts::PI;
        (from_sun > 0.0 && from_sun < FAINT_SUN * from_sky).then(|| {
            format!(
                "the sun gives {from_sun:.3e} W/m² (its radiance {:.3e} per steradian times its disc's {omega:.2e} sr), {:.2} % of the sky's {from_sky:.3} on a surface facing up: the sun's radiance is per steradian; for an irradiance E give a radiance of E / {omega:.2e}",
                mean(sun.radiance),
                100.0 * from_sun / from_sky
            )
        })
    }

    /// Checks ranges; the message names the field.
    pub fn validate(&self) -> Result<(), String> {
        if let Some(s) = &self.sky
            && (!s.radiance.is_finite() || s.radiance.min_element() < 0.0)
        {
            return Err(format!(
                "lighting.sky.radiance must be finite and >= 0, got {:?}",
                s.radiance.to_array()
            ));
        }
        if let Some(s) = &self.sun {
            if !s.direction.is_finite() || s.direction.length() < 1e-6 {
                return Err(format!(
                    "lighting.sun.direction must be a non-zero finite vector, got {:?}",
                    s.direction.to_array()
                ));
            }
            if !(s.angular_diameter > 0.0 && s.angular_diameter < std::f32::consts::PI) {
                return Err(format!(
                    "lighting.sun.angular_diameter_deg must be in (0, 180), got {}",
                    s.angular_diameter.to_degrees()
                ));
            }
            if !s.radiance.is_finite() || s.radiance.min_element() < 0.0 {
                return Err(format!(
                    "lighting.sun.radiance must be finite and >= 0, got {:?}",
                    s.radiance.to_array()
                ));
            }
        }
        Ok(())
    }
}
