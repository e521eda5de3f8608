//! The renderer: the decoded mesh lit, fogged and coloured, over a sky, into any texture
//! view (a window's surface or an offscreen texture: the same code).

use anyhow::{Context, Result, anyhow};
use wgpu::util::DeviceExt;

/// What does not change during a session: the map's scales, sun, fog and colours.
#[derive(Clone, Debug)]
pub struct Scene {
    pub levels: u32,
    pub h_scale: f64,
    pub v_scale: f64,
    pub sun_dir: [f32; 3],
    pub sun_color: [u8; 3],
    pub fog_density: f32,
    pub fog_color: [u8; 3],
    /// `cells × cells` RGB texels, row 0 north.
    pub cells: u32,
    pub colors: Vec<u8>,
}

/// Where the camera is and what it sees.
#[derive(Clone, Copy, Debug)]
pub struct View {
    pub eye: [f32; 3],
    /// Heading convention: 0 faces south (+Z), 90 east (+X).
    pub yaw_deg: f32,
    /// Positive looks up.
    pub pitch_deg: f32,
    pub fov_y_deg: f32,
}

/// The viewer's switches.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Toggles {
    pub fog: bool,
    pub lighting: bool,
    pub wireframe: bool,
}

impl Default for Toggles {
    fn default() -> Self {
        Toggles {
            fog: true,
            lighting: true,
            wireframe: false,
        }
    }
}

/// A device to draw with.
pub struct Gpu {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub adapter: wgpu::AdapterInfo,
}

