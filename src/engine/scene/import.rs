//! glTF 2.0 import: `.glb`, or `.gltf` with external or data-URI buffers and images.
//!
//! How: the `gltf` crate parses and validates the JSON; buffers and images are resolved
//! here rather than with its `import` feature, because every range is checked before it
//! is read (buffer view inside its buffer, accessor inside its view) and each failure must
//! name the buffer, mesh, primitive and accessor involved. The node hierarchy is walked
//! from the default scene (or every root when there is none) and every TRIANGLES
//! primitive is flattened into world space; a transform with a negative determinant
//! mirrors the mesh, so its winding is flipped to keep front faces in front.
//!
//! Validation (DESIGN §5): NaN or infinite positions, normals or UVs are rejected with the
//! accessor named; lightmap UVs must lie in [0, 1]; degenerate and zero-area triangles are
//! dropped and counted (they cover no texel and carry no light). Triangles with a
//! zero-area lightmap-UV footprint are kept for transport but counted, since they get no
//! texel of their own.
//!
//! Hostile input: [`ImportLimits`] caps what one import may allocate. The triangle cap is
//! checked while the node tree is flattened (a small file can instance one mesh from
//! millions of nodes), and a texture's size is read from its header before it is decoded
//! (a small PNG can claim 100 000² pixels). `import_slice` has no caps; the service calls
//! [`import_slice_limited`] with its configured ones.
//!
//! Real files (issue 19): only the default scene's node trees are walked, so meshes no
//! node of it places neither cast nor get texels; `KHR_mesh_quantization`'s integer
//! positions, normals and UVs are decoded; a primitive without normals gets flat ones; a
//! base colour `KHR_texture_transform` is applied to TEXCOORD_0; a node's
//! `extras.lightmap_scale`, `extras.lightmap: false` and `extras.lightmap.scale_offset`
//! are read; what the bake does not read (extensions by name, skins, animations, alpha
//! modes, normal textures, morph targets) is listed in one warning; albedo is bounded
//! (`scene::ALBEDO_BOUND`) and the report says so. A warning about one malformed item (a
//! bad `extras` field, an unread `texCoord` override, a non-triangle primitive, an index
//! count not a multiple of 3) is written one an item up to eight items of its kind, then
//! as one line that names eight and counts the rest: an exporter's mistake repeated on
//! every node of a level is one line, not thousands.
//!
//! Limits: sparse accessors, morph targets and skins are not read (sparse position or UV
//! accessors are an error; the others are listed in the report).

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use base64::Engine as _;
use glam::{DMat4, DVec3, Vec2, Vec3, Vec4};
use gltf::accessor::{DataType, Dimensions};
use gltf::mesh::Mode;
use serde::Serialize;

use super::error::{ImportError, PrimitiveRef};
use super::{
    AlphaMode, Bounds, Instance, LISTED, LightKind, LocalMesh, LocalPrimitive, Material, MeshInfo, PunctualLight,
    Scene, SourceDocument, Texture, TextureRef, TriSource, Triangle, Wrap, listed, warn_each,
};

/// What import found, for the CLI summary and the service's scene report.
#[derive(Clone, Debug, Default, Serialize)]
pub struct ImportReport {
    pub meshes: usize,
    pub primitives: usize,
    pub triangles: usize,
    pub materials: usize,
    pub textures: usize,
    pub lights: usize,
    /// How many of `lights` are directional (the rest are point or spot).
    #[serde(default)]
    pub directional_lights: usize,
    /// The lights' names in import order (a glTF light without one is `light <index>`),
    /// which a job's `shadowmask_lights` names.
    #[serde(default)]
    pub light_names: Vec<String>,
    /// Nodes marked `extras.light_probe` (probe positions a job's `probes` bakes).
    #[serde(default)]
    pub probe_nodes: usize,
    pub emissive_triangles: usize,
    /// Dropped because their world-space area is zero (or too small to have a normal).
    pub degenerate_triangles: usize,
    /// Kept, but with no area in lightmap UV space, so they own no texel.
    pub zero_uv_area_triangles: usize,
    pub bounds_min: [f64; 3],
    pub bounds_max: [f64; 3],
    /// Every mesh has TEXCOORD_1.
    pub has_lightmap_uvs: bool,
    /// Pixels of every decoded texture together (each is kept as four f32).
    #[serde(default)]
    pub texture_texels: u64,
    /// Largest diffuse albedo any material has for bounced light ([`super::ALBEDO_BOUND`]).
    pub albedo_bound: f32,
    /// Albedo used for glTF's default (white) material ([`super::DEFAULT_MATERIAL_ALBEDO`]).
    pub default_material_albedo: f32,
    /// Some primitive has no material (glTF's default white is used).
    pub default_material_used: bool,
    /// Materials with `alphaMode` MASK (with the cutoff) or BLEND, e.g. `leaves (MASK
    /// 0.5)`: their surfaces are alpha-tested where the technique's plan says.
    #[serde(default)]
    pub alpha_materials: Vec<String>,
    pub warnings: Vec<String>,
}

/// Caps on one import, for input nobody vetted (module doc).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImportLimits {
    /// Triangles after the node tree is flattened (instances count once each).
    pub max_triangles: usize,
    /// Width and height of each texture, read from the image header before decoding.
    pub max_texture_side: u32,
}

impl ImportLimits {
    pub const NONE: ImportLimits = ImportLimits {
        max_triangles: usize::MAX,
        max_texture_side: u32::MAX,
    };
}

/// Imports a `.glb` or `.gltf` file; relative URIs resolve against its folder.
pub fn import_file(path: &Path) -> Result<(Scene, ImportReport), ImportError> {
    let bytes = std::fs::read(path).map_err(|source| ImportError::Io {
        path: path.display().to_string(),
        source,
    })?;
    import_slice(&bytes, path.parent())
}

/// Imports glTF from memory. `base_dir` resolves relative URIs; `None` allows only
/// embedded data (GLB binary chunk and data URIs), which is what the service wants.
pub fn import_slice(bytes: &[u8], base_dir: Option<&Path>) -> Result<(Scene, ImportReport), ImportError> {
    import_slice_limited(bytes, base_dir, &ImportLimits::NONE)
}

