//! Writes the baked level back as `.glb`: the input document with lightmap UVs added,
//! the file a renderer needs next to the lightmap.
//!
//! How ([`to_glb`]): the input's JSON is copied as it was parsed (node hierarchy, names,
//! transforms, mesh sharing, primitives and their materials, samplers, textures,
//! extensions and extras), its buffers are concatenated into the GLB binary chunk (each
//! buffer view re-pointed, no data re-encoded; external images are embedded byte for
//! byte). Only primitives of meshes that got generated UVs change: their vertices are
//! split where a UV seam needs it (every attribute and morph target copied per split
//! vertex, in its own component type), with new indices and a new `TEXCOORD_1`; a
//! primitive with no `TEXCOORD_0` gets the same accessor as `TEXCOORD_0` too, because
//! glTF requires texture coordinate sets to be numbered from 0 without gaps. Authored
//! `TEXCOORD_1` accessors are left untouched (bit for bit). Every node of the scene that
//! places a mesh and did not opt out gets `extras.lightmap = {"page", "scale_offset",
//! "file"}` (docs/conventions.md); other keys of its `extras` stay. An instance whose
//! transform stretches its mesh past `atlas::unwrap::OWN_LAYOUT_RATIO` has a layout of its
//! own: its mesh is copied (appended to `meshes`, named "NAME (own lightmap layout C)"),
//! split for that layout, and its node points at the copy.
//!
//! The accessors a split primitive used before, and the buffer views only they used,
//! are removed once nothing else refers to them (`prune_orphans`: other primitives,
//! morph targets, skins, animations and `EXT_mesh_gpu_instancing` may share them), and
//! every reference renumbered, so the written file has no unused object the input did not
//! have. Their bytes stay in the binary chunk (nothing points at them; re-packing it
//! would move every other view). A document using an extension not known to refer to
//! no accessor or buffer view keeps them, unused, as before.
//!
//! Limits: sparse accessors on a primitive that gets new vertices are an error; a node
//! whose `extras` is not a JSON object gets no `extras.lightmap` (the file stays valid).
//! [`to_glb_flattened`] is the older writer for scenes without a source document.

use std::collections::BTreeMap;

use glam::{Quat, Vec2, Vec3};
use serde_json::{Value, json};

use super::build::write_glb;
use super::{GeneratedPrimitive, LightKind, Scene, SourceDocument, Triangle, Wrap};

