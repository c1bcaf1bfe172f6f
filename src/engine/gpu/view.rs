//! Orthographic views of the whole scene along one global direction, over the lightmap's
//! texel map: the layout every map-based GPU pass shares (`View` in `shaders/gpu/common.wgsl`,
//! [`GpuView`] here), the per-triangle flags, the texel fill map that lets bilinear lookups
//! at chart borders find a valid texel, and the closed-surface test that decides which back
//! faces may be culled (stochastic-depth-buffering seed, section 6).
//!
//! Used by `sdb` (illumination and shadow maps) and `obscurance` (depth layers, shadow
//! maps). Precision: f32 in the normalised scene frame ([`crate::engine::gpu::frame`]), so
//! the map's pixel size is relative to the scene and scale-invariant.
//!
//! Map size ([`auto_map_size`]): a map's pixel is the scene's span over its size, so a
//! fixed size that is fine for a room is coarse for a level: at 512 pixels the Kenney
//! level's 91 m diagonal makes 18 cm pixels against its 10 cm lightmap texels, and a
//! technique that reads a neighbourhood of map pixels sees geometry that far to the
//! side of a texel's ray (docs/sdb.md, "The map's size on a level"). The automatic size
//! gives a pixel of at most half the lightmap's median texel, between 512 and 4096;
//! `sdb` and `obscurance` take it when a job leaves `map_size` unset, `vpl` for its
//! distant lights' shadow maps when `shadow_map_size` is unset.

use bytemuck::{Pod, Zeroable};
use glam::Vec3;

use crate::engine::gpu::map_scene::{MapTexel, MapTriangle};

/// The smallest map [`auto_map_size`] chooses: the size every map-based technique had
/// before it, enough for a room (the seed's 512).
pub const AUTO_MAP_SIZE_MIN: u32 = 512;
/// The largest map [`auto_map_size`] chooses: 4096² RGBA32F is 256 MiB a layer, which
/// every GPU this service targets holds beside the scene; a larger map must be asked for.
pub const AUTO_MAP_SIZE_MAX: u32 = 4096;
/// Map pixels across one lightmap texel that [`auto_map_size`] aims for: two, so a
/// 5 x 5 neighbourhood reaches about a texel to the side of the texel's ray.
pub const AUTO_MAP_PIXELS_PER_TEXEL: f32 = 2.0;

/// The map size for a scene of diagonal `diagonal` whose lightmap texels have the sides
/// `texel_sizes` (metres): the pixel at most half the median texel side over the
/// diagonal, rounded up to a multiple of 256 and held within [`AUTO_MAP_SIZE_MIN`] ..=
/// [`AUTO_MAP_SIZE_MAX`] and the device's `max_dimension` ([`map_size_for`]). The median,
/// so that a few dense meshes (a `lightmap_scale` of 4 on a prop) do not set a whole
/// level's cost. A caller passes the whole grid's texels and the triangles' bounds, so
/// that a task baking one region of the grid (`engine::tasks`) chooses the single bake's
/// size.
pub fn auto_map_size(diagonal: f32, texel_sizes: impl IntoIterator<Item = f32>, max_dimension: u32) -> u32 {
    let mut sizes: Vec<f32> = texel_sizes.into_iter().filter(|s| s.is_finite() && *s > 0.0).collect();
    let median = if sizes.is_empty() {
        0.0
    } else {
        let mid = sizes.len() / 2;
        *sizes.select_nth_unstable_by(mid, f32::total_cmp).1
    };
    map_size_for(diagonal, median, max_dimension)
}

/// An automatic size `n` lowered until `fits` holds: `n`, else the first of n - 256,
/// n - 512, ... that fits, never below [`AUTO_MAP_SIZE_MIN`] (which is taken when
/// nothing above it fits: an explicit size is the job's to lower further). For what else
/// bounds a map besides the texture limit: `obscurance`'s fragment pool, `vpl`'s atlas.
pub fn largest_fitting(n: u32, fits: impl Fn(u32) -> bool) -> u32 {
    let mut n = n;
    while n > AUTO_MAP_SIZE_MIN && !fits(n) {
        n = n.saturating_sub(256).max(AUTO_MAP_SIZE_MIN);
    }
    n
}

