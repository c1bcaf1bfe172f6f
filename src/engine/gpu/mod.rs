//! Headless wgpu context shared by the GPU techniques.
//!
//! What: one [`GpuContext`] (instance, adapter, device, queue) per bake, plus helpers for
//! buffers, one-shot readback and shader modules built from `shaders/` (see [`shaders`]).
//!
//! Adapter choice: a discrete GPU, else an integrated one, else a virtual one, else a CPU
//! adapter (Mesa's lavapipe on a machine with no GPU, logged as a warning because it is
//! one to two orders of magnitude slower). `LIGHTMAPD_ADAPTER` forces a choice: `gpu`
//! (best hardware adapter), `cpu` (a software one), or any other text, matched as a
//! case-insensitive substring of the adapter name ("llvmpipe", "RTX", ...). wgpu's own
//! `WGPU_BACKEND` still selects which backends are enumerated. No adapter at all is an
//! error that says what to install.
//!
//! Features and limits are checked once, up front, against [`Requirements`], with an
//! error that names the missing capability; the device is then created with the
//! adapter's own limits (so large lightmaps and maps work where the hardware allows).
//!
//! Errors: shader modules are created inside an error scope, so a naga diagnostic becomes
//! a [`GpuError::Shader`] instead of wgpu's default panic. Any other uncaptured device
//! error (a validation error in a pass) is recorded rather than panicking, and
//! [`GpuContext::take_error`] turns it into an error for the bake step that caused it.
//!
//! Precision and randomness are the techniques' business; see their module docs and
//! `shaders/gpu/common.wgsl`.
//!
//! Readback ([`GpuContext::read_buffer`]) blocks on the device and is meant for
//! snapshots only, never once per step.
//!
//! Old lavapipe: Mesa 22.3.6's lavapipe (Debian bookworm's) keeps a quarter to three
//! quarters of a megabyte for every step of `obscurance`, `sdb` and `hemicube` (heaptrack:
//! 32 KiB blocks allocated on the driver's queue thread and never freed; skipping
//! obscurance's gather dispatch, and nothing else, stops it), so their long bakes on it
//! grow without bound; Mesa 25.0.7's (bookworm-backports) does not, and runs their steps
//! three to five times faster (docs/deploy.md, "Machines without a GPU"). The context
//! warns when it gets a lavapipe older than Mesa 23 ([`old_lavapipe`]).

pub mod bvh;
pub mod direct_light;
pub mod directions;
pub mod frame;
pub mod halves;
pub mod layout;
pub mod map_scene;
pub mod scene_lights;
pub mod scene_rays;
pub mod shaders;
pub mod shadow;
pub mod shadowmask;
pub mod slices;
pub mod texel_pass;
pub mod texels;
pub mod tracer;
pub mod validate;
pub mod view;

use std::sync::{Arc, Mutex};

use bytemuck::Pod;
use wgpu::util::DeviceExt;

/// Environment variable that forces the adapter choice.
pub const ADAPTER_ENV: &str = "LIGHTMAPD_ADAPTER";

/// What to install when there is no adapter at all.
pub const INSTALL_HINT: &str = "no GPU adapter found: install a Vulkan driver. On a machine \
without a GPU, Mesa's software rasteriser works: `apt-get install mesa-vulkan-drivers libvulkan1` \
(Debian/Ubuntu) or `dnf install mesa-vulkan-drivers vulkan-loader` (Fedora)";

/// Errors from the GPU layer.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    #[error("{INSTALL_HINT}")]
    NoAdapter,
    #[error("{ADAPTER_ENV}={wanted:?} matches no adapter; available: {available}")]
    AdapterNotFound { wanted: String, available: String },
    #[error("adapter {adapter:?} lacks what lightmapd needs: {missing}")]
    Unsupported { adapter: String, missing: String },
    #[error("could not create a device on {adapter:?}: {source}")]
    RequestDevice {
        adapter: String,
        source: wgpu::RequestDeviceError,
    },
    #[error("shader {name} failed to compile:\n{message}")]
    Shader { name: String, message: String },
    #[error("GPU error during {during}: {message}")]
    Device { during: String, message: String },
    #[error("reading back {label}: {message}")]
    Readback { label: String, message: String },
}