/// [`import_slice`] with caps: over one, [`ImportError::Limit`] names it.
pub fn import_slice_limited(
    bytes: &[u8],
    base_dir: Option<&Path>,
    limits: &ImportLimits,
) -> Result<(Scene, ImportReport), ImportError> {
    let gltf = parse(bytes)?;
    let json = document_json(bytes)?;
    let buffers = load_buffers(&gltf, base_dir)?;
    let mut report = ImportReport::default();
    let textures = load_textures(&gltf, &buffers, base_dir, limits.max_texture_side)?;
    report.texture_texels = textures.iter().map(|t| u64::from(t.width) * u64::from(t.height)).sum();
    let mut materials = load_materials(&gltf)?;
    let mut items = ItemWarnings::default();
    let uv_transforms = texture_transforms(&json, materials.len(), &mut items);

    for ext in gltf.extensions_required() {
        if !matches!(
            ext,
            "KHR_lights_punctual"
                | "KHR_materials_emissive_strength"
                | "KHR_mesh_quantization"
                | "KHR_texture_transform"
        ) {
            report
                .warnings
                .push(format!("required extension {ext} is not supported and is ignored"));
        }
    }

    let mut ctx = Flatten {
        buffers: &buffers,
        triangles: Vec::new(),
        lights: Vec::new(),
        probe_nodes: Vec::new(),
        meshes: gltf
            .meshes()
            .map(|m| MeshInfo {
                name: m.name().unwrap_or("").to_string(),
                index: m.index(),
                lightmap_scale: lightmap_scale(&m, &mut items),
            })
            .collect(),
        report: &mut report,
        materials_len: materials.len() - 1,
        missing_lightmap_uvs: Vec::new(),
        visited_meshes: HashSet::new(),
        max_triangles: limits.max_triangles,
        local_meshes: vec![None; gltf.meshes().len()],
        uv_transforms,
        instances: Vec::new(),
        items,
    };
    let roots: Vec<gltf::Node> = match gltf.default_scene().or_else(|| gltf.scenes().next()) {
        Some(s) => s.nodes().collect(),
        None => {
            // No scene: glTF allows it; bake every node tree once, from its root.
            let children: HashSet<usize> = gltf.nodes().flat_map(|n| n.children().map(|c| c.index())).collect();
            gltf.nodes().filter(|n| !children.contains(&n.index())).collect()
        }
    };
    let mut seen_nodes = HashSet::new();
    for node in roots {
        ctx.visit(&node, DMat4::IDENTITY, &mut seen_nodes)?;
    }
    let Flatten {
        mut triangles,
        mut lights,
        probe_nodes,
        meshes,
        missing_lightmap_uvs,
        local_meshes,
        instances,
        items,
        ..
    } = ctx;
    items.write(&mut report.warnings);

    if !missing_lightmap_uvs.is_empty() {
        let which = match missing_lightmap_uvs.len() {
            1 => format!("{} has", missing_lightmap_uvs[0]),
            n if n <= LISTED => format!("{} have", missing_lightmap_uvs.join("; ")),
            n => format!("{n} primitives ({}) have", listed(&missing_lightmap_uvs, "; ")),
        };
        report.warnings.push(format!(
            "{which} no TEXCOORD_1: lightmap UVs will be generated for the meshes without them, authored ones are kept (bake --write-gltf saves them)"
        ));
    }
    shared_authored_warning(&instances, &local_meshes, &gltf, &mut report.warnings);
    unread_features(&json, &mut report.warnings);
    bound_albedo(&mut materials, &mut report);
    note_alpha(&materials, &mut report);
    if triangles.is_empty() {
        let why = if report.degenerate_triangles > 0 {
            format!(" (all {} triangles are degenerate)", report.degenerate_triangles)
        } else {
            String::new()
        };
        return Err(ImportError::NoTriangles(why));
    }

    // Re-centre in f64 so a scene far from the origin keeps f32 precision (module doc).
    let mut dmin = DVec3::splat(f64::INFINITY);
    let mut dmax = DVec3::splat(f64::NEG_INFINITY);
    for t in &triangles {
        for p in &t.world {
            dmin = dmin.min(*p);
            dmax = dmax.max(*p);
        }
    }
    let offset = 0.5 * (dmin + dmax);
    let mut bounds = Bounds::EMPTY;
    let tri_source: Vec<TriSource> = triangles.iter().map(|t| t.source).collect();
    let tris: Vec<Triangle> = triangles
        .drain(..)
        .map(|t| {
            let p = t.world.map(|w| (w - offset).as_vec3());
            p.iter().for_each(|q| bounds.grow(*q));
            Triangle {
                p,
                n: t.n,
                uv: t.uv,
                lm: t.lm,
                material: t.material,
                mesh: t.mesh,
            }
        })
        .collect();
    for l in &mut lights {
        l.light.position = (l.world_position - offset).as_vec3();
    }

    report.meshes = meshes.len();
    report.triangles = tris.len();
    report.materials = gltf.materials().len();
    report.textures = textures.len();
    report.lights = lights.len();
    report.light_names = lights.iter().map(|l| l.light.name.clone()).collect();
    report.probe_nodes = probe_nodes.len();
    report.directional_lights = lights
        .iter()
        .filter(|l| matches!(l.light.kind, LightKind::Directional))
        .count();
    report.emissive_triangles = tris
        .iter()
        .filter(|t| {
            materials
                .get(t.material as usize)
                .is_some_and(|m| m.emissive != Vec3::ZERO)
        })
        .count();
    report.bounds_min = dmin.to_array();
    report.bounds_max = dmax.to_array();
    report.has_lightmap_uvs = missing_lightmap_uvs.is_empty();

    let scene = Scene {
        triangles: tris,
        materials,
        textures,
        lights: lights.into_iter().map(|l| l.light).collect(),
        probe_nodes: probe_nodes
            .into_iter()
            .map(|(name, p)| (name, (p - offset).as_vec3()))
            .collect(),
        meshes,
        bounds,
        origin_offset: offset,
        needs_lightmap_uvs: !missing_lightmap_uvs.is_empty(),
        source: Some(std::sync::Arc::new(SourceDocument {
            json,
            buffers,
            base_dir: base_dir.map(Path::to_path_buf),
            meshes: local_meshes,
            instances,
        })),
        tri_source,
        layout: None,
    };
    Ok((scene, report))
}

/// A mesh's `extras.lightmap_scale`, if it is a positive finite number (else 1, warned).
fn lightmap_scale(mesh: &gltf::Mesh, items: &mut ItemWarnings) -> f32 {
    let Some(raw) = mesh.extras() else { return 1.0 };
    let Ok(value) = serde_json::from_str::<serde_json::Value>(raw.get()) else {
        return 1.0;
    };
    match value.get("lightmap_scale") {
        None => 1.0,
        Some(v) => match v.as_f64() {
            Some(s) if s.is_finite() && s > 0.0 && s <= 1e3 => s as f32,
            _ => {
                let name = match mesh.name() {
                    Some(n) => format!("mesh {} \"{n}\"", mesh.index()),
                    None => format!("mesh {}", mesh.index()),
                };
                items.push(
                    ItemKind::MeshScale,
                    format!("{name} ({v})"),
                    format!("{name}: extras.lightmap_scale {v} is not a number in (0, 1000]; using 1"),
                );
                1.0
            }
        },
    }
}