/// The scene flattened into world space, one node per mesh (no source document needed).
pub fn to_glb_flattened(scene: &Scene) -> Result<Vec<u8>, String> {
    let mut bin: Vec<u8> = Vec::new();
    let mut views: Vec<Value> = Vec::new();
    let mut accessors: Vec<Value> = Vec::new();
    let mut push_view = |bin: &mut Vec<u8>, bytes: &[u8], target: Option<u32>| -> usize {
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        let mut v = json!({"buffer": 0, "byteOffset": bin.len(), "byteLength": bytes.len()});
        if let Some(t) = target {
            v["target"] = json!(t);
        }
        views.push(v);
        bin.extend_from_slice(bytes);
        views.len() - 1
    };

    let mut groups: BTreeMap<u32, Vec<&Triangle>> = BTreeMap::new();
    for t in &scene.triangles {
        groups.entry(t.mesh).or_default().push(t);
    }
    let offset = scene.origin_offset.to_array();
    let mut meshes = Vec::new();
    let mut nodes = Vec::new();
    for (mesh, tris) in &groups {
        let positions: Vec<Vec3> = tris.iter().flat_map(|t| t.p).collect();
        let normals: Vec<Vec3> = tris.iter().flat_map(|t| t.n).collect();
        let uv0: Vec<Vec2> = tris.iter().flat_map(|t| t.uv).collect();
        let uv1: Vec<Vec2> = tris.iter().flat_map(|t| t.lm).collect();
        let (lo, hi) = positions.iter().fold(
            (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
            |(lo, hi), p| (lo.min(*p), hi.max(*p)),
        );
        let mut attr = |bytes: &[u8], acc: Value| {
            let view = push_view(&mut bin, bytes, Some(34962));
            let mut acc = acc;
            acc["bufferView"] = json!(view);
            accessors.push(acc);
            accessors.len() - 1
        };
        let n = positions.len();
        let pos = attr(
            bytemuck::cast_slice(&positions),
            json!({"componentType": 5126, "count": n, "type": "VEC3", "min": lo.to_array(), "max": hi.to_array()}),
        );
        let nrm = attr(
            bytemuck::cast_slice(&normals),
            json!({"componentType": 5126, "count": n, "type": "VEC3"}),
        );
        let t0 = attr(
            bytemuck::cast_slice(&uv0),
            json!({"componentType": 5126, "count": n, "type": "VEC2"}),
        );
        let t1 = attr(
            bytemuck::cast_slice(&uv1),
            json!({"componentType": 5126, "count": n, "type": "VEC2"}),
        );
        let name = scene
            .meshes
            .get(*mesh as usize)
            .map(|m| m.name.clone())
            .unwrap_or_default();
        meshes.push(json!({
            "name": name,
            "primitives": [{
                "attributes": {"POSITION": pos, "NORMAL": nrm, "TEXCOORD_0": t0, "TEXCOORD_1": t1},
                "material": tris[0].material,
                "mode": 4
            }]
        }));
        nodes.push(json!({"name": name, "mesh": meshes.len() - 1, "translation": offset}));
    }

    // Textures: linear floats back to 8-bit sRGB PNG.
    let mut images = Vec::new();
    let mut samplers = Vec::new();
    let mut textures = Vec::new();
    for (i, tex) in scene.textures.iter().enumerate() {
        let bytes: Vec<u8> = tex
            .texels
            .iter()
            .flat_map(|c| {
                [
                    linear_to_srgb8(c.x),
                    linear_to_srgb8(c.y),
                    linear_to_srgb8(c.z),
                    (c.w.clamp(0.0, 1.0) * 255.0).round() as u8,
                ]
            })
            .collect();
        let img =
            image::RgbaImage::from_raw(tex.width, tex.height, bytes).ok_or("texture size does not match its data")?;
        let mut png = std::io::Cursor::new(Vec::new());
        img.write_to(&mut png, image::ImageFormat::Png)
            .map_err(|e| format!("encoding texture {i}: {e}"))?;
        let view = push_view(&mut bin, png.get_ref(), None);
        images.push(json!({"bufferView": view, "mimeType": "image/png"}));
        let wrap = |w: Wrap| match w {
            Wrap::Repeat => 10497,
            Wrap::Mirror => 33648,
            Wrap::Clamp => 33071,
        };
        samplers.push(json!({"wrapS": wrap(tex.wrap_u), "wrapT": wrap(tex.wrap_v)}));
        textures.push(json!({"source": i, "sampler": i}));
    }

    let materials: Vec<Value> = scene
        .materials
        .iter()
        .map(|m| {
            let mut pbr = json!({
                "baseColorFactor": m.base_color.to_array(),
                "metallicFactor": m.metallic,
                "roughnessFactor": m.roughness
            });
            if let Some(t) = m.base_color_texture {
                pbr["baseColorTexture"] = json!({"index": t.texture, "texCoord": t.texcoord});
            }
            let mut v = json!({"name": m.name, "pbrMetallicRoughness": pbr, "doubleSided": m.double_sided});
            let peak = m.emissive.max_element();
            if peak > 0.0 {
                let (factor, strength) = if peak > 1.0 {
                    (m.emissive / peak, peak)
                } else {
                    (m.emissive, 1.0)
                };
                v["emissiveFactor"] = json!(factor.to_array());
                if strength != 1.0 {
                    v["extensions"] = json!({"KHR_materials_emissive_strength": {"emissiveStrength": strength}});
                }
                if let Some(t) = m.emissive_texture {
                    v["emissiveTexture"] = json!({"index": t.texture, "texCoord": t.texcoord});
                }
            }
            v
        })
        .collect();

    let mut lights = Vec::new();
    for l in &scene.lights {
        let (kind, spot) = match l.kind {
            LightKind::Directional => ("directional", None),
            LightKind::Point => ("point", None),
            LightKind::Spot { inner_cone, outer_cone } => (
                "spot",
                Some(json!({"innerConeAngle": inner_cone, "outerConeAngle": outer_cone})),
            ),
        };
        let peak = l.intensity.max_element().max(f32::MIN_POSITIVE);
        let mut light =
            json!({"name": l.name, "type": kind, "color": (l.intensity / peak).to_array(), "intensity": peak});
        if let Some(s) = spot {
            light["spot"] = s;
        }
        if let Some(r) = l.range {
            light["range"] = json!(r);
        }
        lights.push(light);
        let position = l.position.as_dvec3() + scene.origin_offset;
        let rotation = if l.direction.length_squared() > 0.0 {
            Quat::from_rotation_arc(Vec3::NEG_Z, l.direction.normalize())
        } else {
            Quat::IDENTITY
        };
        nodes.push(json!({
            "name": l.name,
            "translation": position.to_array(),
            "rotation": rotation.to_array(),
            "extensions": {"KHR_lights_punctual": {"light": lights.len() - 1}}
        }));
    }

    let mut root = json!({
        "asset": {"version": "2.0", "generator": concat!("lightmapd ", env!("CARGO_PKG_VERSION"))},
        "scene": 0,
        "scenes": [{"nodes": (0..nodes.len()).collect::<Vec<_>>()}],
        "nodes": nodes,
        "meshes": meshes,
        "materials": materials,
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": bin.len()}],
        "extensionsUsed": ["KHR_materials_emissive_strength", "KHR_lights_punctual"],
    });
    if !textures.is_empty() {
        root["images"] = json!(images);
        root["samplers"] = json!(samplers);
        root["textures"] = json!(textures);
    }
    if !lights.is_empty() {
        root["extensions"] = json!({"KHR_lights_punctual": {"lights": lights}});
    }
    Ok(write_glb(&root, &bin))
}

fn linear_to_srgb8(c: f32) -> u8 {
    let c = c.clamp(0.0, 1.0);
    let s = if c <= 0.003_130_8 {
        12.92 * c
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0).round() as u8
}

/// The lightmap EXR of page `page`, as `extras.lightmap.file` names it.
pub fn page_file(page: u32) -> String {
    format!("lightmap-{page}.exr")
}

/// The input document with lightmap UVs added (module doc).
pub fn to_glb(scene: &Scene) -> Result<Vec<u8>, String> {
    let Some(source) = scene.source.as_deref() else {
        return to_glb_flattened(scene);
    };
    let mut doc = source.json.clone();
    let mut bin: Vec<u8> = Vec::new();

    // Buffers, one after another in the binary chunk; views re-pointed.
    let declared: Vec<usize> = doc["buffers"]
        .as_array()
        .map(|a| {
            a.iter()
                .map(|b| b["byteLength"].as_u64().unwrap_or(0) as usize)
                .collect()
        })
        .unwrap_or_default();
    let mut base = Vec::new();
    for (i, data) in source.buffers.iter().enumerate() {
        align(&mut bin, 16);
        base.push(bin.len());
        let len = declared.get(i).copied().unwrap_or(data.len()).min(data.len());
        bin.extend_from_slice(&data[..len]);
    }
    if let Some(views) = doc.get_mut("bufferViews").and_then(Value::as_array_mut) {
        for v in views {
            let b = v["buffer"].as_u64().unwrap_or(0) as usize;
            let off = v["byteOffset"].as_u64().unwrap_or(0) as usize + base.get(b).copied().unwrap_or(0);
            v["buffer"] = json!(0);
            v["byteOffset"] = json!(off);
        }
    }
    let mut new_views: Vec<Value> = Vec::new();
    let view_count = doc["bufferViews"].as_array().map_or(0, Vec::len);
    // External images are embedded as they are (not re-encoded).
    if let Some(images) = doc.get_mut("images").and_then(Value::as_array_mut) {
        for (i, img) in images.iter_mut().enumerate() {
            let Some(uri) = img["uri"].as_str().map(str::to_string) else {
                continue;
            };
            if uri.starts_with("data:") {
                continue;
            }
            let bytes = super::import::read_external(&uri, source.base_dir.as_deref())
                .map_err(|e| format!("image {i}: {e}"))?;
            let mime = if bytes.starts_with(b"\x89PNG") {
                "image/png"
            } else {
                "image/jpeg"
            };
            align(&mut bin, 4);
            new_views.push(json!({"buffer": 0, "byteOffset": bin.len(), "byteLength": bytes.len()}));
            bin.extend_from_slice(&bytes);
            let obj = img.as_object_mut().ok_or("image is not an object")?;
            obj.remove("uri");
            obj.insert("bufferView".into(), json!(view_count + new_views.len() - 1));
            obj.insert(
                "mimeType".into(),
                json!(obj.get("mimeType").cloned().unwrap_or(json!(mime))),
            );
        }
    }

    // Generated UVs: new vertices per primitive.
    let mut new_accessors: Vec<Value> = Vec::new();
    let accessor_count = doc["accessors"].as_array().map_or(0, Vec::len);
    // The accessors the split primitives used: unused afterwards unless shared.
    let mut replaced = std::collections::BTreeSet::new();
    if let Some(layout) = scene.layout.as_deref() {
        let mut w = Writer {
            doc: &doc,
            source,
            bin: &mut bin,
            views: &mut new_views,
            view_base: view_count,
            accessors: &mut new_accessors,
            accessor_base: accessor_count,
        };
        let mut split = Vec::new();
        for (m, generated) in layout.meshes.iter().enumerate() {
            if let Some(g) = generated {
                split.push((
                    m,
                    w.split_mesh(&doc["meshes"][m], g, &mut replaced, &format!("mesh {m}"))?,
                ));
            }
        }
        // A stretched instance's own layout: a copy of its mesh (as the input had it),
        // appended, its nodes pointed at it.
        let mut copies = Vec::new();
        for (c, copy) in layout.copies.iter().enumerate() {
            let what = format!("mesh {} (copy {c})", copy.mesh);
            let mut mesh = w.split_mesh(&doc["meshes"][copy.mesh], &copy.generated, &mut replaced, &what)?;
            if let Some(name) = mesh.get("name").and_then(Value::as_str).map(str::to_string) {
                mesh["name"] = json!(format!("{name} (own lightmap layout {c})"));
            }
            copies.push(mesh);
        }
        for (m, mesh) in split {
            doc["meshes"][m] = mesh;
        }
        for (copy, mesh) in layout.copies.iter().zip(copies) {
            let meshes = doc["meshes"]
                .as_array_mut()
                .ok_or("the document's meshes are not a list")?;
            meshes.push(mesh);
            let index = meshes.len() - 1;
            for &k in &copy.instances {
                doc["nodes"][source.instances[k].node]["mesh"] = json!(index);
            }
        }
    }
    if !new_views.is_empty() {
        match doc.get_mut("bufferViews").and_then(Value::as_array_mut) {
            Some(v) => v.extend(new_views),
            None => doc["bufferViews"] = Value::Array(new_views),
        }
    }
    if !new_accessors.is_empty() {
        match doc.get_mut("accessors").and_then(Value::as_array_mut) {
            Some(a) => a.extend(new_accessors),
            None => doc["accessors"] = Value::Array(new_accessors),
        }
    }
    prune_orphans(&mut doc, &replaced);

    // Per node, where its lightmap is.
    for place in scene.placements() {
        let node = &mut doc["nodes"][place.node];
        if node.get("extras").is_none() {
            node["extras"] = json!({});
        }
        if let Some(extras) = node["extras"].as_object_mut() {
            extras.insert(
                "lightmap".into(),
                json!({"page": place.page, "scale_offset": place.scale_offset, "file": page_file(place.page)}),
            );
        }
    }

    align(&mut bin, 4);
    doc["buffers"] = json!([{"byteLength": bin.len()}]);
    Ok(write_glb(&doc, &bin))
}

/// Extensions known to refer to no accessor and no buffer view (beyond what
/// [`prune_orphans`] renumbers): with any other in `extensionsUsed`, nothing is removed.
const PRUNE_SAFE_EXTENSIONS: &[&str] = &[
    "KHR_lights_punctual",
    "KHR_materials_clearcoat",
    "KHR_materials_emissive_strength",
    "KHR_materials_ior",
    "KHR_materials_iridescence",
    "KHR_materials_sheen",
    "KHR_materials_specular",
    "KHR_materials_transmission",
    "KHR_materials_unlit",
    "KHR_materials_variants",
    "KHR_materials_volume",
    "KHR_mesh_quantization",
    "KHR_texture_transform",
    "EXT_mesh_gpu_instancing",
];

/// Calls `f` with every accessor a primitive refers to (attributes, indices, targets).
fn primitive_accessors(prim: &Value, f: &mut dyn FnMut(usize)) {
    let mut each = |v: &Value| {
        if let Some(a) = v.as_u64() {
            f(a as usize);
        }
    };
    prim["attributes"]
        .as_object()
        .into_iter()
        .flatten()
        .for_each(|(_, v)| each(v));
    each(&prim["indices"]);
    for t in prim["targets"].as_array().into_iter().flatten() {
        t.as_object().into_iter().flatten().for_each(|(_, v)| each(v));
    }
}

/// The array at `key` of `v`, if any. (Not `v[key]`: indexing a JSON object mutably
/// inserts a `null` where the key is absent, which would write `"skins": null`.)
fn array_at<'v>(v: &'v mut Value, key: &str) -> impl Iterator<Item = &'v mut Value> {
    v.get_mut(key).and_then(Value::as_array_mut).into_iter().flatten()
}