/// Capabilities a technique needs, checked before any work.
#[derive(Debug, Clone)]
pub struct Requirements {
    /// Optional wgpu features.
    pub features: wgpu::Features,
    /// Minimum limits; only the fields that differ from the WebGPU defaults matter.
    pub limits: wgpu::Limits,
}

impl Default for Requirements {
    /// The WebGPU defaults: compute shaders, 8192^2 textures, 128 MiB storage bindings,
    /// 8 storage buffers per stage. The device itself is requested with the adapter's own
    /// limits, which some passes need: `hemicube`'s shooter selection binds 11 storage
    /// buffers (lavapipe and the NVIDIA drivers allow far more than 8).
    fn default() -> Self {
        Requirements {
            features: wgpu::Features::empty(),
            limits: wgpu::Limits::default(),
        }
    }
}

/// How the adapter was chosen (from [`ADAPTER_ENV`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum AdapterPreference {
    /// Best available: discrete, integrated, virtual, then CPU.
    Auto,
    /// Hardware only (discrete, integrated or virtual).
    Gpu,
    /// Software only.
    Cpu,
    /// Case-insensitive substring of the adapter name.
    Name(String),
}

impl AdapterPreference {
    /// Read [`ADAPTER_ENV`]; unset or empty means [`AdapterPreference::Auto`].
    pub fn from_env() -> Self {
        match std::env::var(ADAPTER_ENV) {
            Ok(v) => Self::parse(&v),
            Err(_) => Self::Auto,
        }
    }

    pub fn parse(v: &str) -> Self {
        let v = v.trim();
        match v.to_ascii_lowercase().as_str() {
            "" | "auto" => Self::Auto,
            "gpu" => Self::Gpu,
            "cpu" => Self::Cpu,
            _ => Self::Name(v.to_string()),
        }
    }

    fn wanted(&self) -> String {
        match self {
            Self::Auto => "auto".into(),
            Self::Gpu => "gpu".into(),
            Self::Cpu => "cpu".into(),
            Self::Name(n) => n.clone(),
        }
    }
}

/// Lower is better.
fn device_type_rank(t: wgpu::DeviceType) -> u32 {
    match t {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Cpu => 3,
        wgpu::DeviceType::Other => 4,
    }
}

/// The Mesa version of a lavapipe adapter whose memory grows with every step (module
/// doc, "Old lavapipe"): Mesa 22 and older, from `driver_info` ("Mesa 22.3.6 (LLVM
/// 15.0.6)"). Measured on 22.3.6 (grows) and 25.0.7 (does not); the versions between are
/// not, so only those before 23 are named.
pub fn old_lavapipe(info: &wgpu::AdapterInfo) -> Option<String> {
    if is_hardware(info.device_type) || !info.driver.to_ascii_lowercase().contains("llvmpipe") {
        return None;
    }
    let version = info.driver_info.strip_prefix("Mesa ")?.split_whitespace().next()?;
    let major: u32 = version.split('.').next()?.parse().ok()?;
    (major < 23).then(|| version.to_string())
}

fn is_hardware(t: wgpu::DeviceType) -> bool {
    matches!(
        t,
        wgpu::DeviceType::DiscreteGpu | wgpu::DeviceType::IntegratedGpu | wgpu::DeviceType::VirtualGpu
    )
}

/// Which of `infos` to use, by preference; `None` when nothing matches. Pure, so the
/// policy is unit-tested without adapters. Ties keep enumeration order (wgpu lists Vulkan
/// first, which is the backend tested here).
pub fn choose_adapter(infos: &[wgpu::AdapterInfo], pref: &AdapterPreference) -> Option<usize> {
    let candidates = infos.iter().enumerate().filter(|(_, i)| match pref {
        AdapterPreference::Auto => true,
        AdapterPreference::Gpu => is_hardware(i.device_type),
        AdapterPreference::Cpu => i.device_type == wgpu::DeviceType::Cpu,
        AdapterPreference::Name(n) => i.name.to_lowercase().contains(&n.to_lowercase()),
    });
    candidates
        .min_by_key(|(idx, i)| (device_type_rank(i.device_type), *idx))
        .map(|(idx, _)| idx)
}