fn parse(bytes: &[u8]) -> Result<gltf::Gltf, ImportError> {
    if bytes.is_empty() {
        return Err(ImportError::NotGltf("the file is empty".into()));
    }
    let looks_binary = bytes.starts_with(b"glTF");
    let looks_json = bytes.iter().find(|b| !b.is_ascii_whitespace()) == Some(&b'{');
    if !looks_binary && !looks_json {
        return Err(ImportError::NotGltf(
            "neither a GLB header (\"glTF\" magic) nor a JSON document".into(),
        ));
    }
    // gltf 1.4 subtracts the 12-byte header from the declared length unchecked (an
    // overflow panic in builds with overflow checks; found by the fuzzer, issue 12).
    if looks_binary {
        let declared = bytes
            .get(8..12)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .ok_or_else(|| ImportError::NotGltf("broken GLB container: the 12-byte header is cut short".into()))?;
        if declared < 12 {
            return Err(ImportError::NotGltf(format!(
                "broken GLB container: the header declares {declared} bytes in all, less than the header itself"
            )));
        }
    }
    let map_err = |e: gltf::Error| match e {
        gltf::Error::Binary(b) => ImportError::NotGltf(format!("broken GLB container: {b:?}")),
        gltf::Error::Deserialize(d) => ImportError::NotGltf(format!("JSON: {d}")),
        other => ImportError::NotGltf(other.to_string()),
    };
    let gltf = gltf::Gltf::from_slice_without_validation(bytes).map_err(map_err)?;
    // gltf-json's validator indexes accessors by attribute without a bounds check (and
    // panics), so attribute indices are checked here first.
    let root = gltf.document.as_json();
    for (mi, mesh) in root.meshes.iter().enumerate() {
        for (pi, prim) in mesh.primitives.iter().enumerate() {
            for (semantic, index) in &prim.attributes {
                if index.value() >= root.accessors.len() {
                    return Err(ImportError::Invalid(format!(
                        "mesh {mi}, primitive {pi}: attribute {} refers to accessor {}, but there are {}",
                        semantic.to_string(),
                        index.value(),
                        root.accessors.len()
                    )));
                }
            }
        }
    }
    use gltf::json::validation::Validate;
    let mut errors = Vec::new();
    root.validate(root, gltf::json::Path::new, &mut |path, error| {
        errors.push((path(), error))
    });
    // Extensions read here from the JSON itself (not by the `gltf` crate) may be required.
    // (The path reads `extensionsRequired[i] = "NAME"`.)
    errors.retain(|(path, error)| {
        let p = path.as_str();
        !(matches!(error, gltf::json::validation::Error::Unsupported)
            && p.starts_with("extensionsRequired[")
            && (p.ends_with("\"KHR_mesh_quantization\"") || p.ends_with("\"KHR_texture_transform\"")))
    });
    if !errors.is_empty() {
        return Err(ImportError::Invalid(
            errors
                .iter()
                .take(5)
                .map(|(path, err)| format!("{path}: {err}"))
                .collect::<Vec<_>>()
                .join("; "),
        ));
    }
    Ok(gltf)
}

fn resolve_uri(uri: &str, base_dir: Option<&Path>, what: &str) -> Result<Vec<u8>, String> {
    if let Some(rest) = uri.strip_prefix("data:") {
        let (_, payload) = rest
            .split_once(";base64,")
            .ok_or_else(|| format!("{what}: data URI is not base64"))?;
        return base64::engine::general_purpose::STANDARD
            .decode(payload)
            .map_err(|e| format!("{what}: bad base64 in data URI: {e}"));
    }
    if uri.contains("://") {
        return Err(format!(
            "{what}: URI scheme of {uri:?} is not supported (only relative paths and data URIs)"
        ));
    }
    let base = base_dir
        .ok_or_else(|| format!("{what}: external file {uri:?} cannot be resolved here (upload it with the scene)"))?;
    let decoded = percent_decode(uri);
    let rel = PathBuf::from(&decoded);
    if rel.is_absolute() || rel.components().any(|c| matches!(c, std::path::Component::ParentDir)) {
        return Err(format!(
            "{what}: external file {uri:?} must be a relative path inside the scene's folder"
        ));
    }
    std::fs::read(base.join(&rel)).map_err(|e| format!("{what}: cannot read external file {decoded:?}: {e}"))
}

/// The bytes of an external (relative, non-data) URI, for the exporter.
pub(crate) fn read_external(uri: &str, base_dir: Option<&Path>) -> Result<Vec<u8>, String> {
    resolve_uri(uri, base_dir, "uri")
}

fn percent_decode(s: &str) -> String {
    let bytes = s.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i] == b'%'
            && i + 2 < bytes.len()
            && let Ok(v) = u8::from_str_radix(std::str::from_utf8(&bytes[i + 1..i + 3]).unwrap_or("zz"), 16)
        {
            out.push(v);
            i += 3;
            continue;
        }
        out.push(bytes[i]);
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

fn load_buffers(gltf: &gltf::Gltf, base_dir: Option<&Path>) -> Result<Vec<Vec<u8>>, ImportError> {
    let mut out = Vec::new();
    for buffer in gltf.buffers() {
        let i = buffer.index();
        let data = match buffer.source() {
            gltf::buffer::Source::Bin => gltf.blob.clone().ok_or_else(|| ImportError::Buffer {
                buffer: i,
                problem: "refers to the GLB binary chunk, but the file has none".into(),
            })?,
            gltf::buffer::Source::Uri(uri) => {
                resolve_uri(uri, base_dir, "uri").map_err(|problem| ImportError::Buffer { buffer: i, problem })?
            }
        };
        if data.len() < buffer.length() {
            return Err(ImportError::Buffer {
                buffer: i,
                problem: format!(
                    "truncated: byteLength is {} but only {} bytes are present",
                    buffer.length(),
                    data.len()
                ),
            });
        }
        out.push(data);
    }
    Ok(out)
}

fn view_bytes<'b>(view: &gltf::buffer::View, buffers: &'b [Vec<u8>]) -> Result<&'b [u8], String> {
    let buf = buffers
        .get(view.buffer().index())
        .ok_or("buffer view refers to a missing buffer")?;
    let end = view
        .offset()
        .checked_add(view.length())
        .ok_or("buffer view range overflows")?;
    if end > buf.len() {
        return Err(format!(
            "buffer view {} (bytes {}..{}) lies outside buffer {} of {} bytes",
            view.index(),
            view.offset(),
            end,
            view.buffer().index(),
            buf.len()
        ));
    }
    Ok(&buf[view.offset()..end])
}

fn load_textures(
    gltf: &gltf::Gltf,
    buffers: &[Vec<u8>],
    base_dir: Option<&Path>,
    max_side: u32,
) -> Result<Vec<Texture>, ImportError> {
    // Which images hold colour (sRGB-encoded by glTF's rules); others would be linear,
    // but only base colour and emissive textures are read here, and both are colour.
    let mut textures = Vec::new();
    for tex in gltf.textures() {
        let image = tex.source();
        let i = image.index();
        let bytes = match image.source() {
            gltf::image::Source::View { view, .. } => view_bytes(&view, buffers)
                .map_err(|problem| ImportError::Image { image: i, problem })?
                .to_vec(),
            gltf::image::Source::Uri { uri, .. } => {
                resolve_uri(uri, base_dir, "uri").map_err(|problem| ImportError::Image { image: i, problem })?
            }
        };
        let undecodable = |e: image::ImageError| ImportError::Image {
            image: i,
            problem: format!("cannot decode (PNG and JPEG are supported): {e}"),
        };
        // The header first: a decompression bomb is refused before anything is allocated.
        let (w, h) = image::ImageReader::new(std::io::Cursor::new(&bytes))
            .with_guessed_format()
            .map_err(|e| undecodable(e.into()))?
            .into_dimensions()
            .map_err(undecodable)?;
        if w > max_side || h > max_side {
            return Err(ImportError::Limit {
                what: "texture size",
                detail: format!("image {i} is {w}x{h} pixels, more than the limit of {max_side} per side"),
            });
        }
        let decoded = image::load_from_memory(&bytes)
            .map_err(|e| ImportError::Image {
                image: i,
                problem: format!("cannot decode (PNG and JPEG are supported): {e}"),
            })?
            .to_rgba32f();
        let (width, height) = decoded.dimensions();
        if width == 0 || height == 0 {
            return Err(ImportError::Image {
                image: i,
                problem: "has zero size".into(),
            });
        }
        let texels = decoded
            .pixels()
            .map(|p| Vec4::new(srgb_to_linear(p[0]), srgb_to_linear(p[1]), srgb_to_linear(p[2]), p[3]))
            .collect();
        let sampler = tex.sampler();
        let wrap = |m: gltf::texture::WrappingMode| match m {
            gltf::texture::WrappingMode::Repeat => Wrap::Repeat,
            gltf::texture::WrappingMode::MirroredRepeat => Wrap::Mirror,
            gltf::texture::WrappingMode::ClampToEdge => Wrap::Clamp,
        };
        textures.push(Texture {
            width,
            height,
            texels,
            wrap_u: wrap(sampler.wrap_s()),
            wrap_v: wrap(sampler.wrap_t()),
        });
    }
    Ok(textures)
}

