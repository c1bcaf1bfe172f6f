//! Scenes made in code, written out as `.glb`: the bundled Cornell box and the analytic
//! test scenes. Going through a real file means tests exercise the importer a user's
//! scene takes, and the example scene can be opened in any glTF viewer.
//!
//! How: each mesh is a chart with its own UVs in [0, 1]² (a quad is the unit square, a
//! sphere its latitude-longitude map); charts are packed into a square grid of equal
//! cells with a margin, which becomes TEXCOORD_1. Equal cells give unequal texel density
//! for meshes of unequal size; that is fine for test scenes and is why real scenes bring
//! their own lightmap UVs.
//!
//! The GLB container is written by hand ([`write_glb`]): twenty lines, and tests need to
//! build deliberately broken files that no writer crate would produce.

use glam::{Quat, Vec2, Vec3};

use super::AlphaMode;
use serde_json::{Value, json};

#[derive(Clone, Debug)]
pub struct MaterialDesc {
    pub name: String,
    pub base_color: [f32; 4],
    /// Emitted radiance; written as `emissiveFactor` (normalised to at most 1) times
    /// `KHR_materials_emissive_strength`.
    pub emission: [f32; 3],
    pub double_sided: bool,
    /// glTF `metallicFactor` (0: dielectric).
    pub metallic: f32,
    /// glTF `roughnessFactor` (1: fully rough, Lambertian for every technique).
    pub roughness: f32,
    /// glTF `alphaMode` and `alphaCutoff` (the coverage is `base_color[3]` × the texture's
    /// alpha).
    pub alpha_mode: AlphaMode,
    /// A base colour texture read at TEXCOORD_0 (the mesh's chart UVs), with repeat wrap.
    pub texture: Option<TextureDesc>,
}

/// An RGBA8 image (sRGB colour, linear alpha, as glTF has it), written as an embedded PNG.
#[derive(Clone, Debug)]
pub struct TextureDesc {
    pub width: u32,
    pub height: u32,
    /// Row-major, top row first, `width * height` pixels.
    pub rgba: Vec<[u8; 4]>,
}

impl TextureDesc {
    /// White stripes along u, `period` texels wide, repeated `repeats` times across the
    /// image: the first `period - cut` texels of each period are opaque (alpha 255), the
    /// last `cut` transparent (0). Bilinear filtering crosses alpha 0.5 exactly on texel
    /// edges, so with cutoff 0.5 a MASK material keeps exactly 1 − cut/period of the
    /// surface.
    pub fn alpha_stripes(period: u32, cut: u32, repeats: u32) -> Self {
        let width = period * repeats;
        let rgba = (0..width)
            .map(|x| [255, 255, 255, if x % period < period - cut { 255 } else { 0 }])
            .collect();
        TextureDesc { width, height: 1, rgba }
    }

    fn png(&self) -> Vec<u8> {
        let bytes: Vec<u8> = self.rgba.iter().flatten().copied().collect();
        let img = image::RgbaImage::from_raw(self.width, self.height, bytes).expect("width * height pixels");
        let mut out = std::io::Cursor::new(Vec::new());
        img.write_to(&mut out, image::ImageFormat::Png)
            .expect("PNG encoding into memory");
        out.into_inner()
    }
}

impl MaterialDesc {
    pub fn diffuse(name: &str, albedo: [f32; 3]) -> Self {
        MaterialDesc {
            name: name.into(),
            base_color: [albedo[0], albedo[1], albedo[2], 1.0],
            emission: [0.0; 3],
            double_sided: false,
            metallic: 0.0,
            roughness: 1.0,
            alpha_mode: AlphaMode::Opaque,
            texture: None,
        }
    }

    pub fn emissive(name: &str, albedo: [f32; 3], emission: [f32; 3]) -> Self {
        MaterialDesc {
            emission,
            ..Self::diffuse(name, albedo)
        }
    }

    /// The same material with glTF `metallic` and `roughness` (a glossy lobe where a
    /// technique supports one).
    pub fn glossy(mut self, metallic: f32, roughness: f32) -> Self {
        self.metallic = metallic;
        self.roughness = roughness;
        self
    }

    pub fn two_sided(mut self) -> Self {
        self.double_sided = true;
        self
    }

