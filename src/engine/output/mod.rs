//! Writing lightmaps: OpenEXR with the layers and header attributes of DESIGN §2.
//!
//! How: one single-part scanline EXR, float32, ZIP-compressed (lossless; lightmaps are
//! smooth and compress well). The default `R`, `G`, `B` channels hold the full lightmap
//! (irradiance / π, dilated into gutters). Optional layers follow OpenEXR's naming
//! convention for layers in one part (`direct.R`, `indirect.R`, `validity.Y`, …), so
//! OpenEXR's own tools, Blender and Nuke list them as layers. Header attributes carry
//! the technique, its parameters (JSON text), steps, seconds and the error estimate;
//! they are prefixed `lightmapd:` so they cannot collide with standard attribute names.
//!
//! The `exr` crate does the encoding; this module only arranges channels and attributes.

pub mod pages;

use std::collections::HashMap;
use std::path::Path;

use exr::image::Layer;
use exr::prelude::{
    AnyChannel, AnyChannels, AttributeValue, Encoding, FlatSamples, Image, LayerAttributes, Text, WritableImage,
};
use glam::Vec3;
use smallvec::SmallVec;

use crate::engine::accumulate::Estimate;
use crate::engine::atlas::Atlas;
use crate::engine::post;

/// The optional layers a job may ask for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OutputLayer {
    Validity,
    Direct,
    Indirect,
    /// L1 directional moments of incident light (`sh.x.*`, `sh.y.*`, `sh.z.*`).
    Sh,
    /// Plain obscurance / sky visibility (`ao.Y`), from techniques that compute it.
    Ao,
    /// The validation report as images: `debug.inside.Y` (texels inside geometry),
    /// `debug.overlap.Y` (overlapping charts), `debug.density.Y` (texels per metre).
    Debug,
    /// Baked visibility of up to four chosen lights (`shadowmask.R` … `.A`,
    /// `engine::shadowmask`); the lightmap and `direct.*` then leave their direct light out.
    Shadowmask,
}

impl OutputLayer {
    /// Every layer, in the order the docs list them.
    pub const ALL: &'static [OutputLayer] = &[
        OutputLayer::Validity,
        OutputLayer::Direct,
        OutputLayer::Indirect,
        OutputLayer::Sh,
        OutputLayer::Ao,
        OutputLayer::Debug,
        OutputLayer::Shadowmask,
    ];

    pub fn parse(s: &str) -> Result<OutputLayer, String> {
        match s {
            "validity" => Ok(OutputLayer::Validity),
            "direct" => Ok(OutputLayer::Direct),
            "indirect" => Ok(OutputLayer::Indirect),
            "sh" => Ok(OutputLayer::Sh),
            "ao" => Ok(OutputLayer::Ao),
            "debug" => Ok(OutputLayer::Debug),
            "shadowmask" => Ok(OutputLayer::Shadowmask),
            other => Err(format!(
                "unknown output layer {other:?}; available: validity, direct, indirect, sh, ao, debug, shadowmask"
            )),
        }
    }

    /// The name a job gives it (the inverse of [`OutputLayer::parse`]).
    pub fn name(self) -> &'static str {
        match self {
            OutputLayer::Validity => "validity",
            OutputLayer::Direct => "direct",
            OutputLayer::Indirect => "indirect",
            OutputLayer::Sh => "sh",
            OutputLayer::Ao => "ao",
            OutputLayer::Debug => "debug",
            OutputLayer::Shadowmask => "shadowmask",
        }
    }
}

/// What goes into the header besides the pixels.
#[derive(Clone, Debug)]
pub struct ExrMetadata {
    pub technique: String,
    pub params: serde_json::Value,
    pub steps: u64,
    pub seconds: f64,
    pub relative_error: Option<f32>,
    pub seed: u64,
    /// `no`, or the denoiser that made the lightmap (e.g. `oidn 2.5.1 (cpu) RTLightmap,
    /// blended by error`); `relative_error` is then the denoised lightmap's estimate.
    pub denoised: String,
    /// The raw estimate's relative error, when the lightmap was denoised.
    pub raw_relative_error: Option<f32>,
    /// The light of each `shadowmask.*` channel, in channel order (empty: no shadowmask).
    pub shadowmask: Vec<String>,
    /// `(P, pages)` for page P of a bake's `pages` pages (`lightmapd:page`,
    /// `lightmapd:pages`); None for the whole grid (a snapshot).
    pub page: Option<(u32, u32)>,
}

