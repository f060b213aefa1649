//! Picks the adapter and opens the device: a GPU when present, else the software adapter
//! (lavapipe). `WGPU_BACKEND` and `WGPU_ADAPTER_NAME` are honoured; what was picked is logged.

use std::time::Duration;

use crate::kernels::linear::{LinearKernel, LinearParams};
use crate::kernels::polyline::{PolylineKernel, PolylineParams};
use crate::{Error, Result};

/// How to open the device.
#[derive(Debug, Clone)]
pub struct ContextOptions {
    /// Turn on wgpu's validation layers (tests do; slower).
    pub validation: bool,
    /// Longest wait for one submission before a poll gives up.
    pub poll_timeout: Duration,
    /// The linear layers' kernel; `None` picks per layer ([`LinearKernel::choose`]: blocked
    /// for large layers, row-wise for small ones, with a lower bar on software adapters such as
    /// lavapipe).
    pub linear_kernel: Option<LinearKernel>,
    /// The polyline encoder's kernel; `None` picks by shape ([`PolylineKernel::choose`]).
    pub polyline_kernel: Option<PolylineKernel>,
    /// Most bytes of the map encoder's points a dispatch binds: it runs over the polylines
    /// chunk by chunk (at least 64 polylines each) so that agent maps of large batches fit one
    /// buffer binding. Tests make it tiny to run many chunks.
    pub map_encoder_chunk_bytes: u64,
    /// Pack scenes of mixed agent counts once enough of them move (`GpuStepEngine`; on by
    /// default): several small scenes' agents in one sub-batch scene, kept apart by each agent
    /// row's scene, so that less padding is computed at one batch's dispatches.
    pub pack_scenes: bool,
    /// With `pack_scenes`: pack from 2 moving scenes on any adapter, as on lavapipe, instead of
    /// the adapter's rule (a card's: from 128), so that a bench measures the rule (`road bench
    /// engine --packing eager`). Off by default.
    pub eager_packing: bool,
    /// Compile the kernels without wgpu's runtime checks (index clamping, loop bounding,
    /// division guards): every kernel here bounds its own indices and loops, and divides by
    /// sizes the engine sets. Off by default: on the H100 it gained 4–20 % a step from 8 scenes
    /// and lost at one (2026-11-26, `road bench engine --shader-checks checked unchecked`, one
    /// run each), not yet worth the risk.
    pub unchecked_shaders: bool,
    /// Run what a block does between two attentions as one `residual_chain` dispatch (output
    /// projection, MLP, the next layer behind its norm, the head's preconditioning) instead of
    /// layer by layer: on by default (issue 40: fewer dispatches and bytes moved; the layers
    /// stay as the variant to time against, and for hidden widths past the chain's tile).
    pub residual_chains: bool,
    /// With `residual_chains`: run them on the wide tile (32–64 rows a workgroup, blocks of
    /// 8 × 8, weights read as vec4; `ChainTile::wide`) where the model and device allow it,
    /// else on the narrow one (8 rows). On by default: on lavapipe the wide tile steps
    /// road20-wide4 and road20 1.4–1.6× faster than the narrow one at 1 to 64 scenes
    /// (`docs/benchmarks.md`); a hardware adapter's tuning (`road gpu tune`) times both and
    /// chooses per batch size. Off: the narrow tile (`road bench engine --fusion chains`).
    pub wide_chains: bool,
    /// Keep the map's keys (the agent maps' pick and encoder, every block's map k, v) from one
    /// evaluation to the next while what they are made from holds: the maps, and with agent
    /// maps each agent's anchor state, which a step leaves as it is where σ (and γ) do not
    /// change at the anchor slot (observed slots), as the fast CPU engine's memo does. On by
    /// default; off, every evaluation makes them (to time against, and the tests' reference:
    /// the states are the same to the bit).
    pub keep_map_keys: bool,
    /// The linear layers' arithmetic ([`Precision`]): f32 by default; f16 needs an adapter
    /// with `SHADER_F16` and runs on the tensor cores where cooperative matrices are offered.
    pub precision: Precision,
    /// With f16, use the adapter's cooperative matrices where it offers them
    /// ([`cooperative_f16`]; on by default); off, the f16 layers run `linear_f16` (the same
    /// rounding without tensor cores): to time one against the other.
    pub cooperative_matrices: bool,
}

