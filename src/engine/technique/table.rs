//! The technique table: the one place a technique is registered. Each technique's folder
//! exports a [`TechniqueEntry`] (`ENTRY`: id, summary, plan, prepare, its shaders); this
//! table lists them, and the CLI, the service, the bench and the docs read it
//! ([`TECHNIQUES`], [`create`], [`plan`], [`entry`]), and a job is checked against the row
//! before it bakes ([`check_request`]: parameters and output layers; [`check_lights`]:
//! the light it transports). Adding a technique touches its folder
//! and one line here (docs/architecture.md walks through it).

use serde_json::Value;

use super::api::BakeInputs;
use super::api::{EngineError, Technique};
pub use super::api::{LightSource, TechniqueEntry};
use super::{hemicube, obscurance, path, sdb, sdf, vpl};
use crate::engine::output::OutputLayer;
use crate::engine::plan::{Plan, SceneFeatures};

/// Every technique, in the order the CLI and docs list them.
pub const TABLE: &[TechniqueEntry] = &[
    path::ENTRY,
    sdb::ENTRY,
    vpl::ENTRY,
    obscurance::ENTRY,
    sdf::ENTRY,
    hemicube::ENTRY,
];

/// The identifiers [`create`] accepts, in table order.
pub const TECHNIQUES: &[&str] = &{
    let mut ids = [""; TABLE.len()];
    let mut i = 0;
    while i < TABLE.len() {
        ids[i] = TABLE[i].id;
        i += 1;
    }
    ids
};

/// The entry of technique `id`; an unknown id is a bad-input error listing the known ones.
pub fn entry(id: &str) -> Result<&'static TechniqueEntry, EngineError> {
    TABLE.iter().find(|e| e.id == id).ok_or_else(|| {
        EngineError::BadInput(format!(
            "unknown technique {id:?}; available: {}",
            TECHNIQUES.join(", ")
        ))
    })
}

/// Prepares technique `id` with `params` (a JSON object; unknown fields are rejected).
pub fn create(id: &str, inputs: BakeInputs, params: &Value) -> Result<Box<dyn Technique>, EngineError> {
    (entry(id)?.prepare)(inputs, params)
}

/// The plan technique `id` makes for a scene with `features` (see `engine::plan`).
pub fn plan(id: &str, features: &SceneFeatures) -> Result<Plan, EngineError> {
    Ok((entry(id)?.plan)(features))
}

/// The techniques whose table row lets `ok` through, for "use …" in an error.
fn which(ok: impl Fn(&TechniqueEntry) -> bool) -> String {
    let ids: Vec<&str> = TABLE.iter().filter(|e| ok(e)).map(|e| e.id).collect();
    if ids.is_empty() { "none".into() } else { ids.join(", ") }
}

/// What a job asks of technique `id` that needs no scene: its parameters and its output
/// layers, against the table. Run at submit (service) and before the bake (CLI, engine);
/// each error starts with the field it is about.
pub fn check_request(id: &str, params: &Value, outputs: &[OutputLayer]) -> Result<(), EngineError> {
    let e = entry(id)?;
    if !(params.is_null() || params.is_object()) {
        return Err(EngineError::BadInput("params must be a JSON object".into()));
    }
    (e.check_params)(params)?;
    for (i, layer) in outputs.iter().enumerate() {
        if !e.writes(*layer) {
            return Err(EngineError::BadInput(format!(
                "outputs[{i}]: {id} cannot write the {:?} layer; techniques that can: {}",
                layer.name(),
                which(|t| t.layers.contains(layer))
            )));
        }
    }
    Ok(())
}

/// The light of a scene and job (`features`) against technique `id`'s `lights`: light it
/// does not transport is refused before baking, naming the light and the techniques that
/// do, instead of being dropped from the lightmap.
pub fn check_lights(id: &str, features: &SceneFeatures) -> Result<(), EngineError> {
    lights_of(entry(id)?, features)
}