    /// The same material with `alphaMode` (and `alphaCutoff` for MASK).
    pub fn alpha(mut self, mode: AlphaMode) -> Self {
        self.alpha_mode = mode;
        self
    }

    /// The same material with a base colour texture.
    pub fn textured(mut self, texture: TextureDesc) -> Self {
        self.texture = Some(texture);
        self
    }
}

/// One mesh: one primitive, one chart.
#[derive(Clone, Debug)]
pub struct MeshDesc {
    pub name: String,
    pub positions: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    /// Chart-local UVs in [0, 1]², placed into the atlas by [`SceneBuilder::to_gltf`].
    pub chart_uv: Vec<Vec2>,
    pub indices: Vec<u32>,
    pub material: usize,
}

#[derive(Clone, Debug)]
pub enum LightDesc {
    Point {
        position: Vec3,
        color: [f32; 3],
        intensity: f32,
    },
    Directional {
        direction: Vec3,
        color: [f32; 3],
        intensity: f32,
    },
    Spot {
        position: Vec3,
        direction: Vec3,
        color: [f32; 3],
        intensity: f32,
        inner: f32,
        outer: f32,
    },
}

#[derive(Clone, Debug, Default)]
pub struct SceneBuilder {
    pub materials: Vec<MaterialDesc>,
    pub meshes: Vec<MeshDesc>,
    pub lights: Vec<LightDesc>,
    /// Light probe positions, written as nodes with `extras.light_probe: true`.
    pub probes: Vec<Vec3>,
    /// Margin around each chart in its grid cell, as a fraction of the cell (default 1/16).
    pub margin: Option<f32>,
}

impl SceneBuilder {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn material(&mut self, m: MaterialDesc) -> usize {
        self.materials.push(m);
        self.materials.len() - 1
    }

    /// A parallelogram `corner + s·u + t·v`, s, t in [0, 1]; its front face is `u × v`.
    pub fn quad(&mut self, name: &str, corner: Vec3, u: Vec3, v: Vec3, material: usize) -> usize {
        let n = u.cross(v).normalize();
        self.meshes.push(MeshDesc {
            name: name.into(),
            positions: vec![corner, corner + u, corner + u + v, corner + v],
            normals: vec![n; 4],
            chart_uv: vec![
                Vec2::new(0.0, 1.0),
                Vec2::new(1.0, 1.0),
                Vec2::new(1.0, 0.0),
                Vec2::new(0.0, 0.0),
            ],
            indices: vec![0, 1, 2, 0, 2, 3],
            material,
        });
        self.meshes.len() - 1
    }

    /// A parallelogram like [`quad`](Self::quad), split into `n` × `n` cells (2n² triangles,
    /// one chart): for benchmark scenes that need many triangles.
    pub fn quad_grid(&mut self, name: &str, corner: Vec3, u: Vec3, v: Vec3, n: u32, material: usize) -> usize {
        let normal = u.cross(v).normalize();
        let mut positions = Vec::new();
        let mut chart_uv = Vec::new();
        for j in 0..=n {
            for i in 0..=n {
                let (s, t) = (i as f32 / n as f32, j as f32 / n as f32);
                positions.push(corner + u * s + v * t);
                chart_uv.push(Vec2::new(s, 1.0 - t));
            }
        }
        let mut indices = Vec::new();
        for j in 0..n {
            for i in 0..n {
                let a = j * (n + 1) + i;
                let (b, c, d) = (a + 1, a + n + 2, a + n + 1);
                indices.extend([a, b, c, a, c, d]);
            }
        }
        let count = positions.len();
        self.meshes.push(MeshDesc {
            name: name.into(),
            positions,
            normals: vec![normal; count],
            chart_uv,
            indices,
            material,
        });
        self.meshes.len() - 1
    }

    /// An axis-aligned square of side `size` centred at `centre`, facing `normal`
    /// (one of ±X, ±Y, ±Z).
    pub fn square(&mut self, name: &str, centre: Vec3, size: f32, normal: Vec3, material: usize) -> usize {
        let (u, v) = tangent_frame(normal);
        let corner = centre - 0.5 * size * (u + v);
        self.quad(name, corner, u * size, v * size, material)
    }