/// Features and limits the adapter lacks, as readable text; empty when it has them all.
pub fn missing_capabilities(
    features: wgpu::Features,
    limits: &wgpu::Limits,
    downlevel: &wgpu::DownlevelCapabilities,
    req: &Requirements,
) -> Vec<String> {
    let mut missing = Vec::new();
    let lacking = req.features - features;
    if !lacking.is_empty() {
        missing.push(format!("features {lacking:?}"));
    }
    req.limits.check_limits_with_fail_fn(limits, false, |name, want, have| {
        missing.push(format!("limit {name}: need {want}, adapter has {have}"));
    });
    if !downlevel.flags.contains(wgpu::DownlevelFlags::COMPUTE_SHADERS) {
        missing.push("compute shaders".into());
    }
    if !downlevel.flags.contains(wgpu::DownlevelFlags::FRAGMENT_STORAGE) {
        missing.push("storage buffers in fragment shaders".into());
    }
    missing
}

/// The process's shared context: created by the first GPU bake that asks, then reused by
/// every later one (the service's workers share one device instead of creating one per
/// job, which costs adapter enumeration, device creation and pipeline compilation).
/// A failed creation is not remembered, so a later job tries again.
static SHARED: std::sync::Mutex<Option<Arc<GpuContext>>> = std::sync::Mutex::new(None);

/// The shared context with the default adapter choice and `req` (created on first use).
///
/// Limits: jobs running at once on a shared device also share its uncaptured-error
/// slot, so a device error in one can be reported by another's step; errors inside
/// error scopes (shader creation) stay with their job.
pub fn shared(req: &Requirements) -> Result<Arc<GpuContext>, GpuError> {
    let mut slot = SHARED.lock().unwrap_or_else(|p| p.into_inner());
    if let Some(ctx) = slot.as_ref() {
        return Ok(ctx.clone());
    }
    let ctx = Arc::new(GpuContext::new(req)?);
    *slot = Some(ctx.clone());
    Ok(ctx)
}

/// True when some adapter is a hardware GPU (enumerated once per process).
pub fn hardware_adapter_present() -> bool {
    static PRESENT: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *PRESENT.get_or_init(|| {
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::all()));
        adapters.iter().any(|a| {
            matches!(
                a.get_info().device_type,
                wgpu::DeviceType::DiscreteGpu | wgpu::DeviceType::IntegratedGpu | wgpu::DeviceType::VirtualGpu
            )
        })
    })
}

/// The adapter this process would pick by default, as (name, kind): `discrete`,
/// `integrated`, `virtual`, `cpu` (a software rasterizer such as lavapipe) or `other`;
/// `None` without any adapter. Enumerated once per process (a worker advertises it,
/// issue 25).
pub fn default_adapter() -> Option<(String, &'static str)> {
    static CHOSEN: std::sync::OnceLock<Option<(String, &'static str)>> = std::sync::OnceLock::new();
    CHOSEN
        .get_or_init(|| {
            let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
            let adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::all()));
            let infos: Vec<wgpu::AdapterInfo> = adapters.iter().map(|a| a.get_info()).collect();
            let i = choose_adapter(&infos, &AdapterPreference::from_env())?;
            let kind = match infos[i].device_type {
                wgpu::DeviceType::DiscreteGpu => "discrete",
                wgpu::DeviceType::IntegratedGpu => "integrated",
                wgpu::DeviceType::VirtualGpu => "virtual",
                wgpu::DeviceType::Cpu => "cpu",
                wgpu::DeviceType::Other => "other",
            };
            Some((infos[i].name.clone(), kind))
        })
        .clone()
}

