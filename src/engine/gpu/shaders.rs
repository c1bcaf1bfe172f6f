//! WGSL sources, compiled into the binary, and their composition.
//!
//! Layout (docs/architecture.md): every pass lives in its own file, `shaders/<id>/` for the
//! passes of technique `<id>` and `shaders/gpu/` for the WGSL that several techniques
//! share. WGSL has no include directive, so a pass is compiled as a concatenation:
//! [`COMMON`] (randomness, the orthographic map views, the per-texel and per-triangle
//! layouts that every pass uses), then the pass's own preludes (for example the shadow
//! atlas's view layout, or a technique's own shared structs), then the pass.
//!
//! A technique names its passes with [`pass!`] in its own folder (the technique table
//! lists them); the passes of the shared GPU layer are below ([`SHADOW_ATLAS`]). The
//! validation test that walks `shaders/` lives beside the technique table
//! (`technique/table.rs`), because only the table knows every pass; [`validate_wgsl`]
//! is here so that it needs no device.

/// One WGSL file under `shaders/`.
#[derive(Debug, Clone, Copy)]
pub struct WgslFile {
    /// Path under `shaders/` (e.g. `gpu/common.wgsl`).
    pub name: &'static str,
    pub source: &'static str,
}

/// One WGSL pass file and the preludes it needs besides [`COMMON`].
#[derive(Debug, Clone, Copy)]
pub struct PassShader {
    /// Path under `shaders/`, also the label of the shader module.
    pub name: &'static str,
    /// The pass source, without any prelude.
    pub source: &'static str,
    /// Prepended after [`COMMON`], in this order.
    pub preludes: &'static [WgslFile],
}

/// Includes `shaders/$name` as a [`WgslFile`].
#[macro_export]
macro_rules! wgsl_file {
    ($name:literal) => {
        $crate::engine::gpu::shaders::WgslFile {
            name: $name,
            source: include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/shaders/", $name)),
        }
    };
}

/// Includes `shaders/$name` as a [`PassShader`], with optional preludes.
#[macro_export]
macro_rules! pass_shader {
    ($name:literal) => {
        $crate::pass_shader!($name, [])
    };
    ($name:literal, [$($prelude:expr),*]) => {
        $crate::engine::gpu::shaders::PassShader {
            name: $name,
            source: include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/shaders/", $name)),
            preludes: &[$($prelude),*],
        }
    };
}
pub use crate::{pass_shader as pass, wgsl_file};

/// Shared by every pass: PCG hash, view layout, per-texel and per-triangle structs.
pub const COMMON_FILE: WgslFile = wgsl_file!("gpu/common.wgsl");
pub const COMMON: &str = COMMON_FILE.source;

/// The layout of one map of the shared shadow atlas ([`crate::engine::gpu::shadow`]):
/// prelude of every pass that renders or reads the atlas.
pub const SHADOW_VIEW: WgslFile = wgsl_file!("gpu/shadow_view.wgsl");

/// The shared shadow atlas: cube faces and orthographic maps of one step in one render
/// pass (used by `vpl` for lights and VPLs, `hemicube` for its shooters).
pub const SHADOW_ATLAS: PassShader = pass!("gpu/shadow_atlas.wgsl", [SHADOW_VIEW, MATERIALS]);

/// The scene's materials, textures and glTF alpha (no entry points, no bindings: the
/// composing pass declares `tables`): prelude of every pass that reads materials, the
/// ray passes (before [`LIGHTS`]) and the raster passes that alpha-test.
pub const MATERIALS: WgslFile = wgsl_file!("gpu/materials.wgsl");

/// The GPU BVH traversal library (`engine::gpu::bvh`; no entry points, owns bindings 0
/// and 1): prelude of every pass that casts rays, always followed by [`MATERIALS`] and
/// [`LIGHTS`], which define its alpha test.
pub const BVH: WgslFile = wgsl_file!("gpu/bvh.wgsl");

/// GPU BVH: one closest-hit or any-hit query per invocation (tests, benchmarks).
pub const BVH_QUERY: PassShader = pass!("gpu/bvh_query.wgsl", [BVH, MATERIALS, LIGHTS]);

/// The scene's shading data, its lights and next-event estimation to them
/// (`engine::gpu::scene_lights`; no entry points, owns bindings 2-4): prelude, after
/// [`BVH`], of every pass that samples light with rays.
pub const LIGHTS: WgslFile = wgsl_file!("gpu/lights.wgsl");

/// The shared direct-light pass (`engine::gpu::direct_light`).
pub const DIRECT_LIGHT: PassShader = pass!("gpu/direct_light.wgsl", [BVH, MATERIALS, LIGHTS]);

/// The shadowmask pass (`engine::gpu::shadowmask`).
pub const SHADOWMASK: PassShader = pass!("gpu/shadowmask.wgsl", [BVH, MATERIALS, LIGHTS]);

/// The passes of the shared GPU layer (the technique table adds every technique's).
pub const SHARED_PASSES: &[PassShader] = &[SHADOW_ATLAS, BVH_QUERY, DIRECT_LIGHT, SHADOWMASK];

impl PassShader {
    /// The full source handed to the compiler: common prelude, the pass's preludes, then
    /// the pass.
    pub fn composed(&self) -> String {
        let mut s = String::with_capacity(
            COMMON.len() + self.preludes.iter().map(|p| p.source.len() + 64).sum::<usize>() + self.source.len() + 64,
        );
        s.push_str(COMMON);
        for p in self.preludes {
            s.push_str("\n// ---- ");
            s.push_str(p.name);
            s.push_str(" ----\n");
            s.push_str(p.source);
        }
        s.push_str("\n// ---- ");
        s.push_str(self.name);
        s.push_str(" ----\n");
        s.push_str(self.source);
        s
    }