/// [`auto_map_size`]'s rule for a scene diagonal and a texel side (both in metres).
pub fn map_size_for(diagonal: f32, texel: f32, max_dimension: u32) -> u32 {
    let cap = AUTO_MAP_SIZE_MAX.min(max_dimension);
    let wanted = AUTO_MAP_PIXELS_PER_TEXEL * diagonal / texel;
    let n = if wanted.is_finite() && wanted > 0.0 {
        // Below 2^31 after the cap; the float-to-int cast saturates anyway.
        (wanted.ceil().min(cap as f32) as u32).next_multiple_of(256)
    } else {
        0
    };
    n.max(AUTO_MAP_SIZE_MIN).min(cap)
}

/// One corner of a triangle as the map passes rasterise it: normalised position, lightmap
/// UV, the triangle's index (for per-triangle data), and the alpha test's inputs (the UV
/// the material's base colour texture reads, the material). [`GpuVertex::ATTRIBUTES`].
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct GpuVertex {
    pub position: [f32; 3],
    pub lightmap_uv: [f32; 2],
    pub triangle: u32,
    pub alpha_uv: [f32; 2],
    pub material: u32,
}

impl GpuVertex {
    /// The vertex layout's attributes, locations 0-4 in field order.
    pub const ATTRIBUTES: [wgpu::VertexAttribute; 5] =
        wgpu::vertex_attr_array![0 => Float32x3, 1 => Float32x2, 2 => Uint32, 3 => Float32x2, 4 => Uint32];

    /// The three corners of triangle `index`, positions mapped by `norm`.
    pub fn corners(index: u32, t: &MapTriangle, norm: impl Fn(Vec3) -> Vec3) -> [GpuVertex; 3] {
        [0, 1, 2].map(|k| GpuVertex {
            position: norm(t.p[k]).to_array(),
            lightmap_uv: t.lm[k].to_array(),
            triangle: index,
            alpha_uv: t.alpha_uv[k].to_array(),
            material: t.material,
        })
    }
}

/// A lightmap's size and counts as one uniform (`dims.x` width, `dims.y` height, the rest
/// pass-specific).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct GpuDims {
    pub dims: [u32; 4],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct GpuView {
    pub right: [f32; 4],
    pub up: [f32; 4],
    pub dir: [f32; 4],
    pub extent: [f32; 4],
    pub params: [u32; 4],
}

pub const DEPTH_STOCHASTIC: u32 = 0;
pub const DEPTH_NEAREST: u32 = 1;
pub const TRI_DOUBLE_SIDED: u32 = 1;
pub const TRI_CULL_BACK: u32 = 2;
pub const TRI_TEXTURED_EMISSION: u32 = 4;
pub const NO_TEXEL: u32 = u32::MAX;
pub const EMPTY_T: f32 = 1.0e30;