/// The arithmetic of the linear layers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Precision {
    /// Everything in f32: the reference.
    #[default]
    F32,
    /// The layers of the blocks whose inputs and outputs are multiples of 16 (every q/k/v,
    /// output projection and MLP layer) with f16 weights and inputs and f32 sums; layer norms,
    /// attention, softmax, embeddings and the rest in f32. On the tensor cores
    /// (`linear_coop.wgsl`) where the adapter offers cooperative f16 matrices with f32 sums
    /// ([`cooperative_f16`]), else `linear_f16` with the same rounding.
    F16,
}

impl Precision {
    /// As command lines name it.
    pub fn name(self) -> &'static str {
        match self {
            Self::F32 => "f32",
            Self::F16 => "f16",
        }
    }
}

impl std::str::FromStr for Precision {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "f32" | "fp32" => Ok(Self::F32),
            "f16" | "fp16" => Ok(Self::F16),
            other => Err(format!("unknown precision {other:?}: expected f32 or f16")),
        }
    }
}

/// The cooperative matrices `linear_coop.wgsl` can run on an adapter: tiles of f16 inputs and
/// f32 sums, 16 × 16 × 16 (`linear_coop`) or else 8 × 8 × 8 (`linear_coop8`), with `SHADER_F16`
/// and subgroups of one fixed width (a workgroup is one subgroup).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CooperativeF16 {
    /// The tiles' side: 16 or 8.
    pub tile: u32,
    /// The adapter's subgroup width: the kernel's workgroup.
    pub lanes: u32,
}

/// See [`CooperativeF16`]; `None` where the adapter offers neither configuration.
pub fn cooperative_f16(adapter: &wgpu::Adapter) -> Option<CooperativeF16> {
    let needed = wgpu::Features::SHADER_F16 | wgpu::Features::EXPERIMENTAL_COOPERATIVE_MATRIX;
    let info = adapter.get_info();
    if !adapter.features().contains(needed) || info.subgroup_min_size != info.subgroup_max_size {
        return None;
    }
    let configs = adapter.cooperative_matrix_properties();
    let offers = |side: u32| {
        configs.iter().any(|p| {
            (p.m_size, p.n_size, p.k_size) == (side, side, side)
                && p.ab_type == wgpu::CooperativeScalarType::F16
                && p.cr_type == wgpu::CooperativeScalarType::F32
        })
    };
    [16, 8]
        .into_iter()
        .find(|&side| offers(side))
        .map(|tile| CooperativeF16 {
            tile,
            lanes: info.subgroup_min_size,
        })
}

impl Default for ContextOptions {
    fn default() -> Self {
        Self {
            validation: false,
            poll_timeout: Duration::from_secs(120),
            linear_kernel: None,
            polyline_kernel: None,
            map_encoder_chunk_bytes: 64 << 20,
            unchecked_shaders: false,
            pack_scenes: true,
            eager_packing: false,
            residual_chains: true,
            wide_chains: true,
            keep_map_keys: true,
            precision: Precision::F32,
            cooperative_matrices: true,
        }
    }
}

/// An opened device and what it is.
#[derive(Debug)]
pub struct GpuContext {
    pub adapter: wgpu::Adapter,
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub info: wgpu::AdapterInfo,
    poll_timeout: Duration,
    linear_kernel: Option<LinearKernel>,
    polyline_kernel: Option<PolylineKernel>,
    map_encoder_chunk_bytes: u64,
    unchecked_shaders: bool,
    pack_scenes: bool,
    eager_packing: bool,
    residual_chains: bool,
    wide_chains: bool,
    keep_map_keys: bool,
    precision: Precision,
    /// f16 layers on the tensor cores (`linear_coop.wgsl`): the adapter offers them, the device
    /// has them enabled, and the options asked for them.
    cooperative: Option<CooperativeF16>,
}

/// Advice printed when no adapter exists.
pub const INSTALL_HINT: &str = "install a Vulkan driver; with no GPU, Mesa's software driver lavapipe works \
(Debian/Ubuntu: `apt-get install mesa-vulkan-drivers`)";

impl GpuContext {
    pub fn new(options: &ContextOptions) -> Result<Self> {
        pollster::block_on(Self::new_async(options))
    }