/// Calls `f` with each value of the object at `key` of `v`, if any.
fn object_values<'v>(v: &'v mut Value, key: &str, f: &mut dyn FnMut(&mut Value)) {
    if let Some(o) = v.get_mut(key).and_then(Value::as_object_mut) {
        o.iter_mut().for_each(|(_, x)| f(x));
    }
}

/// Every place in `doc` that holds an accessor index, for reading or renumbering.
fn accessor_refs(doc: &mut Value, f: &mut dyn FnMut(&mut Value)) {
    for mesh in array_at(doc, "meshes") {
        for prim in array_at(mesh, "primitives") {
            object_values(prim, "attributes", f);
            if let Some(i) = prim.get_mut("indices") {
                f(i);
            }
            for t in array_at(prim, "targets") {
                if let Some(o) = t.as_object_mut() {
                    o.iter_mut().for_each(|(_, x)| f(x));
                }
            }
        }
    }
    for skin in array_at(doc, "skins") {
        if let Some(m) = skin.get_mut("inverseBindMatrices") {
            f(m);
        }
    }
    for anim in array_at(doc, "animations") {
        for sampler in array_at(anim, "samplers") {
            for key in ["input", "output"] {
                if let Some(a) = sampler.get_mut(key) {
                    f(a);
                }
            }
        }
    }
    for node in array_at(doc, "nodes") {
        if let Some(attrs) = node
            .pointer_mut("/extensions/EXT_mesh_gpu_instancing/attributes")
            .and_then(Value::as_object_mut)
        {
            attrs.iter_mut().for_each(|(_, v)| f(v));
        }
    }
}