/// What every layer holds (`lightmapd:quantity`, the manifest's `quantity`).
pub const QUANTITY: &str = "irradiance/pi, linear RGB (albedo * lightmap = outgoing radiance)";

/// Builds the channel list for `estimate` (dilated) plus the requested layers.
pub fn lightmap_channels(
    atlas: &Atlas,
    estimate: &Estimate,
    layers: &[OutputLayer],
    rings: u32,
) -> Result<Vec<(String, Vec<f32>)>, String> {
    let mut channels = Vec::new();
    let mut rgb = |prefix: &str, values: &[Vec3]| {
        let mut img = post::dilate(atlas, values, rings);
        post::seams::stitch(&mut img, atlas.width, atlas.height, &atlas.pixel_texel, &atlas.seams);
        for (k, c) in ["R", "G", "B"].iter().enumerate() {
            let name = if prefix.is_empty() {
                c.to_string()
            } else {
                format!("{prefix}.{c}")
            };
            channels.push((name, img.iter().map(|v| v[k]).collect::<Vec<f32>>()));
        }
    };
    rgb("", &estimate.total);
    for layer in layers {
        match layer {
            OutputLayer::Direct | OutputLayer::Indirect => {
                let direct = estimate
                    .direct
                    .as_ref()
                    .ok_or("the technique kept no direct-light layer")?;
                if *layer == OutputLayer::Direct {
                    rgb("direct", direct);
                } else {
                    let indirect: Vec<Vec3> = estimate
                        .total
                        .iter()
                        .zip(direct)
                        .map(|(t, d)| (*t - *d).max(Vec3::ZERO))
                        .collect();
                    rgb("indirect", &indirect);
                }
            }
            OutputLayer::Sh => {
                let m = estimate
                    .moments
                    .as_ref()
                    .ok_or("the technique kept no directional (sh) layer")?;
                for (k, axis) in ["x", "y", "z"].iter().enumerate() {
                    let values: Vec<Vec3> = m.iter().map(|v| v[k]).collect();
                    rgb(&format!("sh.{axis}"), &values);
                }
            }
            OutputLayer::Validity | OutputLayer::Debug | OutputLayer::Ao | OutputLayer::Shadowmask => {}
        }
    }
    if layers.contains(&OutputLayer::Ao) {
        let ao = estimate
            .ao
            .as_ref()
            .ok_or("the technique kept no obscurance (ao) layer")?;
        // Dilated like the lightmap, so gutters hold their chart's value.
        let as_rgb: Vec<Vec3> = ao.iter().map(|a| Vec3::splat(*a)).collect();
        let img = post::dilate(atlas, &as_rgb, rings);
        channels.push(("ao.Y".into(), img.iter().map(|v| v.x).collect()));
    }
    if layers.contains(&OutputLayer::Shadowmask) {
        let mask = estimate
            .shadowmask
            .as_ref()
            .ok_or("the bake kept no shadowmask layer")?;
        // Dilated and stitched like the lightmap, three channels at a time.
        let mut planes: Vec<Vec<f32>> = Vec::new();
        for first in [0, 3] {
            let values: Vec<Vec3> = mask
                .values
                .iter()
                .map(|v| Vec3::from_array(std::array::from_fn(|k| v.get(first + k).copied().unwrap_or(0.0))))
                .collect();
            let mut img = post::dilate(atlas, &values, rings);
            post::seams::stitch(&mut img, atlas.width, atlas.height, &atlas.pixel_texel, &atlas.seams);
            // The seam solver's least squares can overshoot a step from 0 to 1 (seen: 1.37
            // on the Kenney level); a visibility stays a fraction.
            planes.extend((0..3).map(|k| img.iter().map(|v| v[k].clamp(0.0, 1.0)).collect::<Vec<f32>>()));
        }
        for (c, plane) in planes.into_iter().take(mask.lights.len()).enumerate() {
            channels.push((
                format!("shadowmask.{}", crate::engine::accumulate::MASK_CHANNEL_NAMES[c]),
                plane,
            ));
        }
    }
    if layers.contains(&OutputLayer::Debug) {
        let size = (atlas.width * atlas.height) as usize;
        let mark = |pixels: &[u32]| {
            let mut img = vec![0.0f32; size];
            pixels.iter().for_each(|p| img[*p as usize] = 1.0);
            img
        };
        channels.push(("debug.inside.Y".into(), mark(&atlas.inside_pixels)));
        channels.push(("debug.overlap.Y".into(), mark(&atlas.overlap_pixels)));
        let density: Vec<f32> = atlas
            .texels
            .iter()
            .map(|t| if t.size > 0.0 { 1.0 / t.size } else { 0.0 })
            .collect();
        channels.push(("debug.density.Y".into(), post::scatter_scalar(atlas, &density)));
    }
    if layers.contains(&OutputLayer::Validity) {
        let ones = vec![1.0f32; atlas.texels.len()];
        channels.push(("validity.Y".into(), post::scatter_scalar(atlas, &ones)));
    }
    // The NaN guard (DESIGN §5) once more on what is written: after denoising, dilation
    // and seam stitching, every channel of every layer.
    for (name, data) in &channels {
        if let Some((p, v)) = data.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            let p = p as u32;
            return Err(format!(
                "the {name} channel holds the non-finite value {v} at pixel ({}, {}) after denoising and seam \
                 stitching; the lightmap was not written",
                p % atlas.width,
                p / atlas.width
            ));
        }
    }
    Ok(channels)
}