    #[allow(unsafe_code)]
    async fn new_async(options: &ContextOptions) -> Result<Self> {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = wgpu::Backends::VULKAN;
        desc.flags = if options.validation {
            wgpu::InstanceFlags::VALIDATION | wgpu::InstanceFlags::DEBUG
        } else {
            wgpu::InstanceFlags::empty()
        };
        // WGPU_BACKEND, WGPU_DEBUG, WGPU_VALIDATION, ... override the defaults above.
        let instance = wgpu::Instance::new(desc.with_env());
        let adapters = instance.enumerate_adapters(wgpu::Backends::all()).await;
        let described: Vec<String> = adapters.iter().map(|a| describe(&a.get_info())).collect();
        let adapter = match std::env::var("WGPU_ADAPTER_NAME") {
            Ok(wanted) => {
                let wanted_lower = wanted.to_lowercase();
                adapters
                    .into_iter()
                    .find(|a| a.get_info().name.to_lowercase().contains(&wanted_lower))
                    .ok_or_else(|| Error::NoMatchingAdapter {
                        wanted,
                        available: described.join("; "),
                    })?
            }
            Err(_) => pick_preferred(adapters).ok_or(Error::NoAdapter(INSTALL_HINT))?,
        };
        let info = adapter.get_info();
        tracing::info!(adapter = %describe(&info), "picked the GPU adapter");
        // Features only for f16: the f32 path's kernels compile as they always have (the
        // cooperative-matrix feature switches wgpu's SPIR-V to the Vulkan memory model).
        let mut required_features = wgpu::Features::empty();
        let mut cooperative = None;
        if options.precision == Precision::F16 {
            if !adapter.features().contains(wgpu::Features::SHADER_F16) {
                return Err(Error::Device(format!(
                    "precision f16: the adapter {} offers no SHADER_F16 (run with f32)",
                    describe(&info)
                )));
            }
            required_features |= wgpu::Features::SHADER_F16;
            if options.cooperative_matrices {
                cooperative = self::cooperative_f16(&adapter);
            }
            if cooperative.is_some() {
                required_features |= wgpu::Features::EXPERIMENTAL_COOPERATIVE_MATRIX;
            }
            tracing::info!(?cooperative, "f16 linear layers");
        }
        let (device, queue) = adapter
            .request_device(&wgpu::DeviceDescriptor {
                label: Some("road"),
                required_features,
                required_limits: adapter.limits(),
                // SAFETY: the one experimental feature asked for is the cooperative matrices,
                // used by `linear_coop` alone, whose every load and store stays in its bindings
                // and workgroup arrays by construction (`shaders/linear_coop.wgsl`); the
                // self-test compares it with its CPU reference on the adapter.
                experimental_features: if cooperative.is_some() {
                    unsafe { wgpu::ExperimentalFeatures::enabled() }
                } else {
                    wgpu::ExperimentalFeatures::disabled()
                },
                ..Default::default()
            })
            .await
            .map_err(|e| Error::Device(e.to_string()))?;
        Ok(Self {
            adapter,
            device,
            queue,
            info,
            poll_timeout: options.poll_timeout,
            linear_kernel: options.linear_kernel,
            polyline_kernel: options.polyline_kernel,
            map_encoder_chunk_bytes: options.map_encoder_chunk_bytes,
            unchecked_shaders: options.unchecked_shaders,
            pack_scenes: options.pack_scenes,
            eager_packing: options.eager_packing,
            // The chains run f32 only.
            residual_chains: options.residual_chains && options.precision == Precision::F32,
            wide_chains: options.wide_chains,
            keep_map_keys: options.keep_map_keys,
            precision: options.precision,
            cooperative,
        })
    }

    /// See [`ContextOptions::precision`].
    pub fn precision(&self) -> Precision {
        self.precision
    }

    /// Whether the adapter offers `SHADER_F16`, which [`Precision::F16`] needs.
    pub fn offers_shader_f16(&self) -> bool {
        self.adapter.features().contains(wgpu::Features::SHADER_F16)
    }

    /// Whether the f16 layers run on the tensor cores (`linear_coop.wgsl`) rather than
    /// `linear_f16`.
    pub fn cooperative_f16(&self) -> bool {
        self.cooperative.is_some()
    }

    /// The cooperative matrices the f16 layers run on, if they do.
    pub fn cooperative(&self) -> Option<CooperativeF16> {
        self.cooperative
    }

    /// Blocks until the queue's work is done, within the poll timeout.
    pub fn wait(&self) -> Result<()> {
        self.device
            .poll(wgpu::PollType::Wait {
                submission_index: None,
                timeout: Some(self.poll_timeout),
            })
            .map(|_| ())
            .map_err(|e| Error::Poll(e.to_string()))
    }

    /// True for CPU adapters such as lavapipe.
    pub fn is_software(&self) -> bool {
        self.info.device_type == wgpu::DeviceType::Cpu
    }

    /// The kernel for a linear layer of these dimensions on this context.
    pub fn linear_kernel_for(&self, p: &LinearParams) -> LinearKernel {
        LinearKernel::choose(self.linear_kernel, self.is_software(), p)
    }