pub(crate) fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

fn load_materials(gltf: &gltf::Gltf) -> Result<Vec<Material>, ImportError> {
    let mut out = Vec::new();
    for m in gltf.materials() {
        let name = m
            .name()
            .map(str::to_string)
            .unwrap_or_else(|| format!("material {}", m.index().unwrap_or(0)));
        let pbr = m.pbr_metallic_roughness();
        let base_color = Vec4::from_array(pbr.base_color_factor());
        let strength = m.emissive_strength().unwrap_or(1.0);
        let emissive = Vec3::from_array(m.emissive_factor()) * strength;
        let check = |what: &str, ok: bool| -> Result<(), ImportError> {
            if ok {
                Ok(())
            } else {
                Err(ImportError::Material(format!("{name}: {what} must be finite and >= 0")))
            }
        };
        check(
            "baseColorFactor",
            base_color.is_finite() && base_color.min_element() >= 0.0,
        )?;
        check(
            "emissiveFactor × emissive_strength",
            emissive.is_finite() && emissive.min_element() >= 0.0,
        )?;
        let tref = |info: Option<gltf::texture::Info>| {
            info.map(|i| TextureRef {
                texture: i.texture().index() as u32,
                texcoord: i.tex_coord().min(1),
            })
        };
        let alpha_mode = match m.alpha_mode() {
            gltf::material::AlphaMode::Opaque => AlphaMode::Opaque,
            gltf::material::AlphaMode::Blend => AlphaMode::Blend,
            gltf::material::AlphaMode::Mask => {
                let cutoff = m.alpha_cutoff().unwrap_or(0.5);
                check("alphaCutoff", cutoff.is_finite() && cutoff >= 0.0)?;
                AlphaMode::Mask { cutoff }
            }
        };
        out.push(Material {
            alpha_mode,
            name,
            base_color,
            base_color_texture: tref(pbr.base_color_texture()),
            emissive,
            emissive_texture: tref(m.emissive_texture()),
            metallic: pbr.metallic_factor(),
            roughness: pbr.roughness_factor(),
            double_sided: m.double_sided(),
        });
    }
    // Primitives without a material use glTF's default one, kept at the end.
    out.push(Material::default());
    Ok(out)
}

/// A triangle before re-centring, in f64 world space.
struct RawTriangle {
    world: [DVec3; 3],
    n: [Vec3; 3],
    uv: [Vec2; 3],
    lm: [Vec2; 3],
    material: u32,
    mesh: u32,
    source: TriSource,
}

/// Whether a node's `extras.light_probe` is `true` (a light probe position, issue 26).
fn is_probe_node(node: &gltf::Node) -> bool {
    node.extras()
        .as_ref()
        .and_then(|raw| serde_json::from_str::<serde_json::Value>(raw.get()).ok())
        .is_some_and(|v| v.get("light_probe") == Some(&serde_json::Value::Bool(true)))
}

struct RawLight {
    light: PunctualLight,
    world_position: DVec3,
}

struct Flatten<'a> {
    buffers: &'a [Vec<u8>],
    triangles: Vec<RawTriangle>,
    lights: Vec<RawLight>,
    /// Nodes marked `extras.light_probe`: name and world position.
    probe_nodes: Vec<(String, DVec3)>,
    meshes: Vec<MeshInfo>,
    report: &'a mut ImportReport,
    materials_len: usize,
    missing_lightmap_uvs: Vec<String>,
    visited_meshes: HashSet<usize>,
    max_triangles: usize,
    local_meshes: Vec<Option<LocalMesh>>,
    instances: Vec<Instance>,
    /// Per material, the base colour texture's `KHR_texture_transform` as
    /// `[a, b, c, d, ox, oy]`: uv' = (a·u + c·v + ox, b·u + d·v + oy).
    uv_transforms: Vec<Option<[f32; 6]>>,
    /// Malformed items, written one line a kind once the walk is done.
    items: ItemWarnings,
}

/// What a warning about one malformed item is about.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum ItemKind {
    MeshScale,
    NodeScale,
    ScaleOffset,
    Page,
    TexCoord,
    Mode,
    Indices,
}

impl ItemKind {
    /// The one warning for `n` items of this kind, `names` listed by [`listed`].
    fn many(self, n: usize, names: String) -> String {
        match self {
            ItemKind::MeshScale => {
                format!("{n} meshes' extras.lightmap_scale are not numbers in (0, 1000]; using 1 ({names})")
            }
            ItemKind::NodeScale => {
                format!("{n} nodes' extras.lightmap_scale are not numbers in (0, 1000]; using 1 ({names})")
            }
            ItemKind::ScaleOffset => format!(
                "{n} nodes' extras.lightmap.scale_offset are not four finite numbers with positive scales; ignored ({names})"
            ),
            ItemKind::Page => format!(
                "{n} nodes' extras.lightmap.page are not page numbers below {MAX_AUTHORED_PAGES}; page 0 used ({names})"
            ),
            ItemKind::TexCoord => format!(
                "{n} materials' KHR_texture_transform.texCoord is not read; their textures' own TEXCOORD_n are used ({names})"
            ),
            ItemKind::Mode => format!("{n} primitives are not TRIANGLES and are skipped ({names})"),
            ItemKind::Indices => {
                format!("{n} primitives' index counts are not multiples of 3; their last indices are ignored ({names})")
            }
        }
    }
}

/// Warnings about one malformed item each (a mesh's or node's extras, a material's
/// texture transform, a primitive's mode or index count), kept by kind and written by
/// [`warn_each`] once the import has seen them all: a level whose exporter gets one field
/// wrong on every node says so in one line, not one line a node.
#[derive(Debug, Default)]
struct ItemWarnings {
    /// Per kind, in the order kinds first appear: each item's name (with its value
    /// where it has one) and its own warning.
    kinds: Vec<(ItemKind, Vec<(String, String)>)>,
}

impl ItemWarnings {
    fn push(&mut self, kind: ItemKind, name: String, own: String) {
        match self.kinds.iter_mut().find(|(k, _)| *k == kind) {
            Some((_, items)) => items.push((name, own)),
            None => self.kinds.push((kind, vec![(name, own)])),
        }
    }

    fn write(self, warnings: &mut Vec<String>) {
        for (kind, items) in self.kinds {
            warn_each(warnings, items, |n, names| kind.many(n, names));
        }
    }
}

/// Names the alpha-tested materials in the report.
fn note_alpha(materials: &[Material], report: &mut ImportReport) {
    report.alpha_materials = materials
        .iter()
        .filter_map(|m| match m.alpha_mode {
            AlphaMode::Opaque => None,
            AlphaMode::Mask { cutoff } => Some(format!("{} (MASK {cutoff})", m.name)),
            AlphaMode::Blend => Some(format!("{} (BLEND)", m.name)),
        })
        .collect();
}