/// Every place in `doc` that holds a buffer view index.
fn view_refs(doc: &mut Value, f: &mut dyn FnMut(&mut Value)) {
    for acc in array_at(doc, "accessors") {
        for ptr in ["/bufferView", "/sparse/indices/bufferView", "/sparse/values/bufferView"] {
            if let Some(v) = acc.pointer_mut(ptr) {
                f(v);
            }
        }
    }
    for img in array_at(doc, "images") {
        if let Some(v) = img.get_mut("bufferView") {
            f(v);
        }
    }
}

/// Removes the accessors of `candidates` that nothing refers to any more, then the buffer
/// views nothing refers to any more that only removed accessors used, renumbering every
/// reference (module doc). Objects the input already left unused stay.
fn prune_orphans(doc: &mut Value, candidates: &std::collections::BTreeSet<usize>) {
    let safe = doc["extensionsUsed"]
        .as_array()
        .into_iter()
        .flatten()
        .all(|e| e.as_str().is_some_and(|e| PRUNE_SAFE_EXTENSIONS.contains(&e)));
    if candidates.is_empty() || !safe {
        return;
    }
    let mut used = std::collections::BTreeSet::new();
    accessor_refs(doc, &mut |v| {
        if let Some(a) = v.as_u64() {
            used.insert(a as usize);
        }
    });
    let dead: std::collections::BTreeSet<usize> = candidates.difference(&used).copied().collect();
    if dead.is_empty() {
        return;
    }
    let accessors = doc["accessors"].as_array().cloned().unwrap_or_default();
    // Views of the removed accessors: removed too unless something else still uses them.
    let mut view_candidates = std::collections::BTreeSet::new();
    for &a in &dead {
        let acc = &accessors[a];
        for ptr in ["/bufferView", "/sparse/indices/bufferView", "/sparse/values/bufferView"] {
            if let Some(v) = acc.pointer(ptr).and_then(Value::as_u64) {
                view_candidates.insert(v as usize);
            }
        }
    }
    let renumber = |len: usize, dead: &std::collections::BTreeSet<usize>| -> Vec<Option<usize>> {
        let mut next = 0;
        (0..len)
            .map(|i| {
                (!dead.contains(&i)).then(|| {
                    next += 1;
                    next - 1
                })
            })
            .collect()
    };
    let map = renumber(accessors.len(), &dead);
    doc["accessors"] = Value::Array(
        accessors
            .into_iter()
            .enumerate()
            .filter(|(i, _)| map[*i].is_some())
            .map(|(_, a)| a)
            .collect(),
    );
    accessor_refs(doc, &mut |v| {
        if let Some(new) = v.as_u64().and_then(|a| map.get(a as usize).copied().flatten()) {
            *v = json!(new);
        }
    });
    let mut views_used = std::collections::BTreeSet::new();
    view_refs(doc, &mut |v| {
        if let Some(b) = v.as_u64() {
            views_used.insert(b as usize);
        }
    });
    let dead_views: std::collections::BTreeSet<usize> = view_candidates.difference(&views_used).copied().collect();
    if dead_views.is_empty() {
        return;
    }
    let views = doc["bufferViews"].as_array().cloned().unwrap_or_default();
    let vmap = renumber(views.len(), &dead_views);
    doc["bufferViews"] = Value::Array(
        views
            .into_iter()
            .enumerate()
            .filter(|(i, _)| vmap[*i].is_some())
            .map(|(_, v)| v)
            .collect(),
    );
    view_refs(doc, &mut |v| {
        if let Some(new) = v.as_u64().and_then(|b| vmap.get(b as usize).copied().flatten()) {
            *v = json!(new);
        }
    });
}