    /// A UV sphere with `segments` around and `rings` from pole to pole, outward facing.
    /// Vertices sit on a sphere slightly larger than `radius`, chosen so that a regular
    /// `segments`-gon on it has the area of the true circle: the silhouette then blocks
    /// the same solid angle to first order (the inscribed polygon would be visibly
    /// smaller in analytic tests).
    pub fn sphere(
        &mut self,
        name: &str,
        centre: Vec3,
        radius: f32,
        segments: u32,
        rings: u32,
        material: usize,
    ) -> usize {
        let n = segments as f32;
        let r = radius * (std::f32::consts::TAU / (n * (std::f32::consts::TAU / n).sin())).sqrt();
        let mut positions = Vec::new();
        let mut normals = Vec::new();
        let mut chart_uv = Vec::new();
        for j in 0..=rings {
            let theta = std::f32::consts::PI * j as f32 / rings as f32;
            for i in 0..=segments {
                let phi = std::f32::consts::TAU * i as f32 / segments as f32;
                let n = Vec3::new(theta.sin() * phi.cos(), theta.cos(), -theta.sin() * phi.sin());
                positions.push(centre + r * n);
                normals.push(n);
                chart_uv.push(Vec2::new(i as f32 / segments as f32, j as f32 / rings as f32));
            }
        }
        let mut indices = Vec::new();
        let row = segments + 1;
        for j in 0..rings {
            for i in 0..segments {
                let a = j * row + i;
                let (b, c, d) = (a + 1, a + row, a + row + 1);
                if j != 0 {
                    indices.extend([a, c, b]);
                }
                if j != rings - 1 {
                    indices.extend([b, c, d]);
                }
            }
        }
        self.meshes.push(MeshDesc {
            name: name.into(),
            positions,
            normals,
            chart_uv,
            indices,
            material,
        });
        self.meshes.len() - 1
    }

    /// The five visible faces (not the bottom) of a box standing on y = `base.y`, with
    /// half sizes `half`, rotated by `yaw` radians about +Y; outward facing, one chart each.
    pub fn block(&mut self, name: &str, base: Vec3, half: Vec3, yaw: f32, material: usize) {
        let q = Quat::from_rotation_y(yaw);
        let c = base + Vec3::Y * half.y;
        let faces = [
            ("top", Vec3::Y, half.y, Vec3::X * half.x, Vec3::NEG_Z * half.z),
            ("front", Vec3::Z, half.z, Vec3::X * half.x, Vec3::Y * half.y),
            ("back", Vec3::NEG_Z, half.z, Vec3::NEG_X * half.x, Vec3::Y * half.y),
            ("left", Vec3::NEG_X, half.x, Vec3::Z * half.z, Vec3::Y * half.y),
            ("right", Vec3::X, half.x, Vec3::NEG_Z * half.z, Vec3::Y * half.y),
        ];
        for (face, n, d, u, v) in faces {
            let (n, u, v) = (q * n, q * u, q * v);
            let centre = c + n * d;
            self.quad(&format!("{name} {face}"), centre - u - v, 2.0 * u, 2.0 * v, material);
        }
    }

    pub fn light(&mut self, l: LightDesc) {
        self.lights.push(l);
    }

    /// The lightmap UV of chart-local `uv` in mesh `mesh`'s cell.
    pub fn atlas_uv(&self, mesh: usize, uv: Vec2) -> Vec2 {
        let cols = (self.meshes.len() as f32).sqrt().ceil().max(1.0) as usize;
        let cell = 1.0 / cols as f32;
        let margin = self.margin.unwrap_or(1.0 / 16.0) * cell;
        let origin = Vec2::new((mesh % cols) as f32, (mesh / cols) as f32) * cell;
        origin + Vec2::splat(margin) + uv * (cell - 2.0 * margin)
    }

