//! The output set of a bake: one EXR per lightmap page (`lightmap-P.exr`) and the
//! `lightmaps.json` manifest (DESIGN §2 "Pages and instances"; issue 19 point 7).
//!
//! How: a bake runs on one texel grid in which its pages lie one under another as row
//! bands ([`PageRows`], made by `atlas::unwrap`). The delivered channels (dilated within
//! each page, seams stitched, requested layers) are built once for the grid, then each
//! band is cut out and encoded as its own EXR with the header attributes of the whole bake
//! plus `lightmapd:page` and `lightmapd:pages`. Each page is a texel grid of its own in
//! DESIGN §2's sense (its first row is row 0), so a renderer samples page P at
//! `TEXCOORD_1 · (sx, sy) + (ox, oy)` with the node's `scale_offset` from the manifest
//! or from `extras.lightmap` of the written glTF; both come from
//! [`Scene::placements`](crate::engine::scene::Scene::placements).
//!
//! The manifest's error per page is the noise part only (`relative_noise`: the RMS of
//! the per-texel standard error from the two halves over the page's RMS luminance, after
//! denoising when the bake denoised): the bias a biased technique's control texels
//! measure is one figure for the whole bake (`relative_error` at the top), too few
//! control texels fall on each page to split it.
//!
//! Limits: pages share the bake's width and are square (`atlas::unwrap` says why), so the
//! last page of generated charts may be partly empty.

use serde::Serialize;

use crate::engine::accumulate::{Estimate, LUMINANCE};
use crate::engine::atlas::{Atlas, PageRows};
use crate::engine::scene::Scene;

/// The manifest's file name, beside the pages.
pub const MANIFEST_FILE: &str = "lightmaps.json";

/// The manifest's format tag (`format` field); a reader checks it before reading on.
pub const MANIFEST_FORMAT: &str = "lightmapd.lightmaps/1";

pub use crate::engine::scene::export::page_file;

/// The page a file name names (`lightmap-P.exr`), if it is one.
pub fn parse_page_file(name: &str) -> Option<u32> {
    let digits = name.strip_prefix("lightmap-")?.strip_suffix(".exr")?;
    if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) || (digits.len() > 1 && digits.starts_with('0'))
    {
        return None;
    }
    digits.parse().ok()
}

/// One page as the manifest and the job's summary list it.
#[derive(Clone, Debug, Serialize, PartialEq, utoipa::ToSchema)]
pub struct PageEntry {
    pub page: u32,
    /// `lightmap-P.exr`.
    pub file: String,
    pub width: u32,
    pub height: u32,
    /// The page's first row in the bake's grid (where it sits in `lightmap.rgba16f`).
    pub first_row: u32,
    pub valid_texels: usize,
    /// Fraction of the page's texels that are valid.
    pub utilisation: f32,
    /// The noise part of the error on this page (module doc); null before both halves
    /// have a step.
    pub relative_noise: Option<f32>,
}

/// One node's lightmap in the manifest: the same as its `extras.lightmap`.
#[derive(Clone, Debug, Serialize, PartialEq, utoipa::ToSchema)]
pub struct NodeEntry {
    /// glTF node index.
    pub node: usize,
    /// The node's `name`, when it has one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    pub mesh: usize,
    pub page: u32,
    /// Page UV = TEXCOORD_1 · (sx, sy) + (ox, oy).
    pub scale_offset: [f32; 4],
    pub file: String,
}

/// `lightmaps.json`.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct Manifest {
    pub format: &'static str,
    pub technique: String,
    pub steps: u64,
    pub seconds: f64,
    /// The bake's reported error (bias included for biased techniques).
    pub relative_error: Option<f32>,
    pub denoiser: String,
    pub quantity: &'static str,
    pub pages: Vec<PageEntry>,
    /// Every node that places a mesh and did not opt out, in the default scene's order.
    pub nodes: Vec<NodeEntry>,
}

/// A page's encoded EXR with its entry.
#[derive(Clone, Debug)]
pub struct PageFile {
    pub entry: PageEntry,
    pub exr: Vec<u8>,
}

/// The manifest's and the summary's page list for `estimate` on `atlas`.
pub fn page_entries(atlas: &Atlas, estimate: &Estimate) -> Vec<PageEntry> {
    let row_page = atlas.row_pages();
    let n = atlas.pages.len();
    let (mut count, mut lum2, mut err2) = (vec![0usize; n], vec![0f64; n], vec![0f64; n]);
    for (k, t) in atlas.texels.iter().enumerate() {
        let p = row_page[(t.pixel / atlas.width) as usize] as usize;
        count[p] += 1;
        lum2[p] += (estimate.total[k].dot(LUMINANCE) as f64).powi(2);
        if let Some(e) = &estimate.texel_error {
            err2[p] += (e[k] as f64).powi(2);
        }
    }
    atlas
        .pages
        .iter()
        .enumerate()
        .map(|(p, band)| PageEntry {
            page: p as u32,
            file: page_file(p as u32),
            width: atlas.width,
            height: band.rows,
            first_row: band.first_row,
            valid_texels: count[p],
            utilisation: count[p] as f32 / (atlas.width as f32 * band.rows.max(1) as f32),
            relative_noise: estimate.texel_error.as_ref().map(|_| {
                if lum2[p] > 0.0 {
                    (err2[p] / lum2[p]).sqrt() as f32
                } else {
                    0.0
                }
            }),
        })
        .collect()
}

/// The rows of `band` out of each full-grid channel.
pub fn crop_channels(channels: &[(String, Vec<f32>)], width: u32, band: PageRows) -> Vec<(String, Vec<f32>)> {
    let (start, end) = (
        (band.first_row * width) as usize,
        ((band.first_row + band.rows) * width) as usize,
    );
    channels
        .iter()
        .map(|(name, data)| (name.clone(), data[start..end].to_vec()))
        .collect()
}

/// The manifest's node list: [`Scene::placements`] with names and files.
pub fn node_entries(scene: &Scene) -> Vec<NodeEntry> {
    let names = scene
        .source
        .as_ref()
        .and_then(|s| s.json.get("nodes"))
        .and_then(|n| n.as_array());
    scene
        .placements()
        .into_iter()
        .map(|p| NodeEntry {
            node: p.node,
            name: names
                .and_then(|n| n.get(p.node))
                .and_then(|n| n.get("name"))
                .and_then(|n| n.as_str())
                .map(str::to_owned),
            mesh: p.mesh,
            page: p.page,
            scale_offset: p.scale_offset,
            file: page_file(p.page),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn page_file_names_round_trip_and_reject_look_alikes() {
        for p in [0u32, 1, 9, 10, 4095] {
            assert_eq!(parse_page_file(&page_file(p)), Some(p));
        }
        for bad in [
            "lightmap.exr",
            "lightmap-.exr",
            "lightmap-01.exr",
            "lightmap-1.EXR",
            "lightmap--1.exr",
            "lightmap-1.exr.bak",
            "lightmap-99999999999.exr",
            "xlightmap-1.exr",
        ] {
            assert_eq!(parse_page_file(bad), None, "{bad}");
        }
    }

    #[test]
    fn a_band_is_cut_out_row_for_row() {
        let width = 3u32;
        let data: Vec<f32> = (0..12).map(|x| x as f32).collect();
        let out = crop_channels(&[("R".into(), data)], width, PageRows { first_row: 1, rows: 2 });
        assert_eq!(out[0].1, vec![3.0, 4.0, 5.0, 6.0, 7.0, 8.0]);
    }
}
