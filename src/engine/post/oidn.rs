//! Intel Open Image Denoise (OIDN 2), loaded at run time through its C API.
//!
//! What: [`Oidn::get`] finds and opens `libOpenImageDenoise.so.2` once per process;
//! [`Oidn::filter`] runs one filter (`RTLightmap` for HDR irradiance or, with
//! `directional`, normalised directional coefficients; `RT` with `hdr` and a normal
//! image) over a W × H float3 image and returns the filtered image.
//!
//! How, and why run-time loading: the `oidn` crate links the library at build time
//! (through `OIDN_DIR` or pkg-config), so a build without OIDN needs a cargo feature, and
//! a binary built with it does not start on a machine without the library. OIDN's C API
//! is small and stable across 2.x (fifteen entry points are used here), so this module
//! declares them by hand and opens the library with `libloading`: one binary, built with
//! no OIDN present, uses OIDN where it is installed and the own denoiser elsewhere, and
//! the tests run either way. The library is looked for in `$LIGHTMAPD_OIDN_DIR` (a
//! directory holding the library or a `lib/` with it), then in `/opt/lightmapd-oidn/lib`
//! (where `scripts/setup-oidn.sh` installs PyPI's `pyoidn` 2.5.1 wheel's libraries), then
//! on the system loader path. The library finds its core and device modules through its
//! own RUNPATH (`$ORIGIN`), so nothing else needs setting.
//!
//! Images go through OIDN buffers (`oidnNewBuffer`, `oidnWriteBuffer`, `oidnReadBuffer`)
//! rather than shared host pointers: that works on every device, including CUDA, where a
//! host pointer is not device-accessible. The device is the default one (CUDA on an
//! NVIDIA machine, else the CPU), created once and kept; calls are serialised by a mutex
//! (OIDN uses every core for one image, so parallel calls would only compete).
//!
//! Limits: x86-64 Linux only as installed by the set-up script (the wheel's platform);
//! the C declarations must match OIDN 2.x (checked: the version the device reports must
//! be 2.x, else the library is refused).

use std::ffi::{CStr, c_char, c_int, c_void};
use std::path::PathBuf;
use std::sync::{Mutex, OnceLock};

use glam::Vec3;

/// The directory `scripts/setup-oidn.sh` installs into.
pub const DEFAULT_DIR: &str = "/opt/lightmapd-oidn";
const SONAME: &str = "libOpenImageDenoise.so.2";

type Device = *mut c_void;
type Filter = *mut c_void;
type Buffer = *mut c_void;

const DEVICE_TYPE_DEFAULT: c_int = 0;
const FORMAT_FLOAT3: c_int = 3;
const QUALITY_HIGH: c_int = 6;

/// The entry points used, with OIDN 2's C signatures (`OpenImageDenoise/oidn.h`).
struct Api {
    new_device: unsafe extern "C" fn(c_int) -> Device,
    commit_device: unsafe extern "C" fn(Device),
    get_device_error: unsafe extern "C" fn(Device, *mut *const c_char) -> c_int,
    get_device_int: unsafe extern "C" fn(Device, *const c_char) -> c_int,
    new_buffer: unsafe extern "C" fn(Device, usize) -> Buffer,
    write_buffer: unsafe extern "C" fn(Buffer, usize, usize, *const c_void),
    read_buffer: unsafe extern "C" fn(Buffer, usize, usize, *mut c_void),
    release_buffer: unsafe extern "C" fn(Buffer),
    new_filter: unsafe extern "C" fn(Device, *const c_char) -> Filter,
    set_filter_image: unsafe extern "C" fn(Filter, *const c_char, Buffer, c_int, usize, usize, usize, usize, usize),
    set_filter_bool: unsafe extern "C" fn(Filter, *const c_char, bool),
    set_filter_int: unsafe extern "C" fn(Filter, *const c_char, c_int),
    commit_filter: unsafe extern "C" fn(Filter),
    execute_filter: unsafe extern "C" fn(Filter),
    release_filter: unsafe extern "C" fn(Filter),
}

/// An opened OIDN library with its device.
pub struct Oidn {
    api: Api,
    device: Mutex<usize>,
    /// Where the library was found.
    pub path: PathBuf,
    /// `major.minor.patch` as the device reports it.
    pub version: String,
    /// "cpu", "cuda", … as the device reports it.
    pub device_kind: &'static str,
    // Kept last: the library must outlive the function pointers above.
    _lib: libloading::Library,
}

// The device handle is only used under the mutex; OIDN devices may be used from any
// thread.
unsafe impl Send for Oidn {}
unsafe impl Sync for Oidn {}