/// Bounds every material's diffuse albedo for bounced light (module doc of `scene`).
fn bound_albedo(materials: &mut [Material], report: &mut ImportReport) {
    report.albedo_bound = super::ALBEDO_BOUND;
    report.default_material_albedo = super::DEFAULT_MATERIAL_ALBEDO;
    let default = materials.len() - 1;
    let mut bounded = Vec::new();
    for (k, m) in materials.iter_mut().enumerate() {
        let bound = if k == default {
            super::DEFAULT_MATERIAL_ALBEDO
        } else {
            super::ALBEDO_BOUND
        };
        let rgb = m.base_color.truncate();
        if rgb.max_element() > bound {
            m.base_color = rgb.min(Vec3::splat(bound)).extend(m.base_color.w);
            // glTF's default material is always in the list; only named when used.
            if k != default || report.default_material_used {
                bounded.push((k, m.name.clone(), bound));
            }
        }
    }
    if !bounded.is_empty() {
        // Materials that share a name (an exporter's one "colormap" on every mesh) are
        // told apart by their index.
        let shared = |name: &str| materials.iter().filter(|m| m.name == name).count() > 1;
        let bounded: Vec<String> = bounded
            .into_iter()
            .map(|(k, name, bound)| match shared(&name) {
                true => format!("{name} (material {k}) to {bound}"),
                false => format!("{name} to {bound}"),
            })
            .collect();
        report.warnings.push(format!(
            "albedo bounded for bounced light (so paths in closed rooms end): {}",
            listed(&bounded, ", ")
        ));
    }
}

/// Base colour `KHR_texture_transform` per material, read from the document's JSON
/// (the `gltf` crate's feature for it is not enabled). Its `texCoord` override is not read.
fn texture_transforms(json: &serde_json::Value, n: usize, items: &mut ItemWarnings) -> Vec<Option<[f32; 6]>> {
    let mut out = vec![None; n];
    let Some(materials) = json.get("materials").and_then(|v| v.as_array()) else {
        return out;
    };
    for (i, m) in materials.iter().enumerate().take(n) {
        let t = &m["pbrMetallicRoughness"]["baseColorTexture"]["extensions"]["KHR_texture_transform"];
        if !t.is_object() {
            continue;
        }
        let pair = |key: &str, default: [f32; 2]| -> [f32; 2] {
            t.get(key)
                .and_then(|v| v.as_array())
                .filter(|a| a.len() == 2)
                .map_or(default, |a| {
                    [a[0].as_f64().unwrap_or(0.0) as f32, a[1].as_f64().unwrap_or(0.0) as f32]
                })
        };
        let offset = pair("offset", [0.0, 0.0]);
        let scale = pair("scale", [1.0, 1.0]);
        let r = t.get("rotation").and_then(|v| v.as_f64()).unwrap_or(0.0) as f32;
        let base_set = m["pbrMetallicRoughness"]["baseColorTexture"]["texCoord"]
            .as_u64()
            .unwrap_or(0);
        if t.get("texCoord")
            .and_then(|v| v.as_u64())
            .is_some_and(|set| set != base_set)
        {
            items.push(
                ItemKind::TexCoord,
                format!("material {i}"),
                format!(
                    "material {i}: KHR_texture_transform.texCoord is not read (TEXCOORD_{base_set} of the texture is used)"
                ),
            );
        }
        // The extension's matrix: translation · rotation · scale, rotation's columns
        // (cos r, sin r) and (-sin r, cos r).
        let (c, s) = (r.cos(), r.sin());
        out[i] = Some([
            c * scale[0],
            s * scale[0],
            -s * scale[1],
            c * scale[1],
            offset[0],
            offset[1],
        ]);
    }
    out
}

/// Pages an input's `extras.lightmap.page` may name: authored pages are stacked in one
/// bake grid of at most `atlas::MAX_RESOLUTION` rows, so even 1-row pages stop there.
const MAX_AUTHORED_PAGES: u64 = 256;

/// What a node's `extras` say about its lightmap (module doc of `atlas::unwrap`).
struct NodeLightmap {
    scale: f32,
    opt_out: bool,
    scale_offset: [f32; 4],
    page: u32,
}

fn node_lightmap(node: &gltf::Node, items: &mut ItemWarnings) -> NodeLightmap {
    let mut out = NodeLightmap {
        scale: 1.0,
        opt_out: false,
        scale_offset: [1.0, 1.0, 0.0, 0.0],
        page: 0,
    };
    let Some(raw) = node.extras() else { return out };
    let Ok(value) = serde_json::from_str::<serde_json::Value>(raw.get()) else {
        return out;
    };
    let name = node_name(node);
    if let Some(v) = value.get("lightmap_scale") {
        match v.as_f64() {
            Some(s) if s.is_finite() && s > 0.0 && s <= 1e3 => out.scale = s as f32,
            _ => items.push(
                ItemKind::NodeScale,
                format!("{name} ({v})"),
                format!("{name}: extras.lightmap_scale {v} is not a number in (0, 1000]; using 1"),
            ),
        }
    }
    match value.get("lightmap") {
        Some(serde_json::Value::Bool(false)) => out.opt_out = true,
        Some(serde_json::Value::Object(o)) => {
            let so: Option<Vec<f32>> = o.get("scale_offset").and_then(|v| v.as_array()).map(|a| {
                a.iter()
                    .filter_map(|x| x.as_f64().map(|x| x as f32))
                    .filter(|x| x.is_finite())
                    .collect()
            });
            match so {
                Some(so) if so.len() == 4 && so[0] > 0.0 && so[1] > 0.0 => {
                    out.scale_offset = [so[0], so[1], so[2], so[3]]
                }
                None => {}
                Some(_) => items.push(
                    ItemKind::ScaleOffset,
                    name.clone(),
                    format!(
                        "{name}: extras.lightmap.scale_offset is not four finite numbers with positive scales; ignored"
                    ),
                ),
            }
            match o.get("page") {
                None => {}
                Some(v) => match v.as_u64() {
                    Some(p) if p < MAX_AUTHORED_PAGES => out.page = p as u32,
                    _ => items.push(
                        ItemKind::Page,
                        format!("{name} ({v})"),
                        format!("{name}: extras.lightmap.page {v} is not a page number below {MAX_AUTHORED_PAGES}; page 0 used"),
                    ),
                },
            }
        }
        _ => {}
    }
    out
}

fn node_name(node: &gltf::Node) -> String {
    match node.name() {
        Some(n) => format!("node {} \"{n}\"", node.index()),
        None => format!("node {}", node.index()),
    }
}

/// The document's JSON as a tree: the GLB JSON chunk, or the whole `.gltf` file.
fn document_json(bytes: &[u8]) -> Result<serde_json::Value, ImportError> {
    let chunk: std::borrow::Cow<[u8]> = if bytes.starts_with(b"glTF") {
        gltf::binary::Glb::from_slice(bytes)
            .map_err(|e| ImportError::NotGltf(format!("broken GLB container: {e:?}")))?
            .json
    } else {
        std::borrow::Cow::Borrowed(bytes)
    };
    serde_json::from_slice(&chunk).map_err(|e| ImportError::NotGltf(format!("JSON: {e}")))
}