impl Gpu {
    /// Any adapter, a software one (lavapipe) included; no window needed.
    pub fn headless() -> Result<Gpu> {
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            compatible_surface: None,
            force_fallback_adapter: false,
            ..Default::default()
        }))
        .map_err(|e| {
            anyhow!(
                "no GPU adapter ({e}); without a GPU, install a software Vulkan driver: \
                 apt-get install mesa-vulkan-drivers libvulkan1"
            )
        })?;
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("roam"),
            ..Default::default()
        }))
        .context("opening the GPU device")?;
        Ok(Gpu {
            adapter: adapter.get_info(),
            device,
            queue,
        })
    }
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Vertex {
    pos: [f32; 3],
    normal: [f32; 3],
    uv: [f32; 2],
    bary: [f32; 3],
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Uniforms {
    view_proj: [[f32; 4]; 4],
    inv_view_proj: [[f32; 4]; 4],
    eye: [f32; 4],
    sun_dir: [f32; 4],
    sun_color: [f32; 4],
    fog_color: [f32; 4],
    params: [f32; 4],
}

/// Draws a scene's meshes.
pub struct Renderer {
    terrain: wgpu::RenderPipeline,
    sky: wgpu::RenderPipeline,
    uniforms: wgpu::Buffer,
    bind_group: wgpu::BindGroup,
    vertices: Option<(wgpu::Buffer, u32)>,
    depth: Option<(wgpu::Texture, wgpu::TextureView, (u32, u32))>,
    scene: Scene,
    /// Far plane: the map's diagonal and then some.
    far: f32,
}

const DEPTH: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// Near plane, world units.
const NEAR: f32 = 0.5;

fn srgb_to_linear(c: u8) -> f32 {
    let c = f32::from(c) / 255.0;
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

impl Renderer {
    /// A renderer drawing into textures of `format`.
    pub fn new(gpu: &Gpu, format: wgpu::TextureFormat, scene: Scene) -> Renderer {
        let device = &gpu.device;
        let shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("terrain and sky"),
            source: wgpu::ShaderSource::Wgsl(include_str!("shader.wgsl").into()),
        });
        // The colour map, downsampled until the device takes it.
        let max = device.limits().max_texture_dimension_2d.max(1);
        let (mut cells, mut rgb) = (scene.cells.max(1), scene.colors.clone());
        if rgb.len() != (cells * cells * 3) as usize {
            (cells, rgb) = (1, vec![128, 128, 128]);
        }
        while cells > max {
            let half = cells / 2;
            let mut out = Vec::with_capacity((half * half * 3) as usize);
            for z in 0..half {
                for x in 0..half {
                    let i = ((2 * z * cells + 2 * x) * 3) as usize;
                    out.extend_from_slice(&rgb[i..i + 3]);
                }
            }
            (cells, rgb) = (half, out);
        }
        let rgba: Vec<u8> = rgb
            .chunks(3)
            .flat_map(|c| [c[0], c[1], c[2], 255])
            .collect();
        let texture = device.create_texture_with_data(
            &gpu.queue,
            &wgpu::TextureDescriptor {
                label: Some("colour map"),
                size: wgpu::Extent3d {
                    width: cells,
                    height: cells,
                    depth_or_array_layers: 1,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format: wgpu::TextureFormat::Rgba8UnormSrgb,
                usage: wgpu::TextureUsages::TEXTURE_BINDING,
                view_formats: &[],
            },
            wgpu::util::TextureDataOrder::LayerMajor,
            &rgba,
        );
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("colour map"),
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            ..Default::default()
        });
        let uniforms = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("uniforms"),
            size: std::mem::size_of::<Uniforms>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("scene"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::VERTEX_FRAGMENT,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                    count: None,
                },
                wgpu::BindGroupLayoutEntry {
                    binding: 1,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Texture {
                        sample_type: wgpu::TextureSampleType::Float { filterable: true },
                        view_dimension: wgpu::TextureViewDimension::D2,
                        multisampled: false,
                    },
                    count: None,
                },
                wgpu::BindGroupLayoutEntry {
                    binding: 2,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
                    count: None,
                },
            ],
        });
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("scene"),
            layout: &layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: uniforms.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::TextureView(&view),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: wgpu::BindingResource::Sampler(&sampler),
                },
            ],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("scene"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let attributes = wgpu::vertex_attr_array![0 => Float32x3, 1 => Float32x3, 2 => Float32x2, 3 => Float32x3];
        let pipeline =
            |label, vs, fs, buffers: &[Option<wgpu::VertexBufferLayout>], depth_write, compare| {
                device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                    label: Some(label),
                    layout: Some(&pipeline_layout),
                    vertex: wgpu::VertexState {
                        module: &shader,
                        entry_point: Some(vs),
                        compilation_options: Default::default(),
                        buffers,
                    },
                    primitive: wgpu::PrimitiveState {
                        cull_mode: None,
                        ..Default::default()
                    },
                    depth_stencil: Some(wgpu::DepthStencilState {
                        format: DEPTH,
                        depth_write_enabled: Some(depth_write),
                        depth_compare: Some(compare),
                        stencil: Default::default(),
                        bias: Default::default(),
                    }),
                    multisample: Default::default(),
                    fragment: Some(wgpu::FragmentState {
                        module: &shader,
                        entry_point: Some(fs),
                        compilation_options: Default::default(),
                        targets: &[Some(format.into())],
                    }),
                    multiview_mask: None,
                    cache: None,
                })
            };
        let terrain = pipeline(
            "terrain",
            "terrain_vs",
            "terrain_fs",
            &[Some(wgpu::VertexBufferLayout {
                array_stride: std::mem::size_of::<Vertex>() as u64,
                step_mode: wgpu::VertexStepMode::Vertex,
                attributes: &attributes,
            })],
            true,
            wgpu::CompareFunction::Less,
        );
        let sky = pipeline(
            "sky",
            "sky_vs",
            "sky_fs",
            &[],
            false,
            wgpu::CompareFunction::Always,
        );
        let size = scene.h_scale as f32 * (1u32 << scene.levels) as f32;
        Renderer {
            terrain,
            sky,
            uniforms,
            bind_group,
            vertices: None,
            depth: None,
            far: size * 2.0 + 1000.0,
            scene,
        }
    }

    /// Replaces the mesh drawn: `mesh` from the codec (grid vertices, heights, triangles).
    pub fn set_mesh(&mut self, gpu: &Gpu, mesh: &roam_protocol::Mesh) {
        let (h, v) = (self.scene.h_scale as f32, self.scene.v_scale as f32);
        let size = (1u32 << self.scene.levels) as f32;
        let world: Vec<[f32; 3]> = mesh
            .vertices
            .iter()
            .zip(&mesh.heights)
            .map(|(p, &y)| [f32::from(p[0]) * h, f32::from(y) * v, f32::from(p[1]) * h])
            .collect();
        // Smooth normals: each vertex's area-weighted face normals.
        let mut normals = vec![[0f32; 3]; world.len()];
        for t in mesh.indices.chunks_exact(3) {
            let [a, b, c] = [t[0], t[1], t[2]].map(|i| world[i as usize]);
            let (e1, e2) = (sub(b, a), sub(c, a));
            // Counter-clockwise seen from above: e1 × e2 points up.
            let n = cross(e1, e2);
            for &i in t {
                let m = &mut normals[i as usize];
                for k in 0..3 {
                    m[k] += n[k];
                }
            }
        }
        let mut data = Vec::with_capacity(mesh.indices.len());
        for t in mesh.indices.chunks_exact(3) {
            for (corner, &i) in t.iter().enumerate() {
                let p = mesh.vertices[i as usize];
                let mut bary = [0.0; 3];
                bary[corner] = 1.0;
                data.push(Vertex {
                    pos: world[i as usize],
                    normal: normalize(normals[i as usize]),
                    uv: [f32::from(p[0]) / size, f32::from(p[1]) / size],
                    bary,
                });
            }
        }
        let buffer = gpu
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("mesh"),
                contents: bytemuck::cast_slice(&data),
                usage: wgpu::BufferUsages::VERTEX,
            });
        self.vertices = Some((buffer, data.len() as u32));
    }

    /// Draws the sky and the mesh into `target` (`size` pixels).
    pub fn render(
        &mut self,
        gpu: &Gpu,
        target: &wgpu::TextureView,
        size: (u32, u32),
        view: &View,
        toggles: Toggles,
    ) {
        if self.depth.as_ref().is_none_or(|d| d.2 != size) {
            let texture = target_texture(gpu, "depth", size, DEPTH, wgpu::TextureUsages::empty());
            let view = texture.create_view(&Default::default());
            self.depth = Some((texture, view, size));
        }
        let aspect = size.0 as f32 / size.1.max(1) as f32;
        let fov = view.fov_y_deg.to_radians();
        let view_proj = mul(perspective(fov, aspect, NEAR, self.far), look(view));
        let inv_view_proj = mul(
            look_inverse(view),
            perspective_inverse(fov, aspect, NEAR, self.far),
        );
        let s = &self.scene;
        let lin = |c: [u8; 3]| {
            [
                srgb_to_linear(c[0]),
                srgb_to_linear(c[1]),
                srgb_to_linear(c[2]),
                1.0,
            ]
        };
        let u = Uniforms {
            view_proj,
            inv_view_proj,
            eye: [view.eye[0], view.eye[1], view.eye[2], 1.0],
            sun_dir: [s.sun_dir[0], s.sun_dir[1], s.sun_dir[2], 0.0],
            sun_color: lin(s.sun_color),
            fog_color: lin(s.fog_color),
            params: [
                s.fog_density,
                f32::from(u8::from(toggles.fog)),
                f32::from(u8::from(toggles.lighting)),
                f32::from(u8::from(toggles.wireframe)),
            ],
        };
        gpu.queue
            .write_buffer(&self.uniforms, 0, bytemuck::bytes_of(&u));
        let mut encoder = gpu.device.create_command_encoder(&Default::default());
        {
            let depth = &self.depth.as_ref().expect("made above").1;
            let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("frame"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: target,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color::BLACK),
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: depth,
                    depth_ops: Some(wgpu::Operations {
                        load: wgpu::LoadOp::Clear(1.0),
                        store: wgpu::StoreOp::Store,
                    }),
                    stencil_ops: None,
                }),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            pass.set_bind_group(0, &self.bind_group, &[]);
            pass.set_pipeline(&self.sky);
            pass.draw(0..3, 0..1);
            if let Some((buffer, count)) = &self.vertices {
                pass.set_pipeline(&self.terrain);
                pass.set_vertex_buffer(0, buffer.slice(..));
                pass.draw(0..*count, 0..1);
            }
        }
        gpu.queue.submit([encoder.finish()]);
    }
}

