//! Lightmap UV generation end to end (issue 13): a scene with no TEXCOORD_1 bakes, the
//! lightmap sampled at the generated UVs matches the closed-form answer at the same
//! surface points, and the written glTF carries those UVs.

use std::sync::Arc;

use exr::prelude::{ReadChannels, ReadLayers};
use glam::{Vec2, Vec3};
use lightmapd::engine::atlas::unwrap::LightmapUvs;
use lightmapd::engine::bake::StopCriteria;
use lightmapd::engine::job::{self, BakeRequest};
use lightmapd::engine::post::{dilate, seams};
use lightmapd::engine::rng::Rng;
use lightmapd::engine::scene::build::{remove_lightmap_uvs, write_glb};
use lightmapd::engine::scene::library::{sphere_occlusion, sphere_over_plane};
use lightmapd::engine::scene::{Hemisphere, Lighting, PageRows, Sky, export, import_slice};
use serde_json::json;

/// Sphere-over-plane's document with every mesh's TEXCOORD_1 removed, and its buffer.
fn without_lightmap_uvs_gltf() -> (serde_json::Value, Vec<u8>) {
    let (mut json, bin) = sphere_over_plane().to_gltf();
    remove_lightmap_uvs(&mut json, None);
    (json, bin)
}

fn without_lightmap_uvs() -> Vec<u8> {
    let (json, bin) = without_lightmap_uvs_gltf();
    write_glb(&json, &bin)
}

fn bilinear(img: &[Vec3], w: u32, h: u32, uv: Vec2) -> Vec3 {
    let x = (uv.x * w as f32 - 0.5).clamp(0.0, w as f32 - 1.0);
    let y = (uv.y * h as f32 - 0.5).clamp(0.0, h as f32 - 1.0);
    let (x0, y0) = (x.floor() as u32, y.floor() as u32);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let at = |x: u32, y: u32| img[(y * w + x) as usize];
    at(x0, y0)
        .lerp(at(x1, y0), fx)
        .lerp(at(x0, y1).lerp(at(x1, y1), fx), fy)
}

#[test]
fn generated_uvs_bake_and_match_the_closed_form() {
    let (scene, report) = import_slice(&without_lightmap_uvs(), None).unwrap();
    assert!(!report.has_lightmap_uvs);
    let request = BakeRequest {
        resolution: 128,
        lighting: Lighting {
            sky: Some(Sky {
                radiance: Vec3::ONE,
                hemisphere: Hemisphere::Upper,
            }),
            sun: None,
        },
        stop: StopCriteria {
            steps: Some(16),
            ..Default::default()
        },
        params: json!({"samples_per_step": 8}),
        ..Default::default()
    };
    let result = job::bake_unobserved(Arc::new(scene), &request).unwrap();
    let unwrap = result.summary.generated_uvs.clone().expect("UVs were generated");
    eprintln!("generated: {unwrap:?}, {} valid texels", result.atlas.texels.len());
    assert!(unwrap.charts >= 2 && unwrap.utilisation > 0.3, "{unwrap:?}");
    assert_eq!(result.atlas.overlapping_texels, 0, "generated charts must not overlap");

    let (mean, worst) = ground_error(&result);
    eprintln!("lookup at generated UVs vs closed form: mean relative error {mean:.4}, worst {worst:.4}");
    // 128 paths per texel leave about 3 % noise per texel before denoising (measured
    // after it: 0.4 % mean, 1.8 % worst); the lookup also interpolates across texels
    // 7 cm apart over a smooth shadow. Reading the wrong place (a UV convention error)
    // gives 30 % and more.
    assert!(mean < 0.01, "mean relative error {mean}");
    assert!(worst < 0.05, "worst relative error {worst}");

    // The written glTF carries the generated UVs and the world-space geometry.
    let glb = export::to_glb(&result.scene).unwrap();
    let (back, back_report) = import_slice(&glb, None).unwrap();
    assert!(back_report.has_lightmap_uvs);
    assert_eq!(back.triangles.len(), result.scene.triangles.len());
    for (a, b) in back.triangles.iter().zip(&result.scene.triangles) {
        for k in 0..3 {
            assert!((a.lm[k] - b.lm[k]).abs().max_element() < 1e-6);
            let (pa, pb) = (
                a.p[k].as_dvec3() + back.origin_offset,
                b.p[k].as_dvec3() + result.scene.origin_offset,
            );
            assert!((pa - pb).abs().max_element() < 1e-5, "{pa} vs {pb}");
        }
    }
}