/// Which triangles may have their back faces culled (seed section 6): single-sided
/// triangles in a closed surface. Vertices are welded by exact position across the whole
/// scene (a room built from separate wall meshes counts), triangles sharing an edge are
/// joined into components, and a component is closed when every directed edge (a, b) of
/// it is matched by exactly one (b, a) and used once. Only then is a back face never the
/// first surface a point outside the surface sees, so culling it removes overdraw and
/// nothing else. Double-sided triangles take no part (they are never culled).
pub fn cullable_triangles(triangles: &[MapTriangle]) -> Vec<bool> {
    use std::collections::HashMap;
    // Weld on a grid of 1e-6 of the scene size: exact bits would split corners that two
    // meshes computed with different rounding.
    let extent = triangles
        .iter()
        .flat_map(|t| t.p)
        .fold(0.0f32, |m, p| m.max(p.abs().max_element()))
        .max(f32::MIN_POSITIVE);
    let cell = extent * 1e-6;
    let key = |v: Vec3| {
        let q = (v / cell).round();
        (q.x as i64, q.y as i64, q.z as i64)
    };
    let mut ids: HashMap<(i64, i64, i64), u32> = HashMap::new();
    let mut tri_vertices: Vec<Option<[u32; 3]>> = Vec::with_capacity(triangles.len());
    for t in triangles {
        if t.double_sided {
            tri_vertices.push(None);
            continue;
        }
        let mut v = [0u32; 3];
        for (k, p) in t.p.iter().enumerate() {
            let next = ids.len() as u32;
            v[k] = *ids.entry(key(*p)).or_insert(next);
        }
        // Degenerate triangles have no area and no edges that matter.
        tri_vertices.push((v[0] != v[1] && v[1] != v[2] && v[0] != v[2]).then_some(v));
    }
    // Directed edge -> (use count, first triangle using it).
    let mut edges: HashMap<(u32, u32), (u32, usize)> = HashMap::new();
    for (i, v) in tri_vertices.iter().enumerate() {
        if let Some(v) = v {
            for k in 0..3 {
                let e = edges.entry((v[k], v[(k + 1) % 3])).or_insert((0, i));
                e.0 += 1;
            }
        }
    }
    // Union-find over triangles joined by an edge pair.
    let mut parent: Vec<usize> = (0..triangles.len()).collect();
    fn find(parent: &mut [usize], mut i: usize) -> usize {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    }
    for (&(a, b), &(_, t)) in &edges {
        if let Some(&(_, u)) = edges.get(&(b, a)) {
            let (ra, rb) = (find(&mut parent, t), find(&mut parent, u));
            if ra != rb {
                parent[ra] = rb;
            }
        }
    }
    let mut open = vec![false; triangles.len()];
    for (&(a, b), &(count, t)) in &edges {
        let matched = edges.get(&(b, a)).is_some_and(|&(c, _)| c == 1);
        if count != 1 || !matched {
            let r = find(&mut parent, t);
            open[r] = true;
        }
    }
    (0..triangles.len())
        .map(|i| tri_vertices[i].is_some() && !open[find(&mut parent, i)])
        .collect()
}

/// For every lightmap pixel, the valid texel whose values it shows: itself, else the
/// nearest valid texel within 2 pixels (so bilinear lookups at chart borders fetch
/// plausible values, not black), else [`NO_TEXEL`].
pub fn fill_map(width: u32, height: u32, texels: &[MapTexel]) -> Vec<u32> {
    let (w, h) = (width as i64, height as i64);
    let mut fill = vec![NO_TEXEL; (w * h) as usize];
    for (i, t) in texels.iter().enumerate() {
        fill[t.pixel as usize] = i as u32;
    }
    let direct = fill.clone();
    // Offsets by increasing distance, radius 2.
    let mut offsets: Vec<(i64, i64)> = (-2..=2)
        .flat_map(|dy| (-2..=2).map(move |dx| (dx, dy)))
        .filter(|&(dx, dy)| (dx, dy) != (0, 0))
        .collect();
    offsets.sort_by_key(|&(dx, dy)| dx * dx + dy * dy);
    for y in 0..h {
        for x in 0..w {
            let idx = (y * w + x) as usize;
            if direct[idx] != NO_TEXEL {
                continue;
            }
            for &(dx, dy) in &offsets {
                let (sx, sy) = (x + dx, y + dy);
                if sx >= 0 && sy >= 0 && sx < w && sy < h {
                    let s = direct[(sy * w + sx) as usize];
                    if s != NO_TEXEL {
                        fill[idx] = s;
                        break;
                    }
                }
            }
        }
    }
    fill
}

