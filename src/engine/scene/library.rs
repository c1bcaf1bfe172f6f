//! The benchmark and test scenes, made in code, with their closed-form answers where one
//! exists (issue 5's list). Tests and `lightmapd bench` use the same scenes and the same
//! answers, so a figure in `docs/accuracy.md` and an assertion in CI mean the same thing.
//!
//! Analytic answers are functions of a texel's world-space sample point and normal; a
//! scene whose answer covers only some texels (the plane under the sphere, not the
//! sphere) says so by returning `None` for the others.

use std::f64::consts::PI;

use glam::{DVec3, Vec3};

use super::build::{MaterialDesc, SceneBuilder, cornell_box};
use super::{Hemisphere, Lighting, Sky, Sun};

/// Form factor from a differential area to a parallel rectangle [0, a] × [0, b] at
/// height c with one corner straight above it (Howell's catalogue of configuration
/// factors, case B-3).
pub fn corner_form_factor(a: f64, b: f64, c: f64) -> f64 {
    let (x, y) = (a / c, b / c);
    let (sx, sy) = ((1.0 + x * x).sqrt(), (1.0 + y * y).sqrt());
    (x / sx * (y / sx).atan() + y / sy * (x / sy).atan()) / (2.0 * PI)
}

/// Form factor from a point to the parallel rectangle [x0, x1] × [z0, z1] a height `c`
/// above it, the point at (px, pz): superposition of four corner rectangles with signs.
pub fn rect_form_factor(px: f64, pz: f64, x0: f64, x1: f64, z0: f64, z1: f64, c: f64) -> f64 {
    let s = |a: f64, b: f64| a.signum() * b.signum() * corner_form_factor(a.abs(), b.abs(), c);
    s(x1 - px, z1 - pz) - s(x0 - px, z1 - pz) - s(x1 - px, z0 - pz) + s(x0 - px, z0 - pz)
}

/// Irradiance / π on an upward plane under a uniform upper-hemisphere sky `l`, with a
/// black sphere of radius `r` centred `h` above a point at horizontal distance `s`: the
/// sphere, fully above the horizon when h > r, hides the projected solid angle
/// π sin²α cos θ (sin α = r/d, cos θ = h/d, d² = s² + h²).
pub fn sphere_occlusion(l: f64, r: f64, h: f64, s: f64) -> f64 {
    let d2 = s * s + h * h;
    l * (1.0 - r * r / d2 * (h / d2.sqrt()))
}

/// The answer at a texel: world-space sample point and geometric normal in, irradiance / π
/// out, `None` where the scene has no closed form.
pub type Analytic = fn(p: DVec3, n: Vec3) -> Option<Vec3>;

/// A scene with the lighting and resolution it is baked at.
pub struct LibraryScene {
    pub name: &'static str,
    pub description: &'static str,
    /// The scene as a .glb (made in code, or a bundled file).
    pub glb: fn() -> Vec<u8>,
    pub lighting: Lighting,
    /// The page width; meshes without `TEXCOORD_1` get UVs generated for it.
    pub resolution: u32,
    /// Lightmap UV density for meshes without `TEXCOORD_1`, texels a metre (`None`: the
    /// highest at which every chart fits one page, a bake's default).
    pub texels_per_metre: Option<f32>,
    pub analytic: Option<Analytic>,
}

/// A uniform sky of radiance `l` over the upper hemisphere, no sun: the lighting of most
/// closed-form scenes (and of tests).
pub fn upper_sky(l: f32) -> Lighting {
    Lighting {
        sky: Some(Sky {
            radiance: Vec3::splat(l),
            hemisphere: Hemisphere::Upper,
        }),
        sun: None,
    }
}

/// Closed cube of side 2 with inward faces, albedo ρ, emitting Le = 1 − ρ: answer 1.
pub fn closed_box(rho: f32) -> SceneBuilder {
    let mut b = SceneBuilder::new();
    let m = b.material(MaterialDesc::emissive("wall", [rho; 3], [1.0 - rho; 3]));
    for n in [Vec3::X, Vec3::NEG_X, Vec3::Y, Vec3::NEG_Y, Vec3::Z, Vec3::NEG_Z] {
        b.square(&format!("face {n}"), -n, 2.0, n, m);
    }
    b
}