/// `extras.lightmap_scale` on a mesh gives it that many times the texels per metre.
#[test]
fn lightmap_scale_from_extras() {
    use lightmapd::engine::atlas::unwrap::{UvUnwrap, generate_lightmap_uvs};
    use lightmapd::engine::scene::build::{MaterialDesc, SceneBuilder};
    let mut b = SceneBuilder::new();
    let m = b.material(MaterialDesc::diffuse("grey", [0.5; 3]));
    b.square("plain", Vec3::ZERO, 1.0, Vec3::Y, m);
    b.square("detailed", Vec3::new(3.0, 0.0, 0.0), 1.0, Vec3::Y, m);
    let (mut json, bin) = b.to_gltf();
    json["meshes"][1]["extras"] = json!({"lightmap_scale": 2.0});
    remove_lightmap_uvs(&mut json, None);
    let (mut scene, _) = import_slice(&write_glb(&json, &bin), None).unwrap();
    assert_eq!(scene.meshes[1].lightmap_scale, 2.0);
    generate_lightmap_uvs(&mut scene, 64, &UvUnwrap).unwrap();
    let uv_area = |mesh: u32| -> f32 {
        scene
            .triangles
            .iter()
            .filter(|t| t.mesh == mesh)
            .map(|t| 0.5 * (t.lm[1] - t.lm[0]).perp_dot(t.lm[2] - t.lm[0]).abs())
            .sum()
    };
    let ratio = uv_area(1) / uv_area(0);
    assert!((ratio - 4.0).abs() < 0.2, "UV area ratio {ratio}");

    // A bad value is warned about and ignored.
    json["meshes"][1]["extras"] = json!({"lightmap_scale": -1});
    let (scene, report) = import_slice(&write_glb(&json, &bin), None).unwrap();
    assert_eq!(scene.meshes[1].lightmap_scale, 1.0);
    assert!(
        report
            .warnings
            .iter()
            .any(|w| w.contains("extras.lightmap_scale -1 is not a number in (0, 1000]"))
    );
}

/// One channel of an EXR, in pixel order.
fn exr_channel(bytes: &[u8], name: &str) -> Vec<f32> {
    let image = exr::prelude::read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .all_layers()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(bytes.to_vec()))
        .unwrap();
    image.layer_data[0]
        .channel_data
        .list
        .iter()
        .find(|c| c.name.to_string() == name)
        .unwrap_or_else(|| panic!("no channel {name}"))
        .sample_data
        .values_as_f32()
        .collect()
}

/// Mean and worst relative error of bilinear lookups at the ground's lightmap UVs (what a
/// renderer does) against the closed form of the sphere's occlusion.
fn ground_error(result: &job::BakeResult) -> (f64, f64) {
    // What a renderer does: bilinear lookups at the surface's lightmap UV.
    let atlas = &result.atlas;
    let mut img = dilate(atlas, &result.estimate.total, 8);
    seams::stitch(&mut img, atlas.width, atlas.height, &atlas.pixel_texel, &atlas.seams);
    let scene = &result.scene;
    let offset = scene.origin_offset.as_vec3();
    let ground: Vec<_> = scene
        .triangles
        .iter()
        .filter(|t| t.geometric_normal().y > 0.99 && (t.p[0].y + offset.y).abs() < 1e-3)
        .collect();
    assert_eq!(ground.len(), 2);
    let mut rng = Rng::new(11, 0, 0, 0);
    let (mut sum, mut worst, n) = (0.0f64, 0.0f64, 2000);
    for _ in 0..n {
        let t = ground[(rng.next_u32() as usize) % ground.len()];
        let (mut a, mut b) = (rng.next_f32(), rng.next_f32());
        if a + b > 1.0 {
            (a, b) = (1.0 - a, 1.0 - b);
        }
        let bary = Vec3::new(1.0 - a - b, a, b);
        let p = t.point(bary) + offset;
        let uv = t.lm[0] * bary.x + t.lm[1] * bary.y + t.lm[2] * bary.z;
        let want = sphere_occlusion(1.0, 1.0, 2.0, ((p.x * p.x + p.z * p.z) as f64).sqrt());
        let got = bilinear(&img, atlas.width, atlas.height, uv).x as f64;
        let err = (got - want).abs() / want;
        sum += err;
        worst = worst.max(err);
    }
    (sum / n as f64, worst)
}

