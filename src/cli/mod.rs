//! What the commands share: the failure a command returns and the exit code it earns,
//! the async runtime of the commands that talk to a service, the Mesa device-select
//! switch, and the lighting options that `bake` and `submit` both take (the sky and the
//! sun, [`LightingArgs`]).

pub mod bake;
pub mod bench;
pub mod log_format;
pub mod serve;
pub mod submit;
pub mod token;

use clap::ValueEnum;
use glam::Vec3;
use lightmapd::engine::scene::{Hemisphere, Lighting, Sky, Sun};

/// A failure and the exit code it earns.
pub(crate) struct Failure {
    pub(crate) code: u8,
    pub(crate) message: String,
}

pub(crate) fn bad_input(message: impl Into<String>) -> Failure {
    Failure {
        code: 2,
        message: message.into(),
    }
}

/// An engine error as the process's failure: exit code 2 for bad input, else 1.
pub(crate) fn engine_failure(e: lightmapd::engine::technique::EngineError) -> Failure {
    Failure {
        code: if e.is_bad_input() { 2 } else { 1 },
        message: e.to_string(),
    }
}

/// A relative error estimate as printed: "1.23%", or "n/a" without one.
pub(crate) fn error_text(relative: Option<f32>) -> String {
    relative.map_or_else(|| "n/a".into(), |e| format!("{:.2}%", e * 100.0))
}

pub(crate) fn runtime() -> Result<tokio::runtime::Runtime, Failure> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(|e| Failure {
            code: 1,
            message: format!("cannot start the async runtime: {e}"),
        })
}

/// On a machine without a display session (no `XDG_RUNTIME_DIR`: a server, a container, CI)
/// Mesa's Vulkan device-select layer prints "error: XDG_RUNTIME_DIR is invalid or not set
/// in the environment" up to four times a bake while it looks for a display to order the
/// GPUs by; nothing is wrong, but it reads as a failure. lightmapd picks its adapter itself
/// (`LIGHTMAPD_ADAPTER`, `engine::gpu`), so there the layer is switched off
/// (`NODEVICE_SELECT=1`, Mesa's own switch) unless the user has set it or chosen a device
/// through it (`MESA_VK_DEVICE_SELECT`). Called first thing in `main`, before any thread
/// exists.
pub(crate) fn quiet_device_select() {
    // Empty counts as unset, as it does for Mesa.
    let unset = |name: &str| std::env::var_os(name).is_none_or(|v| v.is_empty());
    if unset("XDG_RUNTIME_DIR") && unset("NODEVICE_SELECT") && unset("MESA_VK_DEVICE_SELECT") {
        // SAFETY: no other thread exists yet (this runs first in `main`), so nothing reads
        // the environment while it is written.
        unsafe { std::env::set_var("NODEVICE_SELECT", "1") };
    }
}

/// The lighting options `bake` and `submit` both take, flattened into each.
#[derive(clap::Args)]
pub(crate) struct LightingArgs {
    /// Uniform sky radiance R,G,B.
    #[arg(long, value_parser = parse_vec3)]
    sky: Option<Vec3>,
    #[arg(long, value_enum, default_value = "upper")]
    sky_hemisphere: HemisphereArg,
    /// Sun: DX,DY,DZ (from the sun toward the scene),DIAMETER_DEG,R,G,B (radiance, per steradian: a 0.53° disc is 6.7e-5 sr, so an irradiance E needs a radiance of E / 6.7e-5).
    #[arg(long, value_parser = parse_sun)]
    sun: Option<Sun>,
}

impl LightingArgs {
    /// The job's lighting: the sky over the hemisphere given, and the sun.
    pub(crate) fn lighting(&self) -> Lighting {
        Lighting {
            sky: self.sky.map(|radiance| Sky {
                radiance,
                hemisphere: match self.sky_hemisphere {
                    HemisphereArg::Upper => Hemisphere::Upper,
                    HemisphereArg::Full => Hemisphere::Full,
                },
            }),
            sun: self.sun,
        }
    }
}

#[derive(Clone, Copy, ValueEnum)]
enum HemisphereArg {
    Upper,
    Full,
}

fn parse_floats(s: &str, n: usize, what: &str) -> Result<Vec<f32>, String> {
    let v: Result<Vec<f32>, _> = s.split(',').map(|x| x.trim().parse::<f32>()).collect();
    match v {
        Ok(v) if v.len() == n && v.iter().all(|x| x.is_finite()) => Ok(v),
        _ => Err(format!(
            "expected {what} as {n} comma-separated finite numbers, got {s:?}"
        )),
    }
}

fn parse_vec3(s: &str) -> Result<Vec3, String> {
    parse_floats(s, 3, "R,G,B").map(|v| Vec3::new(v[0], v[1], v[2]))
}

fn parse_sun(s: &str) -> Result<Sun, String> {
    let v = parse_floats(s, 7, "DX,DY,DZ,DIAMETER_DEG,R,G,B")?;
    let direction = Vec3::new(v[0], v[1], v[2]);
    if direction.length() < 1e-6 {
        return Err("sun direction must not be zero".into());
    }
    Ok(Sun {
        direction: direction.normalize(),
        angular_diameter: v[3].to_radians(),
        radiance: Vec3::new(v[4], v[5], v[6]),
    })
}