/// A 10 m grey plane at y = 0 facing up.
pub fn sky_plane() -> SceneBuilder {
    let mut b = SceneBuilder::new();
    let m = b.material(MaterialDesc::diffuse("grey", [0.5; 3]));
    b.square("ground", Vec3::ZERO, 10.0, Vec3::Y, m);
    b
}

/// A black 6 m plane and a black sphere of radius 1 centred 2 m above it.
pub fn sphere_over_plane() -> SceneBuilder {
    let mut b = SceneBuilder::new();
    let black = b.material(MaterialDesc::diffuse("black", [0.0; 3]));
    b.square("ground", Vec3::ZERO, 6.0, Vec3::Y, black);
    b.sphere("ball", Vec3::new(0.0, 2.0, 0.0), 1.0, 96, 48, black);
    b
}

/// Two coaxial black unit squares 1 m apart, the upper one emitting 1 downward.
pub fn parallel_plates() -> SceneBuilder {
    let mut b = SceneBuilder::new();
    let black = b.material(MaterialDesc::diffuse("black", [0.0; 3]));
    let lamp = b.material(MaterialDesc::emissive("lamp", [0.0; 3], [1.0; 3]));
    b.square("receiver", Vec3::ZERO, 1.0, Vec3::Y, black);
    b.square("emitter", Vec3::new(0.0, 1.0, 0.0), 1.0, Vec3::NEG_Y, lamp);
    b
}

/// A box standing on the ground at `base` (the centre of its bottom), of half extents
/// `half`, open below: five faces of `cells` × `cells` quads facing out, named
/// "`name` face 0" (top) to "`name` face 4".
fn open_box(b: &mut SceneBuilder, name: &str, base: Vec3, half: Vec3, cells: u32, material: usize) {
    let c = base + Vec3::Y * half.y;
    let faces = [
        (Vec3::Y, half.y, Vec3::X * half.x, Vec3::NEG_Z * half.z),
        (Vec3::Z, half.z, Vec3::X * half.x, Vec3::Y * half.y),
        (Vec3::NEG_Z, half.z, Vec3::NEG_X * half.x, Vec3::Y * half.y),
        (Vec3::NEG_X, half.x, Vec3::Z * half.z, Vec3::Y * half.y),
        (Vec3::X, half.x, Vec3::NEG_Z * half.z, Vec3::Y * half.y),
    ];
    for (f, (n, d, u, v)) in faces.into_iter().enumerate() {
        let centre = c + n * d;
        b.quad_grid(
            &format!("{name} face {f}"),
            centre - u - v,
            2.0 * u,
            2.0 * v,
            cells,
            material,
        );
    }
}

/// About 25 000 triangles: 40 boxes of subdivided faces (8 × 8 cells a face, 640
/// triangles a box) on a ground plane, under the sky.
pub fn procedural_blocks() -> SceneBuilder {
    let mut b = SceneBuilder::new();
    let ground = b.material(MaterialDesc::diffuse("ground", [0.6, 0.55, 0.5]));
    let colours = [[0.8, 0.3, 0.2], [0.3, 0.6, 0.3], [0.7, 0.7, 0.7], [0.2, 0.3, 0.7]];
    let mats: Vec<usize> = colours
        .iter()
        .enumerate()
        .map(|(i, c)| b.material(MaterialDesc::diffuse(&format!("block {i}"), *c)))
        .collect();
    b.quad_grid(
        "ground",
        Vec3::new(-10.0, 0.0, 10.0),
        Vec3::X * 20.0,
        Vec3::NEG_Z * 20.0,
        8,
        ground,
    );
    let mut state = 12345u32;
    let mut rnd = || {
        // A fixed LCG: the scene must be the same on every machine and version.
        state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
        (state >> 8) as f32 / 16_777_216.0
    };
    for k in 0..40 {
        let (i, j) = ((k % 8) as f32, (k / 8) as f32);
        let centre = Vec3::new(-8.0 + i * 2.3 + rnd() * 0.4, 0.0, -6.0 + j * 3.0 + rnd() * 0.4);
        let half = Vec3::new(0.4 + rnd() * 0.4, 0.3 + rnd() * 1.2, 0.4 + rnd() * 0.4);
        let m = mats[k % mats.len()];
        open_box(&mut b, &format!("block {k}"), centre, half, 8, m);
    }
    b
}