fn sky_request(resolution: u32) -> BakeRequest {
    BakeRequest {
        resolution,
        lighting: Lighting {
            sky: Some(Sky {
                radiance: Vec3::ONE,
                hemisphere: Hemisphere::Upper,
            }),
            sun: None,
        },
        stop: StopCriteria {
            steps: Some(16),
            ..Default::default()
        },
        params: json!({"samples_per_step": 8}),
        ..Default::default()
    }
}

/// Issue 19: only the ball lacks TEXCOORD_1. The ground's authored UVs come back bit for
/// bit, the ball's new charts cover none of the ground's texels, and the lightmap read at
/// the ground's authored UVs still matches the closed form.
#[test]
fn authored_uvs_are_kept_beside_generated_ones() {
    let (mut json, bin) = sphere_over_plane().to_gltf();
    remove_lightmap_uvs(&mut json, Some(&[1]));
    let input = write_glb(&json, &bin);
    let (scene, report) = import_slice(&input, None).unwrap();
    assert!(!report.has_lightmap_uvs);
    let authored: Vec<_> = scene.triangles.iter().filter(|t| t.mesh == 0).map(|t| t.lm).collect();

    let result = job::bake_unobserved(Arc::new(scene.clone()), &sky_request(128)).unwrap();
    let unwrap = result.summary.generated_uvs.clone().expect("UVs were generated");
    eprintln!("{unwrap:?}");
    assert_eq!((unwrap.generated_meshes, unwrap.kept_meshes), (1, 1));
    // The authored 128 x 128 page on top, the ball's charts below it.
    assert_eq!(result.atlas.width, 128);
    assert!(result.atlas.height > 128, "{}", result.atlas.height);
    let squeeze = 128.0 / result.atlas.height as f32;
    let baked = &result.scene;
    for (t, lm) in baked.triangles.iter().filter(|t| t.mesh == 0).zip(&authored) {
        for (got, want) in t.lm.iter().zip(lm.iter()) {
            assert_eq!(*got, Vec2::new(want.x, want.y * squeeze));
        }
    }
    for t in baked.triangles.iter().filter(|t| t.mesh == 1) {
        assert!(
            t.lm.iter().all(|uv| uv.y >= squeeze),
            "a generated chart reaches into the authored page"
        );
    }
    assert_eq!(result.atlas.overlapping_texels, 0);
    let ground_texels = result.atlas.texels.iter().filter(|t| t.mesh == 0).count();
    assert!(ground_texels > 1000, "{ground_texels}");

    let (mean, worst) = ground_error(&result);
    eprintln!("authored ground beside generated ball: mean relative error {mean:.4}, worst {worst:.4}");
    assert!(mean < 0.01, "mean relative error {mean}");
    assert!(worst < 0.05, "worst relative error {worst}");

    // The written glTF: the ground's TEXCOORD_1 accessor is the input's, byte for byte,
    // and its node says which part of the taller page the authored UVs address.
    let glb = export::to_glb(baked).unwrap();
    let out = gltf::binary::Glb::from_slice(&glb).unwrap();
    let doc: serde_json::Value = serde_json::from_slice(&out.json).unwrap();
    let uv = |doc: &serde_json::Value, bin: &[u8], mesh: usize| -> Vec<u8> {
        let a = doc["meshes"][mesh]["primitives"][0]["attributes"]["TEXCOORD_1"]
            .as_u64()
            .unwrap() as usize;
        let acc = &doc["accessors"][a];
        let view = &doc["bufferViews"][acc["bufferView"].as_u64().unwrap() as usize];
        let start =
            view["byteOffset"].as_u64().unwrap_or(0) as usize + acc["byteOffset"].as_u64().unwrap_or(0) as usize;
        bin[start..start + 8 * acc["count"].as_u64().unwrap() as usize].to_vec()
    };
    assert_eq!(uv(&json, &bin, 0), uv(&doc, out.bin.as_ref().unwrap(), 0));
    // Two pages: the authored one as authored, the ball's below it in the bake's grid
    // and written as a page of its own (issue 19 point 7).
    let rows = result.atlas.height - 128;
    assert_eq!(
        result.atlas.pages,
        vec![
            PageRows {
                first_row: 0,
                rows: 128
            },
            PageRows { first_row: 128, rows }
        ]
    );
    assert_eq!(
        doc["nodes"][0]["extras"]["lightmap"],
        json!({"page": 0, "scale_offset": [1.0, 1.0, 0.0, 0.0], "file": "lightmap-0.exr"})
    );
    let ball = &doc["nodes"][1]["extras"]["lightmap"];
    assert_eq!(
        (ball["page"].clone(), ball["file"].clone()),
        (json!(1), json!("lightmap-1.exr"))
    );
    assert_eq!(result.pages.len(), 2);
    assert_eq!(
        result
            .pages
            .iter()
            .map(|p| (p.entry.width, p.entry.height))
            .collect::<Vec<_>>(),
        vec![(128, 128), (128, rows)]
    );
    let manifest = serde_json::to_value(&result.manifest).unwrap();
    let f32s = |v: &serde_json::Value| -> Vec<f32> {
        v.as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap() as f32)
            .collect()
    };
    assert_eq!(f32s(&manifest["nodes"][1]["scale_offset"]), f32s(&ball["scale_offset"]));
    assert_eq!(
        manifest["pages"][0]["valid_texels"].as_u64().unwrap() as usize,
        ground_texels,
        "page 0 holds exactly the ground's texels"
    );
    // Each page is its rows of the grid: the pages one under another are the delivered
    // grid, channel for channel and bit for bit.
    let grid = job::delivered_exr(
        &result.atlas,
        &result.estimate,
        &sky_request(128),
        &json!({}),
        std::time::Duration::ZERO,
    )
    .unwrap();
    let stacked: Vec<f32> = result.pages.iter().flat_map(|p| exr_channel(&p.exr, "R")).collect();
    assert_eq!(stacked, exr_channel(&grid, "R"));
    // Re-imported, the file (authored UVs on two pages now) bakes to the same grid UVs:
    // each node's page and scale/offset lead back to the texels it was baked on.
    let (back, _) = import_slice(&glb, None).unwrap();
    let again = job::bake_unobserved(
        Arc::new(back),
        &BakeRequest {
            lightmap_uvs: LightmapUvs::Keep,
            stop: StopCriteria {
                steps: Some(1),
                ..Default::default()
            },
            ..sky_request(128)
        },
    )
    .unwrap();
    assert_eq!(again.atlas.pages, result.atlas.pages);
    assert_eq!(again.scene.triangles.len(), baked.triangles.len());
    for (a, b) in again.scene.triangles.iter().zip(&baked.triangles) {
        for k in 0..3 {
            assert!(
                (a.lm[k] - b.lm[k]).abs().max_element() < 1e-6,
                "{:?} vs {:?}",
                a.lm,
                b.lm
            );
        }
    }

    // keep: the ball's missing UVs are an error naming it; regenerate-all: one page.
    let keep = BakeRequest {
        lightmap_uvs: LightmapUvs::Keep,
        ..sky_request(64)
    };
    let err = job::bake_unobserved(Arc::new(scene.clone()), &keep)
        .err()
        .expect("keep fails");
    assert!(err.to_string().contains("mesh 1 \"ball\" has no TEXCOORD_1"), "{err}");
    let mut all = scene.clone();
    let r = lightmapd::engine::atlas::unwrap::generate_lightmap_uvs_with(
        &mut all,
        64,
        LightmapUvs::RegenerateAll,
        None,
        &lightmapd::engine::atlas::unwrap::UvUnwrap,
    )
    .unwrap();
    assert_eq!((r.generated_meshes, r.kept_meshes, r.width, r.height), (2, 0, 64, 64));
}