/// Encodes channels and metadata as EXR bytes.
pub fn encode_exr(
    width: u32,
    height: u32,
    channels: Vec<(String, Vec<f32>)>,
    meta: &ExrMetadata,
) -> Result<Vec<u8>, String> {
    let list: SmallVec<[AnyChannel<FlatSamples>; 4]> = channels
        .into_iter()
        .map(|(name, data)| AnyChannel::new(name.as_str(), FlatSamples::F32(data)))
        .collect();
    let mut attrs = LayerAttributes::default();
    let mut other: HashMap<Text, AttributeValue> = HashMap::new();
    let text = |s: &str| AttributeValue::Text(Text::new_or_panic(sanitize(s)));
    other.insert(Text::from("lightmapd:technique"), text(&meta.technique));
    other.insert(Text::from("lightmapd:params"), text(&meta.params.to_string()));
    other.insert(
        Text::from("lightmapd:steps"),
        AttributeValue::I32(meta.steps.min(i32::MAX as u64) as i32),
    );
    other.insert(Text::from("lightmapd:seconds"), AttributeValue::F64(meta.seconds));
    other.insert(Text::from("lightmapd:seed"), text(&meta.seed.to_string()));
    other.insert(Text::from("lightmapd:denoised"), text(&meta.denoised));
    if !meta.shadowmask.is_empty() {
        // The light of each shadowmask channel, R first, as JSON text.
        other.insert(
            Text::from("lightmapd:shadowmask"),
            text(&serde_json::to_string(&meta.shadowmask).unwrap_or_default()),
        );
    }
    if let Some(e) = meta.raw_relative_error {
        other.insert(Text::from("lightmapd:raw_relative_error"), AttributeValue::F32(e));
    }
    other.insert(Text::from("lightmapd:quantity"), text(QUANTITY));
    if let Some((page, pages)) = meta.page {
        other.insert(
            Text::from("lightmapd:page"),
            AttributeValue::I32(page.min(i32::MAX as u32) as i32),
        );
        other.insert(
            Text::from("lightmapd:pages"),
            AttributeValue::I32(pages.min(i32::MAX as u32) as i32),
        );
    }
    if let Some(e) = meta.relative_error {
        other.insert(Text::from("lightmapd:relative_error"), AttributeValue::F32(e));
    }
    attrs.other = other;
    attrs.software_name = Some(Text::from(concat!("lightmapd ", env!("CARGO_PKG_VERSION"))));
    let layer = Layer::new(
        (width as usize, height as usize),
        attrs,
        Encoding::SMALL_LOSSLESS,
        AnyChannels::sort(list),
    );
    let image = Image::from_layer(layer);
    let mut out = std::io::Cursor::new(Vec::new());
    image
        .write()
        .to_buffered(&mut out)
        .map_err(|e| format!("encoding EXR: {e}"))?;
    Ok(out.into_inner())
}