/// Several nodes place one mesh whose lightmap UVs are authored: on one page they would
/// cover the same texels.
fn shared_authored_warning(
    instances: &[Instance],
    meshes: &[Option<LocalMesh>],
    gltf: &gltf::Gltf,
    warnings: &mut Vec<String>,
) {
    let mut users: std::collections::BTreeMap<usize, usize> = Default::default();
    for i in instances.iter().filter(|i| !i.opt_out) {
        *users.entry(i.mesh).or_default() += 1;
    }
    let shared: Vec<(usize, String, usize)> = users
        .into_iter()
        .filter(|&(mesh, n)| n > 1 && meshes[mesh].as_ref().is_some_and(LocalMesh::authored))
        .map(|(mesh, n)| {
            let name = gltf
                .meshes()
                .nth(mesh)
                .and_then(|m| m.name().map(str::to_string))
                .unwrap_or_default();
            (mesh, name, n)
        })
        .collect();
    // One warning for them all: a level instances hundreds of props.
    let which = match shared.as_slice() {
        [] => return,
        [(mesh, name, n)] => format!("mesh {mesh} \"{name}\" has authored TEXCOORD_1 and is placed by {n} nodes"),
        _ => {
            let each: Vec<String> = shared
                .iter()
                .map(|(mesh, name, n)| format!("mesh {mesh} \"{name}\" by {n}"))
                .collect();
            format!(
                "{} meshes with authored TEXCOORD_1 are placed by several nodes ({})",
                shared.len(),
                listed(&each, "; ")
            )
        }
    };
    warnings.push(format!(
        "{which}: unless their extras.lightmap.scale_offset differ, they share texels (lightmap_uvs: repack-instances gives each its own rectangle and keeps these UVs; regenerate-all replaces them)"
    ));
}

/// Names what the document uses that the bake does not read.
fn unread_features(json: &serde_json::Value, warnings: &mut Vec<String>) {
    const READ: &[&str] = &[
        "KHR_lights_punctual",
        "KHR_materials_emissive_strength",
        "KHR_mesh_quantization",
        "KHR_texture_transform",
    ];
    let mut unread: Vec<String> = json
        .get("extensionsUsed")
        .and_then(|v| v.as_array())
        .into_iter()
        .flatten()
        .filter_map(|e| e.as_str())
        .filter(|e| !READ.contains(e))
        .map(|e| format!("extension {e}"))
        .collect();
    let has = |key: &str| json.get(key).and_then(|v| v.as_array()).is_some_and(|a| !a.is_empty());
    if has("skins") {
        unread.push("skins (the bind pose is baked)".into());
    }
    if has("animations") {
        unread.push("animations".into());
    }
    let materials = json
        .get("materials")
        .and_then(|v| v.as_array())
        .cloned()
        .unwrap_or_default();
    if materials.iter().any(|m| m.get("normalTexture").is_some()) {
        unread.push("normal textures".into());
    }
    let prims = json
        .get("meshes")
        .and_then(|v| v.as_array())
        .into_iter()
        .flatten()
        .filter_map(|m| m.get("primitives").and_then(|p| p.as_array()))
        .flatten();
    let mut targets = false;
    for p in prims {
        targets |= p.get("targets").is_some();
    }
    if targets {
        unread.push("morph targets".into());
    }
    if !unread.is_empty() {
        warnings.push(format!("not read by the bake: {}", unread.join(", ")));
    }
}