    /// The polyline encoder's kernel for this shape on this context: the one named if it
    /// takes the shape, else [`PolylineKernel::choose`]'s.
    pub fn polyline_kernel_for(&self, p: &PolylineParams) -> PolylineKernel {
        match self.polyline_kernel {
            Some(PolylineKernel::Blocked) if !p.blocked_fits() => PolylineKernel::PerPolyline,
            Some(kernel) => kernel,
            None => PolylineKernel::choose(p),
        }
    }

    /// The polyline kernel the options named, or `"auto"`.
    pub fn polyline_kernel_setting(&self) -> &'static str {
        self.polyline_kernel.map_or("auto", PolylineKernel::entry)
    }

    /// The linear kernel the options named; `None`: chosen per layer.
    pub fn named_linear_kernel(&self) -> Option<LinearKernel> {
        self.linear_kernel
    }

    /// The linear kernel the options named, or `"auto"` (chosen per layer).
    pub fn linear_kernel_setting(&self) -> &'static str {
        self.linear_kernel.map_or("auto", LinearKernel::entry)
    }

    /// See [`ContextOptions::pack_scenes`].
    pub fn pack_scenes(&self) -> bool {
        self.pack_scenes
    }

    /// See [`ContextOptions::eager_packing`].
    pub fn eager_packing(&self) -> bool {
        self.eager_packing
    }

    /// See [`ContextOptions::keep_map_keys`].
    pub fn keep_map_keys(&self) -> bool {
        self.keep_map_keys
    }

    /// See [`ContextOptions::residual_chains`].
    pub fn residual_chains(&self) -> bool {
        self.residual_chains
    }

    /// See [`ContextOptions::wide_chains`].
    pub fn wide_chains(&self) -> bool {
        self.wide_chains
    }

    /// `"chains"`, `"wide-chains"` or `"layers"`: how the blocks' layers between attentions
    /// run (as `road bench engine --fusion` names them).
    pub fn fusion_setting(&self) -> &'static str {
        match (self.residual_chains, self.wide_chains) {
            (true, false) => "chains",
            (true, true) => "wide-chains",
            (false, _) => "layers",
        }
    }

    /// See [`ContextOptions::unchecked_shaders`].
    pub fn unchecked_shaders(&self) -> bool {
        self.unchecked_shaders
    }

    /// `"checked"` or `"unchecked"`: how the kernels were compiled.
    pub fn shader_checks_setting(&self) -> &'static str {
        if self.unchecked_shaders {
            "unchecked"
        } else {
            "checked"
        }
    }

    /// See [`ContextOptions::map_encoder_chunk_bytes`].
    pub fn map_encoder_chunk_bytes(&self) -> u64 {
        self.map_encoder_chunk_bytes
    }

    pub fn describe(&self) -> String {
        describe(&self.info)
    }
}

/// The hardware adapter (a GPU, not a CPU adapter such as lavapipe) that [`GpuContext::new`]
/// would pick here, described; `None` without one. Honours `WGPU_BACKEND` and
/// `WGPU_ADAPTER_NAME` as it does; opens no device.
pub fn hardware_adapter() -> Option<String> {
    pollster::block_on(async {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = wgpu::Backends::VULKAN;
        let instance = wgpu::Instance::new(desc.with_env());
        let adapters = instance.enumerate_adapters(wgpu::Backends::all()).await;
        let wanted = std::env::var("WGPU_ADAPTER_NAME")
            .ok()
            .map(|name| name.to_lowercase());
        let adapters: Vec<wgpu::Adapter> = adapters
            .into_iter()
            .filter(|a| {
                let name = a.get_info().name.to_lowercase();
                wanted.as_ref().is_none_or(|w| name.contains(w))
            })
            .collect();
        let info = pick_preferred(adapters)?.get_info();
        (info.device_type != wgpu::DeviceType::Cpu).then(|| describe(&info))
    })
}

/// Discrete GPU first, then integrated, virtual, others, CPU last.
fn pick_preferred(adapters: Vec<wgpu::Adapter>) -> Option<wgpu::Adapter> {
    let rank = |t: wgpu::DeviceType| match t {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Other => 3,
        wgpu::DeviceType::Cpu => 4,
    };
    adapters
        .into_iter()
        .min_by_key(|a| rank(a.get_info().device_type))
}

fn describe(info: &wgpu::AdapterInfo) -> String {
    format!(
        "{} ({:?}, {:?}, driver {} {})",
        info.name, info.device_type, info.backend, info.driver, info.driver_info
    )
}