/// A generated level of real size (issue 19 point 8, issue 20 point 4): a ground of
/// 100 m square (8 × 8 cells) and `boxes` boxes in a square grid over it, each with five
/// faces of `cells` × `cells` quads (10 · cells² triangles a box; 400 boxes of 8 × 8 are
/// 256,128 triangles), as a .glb whose meshes have no `TEXCOORD_1`, so a bake generates
/// its lightmap UVs at the density it asks for.
pub fn generated_level(boxes: u32, cells: u32) -> Vec<u8> {
    let mut b = SceneBuilder::new();
    let ground = b.material(MaterialDesc::diffuse("ground", [0.6, 0.55, 0.5]));
    let block = b.material(MaterialDesc::diffuse("block", [0.7, 0.7, 0.7]));
    b.quad_grid(
        "ground",
        Vec3::new(-50.0, 0.0, 50.0),
        Vec3::X * 100.0,
        Vec3::NEG_Z * 100.0,
        8,
        ground,
    );
    let side = (boxes as f32).sqrt().ceil() as u32;
    let pitch = 96.0 / side.max(1) as f32;
    for k in 0..boxes {
        let (i, j) = ((k % side) as f32, (k / side) as f32);
        let centre = Vec3::new(-48.0 + (i + 0.5) * pitch, 0.0, -48.0 + (j + 0.5) * pitch);
        let half = Vec3::new(0.3 * pitch, 0.25 * pitch + 0.1 * (k % 7) as f32, 0.3 * pitch);
        open_box(&mut b, &format!("box {k}"), centre, half, cells, block);
    }
    let (mut json, bin) = b.to_gltf();
    // The builder always writes TEXCOORD_1; a level as studios hand it over has none.
    for m in json["meshes"].as_array_mut().into_iter().flatten() {
        for p in m["primitives"].as_array_mut().into_iter().flatten() {
            if let Some(a) = p["attributes"].as_object_mut() {
                a.remove("TEXCOORD_1");
            }
        }
    }
    super::build::write_glb(&json, &bin)
}

/// Every benchmark scene of issue 5, in a fixed order.
pub fn benchmark_scenes() -> Vec<LibraryScene> {
    vec![
        LibraryScene {
            name: "closed-box-0.5",
            description: "closed cube, albedo 0.5, Le 0.5 everywhere: lightmap 1",
            glb: || closed_box(0.5).to_glb(),
            texels_per_metre: None,
            lighting: Lighting::default(),
            resolution: 48,
            analytic: Some(|_, _| Some(Vec3::ONE)),
        },
        LibraryScene {
            name: "closed-box-0.9",
            description: "closed cube, albedo 0.9, Le 0.1 everywhere: lightmap 1",
            glb: || closed_box(0.9).to_glb(),
            texels_per_metre: None,
            lighting: Lighting::default(),
            resolution: 48,
            analytic: Some(|_, _| Some(Vec3::ONE)),
        },
        LibraryScene {
            name: "sky-plane",
            description: "upward plane under a uniform upper sky of 1: lightmap 1",
            glb: || sky_plane().to_glb(),
            texels_per_metre: None,
            lighting: upper_sky(1.0),
            resolution: 32,
            analytic: Some(|_, _| Some(Vec3::ONE)),
        },
        LibraryScene {
            name: "sphere-over-plane",
            description: "black sphere r = 1 centred 2 m over a black plane, sky 1: 1 - sin²α cos θ on the plane",
            glb: || sphere_over_plane().to_glb(),
            texels_per_metre: None,
            lighting: upper_sky(1.0),
            resolution: 98,
            analytic: Some(|p, n| {
                (n.y > 0.99 && p.y.abs() < 0.01)
                    .then(|| Vec3::splat(sphere_occlusion(1.0, 1.0, 2.0 - p.y, (p.x * p.x + p.z * p.z).sqrt()) as f32))
            }),
        },
        LibraryScene {
            name: "parallel-plates",
            description: "unit squares 1 m apart, upper emits 1, both black: the receiver reads the form factor",
            glb: || parallel_plates().to_glb(),
            texels_per_metre: None,
            lighting: Lighting::default(),
            resolution: 62,
            analytic: Some(|p, n| {
                if n.y > 0.99 {
                    Some(Vec3::splat(
                        rect_form_factor(p.x, p.z, -0.5, 0.5, -0.5, 0.5, 1.0 - p.y) as f32
                    ))
                } else {
                    Some(Vec3::ZERO)
                }
            }),
        },
        LibraryScene {
            name: "cornell-box",
            description: "the bundled Cornell box (reference: converged path bake)",
            glb: || cornell_box().to_glb(),
            texels_per_metre: None,
            lighting: Lighting::default(),
            resolution: 64,
            analytic: None,
        },
        LibraryScene {
            name: "blocks-25k",
            description: "40 subdivided boxes on a ground plane under the sky, 25 728 triangles (reference: converged path bake)",
            glb: || procedural_blocks().to_glb(),
            texels_per_metre: None,
            lighting: upper_sky(1.0),
            resolution: 128,
            analytic: None,
        },
    ]
}