impl Flatten<'_> {
    fn visit(&mut self, node: &gltf::Node, parent: DMat4, seen: &mut HashSet<usize>) -> Result<(), ImportError> {
        // glTF forbids cycles, but a hostile file may still have them: never loop.
        if !seen.insert(node.index()) {
            return Err(ImportError::Invalid(format!(
                "node {} is reached twice (the node graph is not a tree)",
                node.index()
            )));
        }
        let local = DMat4::from_cols_array_2d(&node.transform().matrix().map(|c| c.map(f64::from)));
        let world = parent * local;
        if !world.is_finite() {
            return Err(ImportError::Invalid(format!(
                "node {}: transform is not finite",
                node.index()
            )));
        }
        if let Some(mesh) = node.mesh() {
            let lm = node_lightmap(node, &mut self.items);
            let mesh_scale = self.meshes.get(mesh.index()).map_or(1.0, |m| m.lightmap_scale);
            let start = self.triangles.len();
            self.mesh(&mesh, &world, lm.scale_offset)?;
            self.instances.push(Instance {
                node: node.index(),
                mesh: mesh.index(),
                world,
                lightmap_scale: lm.scale * mesh_scale,
                opt_out: lm.opt_out,
                authored_scale_offset: lm.scale_offset,
                authored_page: lm.page,
                triangles: start..self.triangles.len(),
            });
            if lm.opt_out {
                // Casts shadows, owns no texel: a zero-area lightmap footprint.
                for t in &mut self.triangles[start..] {
                    t.lm = [Vec2::ZERO; 3];
                }
            }
        }
        if let Some(light) = node.light() {
            self.light(&light, &world, node.index())?;
        }
        if is_probe_node(node) {
            self.probe_nodes.push((node_name(node), world.w_axis.truncate()));
        }
        for child in node.children() {
            self.visit(&child, world, seen)?;
        }
        Ok(())
    }

    fn light(
        &mut self,
        light: &gltf::khr_lights_punctual::Light,
        world: &DMat4,
        node: usize,
    ) -> Result<(), ImportError> {
        let name = light
            .name()
            .map(str::to_string)
            .unwrap_or_else(|| format!("light {}", light.index()));
        let color = Vec3::from_array(light.color());
        let intensity = light.intensity();
        if !color.is_finite() || color.min_element() < 0.0 || !intensity.is_finite() || intensity < 0.0 {
            return Err(ImportError::Invalid(format!(
                "{name} (node {node}): colour and intensity must be finite and >= 0"
            )));
        }
        let kind = match light.kind() {
            gltf::khr_lights_punctual::Kind::Directional => LightKind::Directional,
            gltf::khr_lights_punctual::Kind::Point => LightKind::Point,
            gltf::khr_lights_punctual::Kind::Spot {
                inner_cone_angle,
                outer_cone_angle,
            } => {
                if !(0.0..=std::f32::consts::FRAC_PI_2).contains(&outer_cone_angle)
                    || inner_cone_angle >= outer_cone_angle
                    || inner_cone_angle.is_nan()
                {
                    return Err(ImportError::Invalid(format!(
                        "{name} (node {node}): spot cone angles need 0 <= inner < outer <= pi/2, got {inner_cone_angle} and {outer_cone_angle}"
                    )));
                }
                LightKind::Spot {
                    inner_cone: inner_cone_angle.max(0.0),
                    outer_cone: outer_cone_angle,
                }
            }
        };
        let position = world.transform_point3(DVec3::ZERO);
        let direction = world.transform_vector3(DVec3::NEG_Z).normalize_or_zero().as_vec3();
        if direction == Vec3::ZERO && kind != LightKind::Point {
            return Err(ImportError::Invalid(format!(
                "{name} (node {node}): transform collapses the light's direction"
            )));
        }
        self.lights.push(RawLight {
            light: PunctualLight {
                name,
                kind,
                intensity: color * intensity,
                position: Vec3::ZERO,
                direction,
                range: light.range().filter(|r| *r > 0.0),
            },
            world_position: position,
        });
        Ok(())
    }

    fn mesh(&mut self, mesh: &gltf::Mesh, world: &DMat4, scale_offset: [f32; 4]) -> Result<(), ImportError> {
        let first_visit = self.visited_meshes.insert(mesh.index());
        if first_visit {
            self.local_meshes[mesh.index()] = Some(LocalMesh {
                primitives: vec![None; mesh.primitives().len()],
            });
        }
        let (so_scale, so_offset) = (
            Vec2::new(scale_offset[0], scale_offset[1]),
            Vec2::new(scale_offset[2], scale_offset[3]),
        );
        let mirrored = world.determinant() < 0.0;
        let normal_matrix = world.inverse().transpose();
        let mesh_name = mesh.name().unwrap_or("").to_string();
        for prim in mesh.primitives() {
            let at = PrimitiveRef {
                mesh: mesh.index(),
                mesh_name: mesh_name.clone(),
                primitive: prim.index(),
            };
            if first_visit {
                self.report.primitives += 1;
            }
            if prim.mode() != Mode::Triangles {
                if first_visit {
                    self.items.push(
                        ItemKind::Mode,
                        format!("{at} ({:?})", prim.mode()),
                        format!("{at}: mode {:?} is not TRIANGLES and is skipped", prim.mode()),
                    );
                }
                continue;
            }
            // glTF's default material sits after the file's own (see `load_materials`).
            let material = match prim.material().index() {
                Some(i) if i < self.materials_len => i as u32,
                Some(i) => {
                    return Err(ImportError::Primitive {
                        at,
                        problem: format!("material {i} does not exist"),
                    });
                }
                None => {
                    self.report.default_material_used = true;
                    self.materials_len as u32
                }
            };

            let positions = read_vec3(&prim, gltf::Semantic::Positions, self.buffers, &at)?.ok_or_else(|| {
                ImportError::Primitive {
                    at: at.clone(),
                    problem: "has no POSITION attribute".into(),
                }
            })?;
            let normals = read_vec3(&prim, gltf::Semantic::Normals, self.buffers, &at)?;
            let uv0 = read_vec2(&prim, 0, self.buffers, &at)?;
            let n = positions.len();
            let authored = prim.get(&gltf::Semantic::TexCoords(1)).is_some();
            let uv1 = match read_vec2(&prim, 1, self.buffers, &at)? {
                Some(uv1) => uv1.iter().map(|uv| *uv * so_scale + so_offset).collect(),
                None => {
                    // Placeholder; `atlas::unwrap` generates the real UVs at bake time.
                    if first_visit {
                        self.missing_lightmap_uvs.push(at.to_string());
                    }
                    vec![Vec2::ZERO; n]
                }
            };
            for (what, len) in [
                ("NORMAL", normals.as_ref().map(Vec::len)),
                ("TEXCOORD_0", uv0.as_ref().map(Vec::len)),
                ("TEXCOORD_1", Some(uv1.len())),
            ] {
                if let Some(len) = len
                    && len != n
                {
                    return Err(ImportError::Primitive {
                        at: at.clone(),
                        problem: format!("{what} has {len} elements but POSITION has {n}"),
                    });
                }
            }
            if let Some((i, uv)) = uv1
                .iter()
                .enumerate()
                .find(|(_, uv)| !(0.0..=1.0).contains(&uv.x) || !(0.0..=1.0).contains(&uv.y))
            {
                let acc = prim.get(&gltf::Semantic::TexCoords(1)).map(|a| a.index()).unwrap_or(0);
                return Err(ImportError::Accessor {
                    at,
                    accessor: acc,
                    attribute: "TEXCOORD_1".into(),
                    problem: if scale_offset == [1.0, 1.0, 0.0, 0.0] {
                        format!("lightmap UV ({}, {}) of vertex {i} is outside [0, 1]", uv.x, uv.y)
                    } else {
                        format!(
                            "lightmap UV ({}, {}) of vertex {i} is outside [0, 1] (after the node's extras.lightmap.scale_offset)",
                            uv.x, uv.y
                        )
                    },
                });
            }
            let indices: Vec<u32> = match prim.indices() {
                Some(acc) => {
                    check_accessor(&acc, self.buffers, &at, "indices")?;
                    check_format(
                        &acc,
                        &at,
                        "indices",
                        Dimensions::Scalar,
                        &[DataType::U8, DataType::U16, DataType::U32],
                    )?;
                    let reader = prim.reader(|b| self.buffers.get(b.index()).map(Vec::as_slice));
                    let idx: Vec<u32> = reader
                        .read_indices()
                        .ok_or_else(|| accessor_err(&at, &acc, "indices", "cannot be read".into()))?
                        .into_u32()
                        .collect();
                    if let Some((k, bad)) = idx.iter().enumerate().find(|(_, i)| **i as usize >= n) {
                        return Err(accessor_err(
                            &at,
                            &acc,
                            "indices",
                            format!("index {bad} at position {k} is past the {n} vertices"),
                        ));
                    }
                    idx
                }
                None => (0..n as u32).collect(),
            };
            if !indices.len().is_multiple_of(3) && first_visit {
                self.items.push(
                    ItemKind::Indices,
                    format!("{at} ({})", indices.len()),
                    format!(
                        "{at}: {} indices is not a multiple of 3; the last ones are ignored",
                        indices.len()
                    ),
                );
            }
            if first_visit && let Some(local) = self.local_meshes[mesh.index()].as_mut() {
                local.primitives[prim.index()] = Some(LocalPrimitive {
                    positions: positions.clone(),
                    indices: indices[..indices.len() / 3 * 3].to_vec(),
                    has_lightmap_uvs: authored,
                });
            }

            let world_pos: Vec<DVec3> = positions.iter().map(|p| world.transform_point3(p.as_dvec3())).collect();
            let world_nrm: Option<Vec<Vec3>> = normals.map(|ns| {
                ns.iter()
                    .map(|v| {
                        normal_matrix
                            .transform_vector3(v.as_dvec3())
                            .normalize_or_zero()
                            .as_vec3()
                    })
                    .collect()
            });
            for (k, tri) in indices.chunks_exact(3).enumerate() {
                let (a, b, c) = if mirrored {
                    (tri[0], tri[2], tri[1])
                } else {
                    (tri[0], tri[1], tri[2])
                };
                let (a, b, c) = (a as usize, b as usize, c as usize);
                let w = [world_pos[a], world_pos[b], world_pos[c]];
                let cross = (w[1] - w[0]).cross(w[2] - w[0]);
                let scale2 = (w[1] - w[0]).length_squared().max((w[2] - w[0]).length_squared());
                // Relative test: a sliver whose normal cannot be computed in f32 is degenerate.
                let well_formed = cross.length_squared() > 1e-12 * scale2 * scale2 && scale2 > 0.0;
                if !well_formed {
                    self.report.degenerate_triangles += 1;
                    continue;
                }
                let flat = cross.normalize().as_vec3();
                let n3 = match &world_nrm {
                    Some(ns) => [ns[a], ns[b], ns[c]].map(|v| if v == Vec3::ZERO { flat } else { v }),
                    None => [flat; 3],
                };
                let lm = [uv1[a], uv1[b], uv1[c]];
                // A primitive without TEXCOORD_1 holds zero placeholders, counted apart (its
                // UVs are generated), not as zero-area triangles.
                if authored && (lm[1] - lm[0]).perp_dot(lm[2] - lm[0]) == 0.0 {
                    self.report.zero_uv_area_triangles += 1;
                }
                let mut uv = uv0.as_ref().map(|u| [u[a], u[b], u[c]]).unwrap_or([Vec2::ZERO; 3]);
                // TEXCOORD_0 is read only for the base colour texture: its transform is
                // applied here, once, so every technique samples the transformed UVs.
                if let Some([ta, tb, tc, td, ox, oy]) = self.uv_transforms.get(material as usize).copied().flatten() {
                    uv = uv.map(|q| Vec2::new(ta * q.x + tc * q.y + ox, tb * q.x + td * q.y + oy));
                }
                if self.triangles.len() >= self.max_triangles {
                    return Err(ImportError::Limit {
                        what: "triangles",
                        detail: format!(
                            "the scene has more than {} triangles (instances counted once each), the limit",
                            self.max_triangles
                        ),
                    });
                }
                self.triangles.push(RawTriangle {
                    world: w,
                    n: n3,
                    uv,
                    lm,
                    material,
                    mesh: mesh.index() as u32,
                    source: TriSource {
                        primitive: prim.index() as u32,
                        triangle: k as u32,
                        mirrored,
                    },
                });
            }
        }
        Ok(())
    }
}