/// Which OIDN filter, and how.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    /// `RTLightmap`: HDR irradiance, colour only (the filter takes no auxiliary images).
    Lightmap,
    /// `RTLightmap` with `directional`: coefficients normalised to [-1, 1].
    Directional,
    /// `RT` with `hdr`, a clean normal image and a white albedo (`cleanAux`): for
    /// comparison.
    RtWithNormal,
}

static LOADED: OnceLock<Result<Oidn, String>> = OnceLock::new();

impl Oidn {
    /// The process's OIDN, loaded on first use; the error says where it was looked for.
    pub fn get() -> Result<&'static Oidn, &'static str> {
        LOADED.get_or_init(Oidn::load).as_ref().map_err(|e| e.as_str())
    }

    /// Whether OIDN can be used in this process.
    pub fn available() -> bool {
        Oidn::get().is_ok()
    }

    fn candidates() -> Vec<PathBuf> {
        let mut out = Vec::new();
        if let Some(dir) = std::env::var_os("LIGHTMAPD_OIDN_DIR").filter(|d| !d.is_empty()) {
            let dir = PathBuf::from(dir);
            out.push(dir.join("lib").join(SONAME));
            out.push(dir.join(SONAME));
        }
        out.push(PathBuf::from(DEFAULT_DIR).join("lib").join(SONAME));
        // Bare soname: the system loader path (a distribution's or a user's install).
        out.push(PathBuf::from(SONAME));
        out
    }

    fn load() -> Result<Oidn, String> {
        let mut tried = Vec::new();
        for path in Oidn::candidates() {
            if path.components().count() > 1 && !path.exists() {
                tried.push(format!("{} (absent)", path.display()));
                continue;
            }
            match Oidn::open(&path) {
                Ok(o) => {
                    tracing::info!(path = %o.path.display(), version = %o.version, device = o.device_kind, "OIDN loaded");
                    return Ok(o);
                }
                Err(e) => tried.push(format!("{} ({e})", path.display())),
            }
        }
        let msg = format!(
            "Open Image Denoise not found (run scripts/setup-oidn.sh, or set LIGHTMAPD_OIDN_DIR); tried {}",
            tried.join(", ")
        );
        tracing::debug!("{msg}");
        Err(msg)
    }

    fn open(path: &PathBuf) -> Result<Oidn, String> {
        // SAFETY: loading runs the library's initialisers; OIDN's are ordinary C++ static
        // constructors. Each symbol below is declared with OIDN 2's C signature.
        unsafe {
            let lib = libloading::Library::new(path).map_err(|e| e.to_string())?;
            macro_rules! sym {
                ($name:literal) => {
                    *lib.get(concat!($name, "\0").as_bytes())
                        .map_err(|e| format!("{}: {e}", $name))?
                };
            }
            let api = Api {
                new_device: sym!("oidnNewDevice"),
                commit_device: sym!("oidnCommitDevice"),
                get_device_error: sym!("oidnGetDeviceError"),
                get_device_int: sym!("oidnGetDeviceInt"),
                new_buffer: sym!("oidnNewBuffer"),
                write_buffer: sym!("oidnWriteBuffer"),
                read_buffer: sym!("oidnReadBuffer"),
                release_buffer: sym!("oidnReleaseBuffer"),
                new_filter: sym!("oidnNewFilter"),
                set_filter_image: sym!("oidnSetFilterImage"),
                set_filter_bool: sym!("oidnSetFilterBool"),
                set_filter_int: sym!("oidnSetFilterInt"),
                commit_filter: sym!("oidnCommitFilter"),
                execute_filter: sym!("oidnExecuteFilter"),
                release_filter: sym!("oidnReleaseFilter"),
            };
            let device = (api.new_device)(DEVICE_TYPE_DEFAULT);
            if device.is_null() {
                return Err("oidnNewDevice returned no device".into());
            }
            (api.commit_device)(device);
            check(&api, device, "creating the device")?;
            let version = (api.get_device_int)(device, c"version".as_ptr());
            if !(20000..30000).contains(&version) {
                return Err(format!("OIDN version {version} is not 2.x"));
            }
            let device_kind = match (api.get_device_int)(device, c"type".as_ptr()) {
                1 => "cpu",
                2 => "sycl",
                3 => "cuda",
                4 => "hip",
                5 => "metal",
                _ => "unknown",
            };
            Ok(Oidn {
                api,
                device: Mutex::new(device as usize),
                path: path.clone(),
                version: format!("{}.{}.{}", version / 10000, version / 100 % 100, version % 100),
                device_kind,
                _lib: lib,
            })
        }
    }