/// A 2D texture to render into, of `size` pixels, with `usage` besides that.
fn target_texture(
    gpu: &Gpu,
    label: &str,
    size: (u32, u32),
    format: wgpu::TextureFormat,
    usage: wgpu::TextureUsages,
) -> wgpu::Texture {
    gpu.device.create_texture(&wgpu::TextureDescriptor {
        label: Some(label),
        size: wgpu::Extent3d {
            width: size.0,
            height: size.1,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format,
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT | usage,
        view_formats: &[],
    })
}

/// Renders offscreen and returns the RGBA pixels, row by row.
pub fn render_offscreen(
    gpu: &Gpu,
    renderer: &mut Renderer,
    size: (u32, u32),
    view: &View,
    toggles: Toggles,
) -> Result<Vec<u8>> {
    let format = wgpu::TextureFormat::Rgba8UnormSrgb;
    let texture = target_texture(
        gpu,
        "offscreen",
        size,
        format,
        wgpu::TextureUsages::COPY_SRC,
    );
    let target = texture.create_view(&Default::default());
    renderer.render(gpu, &target, size, view, toggles);
    let row = (size.0 * 4).div_ceil(256) * 256;
    let buffer = gpu.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("readback"),
        size: u64::from(row * size.1),
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    });
    let mut encoder = gpu.device.create_command_encoder(&Default::default());
    encoder.copy_texture_to_buffer(
        texture.as_image_copy(),
        wgpu::TexelCopyBufferInfo {
            buffer: &buffer,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(row),
                rows_per_image: Some(size.1),
            },
        },
        wgpu::Extent3d {
            width: size.0,
            height: size.1,
            depth_or_array_layers: 1,
        },
    );
    gpu.queue.submit([encoder.finish()]);
    let slice = buffer.slice(..);
    slice.map_async(wgpu::MapMode::Read, |_| {});
    gpu.device
        .poll(wgpu::PollType::wait_indefinitely())
        .context("waiting for the GPU")?;
    let mapped = slice.get_mapped_range().context("reading the frame back")?;
    let mut pixels = Vec::with_capacity((size.0 * size.1 * 4) as usize);
    for y in 0..size.1 {
        let start = (y * row) as usize;
        pixels.extend_from_slice(&mapped[start..start + (size.0 * 4) as usize]);
    }
    Ok(pixels)
}