fn accessor_err(at: &PrimitiveRef, acc: &gltf::Accessor, attribute: &str, problem: String) -> ImportError {
    ImportError::Accessor {
        at: at.clone(),
        accessor: acc.index(),
        attribute: attribute.into(),
        problem,
    }
}

/// Checks that every byte the accessor reads lies inside its view and the view inside its
/// buffer, so reading can never go out of bounds.
fn check_accessor(
    acc: &gltf::Accessor,
    buffers: &[Vec<u8>],
    at: &PrimitiveRef,
    attribute: &str,
) -> Result<(), ImportError> {
    if acc.sparse().is_some() {
        return Err(accessor_err(
            at,
            acc,
            attribute,
            "sparse accessors are not supported".into(),
        ));
    }
    let Some(view) = acc.view() else {
        return Err(accessor_err(
            at,
            acc,
            attribute,
            "has no buffer view (all-zero accessors are not supported)".into(),
        ));
    };
    let bytes = view_bytes(&view, buffers).map_err(|p| accessor_err(at, acc, attribute, p))?;
    if acc.count() == 0 {
        return Err(accessor_err(at, acc, attribute, "count is 0".into()));
    }
    let elem = acc.size();
    let stride = view.stride().unwrap_or(elem);
    let need = (acc.count() - 1)
        .checked_mul(stride)
        .and_then(|s| s.checked_add(acc.offset()))
        .and_then(|s| s.checked_add(elem));
    match need {
        Some(end) if end <= bytes.len() => Ok(()),
        _ => Err(accessor_err(
            at,
            acc,
            attribute,
            format!(
                "out of bounds: {} elements of {} bytes (stride {}, offset {}) need more than buffer view {}'s {} bytes",
                acc.count(),
                elem,
                stride,
                acc.offset(),
                view.index(),
                bytes.len()
            ),
        )),
    }
}

/// The element type and component types glTF allows for an attribute; the `gltf` crate's
/// readers assume them (and panic otherwise), so they are checked first.
fn check_format(
    acc: &gltf::Accessor,
    at: &PrimitiveRef,
    attribute: &str,
    dims: Dimensions,
    types: &[DataType],
) -> Result<(), ImportError> {
    if acc.dimensions() != dims || !types.contains(&acc.data_type()) {
        return Err(accessor_err(
            at,
            acc,
            attribute,
            format!(
                "is {:?} of {:?}; glTF requires {dims:?} of {}",
                acc.dimensions(),
                acc.data_type(),
                types.iter().map(|t| format!("{t:?}")).collect::<Vec<_>>().join(" or ")
            ),
        ));
    }
    Ok(())
}

/// Every element of `acc` as f32 components, decoding the integer types that
/// `KHR_mesh_quantization` allows (normalised ones mapped to [0, 1] or [-1, 1] by glTF's
/// rules, others converted as integers). The range was checked by `check_accessor`.
fn read_components(acc: &gltf::Accessor, buffers: &[Vec<u8>], n: usize) -> Option<Vec<f32>> {
    let view = acc.view()?;
    let bytes = view_bytes(&view, buffers).ok()?;
    let cs = acc.data_type().size();
    let stride = view.stride().unwrap_or(cs * n);
    let normalized = acc.normalized();
    let mut out = Vec::with_capacity(acc.count() * n);
    for i in 0..acc.count() {
        for c in 0..n {
            let at = acc.offset() + i * stride + c * cs;
            let b = bytes.get(at..at + cs)?;
            let v = match acc.data_type() {
                DataType::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
                DataType::I8 if normalized => (f32::from(b[0] as i8) / 127.0).max(-1.0),
                DataType::I8 => f32::from(b[0] as i8),
                DataType::U8 if normalized => f32::from(b[0]) / 255.0,
                DataType::U8 => f32::from(b[0]),
                DataType::I16 if normalized => (f32::from(i16::from_le_bytes([b[0], b[1]])) / 32767.0).max(-1.0),
                DataType::I16 => f32::from(i16::from_le_bytes([b[0], b[1]])),
                DataType::U16 if normalized => f32::from(u16::from_le_bytes([b[0], b[1]])) / 65535.0,
                DataType::U16 => f32::from(u16::from_le_bytes([b[0], b[1]])),
                DataType::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
            };
            out.push(v);
        }
    }
    Some(out)
}

const QUANTIZED: &[DataType] = &[DataType::F32, DataType::I8, DataType::U8, DataType::I16, DataType::U16];

fn read_vec3(
    prim: &gltf::Primitive,
    semantic: gltf::Semantic,
    buffers: &[Vec<u8>],
    at: &PrimitiveRef,
) -> Result<Option<Vec<Vec3>>, ImportError> {
    let Some(acc) = prim.get(&semantic) else {
        return Ok(None);
    };
    let name = semantic.to_string();
    check_accessor(&acc, buffers, at, &name)?;
    // F32, or the integer types of KHR_mesh_quantization.
    check_format(&acc, at, &name, Dimensions::Vec3, QUANTIZED)?;
    let data: Vec<Vec3> = read_components(&acc, buffers, 3)
        .ok_or_else(|| accessor_err(at, &acc, &name, "cannot be read".into()))?
        .chunks_exact(3)
        .map(|c| Vec3::new(c[0], c[1], c[2]))
        .collect();
    if let Some((i, v)) = data.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(accessor_err(
            at,
            &acc,
            &name,
            format!("element {i} is not finite: {:?}", v.to_array()),
        ));
    }
    Ok(Some(data))
}

fn read_vec2(
    prim: &gltf::Primitive,
    set: u32,
    buffers: &[Vec<u8>],
    at: &PrimitiveRef,
) -> Result<Option<Vec<Vec2>>, ImportError> {
    let semantic = gltf::Semantic::TexCoords(set);
    let Some(acc) = prim.get(&semantic) else {
        return Ok(None);
    };
    let name = semantic.to_string();
    check_accessor(&acc, buffers, at, &name)?;
    check_format(&acc, at, &name, Dimensions::Vec2, QUANTIZED)?;
    let data: Vec<Vec2> = read_components(&acc, buffers, 2)
        .ok_or_else(|| accessor_err(at, &acc, &name, "cannot be read".into()))?
        .chunks_exact(2)
        .map(|c| Vec2::new(c[0], c[1]))
        .collect();
    if let Some((i, v)) = data.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(accessor_err(
            at,
            &acc,
            &name,
            format!("element {i} is not finite: {:?}", v.to_array()),
        ));
    }
    Ok(Some(data))
}