/// The shared context when it is a hardware GPU and `LIGHTMAPD_ADAPTER` does not ask for
/// a software one; `None` otherwise, so the caller keeps its CPU route: on a machine
/// with only lavapipe the CPU's own rays are faster than the same rays through a JIT on
/// the same cores. `who` names the caller in the log line of an unusable GPU.
pub fn hardware_context(who: &str) -> Option<Arc<GpuContext>> {
    if AdapterPreference::from_env() == AdapterPreference::Cpu || !hardware_adapter_present() {
        return None;
    }
    match shared(&Requirements::default()) {
        Ok(ctx) if !ctx.is_software() => Some(ctx),
        Ok(_) => None,
        Err(e) => {
            tracing::warn!(error = %e, who, "no usable GPU, running on the CPU");
            None
        }
    }
}

/// Where a technique traces the rays it makes on the CPU or could make on the GPU
/// (`path`'s `device`, `vpl`'s `rays` parameter).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RayDevice {
    /// The GPU when a hardware adapter exists (and `LIGHTMAPD_ADAPTER` does not ask for a
    /// software one), else the CPU: a machine with only lavapipe keeps the CPU route.
    #[default]
    Auto,
    Cpu,
    Gpu,
}

impl RayDevice {
    /// The GPU context this asks for, or `None` for the CPU; `who` names the caller in
    /// the log line of an unusable GPU.
    pub fn context(self, who: &str) -> Result<Option<Arc<GpuContext>>, GpuError> {
        match self {
            RayDevice::Cpu => Ok(None),
            RayDevice::Gpu => shared(&Requirements::default()).map(Some),
            RayDevice::Auto => Ok(hardware_context(who)),
        }
    }
}

/// A headless device and queue.
pub struct GpuContext {
    pub adapter: wgpu::Adapter,
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub info: wgpu::AdapterInfo,
    /// Device limits as granted (the adapter's own).
    pub limits: wgpu::Limits,
    /// First uncaptured device error since the last [`GpuContext::take_error`].
    errors: Arc<Mutex<Option<String>>>,
}

impl std::fmt::Debug for GpuContext {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuContext")
            .field("adapter", &self.info.name)
            .field("backend", &self.info.backend)
            .field("device_type", &self.info.device_type)
            .finish()
    }
}

impl GpuContext {
    /// A context chosen by [`ADAPTER_ENV`], meeting `req`.
    pub fn new(req: &Requirements) -> Result<Self, GpuError> {
        Self::with_preference(&AdapterPreference::from_env(), req)
    }