/// Writes RGBA pixels as a PNG.
pub fn write_png(path: &std::path::Path, size: (u32, u32), rgba: &[u8]) -> Result<()> {
    let file =
        std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), size.0, size.1);
    enc.set_color(png::ColorType::Rgba);
    enc.set_depth(png::BitDepth::Eight);
    let mut w = enc.write_header().context("writing the PNG header")?;
    w.write_image_data(rgba).context("writing the PNG")?;
    Ok(())
}

fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn normalize(v: [f32; 3]) -> [f32; 3] {
    let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if l > 0.0 {
        [v[0] / l, v[1] / l, v[2] / l]
    } else {
        [0.0, 1.0, 0.0]
    }
}

type Mat = [[f32; 4]; 4];

/// Column-major product `a · b`.
fn mul(a: Mat, b: Mat) -> Mat {
    let mut m = [[0.0; 4]; 4];
    for c in 0..4 {
        for r in 0..4 {
            m[c][r] = (0..4).map(|k| a[k][r] * b[c][k]).sum();
        }
    }
    m
}

/// Right-handed perspective, depth 0 (near) to 1 (far).
fn perspective(fov_y: f32, aspect: f32, near: f32, far: f32) -> Mat {
    let f = 1.0 / (fov_y / 2.0).tan();
    let r = far / (near - far);
    [
        [f / aspect, 0.0, 0.0, 0.0],
        [0.0, f, 0.0, 0.0],
        [0.0, 0.0, r, -1.0],
        [0.0, 0.0, r * near, 0.0],
    ]
}

/// The view matrix of a camera at `eye` looking along its heading and pitch.
fn look(v: &View) -> Mat {
    let (yaw, pitch) = (v.yaw_deg.to_radians(), v.pitch_deg.to_radians());
    let f = [
        yaw.sin() * pitch.cos(),
        pitch.sin(),
        yaw.cos() * pitch.cos(),
    ];
    let s = normalize(cross(f, [0.0, 1.0, 0.0]));
    let u = cross(s, f);
    let e = v.eye;
    let dot = |a: [f32; 3], b: [f32; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    [
        [s[0], u[0], -f[0], 0.0],
        [s[1], u[1], -f[1], 0.0],
        [s[2], u[2], -f[2], 0.0],
        [-dot(s, e), -dot(u, e), dot(f, e), 1.0],
    ]
}

/// The inverse of `perspective`.
fn perspective_inverse(fov_y: f32, aspect: f32, near: f32, far: f32) -> Mat {
    let f = 1.0 / (fov_y / 2.0).tan();
    let r = far / (near - far);
    [
        [aspect / f, 0.0, 0.0, 0.0],
        [0.0, 1.0 / f, 0.0, 0.0],
        [0.0, 0.0, 0.0, 1.0 / (r * near)],
        [0.0, 0.0, -1.0, 1.0 / near],
    ]
}

/// The inverse of `look`: the camera's axes as columns, then the eye.
fn look_inverse(v: &View) -> Mat {
    let l = look(v);
    // `look` is a rotation R (rows s, u, −f) then a translation: its inverse is Rᵀ and eye.
    [
        [l[0][0], l[1][0], l[2][0], 0.0],
        [l[0][1], l[1][1], l[2][1], 0.0],
        [l[0][2], l[1][2], l[2][2], 0.0],
        [v.eye[0], v.eye[1], v.eye[2], 1.0],
    ]
}
