//! Picks the adapter and opens the device: a GPU when present, else the software adapter
//! (lavapipe). `WGPU_BACKEND` and `WGPU_ADAPTER_NAME` are honoured; what was picked is logged.

use std::time::Duration;

use crate::{Error, Result};

/// How to open the device.
#[derive(Debug, Clone)]
pub struct ContextOptions {
    /// Turn on wgpu's validation layers (tests do; slower).
    pub validation: bool,
    /// Longest wait for one submission before a poll gives up.
    pub poll_timeout: Duration,
}

impl Default for ContextOptions {
    fn default() -> Self {
        Self {
            validation: false,
            poll_timeout: Duration::from_secs(120),
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
}

/// Advice printed when no adapter exists.
pub const INSTALL_HINT: &str = "install a Vulkan driver; with no GPU, Mesa's software driver lavapipe works \
(Debian/Ubuntu: `apt-get install mesa-vulkan-drivers`)";

impl GpuContext {
    pub fn new(options: &ContextOptions) -> Result<Self> {
        pollster::block_on(Self::new_async(options))
    }

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
        let (device, queue) = adapter
            .request_device(&wgpu::DeviceDescriptor {
                label: Some("road"),
                required_features: wgpu::Features::empty(),
                required_limits: adapter.limits(),
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
        })
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

    pub fn describe(&self) -> String {
        describe(&self.info)
    }
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