/// An instance whose transform is singular (a node scaled to 0 along an axis) cannot get a
/// lightmap rectangle of its own: the bake is refused before sampling with an error naming
/// the node and the mesh (issue 19's acceptance), not a panic or a silent zero-size chart.
#[test]
fn a_singular_instance_transform_names_the_node() {
    let (mut json, bin) = without_lightmap_uvs_gltf();
    // A second node placing the ground, flattened along y.
    let flat = json["nodes"].as_array().unwrap().len();
    json["nodes"]
        .as_array_mut()
        .unwrap()
        .push(json!({"name": "flattened ground", "mesh": 0, "translation": [0.0, 3.0, 0.0], "scale": [1.0, 0.0, 1.0]}));
    json["scenes"][0]["nodes"].as_array_mut().unwrap().push(json!(flat));
    let scene = import_slice(&write_glb(&json, &bin), None).expect("imports").0;
    let err = job::bake_unobserved(Arc::new(scene), &sky_request(64))
        .err()
        .expect("a singular instance is refused");
    let text = err.to_string();
    assert!(
        text.contains(&format!("node {flat}")) && text.contains("singular transform"),
        "{text}"
    );
}

/// A server checks a job's memory against its limit from `resolution` (one page) before
/// queueing it; a scene whose generated charts need a second page needs more, which only
/// the layout step knows. With a limit between the two estimates the bake is refused
/// before the texel set is built, naming the pages and the limit.
#[test]
fn a_memory_limit_is_checked_again_on_the_real_pages() {
    use lightmapd::engine::footprint::{JobShape, estimate_bytes};
    let (mut json, bin) = sphere_over_plane().to_gltf();
    remove_lightmap_uvs(&mut json, Some(&[1]));
    let (scene, _) = import_slice(&write_glb(&json, &bin), None).unwrap();
    let shape = JobShape::new(scene.triangles.len() as u64, 0, 128, &[]);
    let (one, two) = (estimate_bytes(&shape), estimate_bytes(&shape.on_grid(128, 256)));
    assert!(two > one);
    let limit = (one + two) / 2;
    let options = job::BakeOptions {
        max_memory_bytes: Some(limit),
        ..Default::default()
    };
    let mut observer = |_: lightmapd::engine::bake::BakeEvent<'_>| std::ops::ControlFlow::Continue(());
    let mut atlas_built = false;
    let err = job::bake(
        Arc::new(scene.clone()),
        &sky_request(128),
        &options,
        &mut observer,
        &mut |_| atlas_built = true,
        &mut |_| {},
    )
    .err()
    .expect("over the limit");
    assert!(err.is_bad_input(), "{err}");
    assert_eq!(
        err.to_string(),
        format!(
            "the lightmap's 2 page(s), 128x256 texels in all, need an estimated {} MiB, more than this worker's \
             limit of {} MiB (--max-job-memory-mb): lower the resolution, texels_per_unit or the meshes' \
             extras.lightmap_scale",
            two >> 20,
            limit >> 20
        )
    );
    assert!(!atlas_built, "the texel set was built before the check");
    // With room for both pages it bakes.
    let options = job::BakeOptions {
        max_memory_bytes: Some(two),
        ..Default::default()
    };
    let ok = job::bake(
        Arc::new(scene),
        &sky_request(128),
        &options,
        &mut observer,
        &mut |_| {},
        &mut |_| {},
    );
    assert_eq!(ok.unwrap().pages.len(), 2);
}
