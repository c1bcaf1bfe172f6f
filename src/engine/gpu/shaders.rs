//! WGSL sources, compiled into the binary.
//!
//! Every pass lives in its own file under `shaders/`; helpers and layouts that several
//! passes share live in `shaders/common.wgsl`, which is concatenated in front of each pass
//! (WGSL has no include directive). [`ALL`] lists every pass so that the validation test
//! (below, no GPU needed) cannot forget one.

/// Shared helpers: PCG hash, view layout, per-texel and per-triangle structs.
pub const COMMON: &str = include_str!("../../../shaders/common.wgsl");

/// One WGSL pass file.
#[derive(Debug, Clone, Copy)]
pub struct PassShader {
    /// File name under `shaders/`, also the label of the shader module.
    pub name: &'static str,
    /// The pass source, without the common prelude.
    pub source: &'static str,
}

impl PassShader {
    /// The full source handed to the compiler: common prelude, then the pass.
    pub fn composed(&self) -> String {
        let mut s = String::with_capacity(COMMON.len() + self.source.len() + 64);
        s.push_str(COMMON);
        s.push_str("\n// ---- ");
        s.push_str(self.name);
        s.push_str(" ----\n");
        s.push_str(self.source);
        s
    }
}

macro_rules! pass {
    ($name:literal) => {
        PassShader {
            name: $name,
            source: include_str!(concat!("../../../shaders/", $name)),
        }
    };
}

/// `sdb`: outgoing radiance of every lightmap pixel from the running estimate.
pub const SDB_RESOLVE: PassShader = pass!("sdb_resolve.wgsl");
/// `sdb`: the illumination map (stochastic depth) and the shadow maps (nearest depth).
pub const SDB_ILLUMINATION: PassShader = pass!("sdb_illumination.wgsl");
/// `sdb`: gather one direction into the lightmap accumulators.
pub const SDB_GATHER: PassShader = pass!("sdb_gather.wgsl");
/// `sdb`: direct light from the sun and directional lights through a shadow map.
pub const SDB_DIRECT: PassShader = pass!("sdb_direct.wgsl");

/// `vpl`: the step's shadow maps (cube faces and orthographic maps) in one atlas.
pub const VPL_SHADOW: PassShader = pass!("vpl_shadow.wgsl");
/// `vpl`: gather the step's lights and VPLs into the lightmap accumulators.
pub const VPL_GATHER: PassShader = pass!("vpl_gather.wgsl");
/// `obscurance`: every depth layer per pixel as fragment lists, and shadow maps.
pub const OBSCURANCE_LAYERS: PassShader = pass!("obscurance_layers.wgsl");
/// `obscurance`: obscurance, colour bleeding and direct light along one direction.
pub const OBSCURANCE_GATHER: PassShader = pass!("obscurance_gather.wgsl");
/// `obscurance`: direct light from the sun and directional lights through a shadow map.
pub const OBSCURANCE_DIRECT: PassShader = pass!("obscurance_direct.wgsl");
/// `sdf`: seed the voxels each triangle touches.
pub const SDF_VOXELIZE: PassShader = pass!("sdf_voxelize.wgsl");
/// `sdf`: jump flooding and the signed distance of the nearest seed triangle.
pub const SDF_FLOOD: PassShader = pass!("sdf_flood.wgsl");
/// `sdf`: analytic dynamic shapes composited into the volume with min.
pub const SDF_DYNAMIC: PassShader = pass!("sdf_dynamic.wgsl");
/// `sdf`: the pre-blurred mip chain.
pub const SDF_MIPS: PassShader = pass!("sdf_mips.wgsl");
/// `sdf`: sky visibility along the bent normal, and the calibration sums.
pub const SDF_SKY: PassShader = pass!("sdf_sky.wgsl");

