//! Writes a scene back as `.glb`, with its lightmap UVs as `TEXCOORD_1`: after UV
//! generation, this is the file a renderer needs next to the lightmap.
//!
//! How: one glTF mesh per source mesh (every instance's triangles, already in world
//! space), one node per mesh translated by the scene's origin offset (JSON numbers keep
//! it in double precision, so a scene far from the origin comes back where it was);
//! positions, normals, `TEXCOORD_0` and `TEXCOORD_1` per triangle corner; materials with
//! their factors, emission (strength via `KHR_materials_emissive_strength`) and
//! textures, re-encoded as 8-bit sRGB PNG; punctual lights as `KHR_lights_punctual`.
//!
//! Limits: the node hierarchy is flattened (instances become separate geometry, as
//! their lightmap UVs differ); vertices are not welded; 16-bit textures come back as
//! 8-bit; texture transforms, alpha modes and extensions other than the two above are
//! not written.

use std::collections::BTreeMap;

use glam::{Quat, Vec2, Vec3};
use serde_json::{Value, json};

use super::build::write_glb;
use super::{LightKind, Scene, Triangle, Wrap};

/// The scene as GLB bytes.
pub fn to_glb(scene: &Scene) -> Result<Vec<u8>, String> {
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