    /// A context on the adapter `pref` picks, meeting `req`.
    pub fn with_preference(pref: &AdapterPreference, req: &Requirements) -> Result<Self, GpuError> {
        // from_env: WGPU_BACKEND and friends still apply.
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::all()));
        if adapters.is_empty() {
            return Err(GpuError::NoAdapter);
        }
        let infos: Vec<wgpu::AdapterInfo> = adapters.iter().map(|a| a.get_info()).collect();
        let Some(idx) = choose_adapter(&infos, pref) else {
            let available = infos
                .iter()
                .map(|i| format!("{:?} ({:?}, {:?})", i.name, i.device_type, i.backend))
                .collect::<Vec<_>>()
                .join(", ");
            return Err(GpuError::AdapterNotFound {
                wanted: pref.wanted(),
                available,
            });
        };
        let adapter = adapters.into_iter().nth(idx).expect("index from choose_adapter");
        let info = infos[idx].clone();
        let missing = missing_capabilities(
            adapter.features(),
            &adapter.limits(),
            &adapter.get_downlevel_capabilities(),
            req,
        );
        if !missing.is_empty() {
            return Err(GpuError::Unsupported {
                adapter: info.name.clone(),
                missing: missing.join("; "),
            });
        }
        if is_hardware(info.device_type) {
            tracing::info!(adapter = %info.name, backend = ?info.backend, kind = ?info.device_type, "using GPU adapter");
        } else {
            tracing::warn!(
                adapter = %info.name, backend = ?info.backend, kind = ?info.device_type,
                "no hardware GPU adapter{}: using a software (CPU) adapter; bakes will be much slower",
                if *pref == AdapterPreference::Auto { "" } else { " (forced by LIGHTMAPD_ADAPTER)" }
            );
            if let Some(version) = old_lavapipe(&info) {
                tracing::warn!(
                    mesa = %version,
                    "this lavapipe (Mesa {version}) keeps 0.25 to 0.75 MB for every step of obscurance, sdb and hemicube, so their long bakes grow without bound; Mesa 25 (Debian: bookworm-backports) does not, and is faster (docs/deploy.md)"
                );
            }
        }
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("lightmapd device"),
            required_features: req.features,
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|source| GpuError::RequestDevice {
            adapter: info.name.clone(),
            source,
        })?;
        let errors: Arc<Mutex<Option<String>>> = Arc::new(Mutex::new(None));
        let sink = errors.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            tracing::error!("uncaptured GPU error: {e}");
            let mut slot = sink.lock().unwrap_or_else(|p| p.into_inner());
            if slot.is_none() {
                *slot = Some(e.to_string());
            }
        }));
        Ok(GpuContext {
            adapter,
            device,
            queue,
            info,
            limits,
            errors,
        })
    }

    /// True for a software adapter (lavapipe, WARP, ...).
    pub fn is_software(&self) -> bool {
        !is_hardware(self.info.device_type)
    }

    /// The first device error recorded since the last call, as an error for `during`.
    pub fn take_error(&self, during: &str) -> Result<(), GpuError> {
        let mut slot = self.errors.lock().unwrap_or_else(|p| p.into_inner());
        match slot.take() {
            Some(message) => Err(GpuError::Device {
                during: during.to_string(),
                message,
            }),
            None => Ok(()),
        }
    }

    /// Compile a pass shader (common prelude + pass) inside a validation error scope.
    pub fn shader(&self, pass: &shaders::PassShader) -> Result<wgpu::ShaderModule, GpuError> {
        let source = pass.composed();
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = self.device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(pass.name),
            source: wgpu::ShaderSource::Wgsl(source.into()),
        });
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Shader {
                name: pass.name.to_string(),
                message: e.to_string(),
            });
        }
        Ok(module)
    }

    /// A buffer holding `data`.
    pub fn buffer_init<T: Pod>(&self, label: &str, data: &[T], usage: wgpu::BufferUsages) -> wgpu::Buffer {
        // wgpu rejects zero-sized mapped-at-creation buffers in some paths; a 16-byte
        // minimum also keeps empty scenes' bindings valid.
        let bytes: &[u8] = bytemuck::cast_slice(data);
        if bytes.len() < 16 {
            let mut padded = [0u8; 16];
            padded[..bytes.len()].copy_from_slice(bytes);
            return self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: &padded,
                usage,
            });
        }
        self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(label),
            contents: bytes,
            usage,
        })
    }

    /// A zero-filled buffer of `size` bytes (at least 16).
    pub fn buffer_zeroed(&self, label: &str, size: u64, usage: wgpu::BufferUsages) -> wgpu::Buffer {
        // wgpu zero-initialises new buffers (a WebGPU guarantee).
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: size.max(16).next_multiple_of(wgpu::COPY_BUFFER_ALIGNMENT),
            usage,
            mapped_at_creation: false,
        })
    }

    /// A uniform buffer holding `value`, writable later with [`wgpu::Queue::write_buffer`].
    pub fn uniform<T: Pod>(&self, label: &str, value: &T) -> wgpu::Buffer {
        self.buffer_init(
            label,
            std::slice::from_ref(value),
            wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        )
    }

    /// A single-mip, single-sample 2D (or 2D-array, `size.depth_or_array_layers` layers)
    /// texture: the only kind the techniques render into or read.
    pub fn texture_2d(
        &self,
        label: &str,
        size: wgpu::Extent3d,
        format: wgpu::TextureFormat,
        usage: wgpu::TextureUsages,
    ) -> wgpu::Texture {
        self.device.create_texture(&wgpu::TextureDescriptor {
            label: Some(label),
            size,
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format,
            usage,
            view_formats: &[],
        })
    }

    /// Whether one storage binding of `bytes` fits this device; `what` names the buffer's
    /// owner and content for the error (e.g. "vpl: 40000 texels' accumulators"). Every
    /// technique checks its per-texel buffers with this before creating them, so a too
    /// large lightmap is a clear bad-input error instead of a wgpu validation panic.
    pub fn check_storage(&self, what: &str, bytes: u64) -> Result<(), GpuError> {
        let limit = self.limits.max_storage_buffer_binding_size;
        if bytes > limit {
            return Err(GpuError::Unsupported {
                adapter: self.info.name.clone(),
                missing: format!(
                    "{what} needs {bytes} bytes in one storage buffer; the device allows {limit}: lower the resolution"
                ),
            });
        }
        Ok(())
    }

    /// Copy `count` elements of `T` from the start of `buffer` (which needs COPY_SRC) to
    /// the host. Submits, then blocks until the GPU is done: snapshot time only.
    pub fn read_buffer<T: Pod>(&self, label: &str, buffer: &wgpu::Buffer, count: usize) -> Result<Vec<T>, GpuError> {
        let size = (count * std::mem::size_of::<T>()) as u64;
        if size == 0 {
            return Ok(Vec::new());
        }
        let staging_label = format!("{label} readback");
        let staging = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(&staging_label),
            size: size.next_multiple_of(wgpu::COPY_BUFFER_ALIGNMENT),
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut encoder = self.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some(&staging_label),
        });
        encoder.copy_buffer_to_buffer(
            buffer,
            0,
            &staging,
            0,
            size.next_multiple_of(wgpu::COPY_BUFFER_ALIGNMENT),
        );
        self.queue.submit([encoder.finish()]);
        let (tx, rx) = std::sync::mpsc::channel();
        staging.slice(..).map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        let err = |message: String| GpuError::Readback {
            label: label.to_string(),
            message,
        };
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| err(e.to_string()))?;
        rx.recv()
            .map_err(|e| err(e.to_string()))?
            .map_err(|e| err(e.to_string()))?;
        let out = {
            let view = staging.slice(..).get_mapped_range().map_err(|e| err(e.to_string()))?;
            bytemuck::pod_collect_to_vec::<u8, T>(&view[..size as usize])
        };
        staging.unmap();
        self.take_error(label)?;
        Ok(out)
    }

    /// Submits one labelled compute pass of `pipeline` over `n` items of a 64-wide 1D
    /// kernel (`dispatch_size_64`) with `group` at slot 0, in its own command buffer; does
    /// not wait, and returns the submission for [`GpuContext::wait_for`]. Errors are the
    /// caller's to take (`take_error`).
    pub fn submit_compute(
        &self,
        label: &str,
        pipeline: &wgpu::ComputePipeline,
        group: &wgpu::BindGroup,
        n: u32,
    ) -> wgpu::SubmissionIndex {
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(label) });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some(label),
                timestamp_writes: None,
            });
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, group, &[]);
            let (x, y) = dispatch_size_64(n);
            pass.dispatch_workgroups(x, y, 1);
        }
        self.queue.submit([enc.finish()])
    }

    /// Blocks until `submission` (and all before it) has run; `label` names the work in
    /// the error.
    pub fn wait_for(&self, label: &str, submission: wgpu::SubmissionIndex) -> Result<(), GpuError> {
        self.device
            .poll(wgpu::PollType::Wait {
                submission_index: Some(submission),
                timeout: None,
            })
            .map_err(|e| GpuError::Device {
                during: format!("{label}: waiting for a step"),
                message: e.to_string(),
            })?;
        Ok(())
    }

    /// Block until all submitted work is done (benchmarks, tests).
    pub fn wait_idle(&self) -> Result<(), GpuError> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::Device {
                during: "wait".into(),
                message: e.to_string(),
            })?;
        Ok(())
    }
}