/// Sky and sun for the outdoor scenes: sky (0.2, 0.3, 0.5) over the upper hemisphere and a
/// sun of 0.53° from above and aside, about 3 W/m² at normal incidence.
pub fn outdoor_lighting() -> Lighting {
    Lighting {
        sky: Some(Sky {
            radiance: Vec3::new(0.2, 0.3, 0.5),
            hemisphere: Hemisphere::Upper,
        }),
        sun: Some(Sun {
            direction: Vec3::new(-0.4, -1.0, -0.3).normalize(),
            angular_diameter: 0.53f32.to_radians(),
            radiance: Vec3::new(1.0, 0.95, 0.85) * 45_000.0,
        }),
    }
}

/// The scenes of real size (issue 20 point 4): the bundled third-party levels at their
/// default density (`scenes/third-party/SOURCES.md` has their licences; the files are
/// compiled in, so `lightmapd bench` needs no checkout) and the 256k-triangle generated
/// level on one 1024² page. No closed form: their references are long `path` bakes, minutes
/// on a CPU, which is why `lightmapd bench` runs them only when asked (`--scenes real` or by
/// name).
pub fn real_size_scenes() -> Vec<LibraryScene> {
    vec![
        LibraryScene {
            name: "occlusion-room",
            description: "third-party interior, 63,720 triangles, windows to a uniform sky of 1, 512² page",
            glb: || include_bytes!("../../../scenes/third-party/occlusion_room.glb").to_vec(),
            lighting: upper_sky(1.0),
            resolution: 512,
            texels_per_metre: None,
            analytic: None,
        },
        LibraryScene {
            name: "living-room",
            description: "third-party living room and courtyard under sky and sun, 512² page",
            glb: || include_bytes!("../../../scenes/third-party/living_room.glb").to_vec(),
            lighting: outdoor_lighting(),
            resolution: 512,
            texels_per_metre: None,
            analytic: None,
        },
        LibraryScene {
            name: "kenney-fps-level",
            description: "third-party game level under sky and sun, 512² page",
            glb: || include_bytes!("../../../scenes/third-party/kenney_fps_level.glb").to_vec(),
            lighting: outdoor_lighting(),
            resolution: 512,
            texels_per_metre: None,
            analytic: None,
        },
        LibraryScene {
            name: "level-256k",
            description: "generated level, 400 boxes on a 100 m ground, 256,128 triangles, UVs generated at 4.5 texels/m: one 1024² page",
            glb: || generated_level(400, 8),
            lighting: outdoor_lighting(),
            resolution: 1024,
            texels_per_metre: Some(4.5),
            analytic: None,
        },
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn form_factor_of_the_unit_square_at_unit_distance() {
        assert!((rect_form_factor(0.0, 0.0, -0.5, 0.5, -0.5, 0.5, 1.0) - 0.23946).abs() < 1e-5);
    }

    #[test]
    fn sphere_occlusion_below_the_centre() {
        assert!((sphere_occlusion(1.0, 1.0, 2.0, 0.0) - 0.75).abs() < 1e-12);
    }

    #[test]
    fn procedural_scene_has_about_25k_triangles() {
        let b = procedural_blocks();
        let tris: usize = b.meshes.iter().map(|m| m.indices.len() / 3).sum();
        assert_eq!(tris, 128 + 40 * 5 * 128);
    }
}