fn align(bin: &mut Vec<u8>, to: usize) {
    while !bin.len().is_multiple_of(to) {
        bin.push(0);
    }
}

struct Writer<'a> {
    doc: &'a Value,
    source: &'a SourceDocument,
    bin: &'a mut Vec<u8>,
    views: &'a mut Vec<Value>,
    view_base: usize,
    accessors: &'a mut Vec<Value>,
    accessor_base: usize,
}

fn component_size(ct: u64) -> Option<usize> {
    match ct {
        5120 | 5121 => Some(1),
        5122 | 5123 => Some(2),
        5125 | 5126 => Some(4),
        _ => None,
    }
}

fn components(ty: &str) -> Option<usize> {
    match ty {
        "SCALAR" => Some(1),
        "VEC2" => Some(2),
        "VEC3" => Some(3),
        "VEC4" => Some(4),
        _ => None,
    }
}

fn decode(ct: u64, b: &[u8]) -> f64 {
    match ct {
        5120 => f64::from(b[0] as i8),
        5121 => f64::from(b[0]),
        5122 => f64::from(i16::from_le_bytes([b[0], b[1]])),
        5123 => f64::from(u16::from_le_bytes([b[0], b[1]])),
        5125 => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
        _ => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
    }
}

impl Writer<'_> {
    /// `mesh` (the input's JSON) with each primitive that has generated UVs in `generated`
    /// split for them; the accessors the old primitives used go into `replaced`.
    fn split_mesh(
        &mut self,
        mesh: &Value,
        generated: &super::GeneratedMesh,
        replaced: &mut std::collections::BTreeSet<usize>,
        what: &str,
    ) -> Result<Value, String> {
        let mut out = mesh.clone();
        for (p, g) in generated.primitives.iter().enumerate() {
            let Some(g) = g else { continue };
            let prim = &mesh["primitives"][p];
            primitive_accessors(prim, &mut |a| {
                replaced.insert(a);
            });
            out["primitives"][p] = self
                .split_primitive(prim, g)
                .map_err(|e| format!("{what}, primitive {p}: {e}"))?;
        }
        Ok(out)
    }

    fn push_view(&mut self, bytes: &[u8], stride: Option<usize>, target: u32) -> usize {
        align(self.bin, 4);
        let mut v = json!({"buffer": 0, "byteOffset": self.bin.len(), "byteLength": bytes.len(), "target": target});
        if let Some(s) = stride {
            v["byteStride"] = json!(s);
        }
        self.bin.extend_from_slice(bytes);
        self.views.push(v);
        self.view_base + self.views.len() - 1
    }

    fn push_accessor(&mut self, acc: Value) -> usize {
        self.accessors.push(acc);
        self.accessor_base + self.accessors.len() - 1
    }

    /// A copy of accessor `index` holding element `xref[i]` at position `i`.
    fn remap(&mut self, index: usize, xref: &[u32], semantic: &str) -> Result<usize, String> {
        let acc = self.doc["accessors"]
            .get(index)
            .ok_or_else(|| format!("{semantic}: accessor {index} does not exist"))?
            .clone();
        if acc.get("sparse").is_some() {
            return Err(format!(
                "{semantic}: accessor {index} is sparse; vertices cannot be split for new lightmap UVs"
            ));
        }
        let ct = acc["componentType"].as_u64().unwrap_or(0);
        let ty = acc["type"].as_str().unwrap_or("");
        let (Some(cs), Some(nc)) = (component_size(ct), components(ty)) else {
            return Err(format!(
                "{semantic}: accessor {index} has an unsupported type {ty} of {ct}"
            ));
        };
        let elem = cs * nc;
        let count = acc["count"].as_u64().unwrap_or(0) as usize;
        let mut out = json!({"componentType": ct, "type": ty, "count": xref.len()});
        if let Some(n) = acc.get("normalized") {
            out["normalized"] = n.clone();
        }
        if let Some(name) = acc.get("name") {
            out["name"] = name.clone();
        }
        let Some(view_index) = acc["bufferView"].as_u64().map(|v| v as usize) else {
            // All zeros: the copy is all zeros too.
            for key in ["min", "max"] {
                if let Some(v) = acc.get(key) {
                    out[key] = v.clone();
                }
            }
            return Ok(self.push_accessor(out));
        };
        let view = &self.source.json["bufferViews"][view_index];
        let buffer = self
            .source
            .buffers
            .get(view["buffer"].as_u64().unwrap_or(0) as usize)
            .ok_or_else(|| format!("{semantic}: buffer of view {view_index} is missing"))?;
        let start =
            view["byteOffset"].as_u64().unwrap_or(0) as usize + acc["byteOffset"].as_u64().unwrap_or(0) as usize;
        let stride = view["byteStride"].as_u64().map_or(elem, |s| s as usize);
        let padded = elem.div_ceil(4) * 4;
        let mut bytes = vec![0u8; padded * xref.len()];
        let mut lo = vec![f64::INFINITY; nc];
        let mut hi = vec![f64::NEG_INFINITY; nc];
        for (i, &x) in xref.iter().enumerate() {
            let x = x as usize;
            if x >= count {
                return Err(format!(
                    "{semantic}: vertex {x} is past accessor {index}'s {count} elements"
                ));
            }
            let at = start + x * stride;
            let src = buffer
                .get(at..at + elem)
                .ok_or_else(|| format!("{semantic}: accessor {index} reads past its buffer"))?;
            bytes[i * padded..i * padded + elem].copy_from_slice(src);
            for c in 0..nc {
                let v = decode(ct, &src[c * cs..(c + 1) * cs]);
                lo[c] = lo[c].min(v);
                hi[c] = hi[c].max(v);
            }
        }
        let view = self.push_view(&bytes, (padded != elem).then_some(padded), 34962);
        out["bufferView"] = json!(view);
        if (acc.get("min").is_some() || semantic == "POSITION") && !xref.is_empty() {
            let num = |v: f64| if ct == 5126 { json!(v) } else { json!(v as i64) };
            out["min"] = Value::Array(lo.into_iter().map(num).collect());
            out["max"] = Value::Array(hi.into_iter().map(num).collect());
        }
        Ok(self.push_accessor(out))
    }

    fn split_primitive(&mut self, prim: &Value, g: &GeneratedPrimitive) -> Result<Value, String> {
        let mut prim = prim.clone();
        let attributes = prim["attributes"].as_object().cloned().ok_or("has no attributes")?;
        let mut new_attr = serde_json::Map::new();
        for (semantic, index) in &attributes {
            if semantic == "TEXCOORD_1" {
                continue;
            }
            let index = index
                .as_u64()
                .ok_or_else(|| format!("{semantic} is not an accessor index"))? as usize;
            new_attr.insert(semantic.clone(), json!(self.remap(index, &g.xref, semantic)?));
        }
        let uv_bytes: Vec<u8> =
            g.uv.iter()
                .flat_map(|uv| uv.to_array())
                .flat_map(f32::to_le_bytes)
                .collect();
        let view = self.push_view(&uv_bytes, None, 34962);
        let uv =
            self.push_accessor(json!({"bufferView": view, "componentType": 5126, "count": g.uv.len(), "type": "VEC2"}));
        new_attr.insert("TEXCOORD_1".into(), json!(uv));
        new_attr.entry("TEXCOORD_0").or_insert(json!(uv));
        prim["attributes"] = Value::Object(new_attr);
        if let Some(targets) = prim["targets"].as_array().cloned() {
            let mut new_targets = Vec::new();
            for t in targets {
                let mut nt = serde_json::Map::new();
                for (semantic, index) in t.as_object().into_iter().flatten() {
                    let index = index
                        .as_u64()
                        .ok_or("morph target attribute is not an accessor index")?
                        as usize;
                    nt.insert(semantic.clone(), json!(self.remap(index, &g.xref, semantic)?));
                }
                new_targets.push(Value::Object(nt));
            }
            prim["targets"] = Value::Array(new_targets);
        }
        let idx: Vec<u8> = g.indices.iter().flat_map(|i| i.to_le_bytes()).collect();
        let view = self.push_view(&idx, None, 34963);
        let indices = self.push_accessor(
            json!({"bufferView": view, "componentType": 5125, "count": g.indices.len(), "type": "SCALAR"}),
        );
        prim["indices"] = json!(indices);
        Ok(prim)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeSet;

    fn doc() -> Value {
        json!({
            "asset": {"version": "2.0"},
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
            "skins": [{"joints": [0], "inverseBindMatrices": 2}],
            "animations": [{"channels": [], "samplers": [{"input": 3, "output": 0}]}],
            "nodes": [{"mesh": 0}],
            "images": [{"bufferView": 3, "mimeType": "image/png"}],
            "accessors": [
                {"bufferView": 0, "count": 1},
                {"bufferView": 1, "count": 1},
                {"bufferView": 2, "count": 1},
                {"bufferView": 3, "count": 1}
            ],
            "bufferViews": [
                {"buffer": 0, "byteLength": 4},
                {"buffer": 0, "byteLength": 8},
                {"buffer": 0, "byteLength": 12},
                {"buffer": 0, "byteLength": 16}
            ]
        })
    }

    /// Accessor 1 and its view go; accessor 2 stays (a skin's) and 0 (a mesh's and an
    /// animation's); every reference is renumbered, and nothing absent is added.
    #[test]
    fn orphans_go_and_every_reference_is_renumbered() {
        let mut d = doc();
        prune_orphans(&mut d, &BTreeSet::from([0, 1, 2]));
        assert_eq!(d["accessors"].as_array().unwrap().len(), 3);
        assert_eq!(d["skins"][0]["inverseBindMatrices"], 1);
        assert_eq!(d["animations"][0]["samplers"][0], json!({"input": 2, "output": 0}));
        assert_eq!(d["meshes"][0]["primitives"][0]["attributes"]["POSITION"], 0);
        let lengths: Vec<u64> = d["bufferViews"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v["byteLength"].as_u64().unwrap())
            .collect();
        assert_eq!(lengths, [4, 12, 16]);
        let views: Vec<u64> = d["accessors"]
            .as_array()
            .unwrap()
            .iter()
            .map(|a| a["bufferView"].as_u64().unwrap())
            .collect();
        assert_eq!(views, [0, 1, 2]);
        assert_eq!(d["images"][0]["bufferView"], 2);
        assert!(d.get("targets").is_none() && d["meshes"][0]["primitives"][0].get("targets").is_none());
        // A document without skins or animations gets none written.
        let mut bare = doc();
        for key in ["skins", "animations", "images"] {
            bare.as_object_mut().unwrap().remove(key);
        }
        prune_orphans(&mut bare, &BTreeSet::from([1, 2, 3]));
        assert!(bare.get("skins").is_none() && bare.get("animations").is_none() && bare.get("images").is_none());
        assert_eq!(bare["accessors"].as_array().unwrap().len(), 1);
        assert_eq!(bare["bufferViews"].as_array().unwrap().len(), 1);
    }

    /// A view another accessor still uses stays; an extension not known to be safe keeps
    /// everything.
    #[test]
    fn shared_views_and_unknown_extensions_keep_what_they_may_use() {
        let mut d = doc();
        d["accessors"][1]["bufferView"] = json!(0);
        prune_orphans(&mut d, &BTreeSet::from([1]));
        assert_eq!(d["accessors"].as_array().unwrap().len(), 3);
        assert_eq!(d["bufferViews"].as_array().unwrap().len(), 4);
        let mut d = doc();
        d["extensionsUsed"] = json!(["KHR_draco_mesh_compression"]);
        prune_orphans(&mut d, &BTreeSet::from([1]));
        assert_eq!(d, {
            let mut e = doc();
            e["extensionsUsed"] = json!(["KHR_draco_mesh_compression"]);
            e
        });
    }
}