    /// The glTF JSON and binary buffer; tests edit these to make broken files.
    pub fn to_gltf(&self) -> (Value, Vec<u8>) {
        let mut bin: Vec<u8> = Vec::new();
        let mut views = Vec::new();
        let mut accessors = Vec::new();
        let mut push = |bytes: &[u8], target: u32, acc: Value| -> usize {
            while !bin.len().is_multiple_of(4) {
                bin.push(0);
            }
            views.push(json!({"buffer": 0, "byteOffset": bin.len(), "byteLength": bytes.len(), "target": target}));
            bin.extend_from_slice(bytes);
            let mut acc = acc;
            acc["bufferView"] = json!(views.len() - 1);
            accessors.push(acc);
            accessors.len() - 1
        };
        let mut meshes = Vec::new();
        let mut nodes = Vec::new();
        for (mi, m) in self.meshes.iter().enumerate() {
            let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
            m.positions.iter().for_each(|p| {
                lo = lo.min(*p);
                hi = hi.max(*p);
            });
            let pos = push(
                bytemuck::cast_slice(&m.positions),
                34962,
                json!({"componentType": 5126, "count": m.positions.len(), "type": "VEC3", "min": lo.to_array(), "max": hi.to_array()}),
            );
            let nrm = push(
                bytemuck::cast_slice(&m.normals),
                34962,
                json!({"componentType": 5126, "count": m.normals.len(), "type": "VEC3"}),
            );
            let uv0 = push(
                bytemuck::cast_slice(&m.chart_uv),
                34962,
                json!({"componentType": 5126, "count": m.chart_uv.len(), "type": "VEC2"}),
            );
            let lm: Vec<Vec2> = m.chart_uv.iter().map(|uv| self.atlas_uv(mi, *uv)).collect();
            let uv1 = push(
                bytemuck::cast_slice(&lm),
                34962,
                json!({"componentType": 5126, "count": lm.len(), "type": "VEC2"}),
            );
            let idx = push(
                bytemuck::cast_slice(&m.indices),
                34963,
                json!({"componentType": 5125, "count": m.indices.len(), "type": "SCALAR"}),
            );
            meshes.push(json!({
                "name": m.name,
                "primitives": [{
                    "attributes": {"POSITION": pos, "NORMAL": nrm, "TEXCOORD_0": uv0, "TEXCOORD_1": uv1},
                    "indices": idx,
                    "material": m.material,
                    "mode": 4
                }]
            }));
            nodes.push(json!({"name": m.name, "mesh": mi}));
        }
        let mut lights = Vec::new();
        for l in &self.lights {
            let (light, node) = match l {
                LightDesc::Point {
                    position,
                    color,
                    intensity,
                } => (
                    json!({"type": "point", "color": color, "intensity": intensity}),
                    json!({"translation": position.to_array()}),
                ),
                LightDesc::Directional {
                    direction,
                    color,
                    intensity,
                } => (
                    json!({"type": "directional", "color": color, "intensity": intensity}),
                    json!({"rotation": rotation_to(*direction).to_array()}),
                ),
                LightDesc::Spot {
                    position,
                    direction,
                    color,
                    intensity,
                    inner,
                    outer,
                } => (
                    json!({"type": "spot", "color": color, "intensity": intensity,
                           "spot": {"innerConeAngle": inner, "outerConeAngle": outer}}),
                    json!({"translation": position.to_array(), "rotation": rotation_to(*direction).to_array()}),
                ),
            };
            lights.push(light);
            let mut node = node;
            node["extensions"] = json!({"KHR_lights_punctual": {"light": lights.len() - 1}});
            nodes.push(node);
        }
        for (k, p) in self.probes.iter().enumerate() {
            nodes.push(
                json!({"name": format!("probe {k}"), "translation": p.to_array(), "extras": {"light_probe": true}}),
            );
        }
        let mut images = Vec::new();
        let materials: Vec<Value> = self
            .materials
            .iter()
            .map(|m| {
                let peak = m.emission.iter().cloned().fold(0.0f32, f32::max);
                let mut v = json!({
                    "name": m.name,
                    "pbrMetallicRoughness": {"baseColorFactor": m.base_color, "metallicFactor": m.metallic, "roughnessFactor": m.roughness},
                    "doubleSided": m.double_sided
                });
                match m.alpha_mode {
                    AlphaMode::Opaque => {}
                    AlphaMode::Mask { cutoff } => {
                        v["alphaMode"] = json!("MASK");
                        v["alphaCutoff"] = json!(cutoff);
                    }
                    AlphaMode::Blend => v["alphaMode"] = json!("BLEND"),
                }
                if let Some(t) = &m.texture {
                    v["pbrMetallicRoughness"]["baseColorTexture"] = json!({"index": images.len(), "texCoord": 0});
                    images.push(t.png());
                }
                if peak > 0.0 {
                    let (factor, strength) = if peak > 1.0 { (m.emission.map(|e| e / peak), peak) } else { (m.emission, 1.0) };
                    v["emissiveFactor"] = json!(factor);
                    if strength != 1.0 {
                        v["extensions"] = json!({"KHR_materials_emissive_strength": {"emissiveStrength": strength}});
                    }
                }
                v
            })
            .collect();
        // Images last, each in its own buffer view (no target: not vertex data).
        let mut image_json = Vec::new();
        for png in &images {
            while !bin.len().is_multiple_of(4) {
                bin.push(0);
            }
            views.push(json!({"buffer": 0, "byteOffset": bin.len(), "byteLength": png.len()}));
            bin.extend_from_slice(png);
            image_json.push(json!({"bufferView": views.len() - 1, "mimeType": "image/png"}));
        }
        let mut used = vec!["KHR_materials_emissive_strength"];
        let mut root = json!({
            "asset": {"version": "2.0", "generator": "lightmapd scene builder"},
            "scene": 0,
            "scenes": [{"nodes": (0..nodes.len()).collect::<Vec<_>>()}],
            "nodes": nodes,
            "meshes": meshes,
            "materials": materials,
            "accessors": accessors,
            "bufferViews": views,
            "buffers": [{"byteLength": bin.len()}],
        });
        if !images.is_empty() {
            root["images"] = json!(image_json);
            // Repeat wrap, linear filtering (glTF's sampler codes).
            root["samplers"] = json!([{"magFilter": 9729, "minFilter": 9729, "wrapS": 10497, "wrapT": 10497}]);
            root["textures"] = json!(
                (0..images.len())
                    .map(|i| json!({"source": i, "sampler": 0}))
                    .collect::<Vec<_>>()
            );
        }
        if !lights.is_empty() {
            used.push("KHR_lights_punctual");
            root["extensions"] = json!({"KHR_lights_punctual": {"lights": lights}});
        }
        root["extensionsUsed"] = json!(used);
        (root, bin)
    }