/// `hemicube`: the power pyramid (level 0 and the 2 x 2 sums).
pub const HEMICUBE_PYRAMID: PassShader = pass!("hemicube_pyramid.wgsl");
/// `hemicube`: the step's shooters (pyramid descent, texel merging) and their views.
pub const HEMICUBE_SELECT: PassShader = pass!("hemicube_select.wgsl");
/// `hemicube`: every receiver takes the shooters' light; the half accumulators.
pub const HEMICUBE_TRANSFER: PassShader = pass!("hemicube_transfer.wgsl");

/// A pass that casts rays: common prelude, then the BVH traversal library
/// (`shaders/gpu/bvh.wgsl`, which owns bindings 0 and 1), then the pass.
macro_rules! pass_with_bvh {
    ($name:literal) => {
        PassShader {
            name: $name,
            source: concat!(
                include_str!("../../../shaders/gpu/bvh.wgsl"),
                "\n// ---- ",
                $name,
                " ----\n",
                include_str!(concat!("../../../shaders/", $name))
            ),
        }
    };
}

/// The GPU BVH traversal library (no entry points), validated through the passes below.
pub const BVH_LIBRARY: &str = "gpu/bvh.wgsl";
/// GPU BVH: one closest-hit or any-hit query per invocation (tests, benchmarks).
pub const BVH_QUERY: PassShader = pass_with_bvh!("gpu/bvh_query.wgsl");
/// `path` on the GPU: the whole estimator per texel and sample (megakernel).
pub const PATH_TRACE: PassShader = pass_with_bvh!("path/path_trace.wgsl");

/// Every pass shader in the crate.
pub const ALL: &[PassShader] = &[
    SDB_RESOLVE,
    SDB_ILLUMINATION,
    SDB_GATHER,
    SDB_DIRECT,
    VPL_SHADOW,
    VPL_GATHER,
    OBSCURANCE_LAYERS,
    OBSCURANCE_GATHER,
    OBSCURANCE_DIRECT,
    SDF_VOXELIZE,
    SDF_FLOOD,
    SDF_DYNAMIC,
    SDF_MIPS,
    SDF_SKY,
    HEMICUBE_PYRAMID,
    HEMICUBE_SELECT,
    HEMICUBE_TRANSFER,
    BVH_QUERY,
    PATH_TRACE,
];

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
    fn every_wgsl_pass_parses_and_validates_without_a_device() {
        let mut failures = Vec::new();
        for pass in ALL {
            if let Err(e) = validate_wgsl(pass.name, &pass.composed()) {
                failures.push(e);
            }
        }
        assert!(failures.is_empty(), "WGSL validation failed:\n{}", failures.join("\n"));
    }

    #[test]
    fn every_shader_file_is_listed() {
        // A new file in shaders/ (or a folder below it) that is not in ALL would escape the
        // validation test. The two libraries are validated as part of every pass.
        fn walk(dir: &std::path::Path, prefix: &str, out: &mut Vec<String>) {
            for e in std::fs::read_dir(dir).expect("shaders/ exists").flatten() {
                let name = e.file_name().into_string().expect("UTF-8 file name");
                let path = e.path();
                if path.is_dir() {
                    walk(&path, &format!("{prefix}{name}/"), out);
                } else if name.ends_with(".wgsl") {
                    out.push(format!("{prefix}{name}"));
                }
            }
        }
        let mut on_disk = Vec::new();
        walk(std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/shaders")), "", &mut on_disk);
        on_disk.retain(|n| n != "common.wgsl" && n != BVH_LIBRARY);
        on_disk.sort();
        let mut listed: Vec<String> = ALL.iter().map(|p| p.name.to_string()).collect();
        listed.sort();
        assert_eq!(on_disk, listed);
    }

    #[test]
    fn validation_rejects_a_broken_shader() {
        // The validator must actually catch errors: a type mismatch naga parses but
        // rejects, and a syntax error.
        let bad = format!("{COMMON}\nfn f() -> f32 {{ return pcg(1u); }}");
        assert!(validate_wgsl("bad.wgsl", &bad).is_err());
        assert!(validate_wgsl("bad2.wgsl", "fn f( {").is_err());
    }
}