    /// Every file this pass is composed of, [`COMMON`] first.
    pub fn files(&self) -> impl Iterator<Item = &'static str> + '_ {
        std::iter::once(COMMON_FILE.name)
            .chain(self.preludes.iter().map(|p| p.name))
            .chain(std::iter::once(self.name))
    }
}

/// A Rust struct that mirrors a WGSL struct of a pass (a uniform, a storage buffer's
/// element): [`check_mirrors`] compares its size with naga's layout of the struct in the
/// composed pass, so "must match the shader" is a tested fact, not a comment. Each
/// module that declares mirrors lists them and checks them in a unit test (no device).
#[derive(Debug, Clone, Copy)]
pub struct Mirror {
    /// The Rust type's name, for messages.
    pub rust: &'static str,
    pub size: usize,
    /// A pass whose composed source declares the struct.
    pub pass: PassShader,
    pub wgsl: &'static str,
}

impl Mirror {
    pub const fn of<T>(rust: &'static str, pass: PassShader, wgsl: &'static str) -> Mirror {
        Mirror {
            rust,
            size: std::mem::size_of::<T>(),
            pass,
            wgsl,
        }
    }

    /// The WGSL struct's size in bytes as naga lays it out (WGSL's alignment rules:
    /// vec3 aligned to 16 bytes, struct sizes rounded to their alignment).
    pub fn wgsl_size(&self) -> Result<u32, String> {
        let module = validate_wgsl(self.pass.name, &self.pass.composed())?;
        let mut layouter = naga::proc::Layouter::default();
        layouter
            .update(module.to_ctx())
            .map_err(|e| format!("{}: {e}", self.pass.name))?;
        module
            .types
            .iter()
            .find(|(_, t)| t.name.as_deref() == Some(self.wgsl) && matches!(t.inner, naga::TypeInner::Struct { .. }))
            .map(|(h, _)| layouter[h].size)
            .ok_or_else(|| format!("{} declares no struct {}", self.pass.name, self.wgsl))
    }
}

/// Every mirror whose size differs from its WGSL struct's (or whose struct is missing),
/// as messages; empty when all match.
pub fn check_mirrors(mirrors: &[Mirror]) -> Vec<String> {
    mirrors
        .iter()
        .filter_map(|m| match m.wgsl_size() {
            Ok(size) if size as usize == m.size => None,
            Ok(size) => Some(format!(
                "{} is {} bytes, {}'s {} is {size}",
                m.rust, m.size, m.pass.name, m.wgsl
            )),
            Err(e) => Some(format!("{}: {e}", m.rust)),
        })
        .collect()
}

/// Panics with every mismatch [`check_mirrors`] finds: the body of each module's layout
/// test.
pub fn assert_mirrors(mirrors: &[Mirror]) {
    let wrong = check_mirrors(mirrors);
    assert!(
        wrong.is_empty(),
        "Rust mirrors that differ from their WGSL structs:\n{}",
        wrong.join("\n")
    );
}

/// Parse and validate a composed WGSL source with naga alone, no device. Returns the
/// diagnostic text on failure. The same checks run again inside wgpu at
/// `create_shader_module`; doing them here lets a unit test catch a broken shader on a
/// machine with no adapter at all.
pub fn validate_wgsl(name: &str, source: &str) -> Result<naga::Module, String> {
    let module = naga::front::wgsl::parse_str(source).map_err(|e| e.emit_to_string_with_path(source, name))?;
    // Default capabilities: only what every WebGPU implementation has, which is all the
    // shaders may assume (the device is created with no optional shader features).
    let mut validator = naga::valid::Validator::new(naga::valid::ValidationFlags::all(), Default::default());
    validator
        .validate(&module)
        .map_err(|e| e.emit_to_string_with_path(source, name))?;
    Ok(module)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_mirror_of_the_wrong_size_or_name_is_reported() {
        // ShadowView is five vec4: 80 bytes.
        assert!(check_mirrors(&[Mirror::of::<[[f32; 4]; 5]>("Five", SHADOW_ATLAS, "ShadowView")]).is_empty());
        let wrong = check_mirrors(&[
            Mirror::of::<[[f32; 4]; 4]>("Four", SHADOW_ATLAS, "ShadowView"),
            Mirror::of::<[[f32; 4]; 5]>("Five", SHADOW_ATLAS, "NoSuchStruct"),
        ]);
        assert_eq!(
            wrong,
            [
                "Four is 64 bytes, gpu/shadow_atlas.wgsl's ShadowView is 80",
                "Five: gpu/shadow_atlas.wgsl declares no struct NoSuchStruct"
            ]
        );
    }

    #[test]
    fn validation_rejects_a_broken_shader() {
        // The validator must actually catch errors: a type mismatch naga parses but
        // rejects, and a syntax error.
        let bad = format!("{COMMON}\nfn f() -> f32 {{ return pcg(1u); }}");
        assert!(validate_wgsl("bad.wgsl", &bad).is_err());
        assert!(validate_wgsl("bad2.wgsl", "fn f( {").is_err());
    }

    #[test]
    fn shared_passes_validate() {
        for pass in SHARED_PASSES {
            if let Err(e) = validate_wgsl(pass.name, &pass.composed()) {
                panic!("{e}");
            }
        }
    }
}