/// Orthographic frame for direction `d` over the normalised bounds `corners`, with the
/// map origin shifted by `jitter` (in pixels, [0, 1)^2).
pub fn make_view(d: Vec3, corners: &[Vec3; 8], map_size: u32, jitter: (f32, f32), seed: u32, mode: u32) -> GpuView {
    // Right-handed camera looking along +d (as a look-at camera would): screen x = right,
    // screen y = up, so counter-clockwise front faces stay counter-clockwise on screen.
    let helper = if d.y.abs() < 0.9 { Vec3::Y } else { Vec3::X };
    let right = d.cross(helper).normalize();
    let up = right.cross(d).normalize();
    let (mut amin, mut amax, mut bmin, mut bmax, mut tmin, mut tmax) =
        (f32::MAX, f32::MIN, f32::MAX, f32::MIN, f32::MAX, f32::MIN);
    for c in corners {
        let (a, b, t) = (c.dot(right), c.dot(up), c.dot(d));
        amin = amin.min(a);
        amax = amax.max(a);
        bmin = bmin.min(b);
        bmax = bmax.max(b);
        tmin = tmin.min(t);
        tmax = tmax.max(t);
    }
    // Square pixels; one spare pixel so the jittered map still covers the bounds.
    let n = map_size as f32;
    let span = (amax - amin).max(bmax - bmin).max(1e-6) * 1.0001;
    let pixel = span / (n - 1.0);
    let s = pixel * n;
    let a0 = amin - jitter.0 * pixel;
    let b0 = bmin - jitter.1 * pixel;
    // Depth range with a margin so nothing is clipped by the near/far planes.
    let margin = 0.01 * (tmax - tmin).max(1e-3);
    let t0 = tmin - margin;
    let range = (tmax - tmin) + 2.0 * margin;
    GpuView {
        right: [right.x, right.y, right.z, a0],
        up: [up.x, up.y, up.z, b0],
        dir: [d.x, d.y, d.z, t0],
        extent: [s, range, n, 0.0],
        params: [seed, mode, 0, 0],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A room keeps the seed's 512; the Kenney level (91 m diagonal, 10.2 cm texels)
    /// gets pixels of half a texel; a larger level stops at the cap, a smaller device at
    /// its own limit; a grid without texels keeps the smallest size.
    #[test]
    fn the_automatic_map_size_follows_the_texel() {
        assert_eq!(map_size_for(1.0, 0.02, 16384), AUTO_MAP_SIZE_MIN);
        let n = map_size_for(91.0, 0.102, 16384);
        assert_eq!(n, 1792);
        assert!(91.0 / n as f32 <= 0.102 / AUTO_MAP_PIXELS_PER_TEXEL);
        assert_eq!(map_size_for(400.0, 0.05, 16384), AUTO_MAP_SIZE_MAX);
        assert_eq!(map_size_for(400.0, 0.05, 2048), 2048);
        assert_eq!(map_size_for(91.0, 0.0, 16384), AUTO_MAP_SIZE_MIN);
        assert_eq!(map_size_for(f32::NAN, 0.1, 16384), AUTO_MAP_SIZE_MIN);
        // The median texel: a few dense ones (and degenerate ones) do not move it.
        let sizes = [0.102f32, 0.102, 0.102, 0.01, 0.0, f32::NAN, 0.2];
        assert_eq!(auto_map_size(91.0, sizes, 16384), 1792);
        assert_eq!(auto_map_size(91.0, [], 16384), AUTO_MAP_SIZE_MIN);
    }

    /// Lowered by 256 until it fits, never below the smallest automatic size, from a
    /// size that is not a multiple of 256 (a device's odd limit) too.
    #[test]
    fn an_automatic_size_is_lowered_until_it_fits() {
        assert_eq!(largest_fitting(1792, |_| true), 1792);
        assert_eq!(largest_fitting(1792, |n| n <= 1000), 768);
        assert_eq!(largest_fitting(1792, |_| false), AUTO_MAP_SIZE_MIN);
        assert_eq!(largest_fitting(600, |_| false), AUTO_MAP_SIZE_MIN);
        assert_eq!(largest_fitting(512, |_| false), 512);
    }
}