    /// A short name for headers and plans: `oidn 2.5.1 (cpu)`.
    pub fn describe(&self) -> String {
        format!("oidn {} ({})", self.version, self.device_kind)
    }

    /// Filters a W × H image (row-major float3) in `mode`; `normal` (unit world normals,
    /// same layout) is used by [`Mode::RtWithNormal`] only.
    pub fn filter(
        &self,
        width: u32,
        height: u32,
        color: &[Vec3],
        normal: Option<&[Vec3]>,
        mode: Mode,
    ) -> Result<Vec<Vec3>, String> {
        let n = (width as usize) * (height as usize);
        if color.len() != n || normal.is_some_and(|v| v.len() != n) {
            return Err(format!("OIDN: image of {} texels for {width} x {height}", color.len()));
        }
        if n == 0 {
            return Ok(Vec::new());
        }
        let bytes = n * std::mem::size_of::<Vec3>();
        let api = &self.api;
        let guard = self.device.lock().unwrap_or_else(|e| e.into_inner());
        let device = *guard as Device;
        // SAFETY: every handle is created on `device` and released before return; the
        // buffers are `bytes` long and the images described within them (W × H float3,
        // packed); the host slices are exactly `bytes` long (glam's Vec3 is three f32s).
        unsafe {
            let mut buffers = Vec::new();
            let mut make = |data: Option<&[Vec3]>| -> Result<Buffer, String> {
                let b = (api.new_buffer)(device, bytes);
                check(api, device, "allocating a buffer")?;
                if b.is_null() {
                    return Err("OIDN: no buffer".into());
                }
                buffers.push(b);
                if let Some(d) = data {
                    (api.write_buffer)(b, 0, bytes, d.as_ptr() as *const c_void);
                }
                Ok(b)
            };
            let run = (|| {
                let input = make(Some(color))?;
                // `RT` accepts a normal image only beside an albedo one: a white albedo
                // (a lightmap is irradiance, there is no albedo to separate).
                let aux = match (mode, normal) {
                    (Mode::RtWithNormal, Some(nrm)) => Some((make(Some(nrm))?, make(Some(&vec![Vec3::ONE; n]))?)),
                    _ => None,
                };
                let output = make(None)?;
                let kind = if mode == Mode::RtWithNormal {
                    c"RT"
                } else {
                    c"RTLightmap"
                };
                let filter = (api.new_filter)(device, kind.as_ptr());
                check(api, device, "creating the filter")?;
                let image = |name: &CStr, b: Buffer| {
                    (api.set_filter_image)(
                        filter,
                        name.as_ptr(),
                        b,
                        FORMAT_FLOAT3,
                        width as usize,
                        height as usize,
                        0,
                        12,
                        12 * width as usize,
                    )
                };
                image(c"color", input);
                image(c"output", output);
                if let Some((nrm, albedo)) = aux {
                    image(c"normal", nrm);
                    image(c"albedo", albedo);
                    (api.set_filter_bool)(filter, c"cleanAux".as_ptr(), true);
                }
                match mode {
                    Mode::RtWithNormal => (api.set_filter_bool)(filter, c"hdr".as_ptr(), true),
                    Mode::Directional => (api.set_filter_bool)(filter, c"directional".as_ptr(), true),
                    Mode::Lightmap => {}
                }
                (api.set_filter_int)(filter, c"quality".as_ptr(), QUALITY_HIGH);
                (api.commit_filter)(filter);
                let r = check(api, device, "committing the filter").and_then(|_| {
                    (api.execute_filter)(filter);
                    check(api, device, "running the filter")
                });
                (api.release_filter)(filter);
                r?;
                let mut out = vec![Vec3::ZERO; n];
                (api.read_buffer)(output, 0, bytes, out.as_mut_ptr() as *mut c_void);
                check(api, device, "reading the result")?;
                Ok(out)
            })();
            for b in buffers {
                (api.release_buffer)(b);
            }
            run
        }
    }
}

/// OIDN's pending error on `device`, if any, as a message naming the stage.
unsafe fn check(api: &Api, device: Device, stage: &str) -> Result<(), String> {
    let mut msg: *const c_char = std::ptr::null();
    // SAFETY: `device` is live; OIDN returns a message valid until the next call.
    let code = unsafe { (api.get_device_error)(device, &mut msg) };
    if code == 0 {
        return Ok(());
    }
    let text = if msg.is_null() {
        String::new()
    } else {
        // SAFETY: a NUL-terminated string owned by OIDN.
        unsafe { CStr::from_ptr(msg) }.to_string_lossy().into_owned()
    };
    Err(format!("OIDN error {code} {stage}: {text}"))
}