/// Workgroup counts for a 64-wide 1D kernel over `n` items, laid out in 2D because one
/// dimension is capped at 65535 workgroups (`invocation_index` in gpu/common.wgsl undoes it).
pub fn dispatch_size_64(n: u32) -> (u32, u32) {
    let groups = n.div_ceil(64).max(1);
    if groups <= 65535 {
        (groups, 1)
    } else {
        let y = groups.div_ceil(65535);
        (groups.div_ceil(y), y)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shared_context_is_created_once() {
        let Ok(a) = shared(&Requirements::default()) else {
            eprintln!("no GPU adapter (install mesa-vulkan-drivers): nothing to share");
            return;
        };
        let b = shared(&Requirements::default()).unwrap();
        assert!(
            Arc::ptr_eq(&a, &b),
            "a second GPU job must reuse the first one's device"
        );
    }

    fn info(name: &str, t: wgpu::DeviceType) -> wgpu::AdapterInfo {
        wgpu::AdapterInfo {
            name: name.into(),
            ..wgpu::AdapterInfo::new(t, wgpu::Backend::Vulkan)
        }
    }

    /// Mesa 22's lavapipe is named by its version; Mesa 25's, a hardware adapter, another
    /// CPU driver or an unreadable version are not.
    #[test]
    fn an_old_lavapipe_is_recognised() {
        use wgpu::DeviceType::*;
        let with = |t: wgpu::DeviceType, driver: &str, driver_info: &str| wgpu::AdapterInfo {
            driver: driver.into(),
            driver_info: driver_info.into(),
            ..info("llvmpipe (LLVM 15.0.6, 256 bits)", t)
        };
        assert_eq!(
            old_lavapipe(&with(Cpu, "llvmpipe", "Mesa 22.3.6 (LLVM 15.0.6)")).as_deref(),
            Some("22.3.6")
        );
        assert_eq!(
            old_lavapipe(&with(Cpu, "llvmpipe", "Mesa 25.0.7-2~bpo12+1 (LLVM 15.0.6)")),
            None
        );
        assert_eq!(old_lavapipe(&with(DiscreteGpu, "llvmpipe", "Mesa 22.3.6")), None);
        assert_eq!(old_lavapipe(&with(Cpu, "SwiftShader driver", "Mesa 22.3.6")), None);
        assert_eq!(old_lavapipe(&with(Cpu, "llvmpipe", "unknown")), None);
    }

    #[test]
    fn adapter_policy() {
        use wgpu::DeviceType::*;
        let list = [
            info("llvmpipe (LLVM 15)", Cpu),
            info("Intel UHD", IntegratedGpu),
            info("NVIDIA RTX", DiscreteGpu),
        ];
        assert_eq!(choose_adapter(&list, &AdapterPreference::Auto), Some(2));
        assert_eq!(choose_adapter(&list, &AdapterPreference::Gpu), Some(2));
        assert_eq!(choose_adapter(&list, &AdapterPreference::Cpu), Some(0));
        assert_eq!(choose_adapter(&list, &AdapterPreference::parse("uhd")), Some(1));
        assert_eq!(choose_adapter(&list, &AdapterPreference::parse("radeon")), None);
        let cpu_only = [info("llvmpipe", Cpu)];
        assert_eq!(choose_adapter(&cpu_only, &AdapterPreference::Auto), Some(0));
        assert_eq!(choose_adapter(&cpu_only, &AdapterPreference::Gpu), None);
        assert_eq!(AdapterPreference::parse(" CPU "), AdapterPreference::Cpu);
        assert_eq!(AdapterPreference::parse(""), AdapterPreference::Auto);
    }

    #[test]
    fn missing_capabilities_are_named() {
        let req = Requirements::default();
        let small = wgpu::Limits {
            max_texture_dimension_2d: 2048,
            ..Default::default()
        };
        let down = wgpu::DownlevelCapabilities::default();
        let missing = missing_capabilities(wgpu::Features::empty(), &small, &down, &req);
        assert!(
            missing.iter().any(|m| m.contains("max_texture_dimension_2d")),
            "{missing:?}"
        );
        let ok = missing_capabilities(wgpu::Features::empty(), &wgpu::Limits::default(), &down, &req);
        assert!(ok.is_empty(), "{ok:?}");
    }

    #[test]
    fn dispatch_covers_all_items() {
        for n in [1u32, 63, 64, 65, 65535 * 64, 65535 * 64 + 1, 4096 * 4096] {
            let (x, y) = dispatch_size_64(n);
            assert!(x <= 65535 && y <= 65535);
            assert!(x as u64 * y as u64 * 64 >= n as u64, "n={n}");
        }
    }
}
