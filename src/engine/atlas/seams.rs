//! Seam search, part of building the texel set: triangle edges whose two world-space
//! endpoints are shared by another triangle's edge with different lightmap UVs, sampled
//! two per texel of edge length as pairs of UVs that show the same surface point.
//! `post::seams` stitches the lightmap along them after baking. Only smooth seams are
//! kept: where the shading normals on the two sides differ (a box's 90° edges) the
//! irradiance is discontinuous in reality.
//!
//! Limits: seam vertices are matched on a grid of 1e-6 of the scene's size, so two
//! positions a rounding error apart that straddle a grid line are not matched.

use std::collections::HashMap;

use glam::{Vec2, Vec3};

use crate::engine::scene::Scene;

/// Shading normals on the two sides must agree this well for an edge to be a seam to
/// stitch (cos 8°); across a hard edge the irradiance is discontinuous and must stay so.
const SMOOTH: f32 = 0.99;

/// One seam sample: the same surface point at two lightmap UVs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SeamSample {
    pub a: Vec2,
    pub b: Vec2,
}

/// A world-space edge: its endpoints' grid keys, smaller first.
type EdgeKey = ([i64; 3], [i64; 3]);
/// One triangle's view of an edge: lightmap UVs and shading normals of its endpoints.
type EdgeSide = (Vec2, Vec2, Vec3, Vec3);

/// Positions are matched on a grid of 1e-6 × the scene's diagonal: exports often compute
/// a shared corner separately for each face, a few ulps apart.
fn key(p: Vec3, cell: f32) -> [i64; 3] {
    p.to_array().map(|c| (c / cell).round() as i64)
}

/// Seam samples of `scene` for a `width` × `height` lightmap.
pub fn find_seams(scene: &Scene, width: u32, height: u32) -> Vec<SeamSample> {
    // Undirected world-space edge -> (lightmap UVs of its endpoints, in key order).
    // Per edge: lightmap UVs and shading normals of its endpoints, in key order.
    let mut edges: HashMap<EdgeKey, Vec<EdgeSide>> = HashMap::new();
    let cell = 1e-6 * scene.scale();
    for t in &scene.triangles {
        for k in 0..3 {
            let (i, j) = (k, (k + 1) % 3);
            let (ki, kj) = (key(t.p[i], cell), key(t.p[j], cell));
            let (i, j) = if ki <= kj { (i, j) } else { (j, i) };
            let (k0, k1) = (ki.min(kj), ki.max(kj));
            if k0 != k1 {
                edges
                    .entry((k0, k1))
                    .or_default()
                    .push((t.lm[i], t.lm[j], t.n[i], t.n[j]));
            }
        }
    }
    // In key order: a `HashMap`'s order changes from one process to the next, and the
    // samples' order is the order of the stitching's sums, so a bake would not be
    // reproducible from its seed (the living room's lightmap differed between two runs by
    // up to 7e-6 at 887 seam texels).
    let mut edges: Vec<(EdgeKey, Vec<EdgeSide>)> = edges.into_iter().collect();
    edges.sort_unstable_by_key(|e| e.0);
    let size = Vec2::new(width as f32, height as f32);
    let mut samples = Vec::new();
    for (_, uvs) in &edges {
        if uvs.len() != 2 {
            continue; // boundary edge, or non-manifold: nothing to pair
        }
        let ((a0, a1, na0, na1), (b0, b1, nb0, nb1)) = (uvs[0], uvs[1]);
        if na0.dot(nb0) < SMOOTH || na1.dot(nb1) < SMOOTH {
            continue; // a hard edge: the light really differs on its two sides
        }
        let same = (a0 - b0).abs().max_element() < 1e-6 && (a1 - b1).abs().max_element() < 1e-6;
        if same {
            continue; // an interior edge of one chart
        }
        let texels = ((a1 - a0) * size).length().max(((b1 - b0) * size).length());
        let n = (2.0 * texels).ceil().max(1.0) as usize;
        for s in 0..n {
            let t = (s as f32 + 0.5) / n as f32;
            samples.push(SeamSample {
                a: a0.lerp(a1, t),
                b: b0.lerp(b1, t),
            });
        }
    }
    samples
}