/// A lightmap EXR read back: its default `R`, `G`, `B` channels and its error estimate.
pub struct DecodedLightmap {
    pub width: u32,
    pub height: u32,
    /// Rows top first, as written.
    pub rgb: Vec<Vec3>,
    /// `lightmapd:relative_error`, when the header has it.
    pub relative_error: Option<f32>,
}

/// Reads the default channels and the error estimate of a lightmap EXR this module (or
/// any tool keeping DESIGN §2's layout) wrote.
pub fn decode_lightmap(bytes: &[u8]) -> Result<DecodedLightmap, String> {
    use exr::prelude::{ReadChannels, ReadLayers, read};
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(bytes))
        .map_err(|e| format!("cannot read the lightmap EXR: {e}"))?;
    let layer = &image.layer_data;
    let (w, h) = (layer.size.width(), layer.size.height());
    let channel = |name: &str| -> Result<Vec<f32>, String> {
        layer
            .channel_data
            .list
            .iter()
            .find(|c| c.name == *name)
            .map(|c| c.sample_data.values_as_f32().collect())
            .ok_or_else(|| format!("the lightmap EXR has no {name} channel"))
    };
    let (r, g, b) = (channel("R")?, channel("G")?, channel("B")?);
    let relative_error = match layer.attributes.other.get(&Text::from("lightmapd:relative_error")) {
        Some(AttributeValue::F32(e)) => Some(*e),
        _ => None,
    };
    Ok(DecodedLightmap {
        width: w as u32,
        height: h as u32,
        rgb: (0..w * h).map(|i| Vec3::new(r[i], g[i], b[i])).collect(),
        relative_error,
    })
}

/// EXR text attributes are Latin-1; keep JSON printable ASCII so every reader copes.
fn sanitize(s: &str) -> String {
    s.chars()
        .map(|c| if c.is_ascii() && !c.is_ascii_control() { c } else { '?' })
        .collect()
}

/// Writes `bytes` to `path` through a temporary file and a rename, so a failing or
/// interrupted bake never leaves a half-written lightmap where a good one was.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "lightmap".into());
    let tmp = dir.join(format!(".{name}.tmp-{}", std::process::id()));
    std::fs::write(&tmp, bytes)?;
    std::fs::rename(&tmp, path).inspect_err(|_| {
        let _ = std::fs::remove_file(&tmp);
    })
}

/// A tone-mapped PNG of a full lightmap image (for previews and dashboards): exposure so
/// the 99th-percentile luminance maps to 0.9 before the sRGB curve, clamped.
pub fn encode_preview_png(width: u32, height: u32, rgb: &[Vec3]) -> Result<Vec<u8>, String> {
    let mut lum: Vec<f32> = rgb
        .iter()
        .map(|v| v.dot(crate::engine::accumulate::LUMINANCE))
        .filter(|l| *l > 0.0)
        .collect();
    lum.sort_by(f32::total_cmp);
    let white = lum
        .get(lum.len().saturating_sub(1) * 99 / 100)
        .copied()
        .unwrap_or(1.0)
        .max(1e-12);
    let exposure = 0.9 / white;
    let encode = |c: f32| {
        let c = (c * exposure).clamp(0.0, 1.0);
        let s = if c <= 0.003_130_8 {
            12.92 * c
        } else {
            1.055 * c.powf(1.0 / 2.4) - 0.055
        };
        (s * 255.0 + 0.5) as u8
    };
    let bytes: Vec<u8> = rgb
        .iter()
        .flat_map(|v| [encode(v.x), encode(v.y), encode(v.z)])
        .collect();
    let img = image::RgbImage::from_raw(width, height, bytes).ok_or("preview: image size does not match")?;
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png)
        .map_err(|e| format!("encoding PNG: {e}"))?;
    Ok(out.into_inner())
}