/// [`check_lights`] against one row. Every row of [`TABLE`] bakes every light since the
/// shared direct-light module (`engine::gpu::direct_light`); the check stays so that a
/// technique added with a shorter `lights` list is refused, not silently dark.
fn lights_of(e: &TechniqueEntry, features: &SceneFeatures) -> Result<(), EngineError> {
    let id = e.id;
    for light in LightSource::ALL {
        let n = light.count(features);
        if n > 0 && !e.lights.contains(light) {
            return Err(EngineError::BadInput(format!(
                "{}: {id} does not bake {}; techniques that do: {}",
                light.field(),
                light.describe(n),
                which(|t| t.lights.contains(light))
            )));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeSet;
    use std::path::Path;

    use super::*;
    use crate::engine::gpu::shaders::{SHARED_PASSES, validate_wgsl};

    /// Every WGSL file under `shaders/`, as paths relative to it.
    fn wgsl_on_disk() -> BTreeSet<String> {
        fn walk(dir: &Path, root: &Path, out: &mut BTreeSet<String>) {
            for e in std::fs::read_dir(dir).expect("shaders/ is readable") {
                let p = e.expect("a directory entry").path();
                if p.is_dir() {
                    walk(&p, root, out);
                } else if p.extension().is_some_and(|x| x == "wgsl") {
                    out.insert(p.strip_prefix(root).unwrap().to_string_lossy().replace('\\', "/"));
                }
            }
        }
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("shaders");
        let mut out = BTreeSet::new();
        walk(&root, &root, &mut out);
        out
    }

    #[test]
    fn every_wgsl_pass_parses_and_validates_without_a_device() {
        let mut failures = Vec::new();
        let mut count = 0;
        for pass in TABLE.iter().flat_map(|e| e.shaders).chain(SHARED_PASSES) {
            count += 1;
            if let Err(e) = validate_wgsl(pass.name, &pass.composed()) {
                failures.push(e);
            }
        }
        assert!(count >= 17, "only {count} passes listed");
        assert!(failures.is_empty(), "WGSL validation failed:\n{}", failures.join("\n"));
    }

    #[test]
    fn every_wgsl_file_is_reachable_from_a_pipeline() {
        // A file no pass is composed of would escape validation (and is dead code).
        let used: BTreeSet<String> = TABLE
            .iter()
            .flat_map(|e| e.shaders)
            .chain(SHARED_PASSES)
            .flat_map(|p| p.files())
            .map(String::from)
            .collect();
        let on_disk = wgsl_on_disk();
        let unreachable: Vec<&String> = on_disk.difference(&used).collect();
        assert!(unreachable.is_empty(), "WGSL files no pipeline uses: {unreachable:?}");
        let missing: Vec<&String> = used.difference(&on_disk).collect();
        assert!(missing.is_empty(), "passes name files that do not exist: {missing:?}");
    }

    #[test]
    fn a_technique_loads_only_its_own_and_shared_shaders() {
        let ids: BTreeSet<&str> = TABLE.iter().map(|e| e.id).collect();
        for e in TABLE {
            for pass in e.shaders {
                for file in pass.files() {
                    let folder = file.split('/').next().unwrap_or("");
                    assert!(
                        folder == e.id || folder == "gpu",
                        "technique {} loads {file} (only shaders/{}/ and shaders/gpu/ are its own)",
                        e.id,
                        e.id
                    );
                    assert!(!ids.contains(folder) || folder == e.id);
                }
            }
        }
        // The shared layer's own passes use nothing of any technique.
        for pass in SHARED_PASSES {
            assert!(
                pass.files().all(|f| f.starts_with("gpu/")),
                "{} uses a technique's WGSL",
                pass.name
            );
        }
    }

    /// Every technique's plan says what its live error estimate covers (the job status
    /// and the console show it), and only the unbiased `path` claims all of the error
    /// (issue 21: sdb's said nothing, though docs/accuracy.md said "noise only").
    #[test]
    fn every_plan_says_what_its_error_estimate_covers() {
        let f = SceneFeatures {
            sky: true,
            emissive_triangles: 2,
            ..Default::default()
        };
        for e in TABLE {
            let covers = (e.plan)(&f).error_estimate;
            if e.id == "path" {
                assert!(covers.starts_with("all of the error"), "{}: {covers}", e.id);
            } else {
                assert!(
                    covers.starts_with("noise only") || covers.starts_with("only the jitter noise"),
                    "{}: {covers:?}",
                    e.id
                );
            }
        }
    }

    /// A row that does not list a light refuses a job with it, naming the field, the
    /// light and the techniques that bake it; every row of the table bakes everything.
    #[test]
    fn light_a_row_does_not_list_is_refused_by_name() {
        let sky_only = TechniqueEntry {
            id: "sky_only",
            lights: &[LightSource::Sky],
            ..sdf::ENTRY
        };
        let f = SceneFeatures {
            sky: true,
            sun: true,
            ..Default::default()
        };
        let e = lights_of(&sky_only, &f).expect_err("the sun is refused");
        assert!(e.is_bad_input());
        assert_eq!(
            e.to_string(),
            "lighting.sun: sky_only does not bake the job's sun; techniques that do: path, sdb, vpl, obscurance, sdf, hemicube"
        );
        let f = SceneFeatures {
            sky: true,
            emissive_triangles: 2,
            ..Default::default()
        };
        let e = lights_of(&sky_only, &f).expect_err("emitters are refused");
        assert_eq!(
            e.to_string(),
            "technique: sky_only does not bake the scene's 2 emissive triangle(s); techniques that do: path, sdb, vpl, obscurance, sdf, hemicube"
        );
        let sky = SceneFeatures {
            sky: true,
            ..Default::default()
        };
        assert!(lights_of(&sky_only, &sky).is_ok());
        let everything = SceneFeatures {
            sky: true,
            sun: true,
            punctual_lights: 3,
            directional_lights: 1,
            emissive_triangles: 4,
            ..Default::default()
        };
        for row in TABLE {
            assert_eq!(row.lights, LightSource::ALL, "{}", row.id);
            lights_of(row, &everything).unwrap();
        }
    }

    /// A row that lists the direct (or sh) layer must plan to keep it when asked, else the
    /// job asks the technique for nothing and the output fails after the whole bake (sdf
    /// did, until its plan decided `DIRECT_LAYER`).
    #[test]
    fn every_layer_a_row_lists_is_kept_by_its_plan_when_asked() {
        for row in TABLE {
            for (layer, item) in [
                (OutputLayer::Direct, crate::engine::plan::DIRECT_LAYER),
                (OutputLayer::Indirect, crate::engine::plan::DIRECT_LAYER),
                (OutputLayer::Sh, crate::engine::plan::SH_LAYER),
            ] {
                if !row.layers.contains(&layer) {
                    continue;
                }
                let f = SceneFeatures {
                    sky: true,
                    sun: true,
                    want_direct: matches!(layer, OutputLayer::Direct | OutputLayer::Indirect),
                    want_sh: layer == OutputLayer::Sh,
                    ..Default::default()
                };
                let p = plan(row.id, &f).unwrap();
                assert!(
                    p.runs(item),
                    "{}: {:?} is listed but its plan does not keep {item:?}",
                    row.id,
                    layer.name()
                );
            }
        }
    }

    #[test]
    fn ids_are_unique_and_lookups_agree_with_the_table() {
        let ids: BTreeSet<&str> = TECHNIQUES.iter().copied().collect();
        assert_eq!(ids.len(), TABLE.len());
        for e in TABLE {
            assert_eq!(entry(e.id).unwrap().id, e.id);
        }
        let err = entry("nope").err().expect("an unknown id is rejected");
        assert!(err.is_bad_input());
        assert!(
            err.to_string().contains("path, sdb, vpl, obscurance, sdf, hemicube"),
            "{err}"
        );
    }
}