    pub fn to_glb(&self) -> Vec<u8> {
        let (json, bin) = self.to_gltf();
        write_glb(&json, &bin)
    }
}

/// A rotation taking the node's -Z (where glTF lights point) onto `dir`.
fn rotation_to(dir: Vec3) -> Quat {
    Quat::from_rotation_arc(Vec3::NEG_Z, dir.normalize())
}

/// Two unit vectors spanning the plane of `normal`, with `u × v = normal`.
fn tangent_frame(normal: Vec3) -> (Vec3, Vec3) {
    let n = normal.normalize();
    let helper = if n.y.abs() > 0.9 { Vec3::Z } else { Vec3::Y };
    let u = helper.cross(n).normalize();
    (u, n.cross(u))
}

/// Removes `TEXCOORD_1` from every primitive of meshes `meshes` (every mesh for `None`)
/// of a glTF document, such as [`SceneBuilder::to_gltf`] writes: a scene whose lightmap
/// UVs must be generated, for tests and examples.
pub fn remove_lightmap_uvs(doc: &mut Value, meshes: Option<&[usize]>) {
    let Some(all) = doc.get_mut("meshes").and_then(Value::as_array_mut) else {
        return;
    };
    for (k, mesh) in all.iter_mut().enumerate() {
        if meshes.is_some_and(|m| !m.contains(&k)) {
            continue;
        }
        let primitives = mesh.get_mut("primitives").and_then(Value::as_array_mut);
        for p in primitives.into_iter().flatten() {
            if let Some(attributes) = p.get_mut("attributes").and_then(Value::as_object_mut) {
                attributes.remove("TEXCOORD_1");
            }
        }
    }
}

