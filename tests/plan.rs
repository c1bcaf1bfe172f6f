//! The plan leaves out what a scene and job do not need (DESIGN §6), and the technique
//! honours it: nothing left out is allocated or run.

use std::sync::Arc;

use glam::Vec3;
use lightmapd::engine::bake::StopCriteria;
use lightmapd::engine::job::{self, BakeRequest};
use lightmapd::engine::output::OutputLayer;
use lightmapd::engine::plan::Plan;
use lightmapd::engine::scene::build::{LightDesc, cornell_box};
use lightmapd::engine::scene::{Hemisphere, Lighting, Sky, Sun, import_slice};

fn names(items: &[lightmapd::engine::plan::PlanItem]) -> Vec<&str> {
    items.iter().map(|p| p.name.as_str()).collect()
}

fn plan_for(request: &BakeRequest, with_light: bool) -> Plan {
    let mut b = cornell_box();
    if with_light {
        b.light(LightDesc::Point {
            position: Vec3::new(0.0, 1.5, 0.0),
            color: [1.0; 3],
            intensity: 2.0,
        });
    }
    let scene = import_slice(&b.to_glb(), None).unwrap().0;
    lightmapd::engine::job::plan_for(&scene, request).unwrap()
}

#[test]
fn bare_job_leaves_out_lights_environment_glossy_and_layers() {
    let p = plan_for(&BakeRequest::default(), false);
    let left = names(&p.left_out);
    for item in [
        "light sampling: punctual lights",
        "light sampling: sun",
        "sky lookups",
        "direct-light layer",
        "glossy data",
    ] {
        assert!(left.contains(&item), "{item} should be left out: {left:?}");
    }
    assert_eq!(
        names(&p.passes),
        vec!["bvh", "path trace", "light sampling: emissive triangles"]
    );
    let why = |n: &str| p.left_out.iter().find(|i| i.name == n).unwrap().why.clone();
    assert_eq!(
        why("light sampling: punctual lights"),
        "the scene has no punctual lights"
    );
    assert_eq!(why("direct-light layer"), "not asked for in outputs");
    assert!(
        p.summary_line()
            .starts_with("ran: bvh, path trace, light sampling: emissive triangles; left out: ")
    );
}

#[test]
fn what_the_scene_and_job_have_is_planned() {
    let request = BakeRequest {
        lighting: Lighting {
            sky: Some(Sky {
                radiance: Vec3::ONE,
                hemisphere: Hemisphere::Full,
            }),
            sun: Some(Sun {
                direction: Vec3::NEG_Y,
                angular_diameter: 0.01,
                radiance: Vec3::splat(1e4),
            }),
        },
        outputs: vec![OutputLayer::Indirect],
        ..Default::default()
    };
    let p = plan_for(&request, true);
    let ran = names(&p.passes);
    for item in [
        "light sampling: punctual lights",
        "light sampling: sun",
        "sky lookups",
        "direct-light layer",
    ] {
        assert!(ran.contains(&item), "{item} should run: {ran:?}");
    }
    // This sun gives 0.79 W/m² against the sky's π: a quarter, not warned about.
    assert!(p.warnings.is_empty(), "{:?}", p.warnings);
    // A hundred times fainter, 0.25 %: the plan keeps the warning for the job's record.
    let mut faint = request.clone();
    faint.lighting.sun.as_mut().unwrap().radiance = Vec3::splat(100.0);
    let p = plan_for(&faint, true);
    assert_eq!(p.warnings.len(), 1, "{:?}", p.warnings);
    assert!(
        p.warnings[0].starts_with("the sun gives 7.854e-3 W/m²"),
        "{}",
        p.warnings[0]
    );
}

#[test]
fn layers_nobody_asked_for_are_not_allocated() {
    let scene = Arc::new(import_slice(&cornell_box().to_glb(), None).unwrap().0);
    let bake = |outputs: Vec<OutputLayer>| {
        let request = BakeRequest {
            resolution: 16,
            stop: StopCriteria {
                steps: Some(2),
                ..Default::default()
            },
            outputs,
            ..Default::default()
        };
        job::bake_unobserved(scene.clone(), &request).unwrap()
    };
    assert!(bake(vec![]).estimate.direct.is_none());
    assert!(bake(vec![OutputLayer::Validity]).estimate.direct.is_none());
    assert!(bake(vec![OutputLayer::Direct]).estimate.direct.is_some());
}

#[test]
fn unknown_technique_is_refused_before_any_work() {
    let request = BakeRequest {
        technique: "radiosity9000".into(),
        ..Default::default()
    };
    let scene = import_slice(&cornell_box().to_glb(), None).unwrap().0;
    let err = lightmapd::engine::job::plan_for(&scene, &request).unwrap_err();
    assert!(err.is_bad_input());
    assert!(err.to_string().starts_with("unknown technique \"radiosity9000\""));
}
