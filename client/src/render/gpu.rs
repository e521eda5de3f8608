//! The device the renderer draws with ([`Gpu`]: any adapter headless, a window's, or a
//! browser's, awaited) and how a surface is configured for it ([`configure_surface`]: an
//! sRGB view where the surface allows one). The window, the headless viewer and the
//! browser page open theirs here; the [`super::Renderer`] only takes a `Gpu`.

use anyhow::{Context, Result};

/// The longest texture side of every device the native viewer opens ([`Gpu::open`] asks
/// for wgpu's default limits, whatever the adapter has): what a native hello's colour
/// window is sized for ([`crate::conversation::hello`]).
pub fn native_max_texture() -> u32 {
    wgpu::Limits::default().max_texture_dimension_2d
}

/// A device to draw with.
pub struct Gpu {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub adapter: wgpu::AdapterInfo,
}

/// Configures `surface` (a window's, a canvas') at `size` to be drawn through an sRGB view,
/// so the shader's linear colours are encoded on write: the surface's own sRGB format, or
/// an sRGB view of the one it has; without sRGB views either, the renderer encodes in its
/// shaders. Returns the configuration and the format to draw through.
pub fn configure_surface(
    surface: &wgpu::Surface<'_>,
    adapter: &wgpu::Adapter,
    device: &wgpu::Device,
    size: (u32, u32),
) -> Result<(wgpu::SurfaceConfiguration, wgpu::TextureFormat)> {
    let mut config = surface
        .get_default_config(adapter, size.0.max(1), size.1.max(1))
        .context("the surface does not work with this adapter")?;
    let caps = surface.get_capabilities(adapter);
    if let Some(f) = caps.formats.iter().find(|f| f.is_srgb()) {
        config.format = *f;
    }
    let views = adapter
        .get_downlevel_capabilities()
        .flags
        .contains(wgpu::DownlevelFlags::SURFACE_VIEW_FORMATS);
    let mut view_format = config.format;
    if views && config.format.add_srgb_suffix() != config.format {
        view_format = config.format.add_srgb_suffix();
        config.view_formats = vec![view_format];
    }
    config.present_mode = wgpu::PresentMode::AutoVsync;
    surface.configure(device, &config);
    Ok((config, view_format))
}

/// What to say when no adapter is found.
pub const NO_ADAPTER: &str = "without a GPU, install a software Vulkan driver: \
     apt-get install mesa-vulkan-drivers libvulkan1";

impl Gpu {
    /// Any adapter, a software one (lavapipe) included; no window needed.
    #[cfg(not(target_arch = "wasm32"))]
    pub fn headless() -> Result<Gpu> {
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            compatible_surface: None,
            force_fallback_adapter: false,
            ..Default::default()
        }))
        .map_err(|e| anyhow::anyhow!("no GPU adapter ({e}); {NO_ADAPTER}"))?;
        Gpu::open(&adapter)
    }

    /// Opens `adapter`'s device (blocking: native only).
    #[cfg(not(target_arch = "wasm32"))]
    pub fn open(adapter: &wgpu::Adapter) -> Result<Gpu> {
        pollster::block_on(Gpu::open_async(adapter))
    }

    /// Opens `adapter`'s device: what a browser awaits (it cannot block). In a browser
    /// the device asks for the adapter's own limits: WebGL2 has less than wgpu's defaults.
    pub async fn open_async(adapter: &wgpu::Adapter) -> Result<Gpu> {
        let required_limits = if cfg!(target_arch = "wasm32") {
            adapter.limits()
        } else {
            wgpu::Limits::default()
        };
        let (device, queue) = adapter
            .request_device(&wgpu::DeviceDescriptor {
                label: Some("roam"),
                required_limits,
                ..Default::default()
            })
            .await
            .context("opening the GPU device")?;
        Ok(Gpu {
            adapter: adapter.get_info(),
            device,
            queue,
        })
    }
}