/// Writes a GLB container: 12-byte header, a JSON chunk padded with spaces, and a BIN
/// chunk padded with zeros (glTF 2.0 §4.4).
pub fn write_glb(json: &Value, bin: &[u8]) -> Vec<u8> {
    let mut js = serde_json::to_vec(json).expect("serialising a JSON value cannot fail");
    while !js.len().is_multiple_of(4) {
        js.push(b' ');
    }
    let mut b = bin.to_vec();
    while !b.len().is_multiple_of(4) {
        b.push(0);
    }
    let total = 12 + 8 + js.len() + if b.is_empty() { 0 } else { 8 + b.len() };
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(js.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&js);
    if !b.is_empty() {
        out.extend_from_slice(&(b.len() as u32).to_le_bytes());
        out.extend_from_slice(b"BIN\0");
        out.extend_from_slice(&b);
    }
    out
}

/// The bundled example: a Cornell box after the classic measurements (left wall red,
/// right wall green, two white blocks, a warm area light under the ceiling), about 2 m
/// across, open at the front (+Z). Every surface has its own lightmap chart.
pub fn cornell_box() -> SceneBuilder {
    let mut s = SceneBuilder::new();
    let white = s.material(MaterialDesc::diffuse("white", [0.725, 0.71, 0.68]));
    let red = s.material(MaterialDesc::diffuse("red", [0.63, 0.065, 0.05]));
    let green = s.material(MaterialDesc::diffuse("green", [0.14, 0.45, 0.091]));
    let light = s.material(MaterialDesc::emissive("light", [0.78, 0.78, 0.78], [17.0, 12.0, 4.0]));
    let (w, h) = (2.0f32, 2.0f32);
    s.quad("floor", Vec3::new(-1.0, 0.0, 1.0), Vec3::X * w, Vec3::NEG_Z * w, white);
    s.quad("ceiling", Vec3::new(-1.0, h, -1.0), Vec3::X * w, Vec3::Z * w, white);
    s.quad("back wall", Vec3::new(-1.0, 0.0, -1.0), Vec3::X * w, Vec3::Y * h, white);
    s.quad(
        "left wall",
        Vec3::new(-1.0, 0.0, 1.0),
        Vec3::NEG_Z * w,
        Vec3::Y * h,
        red,
    );
    s.quad("right wall", Vec3::new(1.0, 0.0, -1.0), Vec3::Z * w, Vec3::Y * h, green);
    s.quad(
        "light",
        Vec3::new(-0.25, h - 0.005, -0.2),
        Vec3::X * 0.5,
        Vec3::Z * 0.4,
        light,
    );
    s.block(
        "short block",
        Vec3::new(0.33, 0.0, 0.3),
        Vec3::new(0.3, 0.3, 0.3),
        -0.29,
        white,
    );
    s.block(
        "tall block",
        Vec3::new(-0.35, 0.0, -0.3),
        Vec3::new(0.3, 0.6, 0.3),
        0.29,
        white,
    );
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn glb_header_and_chunks_are_aligned() {
        let glb = cornell_box().to_glb();
        assert_eq!(&glb[0..4], b"glTF");
        assert_eq!(u32::from_le_bytes(glb[8..12].try_into().unwrap()) as usize, glb.len());
        let json_len = u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize;
        assert_eq!(json_len % 4, 0);
        assert_eq!(&glb[20 + json_len + 4..20 + json_len + 8], b"BIN\0");
    }

    #[test]
    fn tangent_frame_is_right_handed() {
        for n in [Vec3::X, Vec3::NEG_X, Vec3::Y, Vec3::NEG_Y, Vec3::Z, Vec3::NEG_Z] {
            let (u, v) = tangent_frame(n);
            assert!((u.cross(v) - n).length() < 1e-6, "{n}");
        }
    }

    #[test]
    fn atlas_cells_do_not_overlap() {
        let s = cornell_box();
        let n = s.meshes.len();
        for a in 0..n {
            let (lo_a, hi_a) = (s.atlas_uv(a, Vec2::ZERO), s.atlas_uv(a, Vec2::ONE));
            assert!(lo_a.min_element() > 0.0 && hi_a.max_element() < 1.0);
            for b in a + 1..n {
                let (lo_b, hi_b) = (s.atlas_uv(b, Vec2::ZERO), s.atlas_uv(b, Vec2::ONE));
                let disjoint = hi_a.x < lo_b.x || hi_b.x < lo_a.x || hi_a.y < lo_b.y || hi_b.y < lo_a.y;
                assert!(disjoint, "charts {a} and {b} overlap");
            }
        }
    }
}
